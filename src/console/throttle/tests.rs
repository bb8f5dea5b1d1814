use super::*;

fn ip(last: u8) -> IpAddr {
    IpAddr::from([127, 0, 0, last])
}

#[test]
fn a_few_failures_are_free_then_the_wait_doubles_up_to_its_bound() {
    let t = Throttle::default();
    let now = Instant::now();
    for _ in 0..FREE_PER_USER {
        assert_eq!(t.failed("admin", ip(1), now), None);
    }
    assert_eq!(t.closed("admin", ip(1), now), None);
    assert_eq!(t.failed("admin", ip(1), now), Some(Duration::from_secs(1)));
    assert_eq!(t.failed("admin", ip(1), now), Some(Duration::from_secs(2)));
    assert_eq!(t.failed("admin", ip(1), now), Some(Duration::from_secs(4)));
    assert_eq!(t.closed("admin", ip(1), now), Some(Duration::from_secs(4)));
    // Another address is closed for that name too: the name is what is guessed at.
    assert_eq!(t.closed("admin", ip(2), now), Some(Duration::from_secs(4)));
    // Another name from that address is not (the address has failures to spare).
    assert_eq!(t.closed("olga", ip(1), now), None);
    for _ in 0..20 {
        t.failed("admin", ip(1), now);
    }
    assert_eq!(t.closed("admin", ip(3), now), Some(MAX_WAIT));
}

#[test]
fn once_the_wait_has_passed_a_login_is_looked_at_again() {
    let t = Throttle::default();
    let now = Instant::now();
    for _ in 0..=FREE_PER_USER {
        t.failed("admin", ip(1), now);
    }
    assert!(t.closed("admin", ip(1), now).is_some());
    let later = now + Duration::from_millis(1001);
    assert_eq!(t.closed("admin", ip(1), later), None);
    // A success forgets the name's failures; the next failure is free again.
    t.succeeded("admin");
    assert_eq!(t.failed("admin", ip(1), later), None);
}

#[test]
fn an_address_that_guesses_many_names_is_closed_for_all_of_them() {
    let t = Throttle::default();
    let now = Instant::now();
    for i in 0..FREE_PER_ADDRESS {
        assert_eq!(t.failed(&format!("user{i}"), ip(9), now), None);
    }
    assert_eq!(t.failed("another", ip(9), now), Some(FIRST_WAIT));
    assert!(t.closed("someone-else", ip(9), now).is_some());
    assert_eq!(t.closed("someone-else", ip(8), now), None);
    // A success of one name does not open the address.
    t.succeeded("another");
    assert!(t.closed("someone-else", ip(9), now).is_some());
}

#[test]
fn failures_fade_and_the_tables_stay_bounded() {
    let t = Throttle::default();
    let now = Instant::now();
    for _ in 0..=FREE_PER_USER {
        t.failed("admin", ip(1), now);
    }
    let much_later = now + FORGET;
    assert_eq!(t.closed("admin", ip(1), much_later), None);
    assert_eq!(t.failed("admin", ip(1), much_later), None, "counted anew");
    for i in 0..(MAX_KEYS as u32 + 100) {
        t.failed(&format!("n{i}"), IpAddr::from((i + 1).to_be_bytes()), now);
    }
    let inner = t.inner.lock().unwrap();
    assert!(inner.0.keys.len() <= MAX_KEYS && inner.1.keys.len() <= MAX_KEYS);
}
