//! A port that passes whole 8-bit frames of a 7-bit line, the parity bit in bit 7: the
//! gateway makes and checks the parity itself (`parity_by = "gateway"`, FFU120B §4-3 items
//! 5–6, §5-6; FFU120B notes 10).
//!
//! [`GatewayParity`] wraps another [`Transport`] (a device server set to 8N1 where the line
//! runs 7E1, or a serial port opened that way): every byte written gets its parity bit, and a
//! byte read whose bit 7 is not its parity bit is a character received with a parity error,
//! not delivered and reported through [`Transport::take_line_error`] in line order, as a
//! serial port's driver reports one (the codec is [`cellgate_core::engine::parity`]).

use std::collections::VecDeque;
use std::io;
use std::pin::Pin;
use std::task::{Context, Poll};

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};

use super::{LineError, ModemIn, ModemOut, Transport};
use cellgate_core::engine::parity::{ParityCodec, ParityDecoder};

/// A transport whose bytes carry the parity bit of a 7-bit line in bit 7 (see the [module
/// docs](self)).
pub struct GatewayParity<T> {
    inner: T,
    codec: ParityCodec,
    decoder: ParityDecoder,
    /// What the last write handed on, parity bits set.
    encoded: Vec<u8>,
    /// Characters written so far.
    written: u64,
    /// Characters (counted from 0 in what is written) whose parity bit goes out wrong: a
    /// fault for the simulated device, never set by the gateway.
    spoil: VecDeque<u64>,
}

impl<T> GatewayParity<T> {
    /// `inner` with the parity of `codec` made and checked here.
    pub fn new(inner: T, codec: ParityCodec) -> Self {
        GatewayParity {
            inner,
            codec,
            decoder: ParityDecoder::new(codec),
            encoded: Vec::new(),
            written: 0,
            spoil: VecDeque::new(),
        }
    }

    /// The character numbered `index` in what is written (0 first) goes out with its parity
    /// bit wrong, as a character hit on the line: the simulated device's fault hook.
    pub fn spoil_sent(&mut self, index: u64) {
        let at = self.spoil.partition_point(|&i| i < index);
        self.spoil.insert(at, index);
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for GatewayParity<T> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        if buf.remaining() == 0 {
            return Poll::Ready(Ok(()));
        }
        let this = &mut *self;
        loop {
            let n = this.decoder.decode(buf.initialize_unfilled());
            if n > 0 {
                buf.advance(n);
                return Poll::Ready(Ok(()));
            }
            let mut scratch = [0u8; 1024];
            let mut raw = ReadBuf::new(&mut scratch);
            match Pin::new(&mut this.inner).poll_read(cx, &mut raw) {
                Poll::Pending => return Poll::Pending,
                Poll::Ready(Err(e)) => return Poll::Ready(Err(e)),
                // End of input: every byte read was decoded (a byte is a whole character).
                Poll::Ready(Ok(())) if raw.filled().is_empty() => return Poll::Ready(Ok(())),
                Poll::Ready(Ok(())) => this.decoder.feed(raw.filled()),
            }
        }
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for GatewayParity<T> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = &mut *self;
        this.encoded.clear();
        this.codec.encode(buf, &mut this.encoded);
        let end = this.written + this.encoded.len() as u64;
        for &i in this.spoil.iter().take_while(|&&i| i < end) {
            if let Some(b) = i
                .checked_sub(this.written)
                .and_then(|k| usize::try_from(k).ok())
                .and_then(|k| this.encoded.get_mut(k))
            {
                *b ^= 0x80;
            }
        }
        let n = match Pin::new(&mut this.inner).poll_write(cx, &this.encoded) {
            Poll::Ready(Ok(n)) => n,
            other => return other,
        };
        this.written += n as u64;
        while this.spoil.front().is_some_and(|&i| i < this.written) {
            this.spoil.pop_front();
        }
        Poll::Ready(Ok(n))
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

impl<T: Transport> Transport for GatewayParity<T> {
    fn set_modem(&mut self, out: ModemOut) -> io::Result<()> {
        self.inner.set_modem(out)
    }

    fn modem(&mut self) -> io::Result<ModemIn> {
        self.inner.modem()
    }

    /// The parity errors found here first (they lie before the bytes of the read that found
    /// them), then what the port itself reported (a framing error of a serial port).
    fn take_line_error(&mut self) -> Option<LineError> {
        self.decoder
            .take_error()
            .or_else(|| self.inner.take_line_error())
    }

    fn describe(&self) -> String {
        format!("{}, parity by the gateway", self.inner.describe())
    }

    fn modem_wakes_reader(&self) -> bool {
        self.inner.modem_wakes_reader()
    }

    fn reconnect(&mut self, why: &str) {
        self.inner.reconnect(why);
    }
}

#[cfg(test)]
mod tests;
