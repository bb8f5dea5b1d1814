//! The console's door against a hostile user on the shop network: password guessing, a user
//! who logs everyone else out, bodies sent before the caller is known, event streams that
//! outlive their session, floods of refused writes, other origins and malformed requests.

use std::time::{Duration, Instant};

use serde_json::{Value, json};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use super::{Browser, Gateway, PROGRAM, audited, secured};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn password_guessing_is_throttled_and_the_right_password_waits_its_turn() {
    let gw = Gateway::start(secured).await;
    let mut b = Browser::new(&gw.url);
    // A few failures are free; then each one closes the name for a growing time.
    let mut throttled = None;
    for _ in 0..12 {
        let (status, e) = b.login("erik", "guess").await;
        match status {
            401 => continue,
            429 => {
                throttled = Some(e);
                break;
            }
            other => panic!("{other}: {e}"),
        }
    }
    let e = throttled.expect("guessing is throttled");
    assert_eq!(e["code"], "ERROR_CODE_NOT_PERMITTED", "{e}");
    // While closed, the right password waits too, and says for how long.
    let r = b
        .http
        .post(format!("{}/api/v1/login", gw.url))
        .json(&json!({"user": "erik", "password": "hammer"}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 429);
    let wait: u64 = r.headers()["retry-after"]
        .to_str()
        .unwrap()
        .parse()
        .unwrap();
    assert!((1..=300).contains(&wait), "{wait}");
    // Once the time has passed, it is taken.
    tokio::time::sleep(Duration::from_secs(wait)).await;
    let (status, me) = b.login("erik", "hammer").await;
    assert_eq!(status, 200, "{me}");
    // The failures are in the audit trail, gathered.
    let note = audited(&b, |a| {
        a["origin"]["user"] == "erik"
            && a["detail"]
                .as_str()
                .is_some_and(|d| d.contains("console.login"))
    })
    .await;
    assert_eq!(note["audit"]["ok"], false, "{note}");
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn guessing_a_name_does_not_lock_out_its_user_on_a_browser_they_logged_in_on_before() {
    let gw = Gateway::start(secured).await;
    // The real user logs in once: the browser is trusted for that name from now on.
    let mut erik = Browser::new(&gw.url);
    assert_eq!(erik.login("erik", "hammer").await.0, 200);
    // Someone else guesses erik's password, well under the per-address allowance, until
    // the name is closed to untrusted browsers, the right password included.
    let mut guesser = Browser::new(&gw.url);
    let mut closed = false;
    for _ in 0..15 {
        closed |= guesser.login("erik", "guess").await.0 == 429;
    }
    assert!(closed, "the name was never closed");
    assert_eq!(guesser.login("erik", "hammer").await.0, 429);
    assert_eq!(Browser::new(&gw.url).login("erik", "hammer").await.0, 429);
    // erik, on the browser that logged in before, is let in at once, again and again.
    for _ in 0..3 {
        let (status, me) = erik.login("erik", "hammer").await;
        assert_eq!(status, 200, "{me}");
        assert_eq!(me["user"], "erik");
    }
    // Guessing on that browser closes the browser alone, after its own few free failures.
    let mut refused = 0;
    loop {
        match erik.login("erik", "typo").await.0 {
            401 => refused += 1,
            429 => break,
            other => panic!("{other}"),
        }
        assert!(refused <= 10, "the device was never closed");
    }
    assert_eq!(refused, 5, "a device has as many free failures as a name");
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_user_cannot_log_others_out_and_their_own_oldest_session_goes_first() {
    let gw = Gateway::start(|c, d| {
        secured(c, d);
        c.console.as_mut().unwrap().sessions_per_user = 3;
    })
    .await;
    let mut erik = Browser::new(&gw.url);
    assert_eq!(erik.login("erik", "hammer").await.0, 200);
    let mut first = Browser::new(&gw.url);
    assert_eq!(first.login("olga", "tulips").await.0, 200);
    let mut last = Browser::new(&gw.url);
    for _ in 0..40 {
        last = Browser::new(&gw.url);
        assert_eq!(last.login("olga", "tulips").await.0, 200);
    }
    assert_eq!(
        erik.me().await.0,
        200,
        "another user's logins leave erik's session"
    );
    assert_eq!(first.me().await.0, 401, "olga's oldest session went");
    assert_eq!(last.me().await.0, 200);
    gw.stop().await;
}

/// Sends a request head announcing a `length`-byte body, sends no body, and answers the
/// status line the console replies with (or panics if it waits for the body).
async fn status_without_body(url: &str, head: &str, length: u64) -> String {
    let addr = url.trim_start_matches("http://");
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let request = format!(
        "{head}\r\nHost: {addr}\r\nContent-Type: application/octet-stream\r\n\
         Content-Length: {length}\r\n\r\n"
    );
    s.write_all(request.as_bytes()).await.unwrap();
    let mut buf = vec![0u8; 4096];
    let n = tokio::time::timeout(Duration::from_secs(10), s.read(&mut buf))
        .await
        .expect("answered without the body")
        .unwrap();
    // The status line, and for a refusal of the body, whether the connection ends with it.
    let head = String::from_utf8_lossy(&buf[..n]).to_lowercase();
    let line = head.lines().next().unwrap_or_default().to_uppercase();
    if head.contains("connection: close") {
        format!("{line} (connection: close)")
    } else {
        line
    }
}

/// The status line the console answers a raw request with.
async fn status_of(url: &str, request: &str) -> String {
    let addr = url.trim_start_matches("http://").trim_end_matches('/');
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(request.as_bytes()).await.unwrap();
    let mut buf = vec![0u8; 4096];
    let n = tokio::time::timeout(Duration::from_secs(10), s.read(&mut buf))
        .await
        .expect("answered")
        .unwrap();
    String::from_utf8_lossy(&buf[..n])
        .lines()
        .next()
        .unwrap_or_default()
        .to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_name_pointed_at_the_console_by_another_site_is_not_served() {
    // The default cell: no users, everybody may do anything, on loopback. A page of
    // http://evil.example:PORT whose name was re-pointed at 127.0.0.1 (DNS rebinding) sends
    // Host and Origin of its own name: neither a read nor a write is served.
    let gw = Gateway::start(|_, _| {}).await;
    let addr = gw.url.trim_start_matches("http://").trim_end_matches('/');
    let port = addr.rsplit_once(':').unwrap().1;
    let get = |host: &str| format!("GET /api/v1/me HTTP/1.1\r\nHost: {host}\r\n\r\n");
    let evil = format!("evil.example:{port}");
    assert!(status_of(&gw.url, &get(&evil)).await.contains(" 421 "));
    let post = format!(
        "POST /api/v1/cells/demo/machines/mill-1/do HTTP/1.1\r\nHost: {evil}\r\n\
         Origin: http://{evil}\r\nContent-Type: application/json\r\nContent-Length: 11\r\n\r\n\
         {{\"value\":5}}"
    );
    assert!(status_of(&gw.url, &post).await.contains(" 421 "));
    // Its address, localhost, at its own port: served. Another port: not.
    assert!(status_of(&gw.url, &get(addr)).await.contains(" 200 "));
    assert!(
        status_of(&gw.url, &get(&format!("localhost:{port}")))
            .await
            .contains(" 200 ")
    );
    assert!(
        status_of(&gw.url, &get("127.0.0.1:1"))
            .await
            .contains(" 421 ")
    );
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_field_given_twice_in_a_body_is_refused() {
    let gw = Gateway::start(secured).await;
    let mut olga = Browser::new(&gw.url);
    olga.login("olga", "tulips").await;
    let r = olga
        .http
        .post(format!("{}/api/v1/cells/demo/machines/mill-1/do", gw.url))
        .header("X-CSRF-Token", &olga.csrf)
        .header("Content-Type", "application/json")
        .body(r#"{"value": 1, "value": 255}"#)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 400);
    let e: Value = r.json().await.unwrap();
    assert!(
        e["message"]
            .as_str()
            .unwrap()
            .contains("duplicate field `value`"),
        "{e}"
    );
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_caller_and_the_size_are_known_before_a_body_is_read() {
    let gw = Gateway::start(secured).await;
    const HUGE: u64 = 200 * 1024 * 1024;
    let put = "PUT /api/v1/cells/demo/programs/O5001 HTTP/1.1";
    // Nobody: 401 at once.
    let line = status_without_body(&gw.url, put, HUGE).await;
    assert!(line.contains(" 401 "), "{line}");
    // A viewer of the library (olga may not write programs): 403 at once.
    let mut olga = Browser::new(&gw.url);
    olga.login("olga", "tulips").await;
    let cookie = cookie_of(&olga, &gw.url);
    let head = format!("{put}\r\nCookie: {cookie}\r\nX-CSRF-Token: {}", olga.csrf);
    let line = status_without_body(&gw.url, &head, HUGE).await;
    assert!(line.contains(" 403 "), "{line}");
    // Erik may store, but not more than programs.max_inline: 413 at once.
    let mut erik = Browser::new(&gw.url);
    erik.login("erik", "hammer").await;
    let cookie = cookie_of(&erik, &gw.url);
    let head = format!("{put}\r\nCookie: {cookie}\r\nX-CSRF-Token: {}", erik.csrf);
    let line = status_without_body(&gw.url, &head, HUGE).await;
    assert!(line.contains(" 413 "), "{line}");
    // The body is still coming: the client is told not to reuse the connection.
    assert!(line.ends_with("(connection: close)"), "{line}");
    // Other writes take a few KiB.
    let (status, e) = erik
        .send(
            reqwest::Method::POST,
            "/api/v1/cells/demo/machines/mill-1/submit",
            None,
            Some(vec![b' '; 64 * 1024]),
            true,
        )
        .await;
    assert!(status == 413 || status == 415, "{status} {e}");
    assert!(e["code"].is_string(), "{e}");
    // And a store within the limit still works.
    let (status, info) = erik
        .send(
            reqwest::Method::PUT,
            "/api/v1/cells/demo/programs/O5001",
            None,
            Some(PROGRAM.to_vec()),
            true,
        )
        .await;
    assert_eq!(status, 200, "{info}");
    gw.stop().await;
}

/// The session cookie a browser holds for `url`.
fn cookie_of(b: &Browser, url: &str) -> String {
    use reqwest::cookie::CookieStore as _;
    let _ = (b, url);
    b.jar
        .cookies(&url.parse().unwrap())
        .map(|c| c.to_str().unwrap().to_string())
        .unwrap_or_default()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_event_stream_ends_with_its_session() {
    let gw = Gateway::start(secured).await;
    let mut olga = Browser::new(&gw.url);
    olga.login("olga", "tulips").await;
    let mut stream = olga
        .http
        .get(format!("{}/api/v1/cells/demo/events", gw.url))
        .send()
        .await
        .unwrap();
    assert_eq!(stream.status().as_u16(), 200);
    // Events flow (the machines' status).
    let first = tokio::time::timeout(Duration::from_secs(10), stream.chunk())
        .await
        .expect("an event")
        .unwrap();
    assert!(first.is_some());
    let (status, _) = olga
        .send(reqwest::Method::POST, "/api/v1/logout", None, None, true)
        .await;
    assert_eq!(status, 204);
    assert_eq!(olga.me().await.0, 401);
    // The stream ends within the session check's period.
    let deadline = Instant::now() + Duration::from_secs(15);
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match tokio::time::timeout(left, stream.chunk()).await {
            Ok(Ok(Some(_))) => continue,
            Ok(Ok(None) | Err(_)) => break,
            Err(_) => panic!("the stream outlived its session"),
        }
    }
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_refused_writes_leaves_a_few_audit_records_with_their_count() {
    let gw = Gateway::start(secured).await;
    let mut olga = Browser::new(&gw.url);
    olga.login("olga", "tulips").await;
    let mut erik = Browser::new(&gw.url);
    erik.login("erik", "hammer").await;
    for i in 0..60 {
        let (status, _) = olga
            .post(
                "/api/v1/cells/demo/machines/mill-1/submit",
                json!({"library": format!("O{i}")}),
            )
            .await;
        assert_eq!(status, 403);
    }
    let refused = |a: &Value| {
        a["origin"]["user"] == "olga"
            && a["detail"]
                .as_str()
                .is_some_and(|d| d.contains("job.submit"))
    };
    audited(&erik, refused).await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    let (status, page) = erik
        .get("/api/v1/cells/demo/audit?_time=[now(-10m)..]")
        .await;
    assert_eq!(status, 200, "{page}");
    let records = page["records"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|r| refused(&r["audit"]))
        .count();
    // The first at once; the rest of its minute in one summary when the minute ends (two
    // more if the flood straddled a minute's end).
    assert!(
        (1..=3).contains(&records),
        "{records} records for 60 refusals"
    );
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn other_origins_malformed_bodies_and_odd_names_are_refused_in_the_api_shape() {
    let gw = Gateway::start(secured).await;
    let mut olga = Browser::new(&gw.url);
    olga.login("olga", "tulips").await;
    let send = |origin: Option<&'static str>, site: Option<&'static str>, body: Vec<u8>, ct| {
        let mut r = olga
            .http
            .post(format!("{}/api/v1/cells/demo/machines/mill-1/do", gw.url))
            .header("X-CSRF-Token", &olga.csrf)
            .header("Content-Type", ct)
            .body(body);
        if let Some(o) = origin {
            r = r.header("Origin", o);
        }
        if let Some(s) = site {
            r = r.header("Sec-Fetch-Site", s);
        }
        async move {
            let r = r.send().await.unwrap();
            let status = r.status().as_u16();
            let v: Value = r.json().await.unwrap_or(Value::Null);
            (status, v)
        }
    };
    let good = br#"{"value": 1, "mask": 1}"#.to_vec();
    // Another origin, with a valid token.
    let (status, e) = send(
        Some("http://evil.example"),
        None,
        good.clone(),
        "application/json",
    )
    .await;
    assert_eq!(status, 403, "{e}");
    assert_eq!(e["code"], "ERROR_CODE_NOT_PERMITTED", "{e}");
    let (status, e) = send(None, Some("cross-site"), good.clone(), "application/json").await;
    assert_eq!(status, 403, "{e}");
    // An array is not an object; plain text is not JSON: both in the API's shape.
    let (status, e) = send(None, None, b"[1,2]".to_vec(), "application/json").await;
    assert_eq!(status, 400, "{e}");
    assert_eq!(e["code"], "ERROR_CODE_INVALID_REQUEST", "{e}");
    let (status, e) = send(None, None, good.clone(), "text/plain").await;
    assert_eq!(status, 415, "{e}");
    assert!(e["message"].is_string(), "{e}");
    let (status, e) = send(
        None,
        None,
        br#"{"value": 1, "mask": 1, "x": 2}"#.to_vec(),
        "application/json",
    )
    .await;
    assert_eq!(status, 400, "unknown fields are refused: {e}");
    // Names that would be wildcards or selectors on the bus: 400 at once.
    let mut erik = Browser::new(&gw.url);
    erik.login("erik", "hammer").await;
    for path in [
        "/api/v1/cells/demo/programs/O5001/rev/%2A%2A",
        "/api/v1/cells/demo/programs/O5001/rev/1%3Fx%3D1",
        "/api/v1/cells/demo/programs/%2A",
        "/api/v1/cells/demo/machines/mill-1%24",
    ] {
        let (status, e) = erik.get(path).await;
        assert_eq!(status, 400, "{path}: {e}");
        assert_eq!(e["code"], "ERROR_CODE_INVALID_REQUEST", "{path}: {e}");
    }
    // An unknown API path, too, answers in the API's shape.
    let (status, e) = erik.get("/api/v1/nothing-here").await;
    assert_eq!(status, 404, "{e}");
    assert!(e["code"].is_string(), "{e}");
    gw.stop().await;
}
