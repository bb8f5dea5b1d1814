//! The TCP transport's in-flight window under arbitrary writes and waits: what is unsent never
//! exceeds the window by more than the last write, and a full window opens by itself.
#![no_main]

use std::time::{Duration, Instant};

use cellgate_core::engine::line::{LineSettings, Parity, StopBits};
use cellgate_core::engine::pacer::Pacer;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&a, rest)) = data.split_first() else {
        return;
    };
    let Some((&b, ops)) = rest.split_first() else {
        return;
    };
    let mut line = LineSettings::with_baud(300 + u32::from(a) * 400);
    line.parity = if b & 1 == 0 {
        Parity::None
    } else {
        Parity::Even
    };
    line.stop_bits = if b & 2 == 0 {
        StopBits::One
    } else {
        StopBits::Two
    };
    let window = 1 + usize::from(b) * 8;
    let mut pacer = Pacer::new(line, window);
    let mut now = Instant::now();
    let mut last_write = 0usize;
    for op in ops.chunks(2) {
        let [kind, arg] = [op[0], *op.get(1).unwrap_or(&0)];
        if kind & 1 == 0 {
            now += Duration::from_micros(u64::from(arg) * 97);
        } else {
            let room = pacer.writable(now);
            let n = usize::from(arg).min(room);
            if n > 0 {
                let _ = pacer.wrote(n, now);
                last_write = n;
            }
        }
        assert!(
            pacer.unsent(now) <= (window + last_write) as u64,
            "unsent {} > window {window} + {last_write}",
            pacer.unsent(now)
        );
        if pacer.writable(now) == 0 {
            let at = pacer.next_writable_at(now);
            assert!(at > now || pacer.writable(at) > 0);
            assert!(pacer.writable(at) > 0, "the window does not open by {at:?}");
        }
    }
});
