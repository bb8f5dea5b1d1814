//! The agent's HTTP interface (MTConnect Part 1, "REST"): `/probe`, `/current`, `/sample`,
//! `/assets`, each also per device (`/NAME/probe`…), documents in XML or JSON
//! (`format=json`), errors as MTConnectError documents. `/sample` and `/current` with
//! `interval` stream: a `multipart/x-mixed-replace` response whose parts are documents, at
//! most one per interval (never more often than [`MIN_INTERVAL`]), a part when something
//! selected changed, and after `heartbeat` ms without any, one all the same (for `/sample` an
//! empty one). A client that reads nothing is dropped by its connection's write timeout
//! ([`crate::door`]), which frees its stream's slot.
//!
//! It only reads: any other method than GET is refused (`UNSUPPORTED`). Nothing a client
//! sends reaches the bus.

use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use axum::body::Body;
use axum::extract::rejection::PathRejection;
use axum::extract::{Path, RawQuery, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use bytes::Bytes;
use tokio::sync::Semaphore;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use super::Hub;
use super::now_us;
use cellgate_core::mtconnect::agent::Selection;
use cellgate_core::mtconnect::{ErrorCode, Format, MtError, Query, Request};

/// Streams served at once; one more is refused, so that clients cannot take the gateway's
/// memory and time.
pub const MAX_STREAMS: usize = 64;
/// The heartbeat of a stream that asks for none (Part 1: 10 s).
const DEFAULT_HEARTBEAT_MS: u64 = 10_000;
/// The shortest time between two parts of a stream, whatever `interval` asks (Part 1: the
/// interval is the least time between publications; 0 is not "as fast as the socket goes").
/// Every observation still comes: a part holds all those of its interval, up to `count`.
pub const MIN_INTERVAL: Duration = Duration::from_millis(100);

struct Http {
    hub: Arc<Hub>,
    stop: CancellationToken,
    streams: Arc<Semaphore>,
}

type St = State<Arc<Http>>;

/// The agent's routes.
pub fn router(hub: Arc<Hub>, stop: CancellationToken) -> Router {
    let http = Arc::new(Http {
        hub,
        stop,
        streams: Arc::new(Semaphore::new(MAX_STREAMS)),
    });
    Router::new()
        .route("/", get(probe))
        .route("/probe", get(probe))
        .route("/current", get(current))
        .route("/sample", get(sample))
        .route("/assets", get(assets))
        .route("/asset/{id}", get(asset))
        .route("/assets/{id}", get(asset))
        .route("/{device}", get(device_probe))
        .route("/{device}/probe", get(device_probe))
        .route("/{device}/current", get(device_current))
        .route("/{device}/sample", get(device_sample))
        .route("/{device}/assets", get(device_assets))
        .fallback(invalid_uri)
        .method_not_allowed_fallback(unsupported)
        .with_state(http)
}

fn content_type(format: Format) -> &'static str {
    match format {
        Format::Xml => "text/xml; charset=utf-8",
        Format::Json => "application/json",
    }
}

fn document(status: u16, format: Format, body: String) -> Response {
    let status = StatusCode::from_u16(status).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
    (status, [(header::CONTENT_TYPE, content_type(format))], body).into_response()
}

fn error(http: &Http, e: &MtError, format: Format) -> Response {
    let body = http.hub.lock().error(e, format, now_us());
    document(e.code.http_status(), format, body)
}

/// The query of a request, or the error document it earns. The format asked for is taken
/// even when another parameter is wrong, so that the error comes in it.
fn query(request: Request, raw: Option<&str>) -> Result<Query, (MtError, Format)> {
    let pairs: Vec<(String, String)> = form_urlencoded::parse(raw.unwrap_or("").as_bytes())
        .map(|(k, v)| (k.into_owned(), v.into_owned()))
        .collect();
    let format = pairs
        .iter()
        .find(|(k, _)| k == "format")
        .filter(|(_, v)| v.eq_ignore_ascii_case("json"))
        .map_or(Format::Xml, |_| Format::Json);
    Query::parse(request, pairs.iter().map(|(k, v)| (k.as_str(), v.as_str())))
        .map_err(|e| (e, format))
}

fn device_name(path: Result<Path<String>, PathRejection>) -> Result<String, MtError> {
    path.map(|Path(d)| d)
        .map_err(|e| MtError::new(ErrorCode::InvalidUri, format!("the URI: {e}")))
}

/// What a request gets at once: a document, or a stream to start.
enum Answer {
    Doc(u16, Format, String),
    Stream(Option<usize>, Query, Selection),
}

fn answer(http: &Http, request: Request, device: Option<String>, raw: Option<String>) -> Answer {
    let q = match query(request, raw.as_deref()) {
        Ok(q) => q,
        Err((e, f)) => {
            return Answer::Doc(
                e.code.http_status(),
                f,
                http.hub.lock().error(&e, f, now_us()),
            );
        }
    };
    let now = now_us();
    let agent = http.hub.lock();
    let fail = |e: MtError| {
        Answer::Doc(
            e.code.http_status(),
            q.format,
            laid_out(&q, agent.error(&e, q.format, now)),
        )
    };
    let dev = match device.as_deref().map(|d| agent.device(d)).transpose() {
        Ok(d) => d,
        Err(e) => return fail(e),
    };
    let done = match request {
        Request::Probe => Ok(agent.probe(dev, q.format, now)),
        Request::Assets => agent.assets(dev, None, &q, now),
        Request::Current if q.interval.is_some() => {
            return match agent.select(dev, q.path.as_deref()) {
                Ok(sel) => Answer::Stream(dev, q.clone(), sel),
                Err(e) => fail(e),
            };
        }
        Request::Current => agent.current(dev, &q, now),
        Request::Sample => match agent.select(dev, q.path.as_deref()) {
            // Checked now, so that a bad one is an error document, not a stream.
            Ok(sel) if q.interval.is_some() => {
                return match agent.sample(dev, &q, &sel, now) {
                    Ok(_) => Answer::Stream(dev, q.clone(), sel),
                    Err(e) => fail(e),
                };
            }
            Ok(sel) => agent.sample(dev, &q, &sel, now).map(|(doc, _, _)| doc),
            Err(e) => Err(e),
        },
    };
    match done {
        Ok(body) => Answer::Doc(200, q.format, laid_out(&q, body)),
        Err(e) => fail(e),
    }
}

/// The document as asked: compact, or laid out for reading (`pretty=true`).
fn laid_out(q: &Query, body: String) -> String {
    if q.pretty {
        cellgate_core::mtconnect::pretty::pretty(q.format, &body)
    } else {
        body
    }
}

async fn respond(
    http: &Http,
    request: Request,
    device: Option<String>,
    raw: Option<String>,
) -> Response {
    match answer(http, request, device, raw) {
        Answer::Doc(status, format, body) => document(status, format, body),
        Answer::Stream(dev, q, sel) => stream(http, request, dev, q, sel),
    }
}

async fn probe(State(h): St, RawQuery(q): RawQuery) -> Response {
    respond(&h, Request::Probe, None, q).await
}
async fn current(State(h): St, RawQuery(q): RawQuery) -> Response {
    respond(&h, Request::Current, None, q).await
}
async fn sample(State(h): St, RawQuery(q): RawQuery) -> Response {
    respond(&h, Request::Sample, None, q).await
}
async fn assets(State(h): St, RawQuery(q): RawQuery) -> Response {
    respond(&h, Request::Assets, None, q).await
}
async fn device_probe(
    State(h): St,
    d: Result<Path<String>, PathRejection>,
    RawQuery(q): RawQuery,
) -> Response {
    match device_name(d) {
        Ok(d) => respond(&h, Request::Probe, Some(d), q).await,
        Err(e) => error(&h, &e, Format::Xml),
    }
}
async fn device_current(
    State(h): St,
    d: Result<Path<String>, PathRejection>,
    RawQuery(q): RawQuery,
) -> Response {
    match device_name(d) {
        Ok(d) => respond(&h, Request::Current, Some(d), q).await,
        Err(e) => error(&h, &e, Format::Xml),
    }
}
async fn device_sample(
    State(h): St,
    d: Result<Path<String>, PathRejection>,
    RawQuery(q): RawQuery,
) -> Response {
    match device_name(d) {
        Ok(d) => respond(&h, Request::Sample, Some(d), q).await,
        Err(e) => error(&h, &e, Format::Xml),
    }
}
async fn device_assets(
    State(h): St,
    d: Result<Path<String>, PathRejection>,
    RawQuery(q): RawQuery,
) -> Response {
    match device_name(d) {
        Ok(d) => respond(&h, Request::Assets, Some(d), q).await,
        Err(e) => error(&h, &e, Format::Xml),
    }
}

async fn asset(
    State(h): St,
    id: Result<Path<String>, PathRejection>,
    RawQuery(q): RawQuery,
) -> Response {
    let q = match query(Request::Assets, q.as_deref()) {
        Ok(q) => q,
        Err((e, f)) => return error(&h, &e, f),
    };
    let id = match id {
        Ok(Path(id)) => id,
        Err(e) => {
            let e = MtError::new(ErrorCode::InvalidUri, format!("the URI: {e}"));
            return error(&h, &e, q.format);
        }
    };
    let answer = h.hub.lock().assets(None, Some(&id), &q, now_us());
    match answer {
        Ok(body) => document(200, q.format, laid_out(&q, body)),
        Err(e) => error(&h, &e, q.format),
    }
}

async fn invalid_uri(State(h): St, uri: axum::http::Uri) -> Response {
    let e = MtError::new(
        ErrorCode::InvalidUri,
        format!(
            "{} is not served: /probe, /current, /sample, /assets, or /DEVICE/… of each",
            uri.path()
        ),
    );
    error(&h, &e, Format::Xml)
}

async fn unsupported(State(h): St, method: axum::http::Method) -> Response {
    let e = MtError::new(
        ErrorCode::Unsupported,
        format!("{method} is not supported: the agent only reads (GET)"),
    );
    let mut r = error(&h, &e, Format::Xml);
    r.headers_mut()
        .insert(header::ALLOW, HeaderValue::from_static("GET"));
    r
}

/// One part of a multipart stream (Part 1, "Streaming").
fn part(boundary: &str, q: &Query, body: &str) -> Bytes {
    let format = q.format;
    let body = laid_out(q, body.to_string());
    Bytes::from(format!(
        "--{boundary}\r\nContent-type: {}\r\nContent-length: {}\r\n\r\n{body}\r\n",
        content_type(format),
        body.len()
    ))
}

struct Streaming {
    hub: Arc<Hub>,
    stop: CancellationToken,
    _permit: tokio::sync::OwnedSemaphorePermit,
    request: Request,
    device: Option<usize>,
    q: Query,
    sel: Selection,
    /// Where the next part starts (`/sample`); what the last part saw (`/current`).
    from: Option<u64>,
    boundary: String,
    interval: Duration,
    heartbeat: Duration,
    last_part: Option<Instant>,
    done: bool,
}

/// A part's document, the `nextSequence` it gives and its observations; or an error document.
type Rendered = Result<(String, Option<u64>, usize), String>;

impl Streaming {
    /// The next part's document as the buffer stands, and the buffer's `nextSequence`. A
    /// `/current` part is made when a selected item changed since the last, or when `force`d;
    /// else it holds nothing.
    fn render(&self, force: bool) -> (Rendered, u64) {
        let now = now_us();
        let agent = self.hub.lock();
        let rendered = match self.request {
            Request::Current => {
                let buffer = agent.buffer();
                let changed = match self.from {
                    Some(seen) if seen >= buffer.first() => {
                        let wanted = |i: u32| self.sel.as_ref().is_none_or(|m| m[i as usize]);
                        buffer.sample(seen, 1, wanted).0.len()
                    }
                    _ => 1,
                };
                let next = Some(buffer.next());
                if changed == 0 && !force {
                    Ok((String::new(), next, 0))
                } else {
                    agent
                        .current(self.device, &self.q, now)
                        .map(|d| (d, next, changed))
                }
            }
            _ => {
                let q = Query {
                    from: self.from.map(|f| f as i64),
                    ..self.q.clone()
                };
                agent
                    .sample(self.device, &q, &self.sel, now)
                    .map(|(d, next, n)| (d, Some(next), n))
            }
        };
        let rendered = rendered.map_err(|e| agent.error(&e, self.q.format, now));
        (rendered, agent.buffer().next())
    }

    /// The next part, or `None` when the stream ends (the agent stops, or the client fell
    /// behind the buffer: its last part is an OUT_OF_RANGE error).
    async fn next(&mut self) -> Option<Bytes> {
        if self.done {
            return None;
        }
        let mut watch = self.hub.watch();
        loop {
            let first = self.last_part.is_none();
            if !first {
                // At most one part per interval.
                let earliest = self
                    .last_part
                    .map_or_else(Instant::now, |t| t + self.interval);
                tokio::select! {
                    () = self.stop.cancelled() => return None,
                    () = tokio::time::sleep_until(earliest) => {}
                }
            }
            let heartbeat_due = self
                .last_part
                .is_some_and(|t| t.elapsed() >= self.heartbeat);
            let (rendered, next_seq) = self.render(first || heartbeat_due);
            match rendered {
                Err(body) => {
                    self.done = true;
                    return Some(part(&self.boundary, &self.q, &body));
                }
                Ok((doc, next, n)) => {
                    if let Some(next) = next {
                        self.from = Some(next);
                    }
                    if first || n > 0 || heartbeat_due {
                        self.last_part = Some(Instant::now());
                        return Some(part(&self.boundary, &self.q, &doc));
                    }
                    // Nothing new for this client: wait for the buffer to move on past it,
                    // or for the heartbeat.
                    let wait_for = self.from.unwrap_or(next_seq);
                    let until = self
                        .last_part
                        .map_or_else(Instant::now, |t| t + self.heartbeat);
                    tokio::select! {
                        () = self.stop.cancelled() => return None,
                        () = tokio::time::sleep_until(until) => {}
                        _ = watch.wait_for(|n| *n > wait_for) => {}
                    }
                }
            }
        }
    }
}

fn stream(
    http: &Http,
    request: Request,
    device: Option<usize>,
    q: Query,
    sel: Selection,
) -> Response {
    let Ok(permit) = Arc::clone(&http.streams).try_acquire_owned() else {
        let e = MtError::new(
            ErrorCode::InvalidRequest,
            format!("{MAX_STREAMS} streams are served already; try again later"),
        );
        let mut r = error(http, &e, q.format);
        *r.status_mut() = StatusCode::SERVICE_UNAVAILABLE;
        return r;
    };
    let boundary = format!("{:032x}", rand_u128());
    let content = format!("multipart/x-mixed-replace;boundary={boundary}");
    let s = Streaming {
        hub: Arc::clone(&http.hub),
        stop: http.stop.clone(),
        _permit: permit,
        request,
        device,
        interval: Duration::from_millis(q.interval.unwrap_or(0)).max(MIN_INTERVAL),
        heartbeat: Duration::from_millis(q.heartbeat.unwrap_or(DEFAULT_HEARTBEAT_MS)),
        from: q.from.map(|f| f as u64),
        q,
        sel,
        boundary,
        last_part: None,
        done: false,
    };
    let body = futures::stream::unfold(s, |mut s| async move {
        let part = s.next().await?;
        Some((Ok::<Bytes, std::convert::Infallible>(part), s))
    });
    (
        StatusCode::OK,
        [(header::CONTENT_TYPE, content)],
        Body::from_stream(body),
    )
        .into_response()
}

/// A boundary no document can hold: random.
fn rand_u128() -> u128 {
    let mut b = [0u8; 16];
    if getrandom::fill(&mut b).is_err() {
        // No randomness: the time still makes a boundary no XML text holds.
        return u128::from(now_us());
    }
    u128::from_le_bytes(b)
}
