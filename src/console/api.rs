//! The console's JSON API (docs/console.md): each handler is given a caller the route's
//! [`Need`](super::extract::Need) allows (checked from the request's head, before any body
//! is read), asks the cell's gateway over the bus as that user, and answers the gateway's
//! message as proto3 JSON, or its refusal with its code.

use std::collections::BTreeMap;
use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use axum::Json;
use axum::body::Body;
use axum::extract::{ConnectInfo, RawQuery, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use futures::{Stream, StreamExt as _};
use serde::Deserialize;
use serde_json::json;
use tokio::io::{AsyncReadExt as _, AsyncSeekExt as _, AsyncWriteExt as _};

use super::Console;
use super::auth::{COOKIE, DEVICE_COOKIE, DEVICE_MAX_AGE_S, LoginError, User};
use super::extract::{
    AdoptProgram, ApiError, Caller, CancelJob, JsonObject, Names, OutputDo, Params, ReadAudit,
    ReadHistory, ReadPlcMemory, ReadPrograms, ReadStatus, ReleaseProgram, RemoveProgram, SetTag,
    StoreProgram, SubmitJob, cookie, same_origin, session_id,
};
use super::listen::Peer;
use crate::client::{Client, ClientError};
use cellgate_core::pb;

/// How often an event stream asks whether its session is still valid (expiry, a reload).
const SESSION_CHECK_EVERY: Duration = Duration::from_secs(5);

/// The HTTP status of a gateway's error code.
fn status_of(code: pb::ErrorCode) -> StatusCode {
    use pb::ErrorCode as C;
    match code {
        C::InvalidRequest => StatusCode::BAD_REQUEST,
        C::UnknownMachine | C::NotFound => StatusCode::NOT_FOUND,
        C::NotPermitted => StatusCode::FORBIDDEN,
        C::Locked | C::NotReleased | C::Busy | C::QueueFull | C::QuotaExceeded => {
            StatusCode::CONFLICT
        }
        C::StorageFull => StatusCode::INSUFFICIENT_STORAGE,
        C::Unavailable | C::FetchFailed => StatusCode::SERVICE_UNAVAILABLE,
        C::DeadlineExceeded => StatusCode::GATEWAY_TIMEOUT,
        C::NotSupported => StatusCode::NOT_IMPLEMENTED,
        _ => StatusCode::BAD_GATEWAY,
    }
}

impl From<ClientError> for ApiError {
    fn from(e: ClientError) -> Self {
        match &e {
            ClientError::Refused { code, message, .. } => {
                ApiError::new(status_of(*code), *code, message.clone())
            }
            ClientError::InvalidArgument { .. } | ClientError::ProgramName(_) => {
                ApiError::bad(e.to_string())
            }
            ClientError::NotTaken { .. } => ApiError::new(
                StatusCode::FORBIDDEN,
                pb::ErrorCode::NotPermitted,
                format!("{e} (the console's own bus identity lacks the permission)"),
            ),
            _ => ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                pb::ErrorCode::Unavailable,
                e.to_string(),
            ),
        }
    }
}

type ApiResult = Result<Response, ApiError>;

/// A contract message as the API's JSON.
fn message<M: serde::Serialize>(m: &M) -> Response {
    Json(m).into_response()
}

impl Console {
    /// The cell's client, acting as `user`.
    async fn client(&self, cell: &str, user: &User) -> Result<Client, ApiError> {
        let base = self.cell(cell).await.ok_or_else(|| {
            ApiError::new(
                StatusCode::NOT_FOUND,
                pb::ErrorCode::NotFound,
                format!("no gateway of cell {cell} answers"),
            )
        })?;
        Ok(base.with_origin(&pb::RequestOrigin {
            user: user.name.clone(),
            via: "console".to_string(),
        }))
    }
}

// ---- session ---------------------------------------------------------------------------------

fn me_json(c: &Console, u: &User) -> serde_json::Value {
    json!({
        "user": u.name,
        "via": u.via,
        "permissions": u.permissions.iter().map(|p| p.name()).collect::<Vec<_>>(),
        "csrf": u.csrf,
        "secured": c.auth.secured(),
        "expires_unix_ms": c.auth.expires_unix_ms(u).to_string(),
        "mtconnect": c.mtconnect,
    })
}

fn with_cookie(mut r: Response, id: &str, secure: bool, max_age_s: u64) -> Response {
    let cookie = format!(
        "{COOKIE}={id}; Path=/; HttpOnly; SameSite=Strict; Max-Age={max_age_s}{}",
        if secure { "; Secure" } else { "" }
    );
    if let Ok(v) = HeaderValue::from_str(&cookie) {
        r.headers_mut().insert(header::SET_COOKIE, v);
    }
    r
}

/// The device cookie ([`super::throttle`]): sent back with logins only, kept for a year.
fn with_device_cookie(mut r: Response, token: &str, secure: bool) -> Response {
    let cookie = format!(
        "{DEVICE_COOKIE}={token}; Path=/api/v1/login; HttpOnly; SameSite=Strict; \
         Max-Age={DEVICE_MAX_AGE_S}{}",
        if secure { "; Secure" } else { "" }
    );
    if !token.is_empty()
        && let Ok(v) = HeaderValue::from_str(&cookie)
    {
        r.headers_mut().append(header::SET_COOKIE, v);
    }
    r
}

pub async fn me(
    State(c): State<Arc<Console>>,
    ConnectInfo(peer): ConnectInfo<Peer>,
    headers: HeaderMap,
) -> ApiResult {
    if let Some(u) = session_id(&headers).and_then(|id| c.auth.user(&id)) {
        return Ok(Json(me_json(&c, &u)).into_response());
    }
    match c.auth.implicit(peer.certificate_name.as_deref()) {
        Some((id, u)) => Ok(with_cookie(
            Json(me_json(&c, &u)).into_response(),
            &id,
            c.https,
            c.auth.max_age().as_secs(),
        )),
        None => Err(ApiError::login()),
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LoginBody {
    user: String,
    password: String,
}

/// A login is state-changing: only from the console's own pages (or a client that is no
/// browser), throttled per name and address, every failure counted and in the audit.
pub async fn login(
    State(c): State<Arc<Console>>,
    ConnectInfo(peer): ConnectInfo<Peer>,
    headers: HeaderMap,
    JsonObject(body): JsonObject<LoginBody>,
) -> ApiResult {
    same_origin(&headers, &c.hosts)
        .map_err(|why| ApiError::new(StatusCode::FORBIDDEN, pb::ErrorCode::NotPermitted, why))?;
    let device = cookie(&headers, DEVICE_COOKIE);
    match c.auth.login(
        &body.user,
        &body.password,
        peer.addr.ip(),
        device.as_deref(),
    ) {
        Ok((id, u, device)) => {
            tracing::info!(user = %u.name, address = %peer.addr.ip(), "console: logged in");
            let r = with_cookie(
                Json(me_json(&c, &u)).into_response(),
                &id,
                c.https,
                c.auth.max_age().as_secs(),
            );
            Ok(with_device_cookie(r, &device, c.https))
        }
        Err(e) => {
            let throttled = matches!(e, LoginError::Throttled(_));
            tracing::warn!(user = %body.user, address = %peer.addr.ip(), error = %e, "console: login refused");
            if matches!(e, LoginError::Refused | LoginError::Throttled(_)) {
                crate::telemetry::metrics::event(
                    "cellgate.console.login_failures",
                    &[("outcome", if throttled { "throttled" } else { "refused" })],
                    1,
                );
                c.note_login_failure(&body.user, peer.addr.ip(), &e.to_string());
            }
            let mut err = ApiError::new(
                if throttled {
                    StatusCode::TOO_MANY_REQUESTS
                } else {
                    StatusCode::UNAUTHORIZED
                },
                pb::ErrorCode::NotPermitted,
                e.to_string(),
            );
            if let LoginError::Throttled(wait) = e {
                err.retry_after = Some(wait.as_secs_f64().ceil() as u64);
            }
            Err(err)
        }
    }
}

/// Ends the session (its event streams with it). Only from the console's own pages.
pub async fn logout(State(c): State<Arc<Console>>, headers: HeaderMap) -> ApiResult {
    same_origin(&headers, &c.hosts)
        .map_err(|why| ApiError::new(StatusCode::FORBIDDEN, pb::ErrorCode::NotPermitted, why))?;
    if let Some(id) = session_id(&headers) {
        c.auth.logout(&id);
    }
    Ok(with_cookie(
        StatusCode::NO_CONTENT.into_response(),
        "",
        c.https,
        0,
    ))
}

// ---- cells -----------------------------------------------------------------------------------

pub async fn cells(State(c): State<Arc<Console>>, _: Caller<ReadStatus>) -> ApiResult {
    let cells = c.refresh().await;
    let out: Vec<serde_json::Value> = cells
        .iter()
        .map(|(name, admin)| {
            let names = |what: &str| -> Vec<String> {
                admin["config"][what]
                    .as_array()
                    .map(|a| {
                        a.iter()
                            .filter_map(|m| m["name"].as_str().map(str::to_string))
                            .collect()
                    })
                    .unwrap_or_default()
            };
            // The machines that take G05 streams (a `g05` table in the cell file): the pages
            // show G05 for those only.
            let g05: Vec<String> = admin["config"]["machines"]
                .as_array()
                .map(|a| {
                    a.iter()
                        .filter(|m| m["g05"].is_object())
                        .filter_map(|m| m["name"].as_str().map(str::to_string))
                        .collect()
                })
                .unwrap_or_default();
            json!({
                "cell": name,
                "version": admin["version"],
                "machines": names("machines"),
                "plcs": names("plcs"),
                "g05": g05,
                "started_unix_ms": admin["started_unix_ms"],
            })
        })
        .collect();
    Ok(Json(out).into_response())
}

pub async fn overview(
    State(c): State<Arc<Console>>,
    caller: Caller<ReadStatus>,
    Names(cell): Names<String>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    let (machines, plcs) = tokio::join!(client.status(None), client.plc_status(None));
    let machines = machines?;
    // A cell without PLCs answers nothing there: that is no error.
    let plcs = plcs.unwrap_or_default();
    Ok(Json(json!({
        "cell": cell,
        "machines": machines,
        "plcs": plcs,
        "unix_ms": pb::now_ms().to_string(),
    }))
    .into_response())
}

// ---- machines --------------------------------------------------------------------------------

pub async fn machine(
    State(c): State<Arc<Console>>,
    caller: Caller<ReadStatus>,
    Names((cell, m)): Names<(String, String)>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    // Punched programs of the last 30 days from the history, so that they and their
    // comparisons outlive a restart; none where the user may not read the history.
    let punch_query = [
        ("machine", m.as_str()),
        ("kind", "punch"),
        ("order", "newest"),
        ("limit", "50"),
        ("_time", "[now(-30d)..]"),
    ]
    .map(|(k, v)| (k.to_string(), v.to_string()));
    let (status, queue, jobs, recorded) = tokio::join!(
        client.status(Some(&m)),
        client.queue(&m),
        client.recent_jobs(Some(&m)),
        client.history(false, &punch_query)
    );
    let status = status?.into_iter().next().ok_or_else(|| {
        ApiError::new(
            StatusCode::NOT_FOUND,
            pb::ErrorCode::UnknownMachine,
            format!("cell {cell} has no machine {m}"),
        )
    })?;
    let mut jobs = jobs.unwrap_or_default();
    jobs.sort_by_key(|e| std::cmp::Reverse(e.unix_ms));
    let punched_recorded = recorded.is_ok();
    let punched = punched_list(c.live.punched(&cell, &m), recorded.ok());
    Ok(Json(json!({
        "status": status,
        "queue": queue?,
        "jobs": jobs,
        "punched": punched,
        "punched_recorded": punched_recorded,
    }))
    .into_response())
}

/// The programs a machine punched, newest first: those the console saw (with their text)
/// and those the history recorded (without it), each once.
fn punched_list(
    seen: Vec<pb::PunchedProgram>,
    recorded: Option<pb::HistoryPage>,
) -> Vec<pb::PunchedProgram> {
    let mut all = seen;
    for r in recorded.map(|p| p.records).unwrap_or_default() {
        if let Some(pb::history_record::Record::Punch(p)) = r.record
            && !all
                .iter()
                .any(|s| s.unix_ms == p.unix_ms && s.library_name == p.library_name)
        {
            all.push(p);
        }
    }
    all.sort_by_key(|p| std::cmp::Reverse(p.unix_ms));
    all.truncate(50);
    all
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SubmitBody {
    library: String,
    #[serde(default)]
    revision: String,
    #[serde(default)]
    priority: i32,
    #[serde(default)]
    name: String,
}

pub async fn submit(
    State(c): State<Arc<Console>>,
    caller: Caller<SubmitJob>,
    Names((cell, m)): Names<(String, String)>,
    JsonObject(body): JsonObject<SubmitBody>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Library(body.library)),
        revision: body.revision,
        priority: body.priority,
        name: body.name,
        request_id: crate::client::new_request_id(),
        ..Default::default()
    };
    let (accepted, follower) = client.submit(&m, &request).await?;
    follower.close().await;
    Ok(message(&accepted))
}

pub async fn cancel(
    State(c): State<Arc<Console>>,
    caller: Caller<CancelJob>,
    Names((cell, m, job)): Names<(String, String, String)>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    let event = client.cancel_confirmed(&m, &job).await?;
    Ok((StatusCode::ACCEPTED, Json(event)).into_response())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DoBody {
    value: u8,
    mask: Option<u8>,
}

pub async fn set_do(
    State(c): State<Arc<Console>>,
    caller: Caller<OutputDo>,
    Names((cell, m)): Names<(String, String)>,
    JsonObject(body): JsonObject<DoBody>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    Ok(message(&client.set_do(&m, body.value, body.mask).await?))
}

// ---- programs --------------------------------------------------------------------------------

pub async fn programs(
    State(c): State<Arc<Console>>,
    caller: Caller<ReadPrograms>,
    Names(cell): Names<String>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    Ok(Json(client.program_list().await?).into_response())
}

fn text(bytes: Vec<u8>) -> Response {
    ([(header::CONTENT_TYPE, "text/plain; charset=utf-8")], bytes).into_response()
}

pub async fn program(
    State(c): State<Arc<Console>>,
    caller: Caller<ReadPrograms>,
    Names((cell, name)): Names<(String, String)>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    Ok(text(client.program_get(&name).await?))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CommentQuery {
    #[serde(default)]
    comment: String,
}

/// A program upload: checked before its bytes are taken (the caller, then `Content-Length`
/// against `programs.max_inline` and, through the gateway, the name, a lock and the
/// quotas), then streamed to a temporary file within the limit, and sent to the gateway
/// from there, a few stores at a time. The bus takes a program in one message, so a store
/// holds it whole while it is sent: only `UPLOADS_AT_ONCE` are read back into memory at
/// once, and the rest wait as files.
pub async fn program_put(
    State(c): State<Arc<Console>>,
    caller: Caller<StoreProgram>,
    Names((cell, name)): Names<(String, String)>,
    Params(q): Params<CommentQuery>,
    headers: HeaderMap,
    body: Body,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    let limit = client.max_inline();
    let declared = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    if let Some(n) = declared {
        if n > limit {
            return Err(ApiError::too_large(limit));
        }
        // The gateway says now whether it would take a program of that size.
        client.program_check(&name, n).await?;
    }
    let spooled = spool(body, limit).await?;
    let _sending = c.uploads.acquire().await.map_err(|_| {
        ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            pb::ErrorCode::Unavailable,
            "the console is stopping",
        )
    })?;
    let program = spooled.read().await?;
    Ok(message(
        &client.program_store(&name, program, q.comment).await?,
    ))
}

/// An upload held in an unnamed temporary file (gone with it), and its size.
struct Spooled {
    file: tokio::fs::File,
    size: u64,
}

fn spool_failed(what: &str, e: std::io::Error) -> ApiError {
    ApiError::new(
        StatusCode::INSUFFICIENT_STORAGE,
        pb::ErrorCode::StorageFailed,
        format!("the console could not {what} the upload: {e}"),
    )
}

impl Spooled {
    /// The whole upload, read back: call it only once it may be held (a sending slot).
    async fn read(mut self) -> Result<Vec<u8>, ApiError> {
        self.file
            .rewind()
            .await
            .map_err(|e| spool_failed("read", e))?;
        let mut program = Vec::with_capacity(usize::try_from(self.size).unwrap_or(0));
        (&mut self.file)
            .take(self.size)
            .read_to_end(&mut program)
            .await
            .map_err(|e| spool_failed("read", e))?;
        Ok(program)
    }
}

/// Reads an upload into a temporary file, at most `limit` bytes: a slow upload, or one that
/// waits for its turn to be sent, holds a file, not memory.
async fn spool(body: Body, limit: u64) -> Result<Spooled, ApiError> {
    let file = tokio::task::spawn_blocking(tempfile::tempfile)
        .await
        .map_err(|e| spool_failed("hold", std::io::Error::other(e)))?
        .map_err(|e| spool_failed("hold", e))?;
    let mut file = tokio::fs::File::from_std(file);
    let mut stream = body.into_data_stream();
    let mut size = 0u64;
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|e| ApiError::bad(format!("the upload broke off: {e}")))?;
        size += chunk.len() as u64;
        if size > limit {
            return Err(ApiError::too_large(limit));
        }
        file.write_all(&chunk)
            .await
            .map_err(|e| spool_failed("write", e))?;
    }
    file.flush().await.map_err(|e| spool_failed("write", e))?;
    Ok(Spooled { file, size })
}

pub async fn program_delete(
    State(c): State<Arc<Console>>,
    caller: Caller<RemoveProgram>,
    Names((cell, name)): Names<(String, String)>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    Ok(message(&client.program_remove(&name).await?))
}

pub async fn revisions(
    State(c): State<Arc<Console>>,
    caller: Caller<ReadPrograms>,
    Names((cell, name)): Names<(String, String)>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    Ok(message(&client.program_revisions(&name).await?))
}

pub async fn revision(
    State(c): State<Arc<Console>>,
    caller: Caller<ReadPrograms>,
    Names((cell, name, rev)): Names<(String, String, String)>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    Ok(text(client.program_revision(&name, &rev).await?))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiffQuery {
    a: Option<String>,
    b: Option<String>,
    #[serde(default)]
    ignore: String,
}

pub async fn diff(
    State(c): State<Arc<Console>>,
    caller: Caller<ReadPrograms>,
    Names((cell, name)): Names<(String, String)>,
    Params(q): Params<DiffQuery>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    let ignore: Vec<String> = q
        .ignore
        .split(',')
        .filter(|s| !s.is_empty())
        .map(str::to_string)
        .collect();
    let d = client
        .program_diff(
            &name,
            q.a.as_deref().filter(|s| !s.is_empty()),
            q.b.as_deref().filter(|s| !s.is_empty()),
            &ignore,
        )
        .await?;
    Ok(message(&d))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReleaseBody {
    #[serde(default)]
    revision: String,
    state: String,
    #[serde(default)]
    comment: String,
}

pub async fn release(
    State(c): State<Arc<Console>>,
    caller: Caller<ReleaseProgram>,
    Names((cell, name)): Names<(String, String)>,
    JsonObject(body): JsonObject<ReleaseBody>,
) -> ApiResult {
    let state = pb::RevisionState::from_str_name(&body.state)
        .filter(|s| *s != pb::RevisionState::Unspecified)
        .ok_or_else(|| {
            ApiError::bad(format!(
                "state {:?}: REVISION_STATE_RELEASED, REVISION_STATE_LOCKED or REVISION_STATE_DRAFT",
                body.state
            ))
        })?;
    let client = c.client(&cell, &caller.user).await?;
    let r = client
        .program_release(&name, &body.revision, state, body.comment)
        .await?;
    Ok(message(&r))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AdoptBody {
    from: String,
    #[serde(default)]
    revision: String,
    #[serde(default)]
    comment: String,
}

pub async fn adopt(
    State(c): State<Arc<Console>>,
    caller: Caller<AdoptProgram>,
    Names((cell, name)): Names<(String, String)>,
    JsonObject(body): JsonObject<AdoptBody>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    let info = client
        .program_adopt(&name, &body.from, &body.revision, body.comment)
        .await?;
    Ok(message(&info))
}

// ---- PLC -------------------------------------------------------------------------------------

pub async fn plc(
    State(c): State<Arc<Console>>,
    caller: Caller<ReadStatus>,
    Names((cell, p)): Names<(String, String)>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    let status = client
        .plc_status(Some(&p))
        .await?
        .into_iter()
        .next()
        .ok_or_else(|| {
            ApiError::new(
                StatusCode::NOT_FOUND,
                pb::ErrorCode::UnknownMachine,
                format!("cell {cell} has no PLC {p}"),
            )
        })?;
    Ok(message(&status))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TagBody {
    value: f64,
}

pub async fn tag_set(
    State(c): State<Arc<Console>>,
    caller: Caller<SetTag>,
    Names((cell, p, tag)): Names<(String, String, String)>,
    JsonObject(body): JsonObject<TagBody>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    Ok(message(
        &client.tag_set(&format!("{p}/{tag}"), body.value).await?,
    ))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CountQuery {
    count: Option<usize>,
}

pub async fn mem(
    State(c): State<Arc<Console>>,
    caller: Caller<ReadPlcMemory>,
    Names((cell, p, station, module, address)): Names<(String, String, u8, String, u16)>,
    Params(q): Params<CountQuery>,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    let words = client
        .plc_read(&p, station, &module, address, q.count.unwrap_or(1))
        .await?;
    Ok(message(&words))
}

// ---- history ---------------------------------------------------------------------------------

/// The query string as selector parameters (`a=b&c=d` → `[(a, b), (c, d)]`), without
/// `format`.
fn params(raw: Option<String>) -> (Vec<(String, String)>, bool) {
    let mut csv = false;
    let mut out = Vec::new();
    for (k, v) in form_urlencoded::parse(raw.unwrap_or_default().as_bytes()) {
        if k == "format" {
            csv = v == "csv";
        } else {
            out.push((k.into_owned(), v.into_owned()));
        }
    }
    (out, csv)
}

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// A record's fields as flat `(path, value)` pairs, paths dotted (`job.bytes`,
/// `origin.user`), lists numbered (`tags.0`): a spreadsheet's columns.
fn flatten(prefix: &str, v: &serde_json::Value, out: &mut Vec<(String, String)>) {
    let path = |k: &str| {
        if prefix.is_empty() {
            k.to_string()
        } else {
            format!("{prefix}.{k}")
        }
    };
    match v {
        serde_json::Value::Object(o) => {
            for (k, v) in o {
                flatten(&path(k), v, out);
            }
        }
        serde_json::Value::Array(a) => {
            for (i, v) in a.iter().enumerate() {
                flatten(&path(&i.to_string()), v, out);
            }
        }
        serde_json::Value::Null => {}
        serde_json::Value::String(s) => out.push((prefix.to_string(), s.clone())),
        other => out.push((prefix.to_string(), other.to_string())),
    }
}

/// A history page as CSV: time, number, machine, kind, the record in words (as `cellgate
/// history` prints it), then one column for each field any record of the page has, by its
/// dotted path: no column holds JSON.
fn csv(page: &pb::HistoryPage) -> Response {
    const FIXED: [&str; 4] = ["unix_ms", "seq", "machine", "kind"];
    let rows: Vec<Vec<(String, String)>> = page
        .records
        .iter()
        .map(|r| {
            let mut fields = Vec::new();
            if let Ok(serde_json::Value::Object(o)) = serde_json::to_value(r) {
                for (k, v) in o.iter().filter(|(k, _)| !FIXED.contains(&k.as_str())) {
                    flatten(k, v, &mut fields);
                }
            }
            fields
        })
        .collect();
    // The columns in the order they first appear.
    let mut columns: Vec<&str> = Vec::new();
    for (path, _) in rows.iter().flatten() {
        if !columns.contains(&path.as_str()) {
            columns.push(path);
        }
    }
    let mut out = String::from("unix_ms,utc,seq,machine,kind,text");
    for c in &columns {
        out.push(',');
        out.push_str(&csv_field(c));
    }
    out.push('\n');
    for (r, fields) in page.records.iter().zip(&rows) {
        out.push_str(&format!(
            "{},{},{},{},{},{}",
            r.unix_ms,
            crate::client::render::date_time(r.unix_ms),
            r.seq,
            csv_field(&r.machine),
            r.kind().as_str_name(),
            csv_field(&crate::client::cli::records::record_text(r)),
        ));
        for c in &columns {
            out.push(',');
            if let Some((_, v)) = fields.iter().find(|(p, _)| p == c) {
                out.push_str(&csv_field(v));
            }
        }
        out.push('\n');
    }
    (
        [
            (header::CONTENT_TYPE, "text/csv; charset=utf-8"),
            (
                header::CONTENT_DISPOSITION,
                "attachment; filename=\"cellgate-history.csv\"",
            ),
        ],
        out,
    )
        .into_response()
}

async fn records(
    c: &Console,
    cell: &str,
    user: &User,
    raw: Option<String>,
    audit: bool,
) -> ApiResult {
    let client = c.client(cell, user).await?;
    let (params, as_csv) = params(raw);
    let page = client.history(audit, &params).await?;
    Ok(if as_csv { csv(&page) } else { message(&page) })
}

pub async fn history(
    State(c): State<Arc<Console>>,
    caller: Caller<ReadHistory>,
    Names(cell): Names<String>,
    RawQuery(raw): RawQuery,
) -> ApiResult {
    records(&c, &cell, &caller.user, raw, false).await
}

pub async fn audit(
    State(c): State<Arc<Console>>,
    caller: Caller<ReadAudit>,
    Names(cell): Names<String>,
    RawQuery(raw): RawQuery,
) -> ApiResult {
    records(&c, &cell, &caller.user, raw, true).await
}

pub async fn utilisation(
    State(c): State<Arc<Console>>,
    caller: Caller<ReadHistory>,
    Names(cell): Names<String>,
    RawQuery(raw): RawQuery,
) -> ApiResult {
    let client = c.client(&cell, &caller.user).await?;
    let (params, _) = params(raw);
    Ok(message(&client.utilisation(&params).await?))
}

// ---- live ------------------------------------------------------------------------------------

/// The cell's events as they happen, for as long as the session lasts: a logout, the end
/// of the session (idle, its hours, a user's other sessions) or a change of the user's
/// roles ends the stream.
pub async fn events(
    State(c): State<Arc<Console>>,
    caller: Caller<ReadStatus>,
    Names(cell): Names<String>,
    RawQuery(raw): RawQuery,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ApiError> {
    let machines: Vec<String> = form_urlencoded::parse(raw.unwrap_or_default().as_bytes())
        .filter(|(k, _)| k == "machine")
        .map(|(_, v)| v.into_owned())
        .collect();
    let rx = c.live.subscribe();
    let ended = caller.user.ended.clone();
    let mut check = tokio::time::interval(SESSION_CHECK_EVERY);
    check.reset();
    // The stream ends with the console too, so that a page left open never holds up its stop.
    let state = (rx, cell, machines, c.clone(), ended, caller.session, check);
    let stream = futures::stream::unfold(
        state,
        |(mut rx, cell, machines, c, ended, session, mut check)| async move {
            loop {
                let got = tokio::select! {
                    () = c.stop.cancelled() => return None,
                    () = ended.cancelled() => return None,
                    _ = check.tick() => {
                        if c.auth.live(&session) {
                            continue;
                        }
                        return None;
                    }
                    got = rx.recv() => got,
                };
                let event = match got {
                    Ok(e) => {
                        if e.cell != cell || (!machines.is_empty() && !machines.contains(&e.name)) {
                            continue;
                        }
                        Event::default().event(e.kind).data(e.json.clone())
                    }
                    // The page fell behind: it reloads what it shows.
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {
                        Event::default().event("resync").data("{}")
                    }
                    Err(_) => return None,
                };
                return Some((
                    Ok::<_, Infallible>(event),
                    (rx, cell, machines, c, ended, session, check),
                ));
            }
        },
    );
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}

// ---- health ----------------------------------------------------------------------------------

pub async fn health(State(c): State<Arc<Console>>) -> Response {
    let cells: BTreeMap<String, serde_json::Value> = c.refresh().await;
    let ok = !cells.is_empty();
    let body = json!({ "ok": ok, "cells": cells.keys().collect::<Vec<_>>() });
    let status = if ok {
        StatusCode::OK
    } else {
        StatusCode::SERVICE_UNAVAILABLE
    };
    (status, Json(body)).into_response()
}

pub async fn metrics(State(c): State<Arc<Console>>) -> Response {
    match &c.metrics {
        None => (StatusCode::NOT_FOUND, "no metrics here\n").into_response(),
        Some(e) => match e.render() {
            Ok(text) => {
                ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], text).into_response()
            }
            Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
        },
    }
}
