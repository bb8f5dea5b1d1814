//! Feeds the punched-program assembler arbitrary punched bytes in arbitrary pieces. It must
//! never panic, never hold more than its limit, and every program it hands out must run from
//! `%` to `%` in 7-bit text.
#![no_main]

use cellgate_core::program::punch::PunchAssembler;
use libfuzzer_sys::fuzz_target;

const MAX: usize = 4096;

fuzz_target!(|data: &[u8]| {
    let mut assembler = PunchAssembler::new(MAX);
    let mut rest = data;
    while let Some((&cut, tail)) = rest.split_first() {
        let (piece, next) = tail.split_at(usize::from(cut).min(tail.len()));
        rest = next;
        for program in assembler.feed(piece).into_iter().flatten() {
            assert!(program.text.first() == Some(&b'%') && program.text.last() == Some(&b'%'));
            assert!(program.text.iter().all(|&b| b < 0x80));
        }
        assert!(assembler.pending() <= MAX);
    }
    let _ = assembler.finish();
});
