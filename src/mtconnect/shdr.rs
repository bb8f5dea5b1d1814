//! The SHDR adapter: a TCP port an existing MTConnect agent connects to as to any adapter.
//! It gets every data item's state at once, then each observation as it is made, one line
//! each ([`cellgate_core::mtconnect::shdr`]); its `* PING` is answered with `* PONG`. An
//! agent that falls a whole buffer behind gets the state again.

use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tokio_util::sync::CancellationToken;

use super::Hub;
use cellgate_core::mtconnect::shdr;

/// Agents connected at once, at most.
const MAX_CLIENTS: usize = 16;
/// Observations sent in one write at most.
const BATCH: i64 = 1024;
/// A line from the agent longer than this ends the connection (a `* PING` is 6 bytes).
const MAX_LINE: usize = 1024;
/// Without a byte from the agent for this long (no `* PING`), the connection is dropped.
const IDLE: Duration = Duration::from_secs(3 * shdr::HEARTBEAT_MS / 1000);

/// Serves agents on `listener` until `stop`.
pub async fn serve(listener: TcpListener, hub: Arc<Hub>, stop: CancellationToken) {
    let permits = Arc::new(Semaphore::new(MAX_CLIENTS));
    loop {
        let (socket, peer) = tokio::select! {
            () = stop.cancelled() => return,
            a = listener.accept() => match a {
                Ok(a) => a,
                Err(e) => {
                    tracing::warn!(error = %e, "mtconnect: SHDR accept failed");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
        };
        let Ok(permit) = Arc::clone(&permits).try_acquire_owned() else {
            tracing::warn!(%peer, "mtconnect: SHDR: {MAX_CLIENTS} agents connected already; refused");
            continue;
        };
        let (hub, stop) = (Arc::clone(&hub), stop.clone());
        tokio::spawn(async move {
            tracing::info!(%peer, "mtconnect: SHDR agent connected");
            if let Err(e) = client(socket, hub, stop).await {
                tracing::debug!(%peer, error = %e, "mtconnect: SHDR agent gone");
            }
            drop(permit);
        });
    }
}

async fn client(socket: TcpStream, hub: Arc<Hub>, stop: CancellationToken) -> std::io::Result<()> {
    let (read, mut write) = socket.into_split();
    let mut lines = BufReader::new(read);
    let mut watch = hub.watch();
    let (snapshot, mut from) = {
        let agent = hub.lock();
        (shdr::snapshot(&agent), agent.buffer().next())
    };
    write.write_all(snapshot.as_bytes()).await?;
    let mut line = String::new();
    loop {
        tokio::select! {
            () = stop.cancelled() => return Ok(()),
            read = tokio::time::timeout(IDLE, read_line(&mut lines, &mut line)) => {
                match read {
                    Err(_) => return Ok(()),
                    Ok(Ok(0)) => return Ok(()),
                    Ok(Ok(_)) => {
                        if line.trim_end().starts_with("* PING") {
                            write.write_all(shdr::pong().as_bytes()).await?;
                        }
                        line.clear();
                    }
                    Ok(Err(e)) => return Err(e),
                }
            }
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

/// One line, at most [`MAX_LINE`] bytes.
async fn read_line(
    r: &mut BufReader<tokio::net::tcp::OwnedReadHalf>,
    line: &mut String,
) -> std::io::Result<usize> {
    let n = r.read_line(line).await?;
    if line.len() > MAX_LINE {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            "SHDR line too long",
        ));
    }
    Ok(n)
}
