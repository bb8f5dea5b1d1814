//! The FFU120B host engine under arbitrary replies, line errors and time: never panics, and
//! every request it took ends exactly once.
#![no_main]

use std::collections::HashSet;
use std::time::{Duration, Instant};

use cellgate_core::engine::{Engine, LineError};
use cellgate_core::fuji::command::{Module, Request};
use cellgate_core::fuji::master::{
    Master, MasterCommand, MasterEvent, MasterSettings, OperationMode,
};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let mode = match mode % 3 {
        0 => OperationMode::One,
        1 => OperationMode::Two,
        _ => OperationMode::Three,
    };
    let Ok(mut master) = Master::new(MasterSettings::new(mode)) else {
        return;
    };
    let mut now = Instant::now();
    let mut open = HashSet::new();
    let mut ended = HashSet::new();
    let station = if matches!(mode, OperationMode::One) {
        0
    } else {
        1
    };
    for (i, op) in rest.chunks(5).enumerate() {
        match op[0] % 5 {
            0 => {
                let id = i as u64;
                let request = Request::read_words(Module::D, u16::from(op[0]), 1 + op.len());
                if let Ok(request) = request {
                    master.handle_command(
                        now,
                        MasterCommand::Request {
                            id,
                            station,
                            request,
                        },
                    );
                    open.insert(id);
                }
            }
            1 => master.handle_input(now, &op[1..]),
            2 => master.handle_line_error(now, LineError::Parity),
            3 => {
                now += Duration::from_millis(u64::from(op[0]) * 40);
                master.handle_timeout(now);
            }
            _ => while master.poll_transmit(now).is_some() {},
        }
        while let Some(event) = master.poll_event() {
            if let MasterEvent::Done { id, .. } = event {
                assert!(open.contains(&id), "request {id} ended but was never taken");
                assert!(ended.insert(id), "request {id} ended twice");
            }
        }
        if let Some(t) = master.poll_timeout() {
            assert!(t >= now - Duration::from_secs(1));
        }
    }
});
