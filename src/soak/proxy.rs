//! The line between the gateway and a board, with the faults of a real one: the soak puts one
//! of these in front of every simulated board, as a device server with a flaky cable would
//! be. A cut closes the connection; a corrupted or dropped byte goes to the board in the
//! host's next write (the board answers a checksum error with NAK, §4.3 (3), §5.3).

use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;

/// What the next write from the host suffers.
const CLEAN: u8 = 0;
const CORRUPT: u8 = 1;
const DROP: u8 = 2;

/// A proxy on its own loopback port forwarding to `board`.
#[derive(Debug)]
pub(crate) struct LineProxy {
    pub(crate) port: u16,
    next_write: Arc<AtomicU8>,
    /// Bumped by every cut: each connection ends when it changes.
    cuts: watch::Sender<u64>,
}

impl LineProxy {
    /// Listens on a free loopback port; each connection is forwarded to `board` until `stop`.
    pub(crate) async fn start(board: u16, stop: CancellationToken) -> std::io::Result<LineProxy> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let port = listener.local_addr()?.port();
        let next_write = Arc::new(AtomicU8::new(CLEAN));
        let (cuts, _) = watch::channel(0);
        let proxy = LineProxy {
            port,
            next_write: Arc::clone(&next_write),
            cuts: cuts.clone(),
        };
        tokio::spawn(async move {
            loop {
                let host = tokio::select! {
                    () = stop.cancelled() => return,
                    accepted = listener.accept() => match accepted {
                        Ok((host, _)) => host,
                        Err(_) => {
                            tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                            continue;
                        }
                    },
                };
                let cut = cuts.subscribe();
                tokio::spawn(forward(
                    host,
                    board,
                    Arc::clone(&next_write),
                    cut,
                    stop.clone(),
                ));
            }
        });
        Ok(proxy)
    }

    /// Closes the connection now in place (the cable pulled).
    pub(crate) fn cut(&self) {
        self.cuts.send_modify(|n| *n += 1);
    }

    /// The host's next write reaches the board with one bit flipped.
    pub(crate) fn corrupt_next(&self) {
        self.next_write.store(CORRUPT, Ordering::SeqCst);
    }

    /// The host's next write reaches the board one byte short.
    pub(crate) fn drop_next(&self) {
        self.next_write.store(DROP, Ordering::SeqCst);
    }
}

/// One connection: both directions until either side closes, a cut, or `stop`.
async fn forward(
    host: TcpStream,
    board: u16,
    next_write: Arc<AtomicU8>,
    mut cut: watch::Receiver<u64>,
    stop: CancellationToken,
) {
    // A device server whose serial side is gone takes the connection and closes it.
    let Ok(Ok(device)) = tokio::time::timeout(
        std::time::Duration::from_secs(2),
        TcpStream::connect(("127.0.0.1", board)),
    )
    .await
    else {
        return;
    };
    let _ = host.set_nodelay(true);
    let _ = device.set_nodelay(true);
    let (mut host_rx, mut host_tx) = host.into_split();
    let (mut dev_rx, mut dev_tx) = device.into_split();
    let down = async {
        let mut buf = vec![0u8; 4096];
        loop {
            let n = match host_rx.read(&mut buf).await {
                Ok(0) | Err(_) => return,
                Ok(n) => n,
            };
            let chunk = &mut buf[..n];
            // A one-byte write is not shortened: the fault waits for a longer one.
            let fault = match next_write.load(Ordering::SeqCst) {
                DROP if n < 2 => CLEAN,
                _ => next_write.swap(CLEAN, Ordering::SeqCst),
            };
            let out: &[u8] = match fault {
                CORRUPT => {
                    let i = n / 2;
                    chunk[i] ^= 0x04;
                    chunk
                }
                DROP => {
                    let i = n / 2;
                    chunk.copy_within(i + 1.., i);
                    &chunk[..n - 1]
                }
                _ => chunk,
            };
            if dev_tx.write_all(out).await.is_err() {
                return;
            }
        }
    };
    let up = async {
        let mut buf = vec![0u8; 4096];
        loop {
            let n = match dev_rx.read(&mut buf).await {
                Ok(0) | Err(_) => return,
                Ok(n) => n,
            };
            if host_tx.write_all(&buf[..n]).await.is_err() {
                return;
            }
        }
    };
    tokio::select! {
        () = down => {}
        () = up => {}
        _ = cut.changed() => {}
        () = stop.cancelled() => {}
    }
}
