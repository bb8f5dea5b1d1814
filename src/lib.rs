//! cellgate: one gateway per manufacturing cell, putting the cell's FANUC remote-buffer links
//! and its Fuji MICREX-F PLC on the Zenoh bus.
//!
//! # Layout
//!
//! Bytes flow bottom-up; commands top-down.
//!
//! - [`transport`]: what carries a link's bytes: serial port, TCP device server, simulated line.
//! - [`fanuc`]: FANUC remote-buffer protocols (A, Expansion A, B, Expansion B), sans-IO: bytes
//!   and `now` go in; bytes to send, events and the next deadline come out. Also the tape
//!   codes (ISO, ASCII, EIA) of punched programs ([`fanuc::tape`]).
//! - [`link`]: the async driver that runs one engine over one transport, and the typed
//!   commands and events through which the rest of the gateway talks to a link.
//! - [`sim`]: simulated devices (a remote-buffer board with a CNC behind it) that speak the
//!   device side of the same protocols, for tests, CI and laptops.
//! - [`config`]: the cell file: serde types, defaults, and validation that reports every error.
//! - [`jobs`]: per-machine job queues, program sources and checks, the program library, and
//!   punched programs: split at EOR, named for the library, remote requests ([`jobs::punch`]).
//! - [`bus`]: the Zenoh session, the cell's key expressions, and the routes that serve each
//!   machine's link, its jobs, the programs it punches out and the program library on the
//!   bus ([`bus::serve`]).
//! - [`client`]: a client of the bus contract: the library side of `cellgate submit`,
//!   `status`, `watch`, `do`, `di`, `program` and `cancel`.
//! - [`gateway`]: the running gateway: opens the bus, announces the cell, serves its admin
//!   key, and stops cleanly when the shutdown future completes.
//! - [`telemetry`]: tracing subscriber and the optional OpenTelemetry export.
//! - [`pb`]: the protobuf messages of `proto/cellgate/v1`, the bus's public contract.

pub mod bus;
pub mod cell;
pub mod client;
pub mod codes;
pub mod config;
pub mod engine;
pub mod fanuc;
pub mod fuji;
pub mod gateway;
pub mod jobs;
pub mod link;
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
