//! Feeds the Protocol B / Expansion B host engine an arbitrary script of line input,
//! commands, line errors, modem changes and event taking. It must never panic, its buffers
//! must stay bounded, and after a DC3 it must hand out no more program bytes than one piece
//! until the next DC1 (§6.3).
#![no_main]

use std::time::Instant;

use bytes::Bytes;
use cellgate_core::engine::Engine;
use cellgate_core::engine::{LineError, ModemIn};
use cellgate_core::fanuc::CodeSystem;
use cellgate_core::fanuc::host::{EngineCommand, HostEngine};
use cellgate_core::fanuc::protocol_b::{ProtocolBConfig, ProtocolBHost};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| run(data));

fn run(data: &[u8]) {
    let Some((&setup, mut script)) = data.split_first() else {
        return;
    };
    let code = if setup & 1 == 0 {
        CodeSystem::Ascii
    } else {
        CodeSystem::Iso
    };
    let cfg = ProtocolBConfig::new(code, setup & 2 != 0, setup & 4 != 0);
    let max = cfg.max_buffer;
    let piece = cfg.tx_piece as u64;
    let now = Instant::now();
    let Ok(mut host) = ProtocolBHost::new(cfg, now) else {
        return;
    };
    while let Some((&op, rest)) = script.split_first() {
        let len = usize::from(rest.first().copied().unwrap_or(0));
        let arg = rest.get(1..).unwrap_or(&[]);
        let arg = &arg[..len.min(arg.len())];
        script = rest.get(1 + arg.len()..).unwrap_or(&[]);
        match op % 7 {
            0 | 1 => host.handle_input(now, arg),
            2 => {
                let cmd = match arg.first().copied().unwrap_or(0) % 6 {
                    0 => EngineCommand::StartProgram { total: None },
                    // A driver gives no more than the engine wants.
                    1 | 2 => EngineCommand::ProgramData(Bytes::copy_from_slice(
                        &arg[..arg.len().min(host.data_wanted())],
                    )),
                    3 => EngineCommand::ProgramEnd,
                    4 => EngineCommand::Cancel,
                    _ => EngineCommand::ReadDi,
                };
                host.handle_command(now, cmd);
            }
            3 => {
                let e = [LineError::Parity, LineError::Framing, LineError::Overrun][len % 3];
                host.handle_line_error(now, e);
            }
            4 => host.handle_modem(
                now,
                ModemIn {
                    dr: len & 1 == 0,
                    cs: len & 2 == 0,
                    cd: len & 4 == 0,
                },
            ),
            5 => {
                for _ in 0..len % 8 {
                    let _ = host.poll_transmit(now);
                }
            }
            _ => {
                for _ in 0..len % 4 {
                    let _ = host.poll_event();
                }
            }
        }
        let _ = host.data_wanted();
        if !host.flowing() {
            // Stopped by DC3 (or never started): nothing more than what was handed out.
            let before = host.sent_since_dc3();
            while host.poll_transmit(now).is_some() {}
            assert_eq!(host.sent_since_dc3(), before, "sent after DC3");
        }
        assert!(host.sent_since_dc3() <= u64::MAX - piece);
        assert!(
            host.punch_held() <= max,
            "punched bytes held: {}",
            host.punch_held()
        );
        assert!(
            host.program_buffered() <= max,
            "{}",
            host.program_buffered()
        );
    }
}
