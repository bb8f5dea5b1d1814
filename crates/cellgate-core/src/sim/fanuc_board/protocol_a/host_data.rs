//! What the simulated board does with the host's data: SDO's output image (§4.4.2 5), SET's
//! parameters checked against their ranges (§4.5), and DAT's program bytes converted and
//! stored in the CNC's buffer (§4.4.1).

use std::time::Instant;

use super::{ProtocolA, checked, parse_image};
use crate::fanuc::CodeSystem;
use crate::fanuc::alarm::CncAlarm;
use crate::fanuc::code::with_even_parity;
use crate::fanuc::message::Message;
use crate::fanuc::sat::{AlarmCause, Params, StatusData, StatusDataError, effective_packet_n};
use crate::sim::cnc::{Cnc, Push};
use crate::sim::fanuc_board::{BoardEvent, Outbox};

impl ProtocolA {
    pub(super) fn apply_sdo(
        &mut self,
        now: Instant,
        msg: &Message,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) -> bool {
        match parse_image(&msg.data) {
            Some(image) => {
                cnc.set_do(image);
                out.event(BoardEvent::DoChanged(image));
                true
            }
            None => {
                let detail = format!(
                    "SDO data part {:?} is not two hex digits (§4.4.2 5)",
                    String::from_utf8_lossy(&msg.data)
                );
                self.command_error(now, CncAlarm::Sr0948BadCommand, detail, cnc, out);
                false
            }
        }
    }

    /// SET (§4.4.2 2, §4.5; protocol notes 5): an empty data part changes nothing; each
    /// field outside its range is ignored; n outside {0, 1, 2, 4} means 0.
    pub(super) fn apply_set(
        &mut self,
        data: &[u8],
        out: &mut Outbox,
    ) -> Result<(), StatusDataError> {
        if data.is_empty() {
            return Ok(());
        }
        let set = StatusData::decode(data)?;
        let before = (self.params, self.packet_n, self.conversion);
        if let Some(remote) = set.remote {
            self.remote = remote;
        }
        if let Some(p) = set.params {
            self.params = self.checked_params(p, out);
        }
        if let Some(unit) = set.boring_unit {
            self.boring_unit = unit;
        }
        if let Some(conversion) = set.conversion {
            self.conversion = conversion;
        }
        if let Some(n) = set.packet_n {
            let mut effective = effective_packet_n(n);
            if effective != n {
                out.event(BoardEvent::ProtocolError {
                    detail: format!("SET n = {n} is not 0, 1, 2 or 4: taken as 0 (§5.2 note)"),
                });
            }
            if effective != 0 && !self.expansion {
                out.event(BoardEvent::ProtocolError {
                    detail: format!(
                        "SET n = {n}: this board speaks Protocol A only (Expansion A needs RS-422, §2.2); n stays 0"
                    ),
                });
                effective = 0;
            }
            self.packet_n = effective;
        }
        if (self.params, self.packet_n, self.conversion) != before {
            out.event(BoardEvent::ParamsChanged {
                params: self.params,
                packet_n: self.packet_n,
                conversion: self.conversion,
            });
        }
        Ok(())
    }

    pub(super) fn checked_params(&self, new: Params, out: &mut Outbox) -> Params {
        let cur = self.params;
        let mut p = cur;
        p.no = checked("No", new.no, (2, 2000), cur.no, out);
        p.nb = checked("Nb", new.nb, (p.no.saturating_add(1), 4000), cur.nb, out);
        p.ne = checked("Ne", new.ne, (0, 100), cur.ne, out);
        p.tp = checked("Tp", new.tp, (1, 99), cur.tp, out);
        p.to = checked("To", new.to, (1, 999), cur.to, out);
        p.ti = if new.ti % 2 == 0 {
            checked("Ti", new.ti, (0, 10), cur.ti, out)
        } else {
            checked("Ti (2 ms steps)", new.ti, (0, 0), cur.ti, out)
        };
        p.tx = checked("Tx", new.tx, (0, 100), cur.tx, out);
        p.tw = checked("Tw", new.tw, (0, p.tp), cur.tw.min(p.tp), out);
        p
    }

    /// The SET code conversion of bytes 45–48 (§4.4.2 1 note). With the ISO code the match
    /// ignores the parity bit and the replacement carries even parity.
    pub(super) fn convert(&self, data: &mut [u8]) {
        let (from, to) = self.conversion;
        if from == 0 && to == 0 {
            return;
        }
        match self.framing.code {
            CodeSystem::Ascii => data
                .iter_mut()
                .filter(|b| **b == from)
                .for_each(|b| *b = to),
            CodeSystem::Iso => {
                let to = with_even_parity(to);
                data.iter_mut()
                    .filter(|b| **b & 0x7F == from & 0x7F)
                    .for_each(|b| *b = to);
            }
        }
    }

    /// NC data into the buffer; false when it overflowed (a line error was raised).
    pub(super) fn store(
        &mut self,
        now: Instant,
        mut data: Vec<u8>,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) -> bool {
        self.convert(&mut data);
        match cnc.push_data(now, &data) {
            Push::Stored(bytes) => out.event(BoardEvent::DataReceived {
                bytes,
                buffered: cnc.buffered(),
            }),
            Push::Ignored(bytes) => out.event(BoardEvent::DataIgnored { bytes }),
            Push::Overflow { len, free } => {
                let detail = format!(
                    "buffer full: {len} bytes of NC data with {free} bytes free; the host ignored the stop request (§4.6 1 (5))"
                );
                self.line_error(
                    now,
                    Some(CncAlarm::Sr0856BufferOverflow),
                    AlarmCause::OverrunRetryOver,
                    detail,
                    cnc,
                    out,
                );
                return false;
            }
        }
        true
    }
}
