//! Arbitrary bytes as every request message a client sends, through the bounds the gateway
//! applies before and after decoding: never a panic; a message taken is within every bound,
//! and encodes again within the size it was taken at.
#![no_main]

use cellgate_core::bounds::{Bounded, Limits, decode};
use cellgate_core::pb;
use libfuzzer_sys::fuzz_target;

fn check<M: Bounded>(data: &[u8], limits: &Limits) {
    if let Ok(m) = decode::<M>(data, limits) {
        assert!(m.check().is_ok());
        assert!(
            m.encoded_len() <= M::max_len(limits),
            "{} re-encodes larger",
            M::NAME
        );
    }
}

fuzz_target!(|data: &[u8]| {
    let Some((&sel, rest)) = data.split_first() else {
        return;
    };
    let limits = Limits {
        max_inline: u64::from(sel) * 64,
        max_program: u64::from(sel) * 256,
    };
    check::<pb::JobRequest>(rest, &limits);
    check::<pb::DoCommand>(rest, &limits);
    check::<pb::ProgramWrite>(rest, &limits);
    check::<pb::G05Open>(rest, &limits);
    check::<pb::G05Batch>(rest, &limits);
    check::<pb::PlcWrite>(rest, &limits);
    check::<pb::TagWrite>(rest, &limits);
    check::<pb::PlcTransfer>(rest, &limits);
    check::<pb::ProgramRelease>(rest, &limits);
    check::<pb::RequestOrigin>(rest, &limits);
    check::<pb::AuditRecord>(rest, &limits);
    check::<pb::PlcMessage>(rest, &limits);
});
