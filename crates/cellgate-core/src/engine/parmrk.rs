//! The kernel's parity marks (POSIX termios `PARMRK`): a serial port in that mode marks a
//! character received with a parity or framing error as `FF 00 c` and doubles a real `FF`,
//! so the line errors of §4.6 reach the engine in line order. Sans-IO: the serial transport
//! feeds what the kernel delivered and reads the decoded bytes and errors back.

use std::collections::VecDeque;

use super::LineError;

/// Decodes the kernel's PARMRK marks (POSIX termios): `FF FF` is a data `FF`, `FF 00 c` a
/// character `c` received with a parity or framing error (`FF 00 00` also a break). Bad
/// characters are not delivered; their errors are queued in line order.
#[derive(Debug, Default)]
pub struct MarkDecoder {
    raw: VecDeque<u8>,
    errors: VecDeque<LineError>,
}

impl MarkDecoder {
    /// Bytes held: an incomplete mark, or data not decoded yet.
    pub fn buffered(&self) -> usize {
        self.raw.len()
    }

    /// The oldest line error decoded and not taken yet.
    pub fn take_error(&mut self) -> Option<LineError> {
        self.errors.pop_front()
    }

    /// Bytes as the kernel delivered them.
    pub fn feed(&mut self, raw: &[u8]) {
        self.raw.extend(raw.iter().copied());
    }

    /// Decode into `out` as far as possible. A read never spans an error: decoding stops at a
    /// mark once `out` has bytes, so an error taken after a read lies before that read's bytes.
    /// An incomplete mark at the end waits for the next bytes. Returns the bytes written.
    pub fn decode(&mut self, out: &mut [u8]) -> usize {
        let mut n = 0;
        while n < out.len() {
            let Some(&b) = self.raw.front() else { break };
            if b != 0xFF {
                out[n] = b;
                self.raw.pop_front();
                n += 1;
                continue;
            }
            match (self.raw.get(1).copied(), self.raw.get(2).copied()) {
                (None, _) | (Some(0x00), None) => break,
                (Some(0xFF), _) => {
                    out[n] = 0xFF;
                    self.raw.drain(..2);
                    n += 1;
                }
                (Some(0x00), Some(c)) => {
                    if n > 0 {
                        break;
                    }
                    self.errors.push_back(if c == 0 {
                        LineError::Framing
                    } else {
                        LineError::Parity
                    });
                    self.raw.drain(..3);
                }
                // Not a mark (cannot come from the kernel in PARMRK mode): pass it on.
                (Some(_), _) => {
                    out[n] = 0xFF;
                    self.raw.pop_front();
                    n += 1;
                }
            }
        }
        n
    }

    /// At end of input, hand over an incomplete mark as data.
    /// Returns the bytes written.
    pub fn finish(&mut self, out: &mut [u8]) -> usize {
        let mut n = 0;
        while n < out.len() {
            let Some(b) = self.raw.pop_front() else { break };
            out[n] = b;
            n += 1;
        }
        n
    }
}

#[cfg(test)]
mod tests;
