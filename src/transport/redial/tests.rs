use super::*;

#[tokio::test(start_paused = true)]
async fn doubles_to_the_bound_and_restarts_after_a_lasting_connection() {
    let ms = Duration::from_millis;
    let mut b = Backoff::new(ms(100), ms(500));
    let waits: Vec<_> = (0..5).map(|_| b.take_wait()).collect();
    assert_eq!(waits, [ms(100), ms(200), ms(400), ms(500), ms(500)]);
    assert_eq!(b.failed(), 1);
    assert_eq!(b.failed(), 2);
    assert_eq!(b.up(), 2);
    // Dropped at once: the backoff keeps its size.
    b.lost();
    assert_eq!(b.peek(), ms(500));
    b.up();
    tokio::time::advance(ms(600)).await;
    b.lost();
    assert_eq!(b.peek(), ms(100));
}
