//! What the console listens on: plain HTTP on loopback, or HTTPS with the cell's certificate,
//! where a client certificate of the cell's CA, when one is presented, says who the browser's
//! user is (its common name, as the bus's roles name it).

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_rustls::TlsAcceptor;
use tokio_rustls::rustls;
use tokio_rustls::rustls::pki_types::pem::PemObject;
use tokio_rustls::rustls::pki_types::{CertificateDer, PrivateKeyDer};

use crate::door::{Admitted, Door};
use cellgate_core::config::TlsConfig;

/// How long a TLS handshake may take before the connection is dropped.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);
/// Handshakes under way at once; more connections wait in the kernel's backlog (each
/// handshake holds a connection of the door's cap, too).
const MAX_HANDSHAKES: usize = 64;

/// Who is at the other end of a connection.
#[derive(Debug, Clone)]
pub struct Peer {
    pub addr: SocketAddr,
    /// The common name of a verified client certificate.
    pub certificate_name: Option<String>,
}

/// Why the console's listener could not be set up.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ListenError {
    #[error("console: cannot listen on {addr}: {source}")]
    Bind {
        addr: String,
        #[source]
        source: std::io::Error,
    },
    #[error("console TLS: {what} {}: {why}", path.display())]
    File {
        what: &'static str,
        path: std::path::PathBuf,
        why: String,
    },
    #[error("console TLS: {0}")]
    Tls(String),
}

/// Plain TCP, each connection's peer known by its address only.
pub struct PlainListener(pub Door);

impl axum::serve::Listener for PlainListener {
    type Io = Admitted<TcpStream>;
    type Addr = Peer;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        let (s, addr) = self.0.accept().await;
        (
            s,
            Peer {
                addr,
                certificate_name: None,
            },
        )
    }

    fn local_addr(&self) -> std::io::Result<Self::Addr> {
        Ok(Peer {
            addr: self.0.local_addr()?,
            certificate_name: None,
        })
    }
}

type Tls = tokio_rustls::server::TlsStream<Admitted<TcpStream>>;

/// TLS over TCP. Handshakes run in tasks of their own, so one slow client holds up nobody.
pub struct TlsListener {
    local: SocketAddr,
    ready: mpsc::Receiver<(Tls, Peer)>,
}

impl TlsListener {
    pub fn new(door: Door, acceptor: TlsAcceptor) -> std::io::Result<Self> {
        let local = door.local_addr()?;
        let (tx, ready) = mpsc::channel(MAX_HANDSHAKES);
        let permits = Arc::new(tokio::sync::Semaphore::new(MAX_HANDSHAKES));
        tokio::spawn(async move {
            loop {
                let Ok(permit) = Arc::clone(&permits).acquire_owned().await else {
                    return;
                };
                let (stream, addr) = tokio::select! {
                    () = tx.closed() => return,
                    accepted = door.accept() => accepted,
                };
                let (acceptor, ready) = (acceptor.clone(), tx.clone());
                tokio::spawn(async move {
                    let shaken =
                        tokio::time::timeout(HANDSHAKE_TIMEOUT, acceptor.accept(stream)).await;
                    drop(permit);
                    let tls = match shaken {
                        Ok(Ok(tls)) => tls,
                        Ok(Err(e)) => {
                            return tracing::debug!(%addr, error = %e, "console: TLS handshake failed");
                        }
                        Err(_) => return tracing::debug!(%addr, "console: TLS handshake too slow"),
                    };
                    let certificate_name = tls
                        .get_ref()
                        .1
                        .peer_certificates()
                        .and_then(|c| c.first())
                        .and_then(|c| common_name(c.as_ref()));
                    let _ = ready
                        .send((
                            tls,
                            Peer {
                                addr,
                                certificate_name,
                            },
                        ))
                        .await;
                });
            }
        });
        Ok(TlsListener { local, ready })
    }
}

impl axum::serve::Listener for TlsListener {
    type Io = Tls;
    type Addr = Peer;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        loop {
            if let Some(x) = self.ready.recv().await {
                return x;
            }
            // The acceptor task ended (it cannot, while this listener lives): stay idle.
            std::future::pending::<()>().await;
        }
    }

    fn local_addr(&self) -> std::io::Result<Self::Addr> {
        Ok(Peer {
            addr: self.local,
            certificate_name: None,
        })
    }
}

/// The first common name of a DER certificate's subject.
pub fn common_name(der: &[u8]) -> Option<String> {
    let (_, cert) = x509_parser::parse_x509_certificate(der).ok()?;
    cert.subject()
        .iter_common_name()
        .next()
        .and_then(|cn| cn.as_str().ok())
        .map(str::to_string)
}

/// The TLS acceptor of the cell's `[security.tls]`: its certificate, and client certificates
/// of its CA taken when offered (a browser without one logs in with a password).
pub fn acceptor(tls: &TlsConfig) -> Result<TlsAcceptor, ListenError> {
    let file = |what: &'static str, path: &Path, why: String| ListenError::File {
        what,
        path: path.to_path_buf(),
        why,
    };
    let certs: Vec<CertificateDer<'static>> = CertificateDer::pem_file_iter(&tls.certificate)
        .map_err(|e| file("certificate", &tls.certificate, e.to_string()))?
        .collect::<Result<_, _>>()
        .map_err(|e| file("certificate", &tls.certificate, e.to_string()))?;
    let key = PrivateKeyDer::from_pem_file(&tls.private_key)
        .map_err(|e| file("private key", &tls.private_key, e.to_string()))?;
    let mut roots = rustls::RootCertStore::empty();
    for ca in
        CertificateDer::pem_file_iter(&tls.ca).map_err(|e| file("CA", &tls.ca, e.to_string()))?
    {
        let ca = ca.map_err(|e| file("CA", &tls.ca, e.to_string()))?;
        roots
            .add(ca)
            .map_err(|e| file("CA", &tls.ca, e.to_string()))?;
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let verifier = rustls::server::WebPkiClientVerifier::builder_with_provider(
        Arc::new(roots),
        Arc::clone(&provider),
    )
    .allow_unauthenticated()
    .build()
    .map_err(|e| ListenError::Tls(e.to_string()))?;
    let config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| ListenError::Tls(e.to_string()))?
        .with_client_cert_verifier(verifier)
        .with_single_cert(certs, key)
        .map_err(|e| ListenError::Tls(e.to_string()))?;
    Ok(TlsAcceptor::from(Arc::new(config)))
}

/// Binds `addr`.
pub async fn bind(addr: &str) -> Result<TcpListener, ListenError> {
    TcpListener::bind(addr)
        .await
        .map_err(|source| ListenError::Bind {
            addr: addr.to_string(),
            source,
        })
}
