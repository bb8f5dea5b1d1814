//! The PARMRK mark decoder fed arbitrary kernel output in arbitrary pieces: never panics,
//! never hands out more bytes than came in, and holds at most an incomplete mark at the end.
#![no_main]

use cellgate_core::engine::parmrk::MarkDecoder;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut d = MarkDecoder::default();
    let mut out = [0u8; 64];
    let mut delivered = 0usize;
    let mut errors = 0usize;
    for piece in data.chunks(7) {
        d.feed(piece);
        loop {
            let n = d.decode(&mut out);
            delivered += n;
            while d.take_error().is_some() {
                errors += 1;
            }
            if n == 0 {
                break;
            }
        }
    }
    assert!(
        d.buffered() <= 2,
        "{} bytes held after decoding",
        d.buffered()
    );
    delivered += d.finish(&mut out);
    assert!(delivered + 3 * errors <= data.len());
});
