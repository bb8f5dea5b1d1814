//! Arbitrary bytes as every message of the bus contract, and arbitrary strings as keys of a
//! cell: decoding never panics, a decoded message encodes again, and a key that parses names
//! a chunk of what was given.
#![no_main]

use cellgate_core::keys::{CellKey, CellKeys, cell_of_admin_key, is_plain_chunk};
use cellgate_core::pb;
use libfuzzer_sys::fuzz_target;
use prost::Message;

fn round_trip<M: Message + Default>(data: &[u8]) {
    if let Ok(m) = M::decode(data) {
        let again = M::decode(m.encode_to_vec().as_slice()).expect("re-encoded message decodes");
        assert_eq!(again.encode_to_vec(), m.encode_to_vec());
    }
}

fuzz_target!(|data: &[u8]| {
    round_trip::<pb::JobRequest>(data);
    round_trip::<pb::JobAccepted>(data);
    round_trip::<pb::JobEvent>(data);
    round_trip::<pb::JobQueue>(data);
    round_trip::<pb::MachineStatus>(data);
    round_trip::<pb::DoCommand>(data);
    round_trip::<pb::DiImage>(data);
    round_trip::<pb::AlarmEvent>(data);
    round_trip::<pb::ErrorReply>(data);
    round_trip::<pb::ProgramInfo>(data);
    round_trip::<pb::ProgramWrite>(data);
    round_trip::<pb::PunchedProgram>(data);
    let text = String::from_utf8_lossy(data);
    let keys = CellKeys::new("cellgate", "c1").expect("a valid root");
    let key = format!("cellgate/c1/{text}");
    match keys.parse(&key) {
        Some(CellKey::Machine { machine }) | Some(CellKey::Leaf { machine, .. }) => {
            assert!(text.contains(machine));
        }
        Some(CellKey::JobEvents { machine, job }) => {
            assert!(text.contains(machine) && text.contains(job));
        }
        Some(CellKey::Program { name }) => assert!(text.contains(name)),
        _ => {}
    }
    let _ = is_plain_chunk(&text);
    if let Some(cell) = cell_of_admin_key("cellgate", &text) {
        assert!(is_plain_chunk(cell));
    }
    let _ = CellKeys::new(&text, "c1");
});
