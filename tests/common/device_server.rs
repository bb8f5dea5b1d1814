//! A serial device server for tests: TCP on one side, a (simulated) serial line on the other,
//! one connection at a time, like a Moxa NPort in raw TCP mode. It can be made to misbehave the
//! ways real ones do: a connection that goes silent without closing (the server lost power or
//! was replaced: half-open), a connection dropped, the server gone and back.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::TcpListener;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

enum Ctl {
    /// Keep the connection open but forward nothing more either way (half-open).
    Freeze,
    /// Close the connection.
    Cut,
}

pub struct DeviceServer {
    pub addr: String,
    ctl: mpsc::UnboundedSender<Ctl>,
    connections: Arc<AtomicU64>,
    task: JoinHandle<()>,
}

impl DeviceServer {
    /// Serves `serial` (the host end of a simulated line) on a fresh loopback port.
    pub async fn start<S>(serial: S) -> DeviceServer
    where
        S: AsyncRead + AsyncWrite + Send + 'static,
    {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap().to_string();
        let (ctl, rx) = mpsc::unbounded_channel();
        let connections = Arc::new(AtomicU64::new(0));
        let task = tokio::spawn(serve(listener, serial, rx, connections.clone()));
        DeviceServer {
            addr,
            ctl,
            connections,
            task,
        }
    }

    /// Connections accepted so far.
    pub fn connections(&self) -> u64 {
        self.connections.load(Ordering::SeqCst)
    }

    /// The current connection goes silent without closing.
    pub fn freeze(&self) {
        let _ = self.ctl.send(Ctl::Freeze);
    }

    /// The current connection is closed.
    pub fn cut(&self) {
        let _ = self.ctl.send(Ctl::Cut);
    }

    pub fn stop(self) {
        self.task.abort();
    }
}

async fn serve<S>(
    listener: TcpListener,
    serial: S,
    mut ctl: mpsc::UnboundedReceiver<Ctl>,
    connections: Arc<AtomicU64>,
) where
    S: AsyncRead + AsyncWrite + Send + 'static,
{
    let (mut ser_rd, mut ser_wr) = tokio::io::split(serial);
    // Frozen connections stay open until the server stops.
    let mut frozen = Vec::new();
    let mut net_buf = [0u8; 1024];
    let mut ser_buf = [0u8; 1024];
    loop {
        let Ok((stream, _)) = listener.accept().await else {
            return;
        };
        stream.set_nodelay(true).unwrap();
        connections.fetch_add(1, Ordering::SeqCst);
        let (mut net_rd, mut net_wr) = stream.into_split();
        loop {
            tokio::select! {
                r = net_rd.read(&mut net_buf) => match r {
                    Ok(0) | Err(_) => break,
                    Ok(n) => {
                        if ser_wr.write_all(&net_buf[..n]).await.is_err() {
                            return;
                        }
                    }
                },
                r = ser_rd.read(&mut ser_buf) => match r {
                    Ok(0) | Err(_) => return,
                    Ok(n) => {
                        if net_wr.write_all(&ser_buf[..n]).await.is_err() {
                            break;
                        }
                    }
                },
                c = ctl.recv() => match c {
                    Some(Ctl::Freeze) => {
                        frozen.push((net_rd, net_wr));
                        break;
                    }
                    Some(Ctl::Cut) => break,
                    None => return,
                },
            }
        }
    }
}
