use super::*;
use crate::fanuc::packet::decode_data_packet;

fn program(bytes: &[u8]) -> Program {
    let mut p = Program::new();
    p.push(bytes, None).unwrap();
    p
}

fn numbers(run: &mut PacketRun, p: &mut Program, now: Instant) -> Vec<u8> {
    let mut v = Vec::new();
    while let Some(out) = run.next(now, Some(p), Duration::from_secs(5)) {
        v.push(out.no);
    }
    v
}

#[test]
fn numbering_cycles_and_ends_with_ff() {
    let now = Instant::now();
    let mut data = vec![b'X'; 256 * 11];
    data.push(b'%');
    let mut p = program(&data);
    let mut run = PacketRun::new(1, now);
    assert_eq!(
        numbers(&mut run, &mut p, now),
        [
            0x30, 0x31, 0x32, 0x33, 0x34, 0x35, 0x36, 0x37, 0x38, 0x39, 0x30, 0xFF
        ]
    );
    assert_eq!(run.outcome, RunOutcome::Delivered);
    assert_eq!(run.history.len(), HISTORY);
}

#[test]
fn lone_packet_is_ff_and_padded() {
    let now = Instant::now();
    let mut p = program(b"%\nO1\n%");
    let mut run = PacketRun::new(2, now);
    let out = run.next(now, Some(&mut p), Duration::from_secs(5)).unwrap();
    assert_eq!(out.program, b"%\nO1\n%");
    let pk = decode_data_packet(&out.bytes, 2).unwrap();
    assert_eq!(pk.no, 0xFF);
    assert_eq!(&pk.data[..6], b"%\nO1\n%");
    assert!(pk.data[6..].iter().all(|&b| b == PAD));
    // NAK 0 and NAK 30h both name it.
    run.on_monitor(Monitor::Retransmit(0)).unwrap();
    assert_eq!(
        run.next(now, Some(&mut p), Duration::ZERO).unwrap().bytes,
        out.bytes
    );
    run.on_monitor(Monitor::Retransmit(0x30)).unwrap();
    assert_eq!(
        run.next(now, Some(&mut p), Duration::ZERO).unwrap().bytes,
        out.bytes
    );
    assert_eq!(
        run.on_monitor(Monitor::Retransmit(0x31)),
        Err(UnknownPacket(0x31))
    );
}
