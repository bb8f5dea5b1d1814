//! Payloads on the bus: protobuf messages of `cellgate.v1`, tagged with their encoding
//! `application/protobuf` and the message's full name as schema, and the conversions from
//! the link's typed events to those messages.

use zenoh::bytes::Encoding;

use cellgate_core::fanuc::Protocol;
use cellgate_core::fanuc::host::LinkState;
use cellgate_core::fanuc::sat::{AlarmCause, BufferStatus, StatusData};
use cellgate_core::pb;
use cellgate_core::plc::tags::{Quality, TagValue};

/// A message of the bus contract, with the full name that goes in its encoding's schema.
pub trait BusMessage: prost::Message + Default {
    const SCHEMA: &'static str;
}

macro_rules! bus_messages {
    ($($t:ident),* $(,)?) => {
        $(impl BusMessage for pb::$t {
            const SCHEMA: &'static str = concat!("cellgate.v1.", stringify!($t));
        })*
    };
}

bus_messages!(
    JobRequest,
    JobAccepted,
    JobEvent,
    JobQueue,
    MachineStatus,
    DiImage,
    DoCommand,
    AlarmEvent,
    ErrorReply,
    ProgramInfo,
    ProgramWrite,
    PunchedProgram,
    G05Open,
    G05Opened,
    G05Batch,
    G05Status,
    PlcWords,
    PlcWrite,
    PlcWritten,
    PlcTransfer,
    PlcTransferred,
    PlcMessage,
    PlcMessageSent,
    TagValue,
    TagWrite,
    TagWritten,
    PlcStatus,
    PlcStation,
    ProgramRevision,
    ProgramRevisions,
    ProgramRelease,
    ProgramDiff,
    RequestOrigin,
    HistoryPage,
    Utilisation,
    AuditRecord,
    SimDi,
    SimAutostart,
    SimPunch,
    SimState,
    LibraryEvent,
    ReloadRequest,
    ReloadResult,
);

/// `application/protobuf;<schema>` for `M`.
pub fn encoding<M: BusMessage>() -> Encoding {
    Encoding::APPLICATION_PROTOBUF.with_schema(M::SCHEMA)
}

/// The schema an encoding names, if any (`application/protobuf;cellgate.v1.JobEvent` →
/// `cellgate.v1.JobEvent`). zenoh keeps the schema accessor internal; the text form is
/// `<mime>;<schema>`.
pub fn schema_of(encoding: &Encoding) -> Option<String> {
    encoding
        .to_string()
        .split_once(';')
        .map(|(_, schema)| schema.to_string())
}

/// An `ErrorReply`.
pub fn error_reply(code: pb::ErrorCode, message: impl Into<String>) -> pb::ErrorReply {
    pb::ErrorReply {
        code: code as i32,
        message: message.into(),
        sta: None,
    }
}

pub fn protocol(p: Protocol) -> pb::Protocol {
    match p {
        Protocol::A => pb::Protocol::A,
        Protocol::ExpansionA => pb::Protocol::ExpansionA,
        Protocol::B => pb::Protocol::B,
        Protocol::ExpansionB => pb::Protocol::ExpansionB,
    }
}

pub fn link_state(s: LinkState) -> pb::LinkState {
    match s {
        LinkState::Initialising => pb::LinkState::Connecting,
        LinkState::Ready => pb::LinkState::Idle,
        LinkState::Sending => pb::LinkState::Sending,
        LinkState::Receiving => pb::LinkState::Receiving,
        LinkState::LineDown => pb::LinkState::Down,
    }
}

/// Whether the link is initialised: the machine's liveliness token stands while it is.
pub fn link_up(s: LinkState) -> bool {
    matches!(
        s,
        LinkState::Ready | LinkState::Sending | LinkState::Receiving
    )
}

/// The decoded SAT (§4.4.2) as the contract carries it.
pub fn sat(s: &StatusData) -> pb::Sat {
    pb::Sat {
        remote: s.remote,
        buffer_status: s.status.map_or(pb::BufferStatus::Unknown, |b| match b {
            BufferStatus::NotReady => pb::BufferStatus::NotReady,
            BufferStatus::Reset => pb::BufferStatus::Reset,
            BufferStatus::Operating => pb::BufferStatus::Operating,
            BufferStatus::Alarm => pb::BufferStatus::Alarm,
            BufferStatus::OpenLine => pb::BufferStatus::OpenLine,
            BufferStatus::Other(_) => pb::BufferStatus::Other,
        }) as i32,
        buffer_status_digit: s.status.map(|b| u32::from(b.digit())),
        alarm_cause: s.alarm_cause.map_or(pb::AlarmCause::Unknown, |c| match c {
            AlarmCause::NcAlarm => pb::AlarmCause::NcAlarm,
            AlarmCause::ChecksumRetryOver => pb::AlarmCause::ChecksumRetryOver,
            AlarmCause::CommandError => pb::AlarmCause::CommandError,
            AlarmCause::OverrunRetryOver => pb::AlarmCause::OverrunRetryOver,
            AlarmCause::Other(_) => pb::AlarmCause::Other,
        }) as i32,
        alarm_cause_digit: s.alarm_cause.map(|c| u32::from(c.digit())),
        bytes_buffered: s.buffered.map(u32::from),
        params: s.params.map(|p| pb::RemoteBufferParams {
            nb: u32::from(p.nb),
            no: u32::from(p.no),
            ne: u32::from(p.ne),
            tp: u32::from(p.tp),
            to: u32::from(p.to),
            ti: u32::from(p.ti),
            tx: u32::from(p.tx),
            tw: u32::from(p.tw),
        }),
        packet_n: s.packet_n.map(u32::from),
    }
}

/// A G05 stream's status as published.
pub fn g05_status(s: &crate::link::g05::StreamStatus) -> pb::G05Status {
    use cellgate_core::fanuc::g05::stream::{EndReason, StreamState};
    let f = &s.figures;
    let state = match f.state {
        StreamState::Priming => pb::G05State::Priming,
        StreamState::Streaming => pb::G05State::Streaming,
        StreamState::Ending => pb::G05State::Ending,
        StreamState::Completed => pb::G05State::Completed,
        StreamState::Failed => pb::G05State::Failed,
    };
    let end_reason = match f.end_reason {
        None => pb::G05EndReason::Unspecified,
        Some(EndReason::Producer) => pb::G05EndReason::Producer,
        Some(EndReason::Cancelled) => pb::G05EndReason::Cancelled,
        Some(EndReason::ProducerLost) => pb::G05EndReason::ProducerLost,
        Some(EndReason::ProducerIdle) => pb::G05EndReason::ProducerIdle,
        Some(EndReason::NoBatch) => pb::G05EndReason::NoBatch,
    };
    pb::G05Status {
        stream_id: s.stream.clone(),
        machine: s.machine.clone(),
        state: state as i32,
        credits: f.credits,
        received: f.received,
        on_line: f.on_line,
        cnc_buffer: f.cnc_buffer,
        underruns: f.underruns,
        gaps: f.gaps,
        repeats: f.repeats,
        refused: f.refused,
        next_seq: f.next_seq,
        last_error: f.last_error.clone().unwrap_or_default(),
        end_reason: end_reason as i32,
        unix_ms: pb::now_ms(),
    }
}

/// A tag's value as a message.
pub(crate) fn tag_message(plc: &str, v: &TagValue) -> pb::TagValue {
    pb::TagValue {
        plc: plc.to_string(),
        name: v.name.clone(),
        value: v.value,
        raw: v.raw,
        unix_ms: v.time.map(pb::unix_ms),
        quality: match v.quality {
            Quality::Good => pb::TagQuality::Good,
            Quality::Stale => pb::TagQuality::Stale,
            Quality::StationDown => pb::TagQuality::StationDown,
        } as i32,
        writable: v.writable,
    }
}

/// A put whose encoding names another message than the key takes: refused with a word, never
/// read as the key's message or passed over in silence. A put that names none is read as the
/// key's message (as the bindings send one by default).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "{key}: a put here carries a {expected} (encoding application/protobuf;{expected}, or \
     none said), not {found}: it was not read"
)]
pub(crate) struct WrongEncoding {
    pub(crate) key: String,
    pub(crate) found: String,
    pub(crate) expected: &'static str,
}

#[cfg(test)]
mod tests;
