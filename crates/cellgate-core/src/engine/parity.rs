//! Parity made and checked by the gateway: a line of 7 data bits with a parity bit behind a
//! device server that passes whole 8-bit frames (set to 8N1 where the line runs 7E1), so that
//! each character's parity bit is bit 7 of its byte on the TCP stream (FFU120B §4-3 items 5–6,
//! §5-6; FFU120B notes 10). The gateway then writes the parity bit into what it sends, and a
//! received byte whose bit 7 is not its parity bit is a character with a parity error.
//!
//! Sans-IO: a transport encodes what it writes with [`ParityCodec::encode`], feeds what it
//! reads to a [`ParityDecoder`] and reads the 7-bit characters and errors back, in line order
//! (as the kernel's parity marks are read, [`super::parmrk`]).

use std::collections::VecDeque;

use serde::{Deserialize, Serialize};

use super::{LineError, line::Parity};

/// Where a line's parity bit is made and checked, for a link of 7 data bits with parity
/// (`parity_by` of a transport table).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum ParityBy {
    /// The UART on the line: the serial port's, or the device server's serial side, set to
    /// the line's framing. The gateway reads and writes 7-bit characters; parity errors come
    /// from the driver (a serial port's) or are the device server's to handle.
    #[default]
    Port,
    /// The gateway: the port passes whole 8-bit frames, parity in bit 7, and the gateway
    /// sets and checks it.
    Gateway,
}

impl ParityBy {
    /// The name the cell file uses.
    pub fn name(self) -> &'static str {
        match self {
            ParityBy::Port => "port",
            ParityBy::Gateway => "gateway",
        }
    }
}

/// Even or odd parity over the seven data bits, carried in bit 7.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ParityCodec {
    odd: bool,
}

impl ParityCodec {
    /// The codec of `parity`; `None` for a line without parity.
    pub fn new(parity: Parity) -> Option<Self> {
        match parity {
            Parity::None => None,
            Parity::Even => Some(ParityCodec { odd: false }),
            Parity::Odd => Some(ParityCodec { odd: true }),
        }
    }

    /// The 7-bit character `c` (bit 7 ignored) with its parity bit in bit 7: even parity
    /// makes the number of ones in the eight bits even, odd parity odd.
    pub fn with_parity(self, c: u8) -> u8 {
        let c = c & 0x7F;
        let ones_odd = c.count_ones() % 2 == 1;
        if ones_odd != self.odd { c | 0x80 } else { c }
    }

    /// Every byte of `bytes` with its parity bit, appended to `out`.
    pub fn encode(self, bytes: &[u8], out: &mut Vec<u8>) {
        out.extend(bytes.iter().map(|&c| self.with_parity(c)));
    }

    /// The 7-bit character of a received byte, or a parity error when bit 7 is not its
    /// parity bit.
    pub fn check(self, b: u8) -> Result<u8, LineError> {
        if self.with_parity(b) == b {
            Ok(b & 0x7F)
        } else {
            Err(LineError::Parity)
        }
    }
}

/// Received bytes checked by a [`ParityCodec`]: good characters are delivered without their
/// parity bit, a bad one is not delivered and its error is queued. A read never spans an
/// error: decoding stops at a bad character once `out` has bytes, so an error taken after a
/// read lies before that read's bytes.
#[derive(Debug)]
pub struct ParityDecoder {
    codec: ParityCodec,
    raw: VecDeque<u8>,
    errors: VecDeque<LineError>,
}

impl ParityDecoder {
    /// A decoder that checks with `codec`.
    pub fn new(codec: ParityCodec) -> Self {
        ParityDecoder {
            codec,
            raw: VecDeque::new(),
            errors: VecDeque::new(),
        }
    }

    /// Bytes held, not decoded yet.
    pub fn buffered(&self) -> usize {
        self.raw.len()
    }

    /// Bytes as the port delivered them.
    pub fn feed(&mut self, raw: &[u8]) {
        self.raw.extend(raw.iter().copied());
    }

    /// The oldest parity error decoded and not taken yet.
    pub fn take_error(&mut self) -> Option<LineError> {
        self.errors.pop_front()
    }

    /// Decodes into `out` as far as possible; returns the bytes written.
    pub fn decode(&mut self, out: &mut [u8]) -> usize {
        let mut n = 0;
        while n < out.len() {
            let Some(&b) = self.raw.front() else { break };
            match self.codec.check(b) {
                Ok(c) => {
                    out[n] = c;
                    n += 1;
                }
                Err(_) if n > 0 => break,
                Err(e) => self.errors.push_back(e),
            }
            self.raw.pop_front();
        }
        n
    }
}

#[cfg(test)]
mod tests;
