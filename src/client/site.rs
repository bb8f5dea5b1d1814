//! What the site servers share (`cellgate console`, `cellgate mtconnect`, `cellgate opcua`):
//! a bus session of their own to the endpoint, served until their shutdown, and their errors
//! said one way.

use std::future::Future;

use tokio_util::sync::CancellationToken;
use zenoh::Session;

use super::cli::ConnectArgs;
use super::{ClientError, ConnectOptions};

/// A site server that serves: where, and how it stops.
pub trait SiteServer {
    /// The URL clients reach it at.
    fn url(&self) -> &str;
    /// Waits for it to stop once its stop token is cancelled.
    fn join(self) -> impl Future<Output = ()> + Send;
}

/// Why a site server could not start.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SiteError {
    /// Its options or its cell file are wrong.
    #[error("{0}")]
    Config(String),
    /// The endpoint cannot be reached.
    #[error(transparent)]
    Client(#[from] ClientError),
    /// The server itself could not start (a port taken, a subscription refused).
    #[error(transparent)]
    Serve(Box<dyn std::error::Error + Send + Sync>),
}

/// Opens a session to `connect`'s endpoint, starts a server on it with `start` (the session,
/// the options, its stop token), says where it serves (`cellgate NAME at URL`), and serves
/// until `shutdown`.
pub async fn serve<S, E, Fut>(
    connect: &ConnectArgs,
    name: &str,
    start: impl FnOnce(Session, ConnectOptions, CancellationToken) -> Fut,
    shutdown: impl Future<Output = ()>,
) -> Result<(), SiteError>
where
    S: SiteServer,
    E: std::error::Error + Send + Sync + 'static,
    Fut: Future<Output = Result<S, E>>,
{
    let options = connect.options()?;
    let session = super::open_session(&options).await?;
    let stop = CancellationToken::new();
    let served = match start(session.clone(), options.clone(), stop.clone()).await {
        Ok(s) => s,
        Err(e) => {
            let _ = session.close().await;
            return Err(SiteError::Serve(Box::new(e)));
        }
    };
    tracing::info!(url = %served.url(), endpoint = %options.endpoint, "site {name} at {}", served.url());
    eprintln!(
        "cellgate {name} at {} (cells behind {})",
        served.url(),
        options.endpoint
    );
    shutdown.await;
    stop.cancel();
    served.join().await;
    let _ = session.close().await;
    Ok(())
}
