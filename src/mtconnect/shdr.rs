//! The SHDR adapter: a TCP port an existing MTConnect agent connects to as to any adapter.
//! It gets every data item's state at once, then each observation as it is made, one line
//! each ([`cellgate_core::mtconnect::shdr`]); its `* PING` is answered with `* PONG`. An
//! agent that falls a whole buffer behind gets the state again.
//!
//! The protocol has no login: the port is as open as the network it listens on. What an
//! agent can cost is bounded: [`MAX_CLIENTS`] connections, lines of [`MAX_LINE`] bytes, a
//! connection closed after [`IDLE`] without a line and when it reads nothing for the door's
//! write timeout.

use std::sync::Arc;
use std::time::Duration;

use futures::StreamExt as _;
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;
use tokio::time::Instant;
use tokio_util::codec::{FramedRead, LinesCodec, LinesCodecError};
use tokio_util::sync::CancellationToken;

use super::Hub;
use crate::door::{Admitted, Door};
use cellgate_core::mtconnect::shdr;

/// Agents connected at once, at most (fewer if the open-file budget is smaller).
pub const MAX_CLIENTS: usize = 16;
/// Observations sent in one write at most.
const BATCH: i64 = 1024;
/// A line from the agent longer than this ends the connection (a `* PING` is 6 bytes); what
/// it sends is never held beyond it.
pub const MAX_LINE: usize = 1024;
/// Without a line from the agent for this long (no `* PING`), the connection is dropped,
/// however many observations it is sent.
pub const IDLE: Duration = Duration::from_secs(3 * shdr::HEARTBEAT_MS / 1000);

/// Serves agents coming through `door` until `stop`.
pub async fn serve(door: Door, hub: Arc<Hub>, stop: CancellationToken) {
    loop {
        let (socket, peer) = tokio::select! {
            () = stop.cancelled() => return,
            a = door.accept() => a,
        };
        let (hub, stop) = (Arc::clone(&hub), stop.clone());
        tokio::spawn(async move {
            tracing::info!(%peer, "mtconnect: SHDR agent connected");
            match client(socket, hub, stop).await {
                Ok(()) => tracing::info!(%peer, "mtconnect: SHDR agent gone"),
                Err(e) => tracing::info!(%peer, error = %e, "mtconnect: SHDR agent dropped"),
            }
        });
    }
}

async fn client(
    socket: Admitted<TcpStream>,
    hub: Arc<Hub>,
    stop: CancellationToken,
) -> std::io::Result<()> {
    // Writes fail once the agent has read nothing for the door's write timeout.
    let (read, mut write) = tokio::io::split(socket);
    let mut lines = FramedRead::new(read, LinesCodec::new_with_max_length(MAX_LINE));
    let mut watch = hub.watch();
    let (snapshot, mut from) = {
        let agent = hub.lock();
        (shdr::snapshot(&agent), agent.buffer().next())
    };
    write.write_all(snapshot.as_bytes()).await?;
    // From the agent's last line: what is sent to it does not keep it alive.
    let idle = tokio::time::sleep(IDLE);
    tokio::pin!(idle);
    loop {
        tokio::select! {
            () = stop.cancelled() => return Ok(()),
            () = &mut idle => {
                return Err(std::io::Error::new(
                    std::io::ErrorKind::TimedOut,
                    format!("no line (* PING) for {} s", IDLE.as_secs()),
                ));
            }
            line = lines.next() => match line {
                None => return Ok(()),
                Some(Err(LinesCodecError::Io(e))) => return Err(e),
                Some(Err(LinesCodecError::MaxLineLengthExceeded)) => {
                    return Err(std::io::Error::new(
                        std::io::ErrorKind::InvalidData,
                        format!("a line longer than {MAX_LINE} bytes"),
                    ));
                }
                Some(Ok(line)) => {
                    idle.as_mut().reset(Instant::now() + IDLE);
                    if line.starts_with("* PING") {
                        write.write_all(shdr::pong().as_bytes()).await?;
                    }
                }
            },
            changed = watch.changed() => {
                if changed.is_err() {
                    return Ok(());
                }
                let out = {
                    let agent = hub.lock();
                    let buffer = agent.buffer();
                    if from < buffer.first() {
                        from = buffer.next();
                        shdr::snapshot(&agent)
                    } else {
                        let model = agent.model();
                        let (obs, next) = buffer.sample(from, BATCH, |i| {
                            model.items.get(i as usize).is_some_and(|it| it.device != 0)
                        });
                        from = next;
                        let text = shdr::lines(&agent, &obs);
                        if next < buffer.next() {
                            // More than one batch: come back for the rest at once.
                            watch.mark_changed();
                        }
                        text
                    }
                };
                write.write_all(out.as_bytes()).await?;
            }
        }
    }
}
