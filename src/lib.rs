//! cellgate: one gateway per manufacturing cell, putting the cell's FANUC remote-buffer links
//! and its Fuji MICREX-F PLC on the Zenoh bus.
//!
//! # Layout
//!
//! Bytes flow bottom-up; commands top-down.
//!
//! - [`engine`]: the sans-IO contract every protocol engine keeps ([`engine::Engine`]: bytes,
//!   line errors, modem lines, commands and `now` in; bytes, events and the next deadline
//!   out) and the line's plain data (framing, modem lines, line errors).
//! - [`fanuc`]: FANUC remote-buffer protocols (A, Expansion A, B, Expansion B), sans-IO: the
//!   codecs, the host engines, their contract ([`fanuc::host`]) and typed errors
//!   ([`fanuc::error`]); the tape codes of punched programs ([`fanuc::tape`]).
//! - [`fuji`]: the Fuji FFU120B command set and non-procedure modes, sans-IO: BCC, framing,
//!   commands, the host engine ([`fuji::master::Master`]).
//! - [`transport`]: what carries a link's bytes: serial port, TCP device server, simulated line.
//! - [`link`]: the async side: [`link::pump`] runs any engine over any transport in tokio
//!   time; [`link::driver`] is a FANUC link's task (program queue, streamed sources, typed
//!   commands and events).
//! - [`plc`]: the cell's PLCs: named tags (poll plan, decoding, publish on change, writes;
//!   sans-IO, [`plc::tags`]) and the PLC link task running the FFU120B master ([`plc::link`]).
//! - [`sim`]: simulated devices (a remote-buffer board with a CNC behind it, an FFU120B with a
//!   MICREX-F behind it) that speak the
//!   device side of the same protocols, for tests, CI and laptops.
//! - [`config`]: the cell file, one file per concern, with validation that reports every error.
//! - [`jobs`]: per-machine job queues, program sources and checks, the program library, and
//!   punched programs: split at EOR, named for the library, remote requests ([`jobs::punch`]).
//! - [`g05`]: G05 binary input streams (§9): a producer's blocks through a machine's link,
//!   with credits, priming and the CNC's estimated buffer ([`g05::stream`] holds the rules,
//!   sans-IO).
//! - [`bus`]: the Zenoh session, the cell's key expressions, and one route per kind (status,
//!   jobs, DI/DO, alarms, punched programs, the program library) ([`bus::serve`]); PLC memory,
//!   transfers, status and tags ([`bus::serve_plcs`]).
//! - [`codes`]: the one place where typed errors become bus error codes.
//! - [`cell`]: the cell's links, built from the cell file.
//! - [`gateway`]: the running gateway: opens the bus, announces the cell, serves it, and stops
//!   cleanly when the shutdown future completes.
//! - [`client`]: a client of the bus contract: the library side of `cellgate submit`,
//!   `status`, `watch`, `do`, `di`, `program` and `cancel`.
//! - [`telemetry`]: tracing subscriber, the counters links and jobs keep ([`telemetry::metrics`]),
//!   and the optional OTLP export of spans and metrics and Prometheus endpoint.
//! - [`pb`]: the protobuf messages of `proto/cellgate/v1`, the bus's public contract.
//!
//! # Who imports whom
//!
//! - `engine` imports nothing of the crate. `fanuc` (and every protocol engine or codec) imports
//!   only `engine` and its own modules: no tokio, no sockets, nothing of `link` or
//!   `transport`, so it can be tested in plain time, fuzzed, and reused by the simulators.
//! - `transport` imports `engine` (the line's data) and tokio; `link` imports `engine`, the
//!   protocol engines and `transport`; `sim`'s device engines import `engine` and the
//!   codecs, its runners `link::pump` and `transport`.
//! - `jobs` imports `fanuc`, `link` and `pb`; `config` imports `engine`, `fanuc`, `fuji` (the
//!   module table), `jobs` and `telemetry`, never `bus` or `link`.
//! - `plc` imports `fuji`, `config`, `link::pump` and `transport`; `bus` uses it.
//! - `g05` imports `fanuc` (the block codec), `link`, `config` and `engine`; `bus` uses it.
//!   Its rules, `g05::stream`, are sans-IO like the engines: `fanuc` and `config` only.
//! - `bus` may import everything below it; only `cell`, `gateway` and `client` import `bus`.
//! - `codes` imports the error types it maps; every layer that builds a bus message uses it.
//! - `telemetry` imports nothing of the crate; `link`, `jobs` and `g05` count into
//!   [`telemetry::metrics`] and open their spans themselves.

pub mod bus;
pub mod cell;
pub mod client;
pub mod codes;
pub mod config;
pub mod engine;
pub mod fanuc;
pub mod fuji;
pub mod g05;
pub mod gateway;
pub mod jobs;
pub mod link;
pub mod plc;
pub mod sim;
pub mod telemetry;
pub mod transport;

/// Protobuf messages generated from `proto/cellgate/v1/*.proto` (package `cellgate.v1`).
/// The .proto files document every field; they are the contract clients build against.
#[allow(clippy::all, clippy::pedantic, missing_docs)]
pub mod pb {
    include!(concat!(env!("OUT_DIR"), "/cellgate.v1.rs"));

    #[cfg(test)]
    mod tests {
        use super::*;
        use prost::Message;

        #[test]
        fn job_request_round_trips_through_the_wire_format() {
            let request = JobRequest {
                program: Some(job_request::Program::Inline(b"%\nO0001\nG00X0\n%".to_vec())),
                name: "O0001".to_string(),
                priority: -3,
                append_eor: true,
                request_id: "r-1".to_string(),
                start_at: Some(BlockStart {
                    at: Some(block_start::At::SequenceNumber(1234)),
                    header_lines: 0,
                }),
                resume_after_restart: true,
                deadline_s: 30,
            };
            let bytes = request.encode_to_vec();
            let decoded = JobRequest::decode(bytes.as_slice()).unwrap();
            assert_eq!(decoded, request);
        }

        #[test]
        fn job_event_oneof_survives_decoding() {
            let event = JobEvent {
                job_id: "j1".to_string(),
                machine: "lathe1".to_string(),
                unix_ms: 1_700_000_000_000,
                kind: Some(job_event::Kind::Failed(job_event::Failed {
                    reason: "retry over".to_string(),
                    byte_offset: 512,
                    alarm_number: "SR0945".to_string(),
                    code: ErrorCode::LinkFailed as i32,
                    ..job_event::Failed::default()
                })),
            };
            let decoded = JobEvent::decode(event.encode_to_vec().as_slice()).unwrap();
            match decoded.kind {
                Some(job_event::Kind::Failed(f)) => {
                    assert_eq!(f.byte_offset, 512);
                    assert_eq!(f.alarm_number, "SR0945");
                    assert_eq!(f.code(), ErrorCode::LinkFailed);
                }
                other => panic!("decoded kind {other:?}"),
            }
        }

        #[test]
        fn garbage_is_a_decode_error_not_a_panic() {
            assert!(MachineStatus::decode(&[0xFF, 0xFF, 0xFF][..]).is_err());
        }
    }
}
