//! The gateway as a whole on loopback: its session, its token and admin key, a clean stop.

use crate::common;

use std::time::Duration;

use cellgate::bus;
use cellgate::bus::keys::CellKeys;
use cellgate::gateway::{self, VERSION};
use cellgate_core::config::CellConfig;

use common::bus::free_port;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn opens_on_loopback_and_closes() {
    let port = free_port();
    let cfg = bus::BusConfig {
        listen: vec![format!("tcp/127.0.0.1:{port}")],
        ..bus::BusConfig::default()
    };
    let session = bus::open(&cfg).await.unwrap();
    // The listen endpoint is bound on loopback.
    tokio::net::TcpStream::connect(("127.0.0.1", port))
        .await
        .expect("nothing listens on the configured endpoint");
    session.close().await.unwrap();
    assert!(session.is_closed());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn announces_the_cell_answers_admin_and_stops_on_shutdown() {
    let port = free_port();
    let mut config = CellConfig::embedded_default();
    // Its console would take a fixed port; this test does not look at it.
    config.console = None;
    config.mtconnect = None;
    config.opcua = None;
    config.bus.listen = vec![format!("tcp/127.0.0.1:{port}")];
    config.bus.connect = Vec::new();
    let dir = tempfile::tempdir().unwrap();
    config.programs.dir = dir.path().join("programs");
    let keys = CellKeys::new(&config.bus.prefix, &config.cell).unwrap();
    let token_key = keys.gateway();
    let admin = keys.admin();
    let cell = config.cell.clone();

    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let gateway = tokio::spawn(gateway::run(config, async {
        let _ = stopped.await;
    }));

    let client_cfg = bus::BusConfig {
        mode: bus::BusMode::Client,
        listen: Vec::new(),
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        ..bus::BusConfig::default()
    };
    // The gateway may still be starting: retry opening the client for a while.
    let mut client = None;
    for _ in 0..100 {
        match bus::open(&client_cfg).await {
            Ok(s) => {
                client = Some(s);
                break;
            }
            Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
        }
    }
    let client = client.expect("the gateway never accepted a connection");

    // The token shows the gateway is up (declarations propagate asynchronously).
    let mut alive = false;
    for _ in 0..100 {
        let replies = client.liveliness().get(token_key.as_str()).await.unwrap();
        if replies.recv_async().await.is_ok() {
            alive = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(alive, "no liveliness token on {token_key}");

    let replies = client.get(admin.as_str()).await.unwrap();
    let reply = replies.recv_async().await.expect("no admin reply");
    let sample = reply.result().expect("admin replied with an error");
    let text = sample.payload().try_to_string().unwrap().into_owned();
    let doc: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(doc["version"], VERSION);
    assert_eq!(doc["cell"], cell.as_str());
    assert_eq!(doc["config"]["cell"], cell.as_str());

    stop.send(()).unwrap();
    let result = tokio::time::timeout(Duration::from_secs(10), gateway)
        .await
        .expect("the gateway did not stop within 10 s")
        .unwrap();
    result.unwrap();

    // Once stopped, the token is gone.
    let replies = client.liveliness().get(token_key.as_str()).await.unwrap();
    assert!(
        replies.recv_async().await.is_err(),
        "token still alive after shutdown"
    );
    client.close().await.unwrap();
}
