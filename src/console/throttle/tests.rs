use super::*;

fn ip(last: u8) -> IpAddr {
    IpAddr::from([127, 0, 0, last])
}

#[test]
fn a_few_failures_are_free_then_the_wait_doubles_up_to_its_bound() {
    let t = Throttle::default();
    let now = Instant::now();
    for _ in 0..FREE_PER_USER {
        assert_eq!(t.failed("admin", ip(1), None, now), None);
    }
    assert_eq!(t.closed("admin", ip(1), None, now), None);
    assert_eq!(
        t.failed("admin", ip(1), None, now),
        Some(Duration::from_secs(1))
    );
    assert_eq!(
        t.failed("admin", ip(1), None, now),
        Some(Duration::from_secs(2))
    );
    assert_eq!(
        t.failed("admin", ip(1), None, now),
        Some(Duration::from_secs(4))
    );
    assert_eq!(
        t.closed("admin", ip(1), None, now),
        Some(Duration::from_secs(4))
    );
    // Another address is closed for that name too: the name is what is guessed at.
    assert_eq!(
        t.closed("admin", ip(2), None, now),
        Some(Duration::from_secs(4))
    );
    // Another name from that address is not (the address has failures to spare).
    assert_eq!(t.closed("olga", ip(1), None, now), None);
    for _ in 0..20 {
        t.failed("admin", ip(1), None, now);
    }
    assert_eq!(t.closed("admin", ip(3), None, now), Some(MAX_WAIT));
}

#[test]
fn once_the_wait_has_passed_a_login_is_looked_at_again() {
    let t = Throttle::default();
    let now = Instant::now();
    for _ in 0..=FREE_PER_USER {
        t.failed("admin", ip(1), None, now);
    }
    assert!(t.closed("admin", ip(1), None, now).is_some());
    let later = now + Duration::from_millis(1001);
    assert_eq!(t.closed("admin", ip(1), None, later), None);
    // A success forgets the name's failures; the next failure is free again.
    t.trust("admin", None, later);
    assert_eq!(t.failed("admin", ip(1), None, later), None);
}

#[test]
fn an_address_that_guesses_many_names_is_closed_for_all_of_them() {
    let t = Throttle::default();
    let now = Instant::now();
    for i in 0..FREE_PER_ADDRESS {
        assert_eq!(t.failed(&format!("user{i}"), ip(9), None, now), None);
    }
    assert_eq!(t.failed("another", ip(9), None, now), Some(FIRST_WAIT));
    assert!(t.closed("someone-else", ip(9), None, now).is_some());
    assert_eq!(t.closed("someone-else", ip(8), None, now), None);
    // A success of one name does not open the address.
    t.trust("another", None, now);
    assert!(t.closed("someone-else", ip(9), None, now).is_some());
}

#[test]
fn failures_fade_and_the_tables_stay_bounded() {
    let t = Throttle::default();
    let now = Instant::now();
    for _ in 0..=FREE_PER_USER {
        t.failed("admin", ip(1), None, now);
    }
    let much_later = now + FORGET;
    assert_eq!(t.closed("admin", ip(1), None, much_later), None);
    assert_eq!(
        t.failed("admin", ip(1), None, much_later),
        None,
        "counted anew"
    );
    for i in 0..(MAX_KEYS as u32 + 100) {
        t.failed(
            &format!("n{i}"),
            IpAddr::from((i + 1).to_be_bytes()),
            None,
            now,
        );
    }
    let inner = t.inner.lock().unwrap();
    assert!(inner.users.keys.len() <= MAX_KEYS && inner.addrs.keys.len() <= MAX_KEYS);
}

#[test]
fn a_browser_that_logged_in_before_keeps_its_own_allowance_while_the_name_is_guessed() {
    let t = Throttle::default();
    let now = Instant::now();
    let device = t.trust("admin", None, now);
    assert!(!device.is_empty());
    // Someone elsewhere guesses admin's password until the name is closed for the longest.
    for _ in 0..40 {
        t.failed("admin", ip(66), None, now);
    }
    assert_eq!(t.closed("admin", ip(66), None, now), Some(MAX_WAIT));
    assert_eq!(t.closed("admin", ip(1), None, now), Some(MAX_WAIT));
    // The admin's own browser is not closed, from any address.
    assert_eq!(t.closed("admin", ip(1), Some(&device), now), None);
    assert_eq!(t.closed("admin", ip(66), Some(&device), now), None);
    // A device token is its user's alone, and a made-up one is no device.
    assert!(t.closed("admin", ip(1), Some("made-up"), now).is_some());
    let olgas = t.trust("olga", None, now);
    assert!(t.closed("admin", ip(1), Some(&olgas), now).is_some());
    // The device's own failures close the device alone, after as many free ones as a name's.
    for _ in 0..FREE_PER_DEVICE {
        assert_eq!(t.failed("admin", ip(1), Some(&device), now), None);
    }
    assert_eq!(
        t.failed("admin", ip(1), Some(&device), now),
        Some(FIRST_WAIT)
    );
    assert_eq!(
        t.closed("admin", ip(1), Some(&device), now),
        Some(FIRST_WAIT)
    );
    // Once it passed, the login on the device is taken; the device gets a new token and
    // the old one is no device any more; the guessed name stays closed for the others.
    let later = now + FIRST_WAIT;
    let renewed = t.trust("admin", Some(&device), later);
    assert_ne!(renewed, device);
    assert_eq!(t.closed("admin", ip(1), Some(&renewed), later), None);
    assert!(t.closed("admin", ip(1), Some(&device), later).is_some());
    assert!(t.closed("admin", ip(66), None, later).is_some());
}
