//! Zenoh client helpers for tests that talk to a gateway over loopback.
#![allow(dead_code)]

use std::time::Duration;

use cellgate::pb;
use prost::Message;
use zenoh::Session;

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A client session connecting to a gateway on `tcp/127.0.0.1:port`, multicast scouting off.
pub fn client_config(port: u16) -> cellgate::bus::BusConfig {
    cellgate::bus::BusConfig {
        mode: cellgate::bus::BusMode::Client,
        listen: Vec::new(),
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        ..cellgate::bus::BusConfig::default()
    }
}

pub type Replies = Vec<Result<(String, Vec<u8>, String), (Vec<u8>, String)>>;

/// Every reply to a get on `key`, with its key, payload and encoding (or error payload and
/// encoding).
pub async fn get(client: &Session, key: &str, payload: Option<Vec<u8>>) -> Replies {
    let mut builder = client.get(key.to_string()).timeout(Duration::from_secs(5));
    if let Some(p) = payload {
        builder = builder.payload(p);
    }
    let replies = builder.await.unwrap();
    let mut out = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        out.push(match reply.result() {
            Ok(s) => Ok((
                s.key_expr().to_string(),
                s.payload().to_bytes().into_owned(),
                s.encoding().to_string(),
            )),
            Err(e) => Err((
                e.payload().to_bytes().into_owned(),
                e.encoding().to_string(),
            )),
        });
    }
    out
}

/// The one message answering a get, decoded; panics on an error reply.
pub async fn get_one<M: Message + Default>(
    client: &Session,
    key: &str,
    payload: Option<Vec<u8>>,
) -> M {
    let replies = get(client, key, payload).await;
    assert_eq!(replies.len(), 1, "{key}: {replies:?}");
    match replies.into_iter().next().unwrap() {
        Ok((_, bytes, _)) => M::decode(bytes.as_slice()).unwrap(),
        Err((bytes, _)) => panic!(
            "{key}: error reply {:?}",
            pb::ErrorReply::decode(bytes.as_slice())
        ),
    }
}

/// The one error reply to a get.
pub async fn get_err(client: &Session, key: &str, payload: Option<Vec<u8>>) -> pb::ErrorReply {
    let replies = get(client, key, payload).await;
    assert_eq!(replies.len(), 1, "{key}: {replies:?}");
    match replies.into_iter().next().unwrap() {
        Err((bytes, encoding)) => {
            assert_eq!(encoding, "application/protobuf;cellgate.v1.ErrorReply");
            pb::ErrorReply::decode(bytes.as_slice()).unwrap()
        }
        Ok(ok) => panic!("{key}: expected an error, got {ok:?}"),
    }
}

pub async fn wait_token(client: &Session, key: &str, present: bool) {
    for _ in 0..100 {
        let replies = client.liveliness().get(key.to_string()).await.unwrap();
        if replies.recv_async().await.is_ok() == present {
            return;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("liveliness token {key} never became present = {present}");
}

/// Polls `check` until it holds, for up to 5 s.
pub async fn eventually(what: &str, mut check: impl FnMut() -> bool) {
    for _ in 0..250 {
        if check() {
            return;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    panic!("never happened: {what}");
}
