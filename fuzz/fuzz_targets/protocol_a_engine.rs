//! Feeds the Protocol A / Expansion A host engine an arbitrary script of line input, time
//! steps, commands, line errors and modem changes. It must never panic, its buffers must stay
//! bounded, and a deadline it has acted on must not stay due (a driver would spin).
#![no_main]

use std::time::{Duration, Instant};

use bytes::Bytes;
use cellgate_core::engine::Engine;
use cellgate_core::engine::{LineError, ModemIn};
use cellgate_core::fanuc::host::{EngineCommand, HostEngine};
use cellgate_core::fanuc::message::{Framing, MAX_FRAME};
use cellgate_core::fanuc::protocol_a::{ProtocolAConfig, ProtocolAHost};
use cellgate_core::fanuc::{CodeSystem, EndCode};
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
    let end = if setup & 2 == 0 {
        EndCode::Cr
    } else {
        EndCode::Etx
    };
    let packet_n = [0, 1, 2, 4][usize::from((setup >> 2) & 3)];
    let cfg = ProtocolAConfig {
        framing: Framing::new(code, end),
        packet_n,
        max_buffer: 8192,
        ..Default::default()
    };
    let mut now = Instant::now();
    let Ok(mut host) = ProtocolAHost::new(cfg, now) else {
        return;
    };
    while let Some((&op, rest)) = script.split_first() {
        let len = usize::from(rest.first().copied().unwrap_or(0));
        let arg = rest.get(1..).unwrap_or(&[]);
        let arg = &arg[..len.min(arg.len())];
        script = rest.get(1 + arg.len()..).unwrap_or(&[]);
        match op % 8 {
            0 | 1 => host.handle_input(now, arg),
            2 => now += Duration::from_millis(len as u64 * 100),
            3 => {
                let cmd = match arg.first().copied().unwrap_or(0) % 7 {
                    0 => EngineCommand::StartProgram { total: None },
                    1 | 2 => EngineCommand::ProgramData(Bytes::copy_from_slice(arg)),
                    3 => EngineCommand::ProgramEnd,
                    4 => EngineCommand::Cancel,
                    5 => EngineCommand::SetDo(len as u8),
                    _ => EngineCommand::ReadDi,
                };
                host.handle_command(now, cmd);
            }
            4 => {
                let e = [LineError::Parity, LineError::Framing, LineError::Overrun][len % 3];
                host.handle_line_error(now, e);
            }
            5 => host.handle_modem(
                now,
                ModemIn {
                    dr: len & 1 == 0,
                    cs: len & 2 == 0,
                    cd: true,
                },
            ),
            6 => {
                for _ in 0..len % 8 {
                    let _ = host.poll_transmit(now);
                }
            }
            _ => {
                let _ = host.data_wanted();
            }
        }
        if let Some(t) = host.poll_timeout()
            && t <= now
        {
            host.handle_timeout(now);
            while host.poll_transmit(now).is_some() {}
            assert!(
                host.poll_timeout().is_none_or(|t| t > now),
                "deadline stays due"
            );
        }
        while host.poll_event().is_some() {}
        let u = host.buffer_usage();
        assert!(u.rx <= MAX_FRAME + 5, "{u:?}");
        assert!(u.tx <= 4 * MAX_FRAME, "{u:?}");
        assert!(u.program <= 8192 + 256, "{u:?}");
        assert!(u.packets <= 2 * 10 * 1028, "{u:?}");
    }
}
