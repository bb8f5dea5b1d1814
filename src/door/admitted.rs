//! A connection a door let in: it holds its slot until dropped, and a write that its peer
//! leaves waiting longer than the write timeout fails.

use std::io;
use std::pin::Pin;
use std::task::{Context, Poll, ready};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::sync::OwnedSemaphorePermit;
use tokio::time::{Instant, Sleep};

use super::WRITE_TIMEOUT;

/// A stream whose writes and flushes fail with [`io::ErrorKind::TimedOut`] once they have
/// waited [`WRITE_TIMEOUT`] for the peer to take anything; reads pass through. Holds its
/// door's slot until dropped.
pub struct Admitted<T> {
    inner: T,
    timeout: Duration,
    /// Set when a write first waits; cleared when one goes through.
    stalled: Option<Pin<Box<Sleep>>>,
    _slot: Option<OwnedSemaphorePermit>,
}

impl<T> Admitted<T> {
    pub fn new(inner: T, slot: Option<OwnedSemaphorePermit>) -> Self {
        Self::with_timeout(inner, slot, WRITE_TIMEOUT)
    }

    pub fn with_timeout(inner: T, slot: Option<OwnedSemaphorePermit>, timeout: Duration) -> Self {
        Admitted {
            inner,
            timeout,
            stalled: None,
            _slot: slot,
        }
    }

    pub fn get_ref(&self) -> &T {
        &self.inner
    }

    /// `poll`'s answer, or the time-out's error once a write has waited too long.
    fn guard<R>(
        &mut self,
        cx: &mut Context<'_>,
        poll: impl FnOnce(Pin<&mut T>, &mut Context<'_>) -> Poll<io::Result<R>>,
    ) -> Poll<io::Result<R>>
    where
        T: Unpin,
    {
        match poll(Pin::new(&mut self.inner), cx) {
            Poll::Ready(r) => {
                self.stalled = None;
                Poll::Ready(r)
            }
            Poll::Pending => {
                let timeout = self.timeout;
                let stalled = self.stalled.get_or_insert_with(|| {
                    Box::pin(tokio::time::sleep_until(Instant::now() + timeout))
                });
                ready!(stalled.as_mut().poll(cx));
                Poll::Ready(Err(io::Error::new(
                    io::ErrorKind::TimedOut,
                    format!("the peer read nothing for {} s", timeout.as_secs()),
                )))
            }
        }
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for Admitted<T> {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().inner).poll_read(cx, buf)
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for Admitted<T> {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        self.get_mut().guard(cx, |t, cx| t.poll_write(cx, buf))
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        self.get_mut()
            .guard(cx, |t, cx| t.poll_write_vectored(cx, bufs))
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        self.get_mut().guard(cx, |t, cx| t.poll_flush(cx))
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        self.get_mut().guard(cx, |t, cx| t.poll_shutdown(cx))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::AsyncWriteExt;

    #[tokio::test(start_paused = true)]
    async fn a_write_nobody_reads_fails_after_the_timeout_and_one_read_in_time_goes_through() {
        // A pipe of 64 bytes whose other end reads nothing.
        let (a, b) = tokio::io::duplex(64);
        let mut w = Admitted::with_timeout(a, None, Duration::from_secs(30));
        let started = Instant::now();
        let e = w.write_all(&[0u8; 1024]).await.unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::TimedOut);
        assert_eq!(started.elapsed(), Duration::from_secs(30));
        // A reader that takes the bytes within the time: the writes go through.
        let (a, mut b2) = tokio::io::duplex(64);
        let mut w = Admitted::with_timeout(a, None, Duration::from_secs(30));
        let reader = tokio::spawn(async move {
            let mut got = Vec::new();
            let mut buf = [0u8; 64];
            loop {
                tokio::time::sleep(Duration::from_secs(20)).await;
                match tokio::io::AsyncReadExt::read(&mut b2, &mut buf).await {
                    Ok(0) | Err(_) => return got.len(),
                    Ok(n) => got.extend_from_slice(&buf[..n]),
                }
            }
        });
        w.write_all(&[1u8; 256]).await.unwrap();
        drop(w);
        assert_eq!(reader.await.unwrap(), 256);
        drop(b);
    }
}
