//! The console's JSON API (docs/console.md): each handler checks the user's permission, asks
//! the cell's gateway over the bus as that user, and answers the gateway's message as proto3
//! JSON, or its refusal with its code.

use std::collections::BTreeMap;
use std::convert::Infallible;
use std::sync::Arc;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{ConnectInfo, Path, Query, RawQuery, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use futures::Stream;
use serde::Deserialize;
use serde_json::json;

use super::Console;
use super::auth::{Auth, COOKIE, User};
use super::listen::Peer;
use crate::client::{Client, ClientError};
use cellgate_core::config::Permission;
use cellgate_core::pb;

/// A refusal as the API answers it.
#[derive(Debug)]
pub struct ApiError {
    status: StatusCode,
    code: pb::ErrorCode,
    message: String,
}

impl ApiError {
    pub fn new(status: StatusCode, code: pb::ErrorCode, message: impl Into<String>) -> Self {
        ApiError {
            status,
            code,
            message: message.into(),
        }
    }

    fn login() -> Self {
        Self::new(
            StatusCode::UNAUTHORIZED,
            pb::ErrorCode::NotPermitted,
            "log in first",
        )
    }

    fn forbidden(p: Permission) -> Self {
        Self::new(
            StatusCode::FORBIDDEN,
            pb::ErrorCode::NotPermitted,
            format!("your roles do not allow {}", p.name()),
        )
    }

    fn bad(message: impl Into<String>) -> Self {
        Self::new(
            StatusCode::BAD_REQUEST,
            pb::ErrorCode::InvalidRequest,
            message,
        )
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (
            self.status,
            Json(json!({ "code": self.code.as_str_name(), "message": self.message })),
        )
            .into_response()
    }
}

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

fn session_id(headers: &HeaderMap) -> Option<String> {
    let cookies = headers.get(header::COOKIE)?.to_str().ok()?;
    cookies.split(';').find_map(|c| {
        let (k, v) = c.trim().split_once('=')?;
        (k == COOKIE).then(|| v.to_string())
    })
}

impl Console {
    /// The user of a request: its session, with the permission `p` and, for a write, the
    /// CSRF token. A refusal of a write is in the console's log and the cell's audit trail.
    async fn allowed(
        &self,
        headers: &HeaderMap,
        p: Permission,
        write: Option<(&str, &str, &str)>,
    ) -> Result<User, ApiError> {
        let user = session_id(headers)
            .and_then(|id| self.auth.user(&id))
            .ok_or_else(ApiError::login)?;
        let csrf_ok = write.is_none()
            || Auth::csrf_ok(
                &user,
                headers.get("x-csrf-token").and_then(|v| v.to_str().ok()),
            );
        let refusal = if !user.may(p) {
            Some(ApiError::forbidden(p))
        } else if !csrf_ok {
            Some(ApiError::new(
                StatusCode::FORBIDDEN,
                pb::ErrorCode::NotPermitted,
                "missing or wrong X-CSRF-Token: reload the page",
            ))
        } else {
            None
        };
        if let Some(e) = refusal {
            if let Some((cell, target, action)) = write {
                tracing::warn!(user = %user.name, cell, target, action, error = %e.message, "console: request refused");
                self.note_refusal(cell, &user, action, p, target, &e.message)
                    .await;
            }
            return Err(e);
        }
        Ok(user)
    }

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
            c.session_max_s,
        )),
        None => Err(ApiError::login()),
    }
}

#[derive(Deserialize)]
pub struct LoginBody {
    user: String,
    password: String,
}

pub async fn login(State(c): State<Arc<Console>>, body: Json<LoginBody>) -> ApiResult {
    match c.auth.login(&body.user, &body.password) {
        Ok((id, u)) => {
            tracing::info!(user = %u.name, "console: logged in");
            Ok(with_cookie(
                Json(me_json(&c, &u)).into_response(),
                &id,
                c.https,
                c.session_max_s,
            ))
        }
        Err(e) => {
            tracing::warn!(user = %body.user, error = %e, "console: login refused");
            Err(ApiError::new(
                StatusCode::UNAUTHORIZED,
                pb::ErrorCode::NotPermitted,
                e.to_string(),
            ))
        }
    }
}

pub async fn logout(State(c): State<Arc<Console>>, headers: HeaderMap) -> Response {
    if let Some(id) = session_id(&headers) {
        c.auth.logout(&id);
    }
    with_cookie(StatusCode::NO_CONTENT.into_response(), "", c.https, 0)
}

// ---- cells -----------------------------------------------------------------------------------

pub async fn cells(State(c): State<Arc<Console>>, headers: HeaderMap) -> ApiResult {
    c.allowed(&headers, Permission::StatusRead, None).await?;
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
            json!({
                "cell": name,
                "version": admin["version"],
                "machines": names("machines"),
                "plcs": names("plcs"),
                "started_unix_ms": admin["started_unix_ms"],
            })
        })
        .collect();
    Ok(Json(out).into_response())
}

pub async fn overview(
    State(c): State<Arc<Console>>,
    Path(cell): Path<String>,
    headers: HeaderMap,
) -> ApiResult {
    let user = c.allowed(&headers, Permission::StatusRead, None).await?;
    let client = c.client(&cell, &user).await?;
    let (machines, plcs) = tokio::join!(client.status(None), client.plc_status(None));
    let machines = machines?;
    // A cell without PLCs answers nothing there: that is no error.
    let plcs = plcs.unwrap_or_default();
    Ok(Json(json!({
        "cell": cell,
        "machines": machines,
        "plcs": plcs,
        "unix_ms": pb::unix_ms(std::time::SystemTime::now()).to_string(),
    }))
    .into_response())
}

// ---- machines --------------------------------------------------------------------------------

pub async fn machine(
    State(c): State<Arc<Console>>,
    Path((cell, m)): Path<(String, String)>,
    headers: HeaderMap,
) -> ApiResult {
    let user = c.allowed(&headers, Permission::StatusRead, None).await?;
    let client = c.client(&cell, &user).await?;
    let (status, queue, jobs) = tokio::join!(
        client.status(Some(&m)),
        client.queue(&m),
        client.recent_jobs(Some(&m))
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
    Ok(Json(json!({
        "status": status,
        "queue": queue?,
        "jobs": jobs,
        "punched": c.live.punched(&cell, &m),
    }))
    .into_response())
}

#[derive(Deserialize)]
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
    Path((cell, m)): Path<(String, String)>,
    headers: HeaderMap,
    body: Json<SubmitBody>,
) -> ApiResult {
    let user = c
        .allowed(
            &headers,
            Permission::JobSubmit,
            Some((&cell, &m, "job.submit")),
        )
        .await?;
    let client = c.client(&cell, &user).await?;
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Library(body.library.clone())),
        revision: body.revision.clone(),
        priority: body.priority,
        name: body.name.clone(),
        request_id: crate::client::cli::new_request_id(),
        ..Default::default()
    };
    let (accepted, follower) = client.submit(&m, &request).await?;
    follower.close().await;
    Ok(message(&accepted))
}

pub async fn cancel(
    State(c): State<Arc<Console>>,
    Path((cell, m, job)): Path<(String, String, String)>,
    headers: HeaderMap,
) -> ApiResult {
    let user = c
        .allowed(
            &headers,
            Permission::JobCancel,
            Some((&cell, &job, "job.cancel")),
        )
        .await?;
    let client = c.client(&cell, &user).await?;
    let event = client.cancel_confirmed(&m, &job).await?;
    Ok((StatusCode::ACCEPTED, Json(event)).into_response())
}

#[derive(Deserialize)]
pub struct DoBody {
    value: u8,
    mask: Option<u8>,
}

pub async fn set_do(
    State(c): State<Arc<Console>>,
    Path((cell, m)): Path<(String, String)>,
    headers: HeaderMap,
    body: Json<DoBody>,
) -> ApiResult {
    let user = c
        .allowed(&headers, Permission::IoDo, Some((&cell, &m, "io.do")))
        .await?;
    let client = c.client(&cell, &user).await?;
    Ok(message(&client.set_do(&m, body.value, body.mask).await?))
}

// ---- programs --------------------------------------------------------------------------------

pub async fn programs(
    State(c): State<Arc<Console>>,
    Path(cell): Path<String>,
    headers: HeaderMap,
) -> ApiResult {
    let user = c.allowed(&headers, Permission::ProgramRead, None).await?;
    let client = c.client(&cell, &user).await?;
    Ok(Json(client.program_list().await?).into_response())
}

fn text(bytes: Vec<u8>) -> Response {
    ([(header::CONTENT_TYPE, "text/plain; charset=utf-8")], bytes).into_response()
}

pub async fn program(
    State(c): State<Arc<Console>>,
    Path((cell, name)): Path<(String, String)>,
    headers: HeaderMap,
) -> ApiResult {
    let user = c.allowed(&headers, Permission::ProgramRead, None).await?;
    let client = c.client(&cell, &user).await?;
    Ok(text(client.program_get(&name).await?))
}

#[derive(Deserialize)]
pub struct CommentQuery {
    #[serde(default)]
    comment: String,
}

pub async fn program_put(
    State(c): State<Arc<Console>>,
    Path((cell, name)): Path<(String, String)>,
    Query(q): Query<CommentQuery>,
    headers: HeaderMap,
    body: Bytes,
) -> ApiResult {
    let user = c
        .allowed(
            &headers,
            Permission::ProgramWrite,
            Some((&cell, &name, "program.store")),
        )
        .await?;
    let client = c.client(&cell, &user).await?;
    Ok(message(
        &client.program_put_with(&name, &body, q.comment).await?,
    ))
}

pub async fn program_delete(
    State(c): State<Arc<Console>>,
    Path((cell, name)): Path<(String, String)>,
    headers: HeaderMap,
) -> ApiResult {
    let user = c
        .allowed(
            &headers,
            Permission::ProgramWrite,
            Some((&cell, &name, "program.remove")),
        )
        .await?;
    let client = c.client(&cell, &user).await?;
    Ok(message(&client.program_remove(&name).await?))
}

pub async fn revisions(
    State(c): State<Arc<Console>>,
    Path((cell, name)): Path<(String, String)>,
    headers: HeaderMap,
) -> ApiResult {
    let user = c.allowed(&headers, Permission::ProgramRead, None).await?;
    let client = c.client(&cell, &user).await?;
    Ok(message(&client.program_revisions(&name).await?))
}

pub async fn revision(
    State(c): State<Arc<Console>>,
    Path((cell, name, rev)): Path<(String, String, String)>,
    headers: HeaderMap,
) -> ApiResult {
    let user = c.allowed(&headers, Permission::ProgramRead, None).await?;
    let client = c.client(&cell, &user).await?;
    Ok(text(client.program_revision(&name, &rev).await?))
}

#[derive(Deserialize)]
pub struct DiffQuery {
    a: Option<String>,
    b: Option<String>,
    #[serde(default)]
    ignore: String,
}

pub async fn diff(
    State(c): State<Arc<Console>>,
    Path((cell, name)): Path<(String, String)>,
    Query(q): Query<DiffQuery>,
    headers: HeaderMap,
) -> ApiResult {
    let user = c.allowed(&headers, Permission::ProgramRead, None).await?;
    let client = c.client(&cell, &user).await?;
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
pub struct ReleaseBody {
    #[serde(default)]
    revision: String,
    state: String,
    #[serde(default)]
    comment: String,
}

pub async fn release(
    State(c): State<Arc<Console>>,
    Path((cell, name)): Path<(String, String)>,
    headers: HeaderMap,
    body: Json<ReleaseBody>,
) -> ApiResult {
    let user = c
        .allowed(
            &headers,
            Permission::ProgramRelease,
            Some((&cell, &name, "program.release")),
        )
        .await?;
    let state = pb::RevisionState::from_str_name(&body.state)
        .filter(|s| *s != pb::RevisionState::Unspecified)
        .ok_or_else(|| {
            ApiError::bad(format!(
                "state {:?}: REVISION_STATE_RELEASED, REVISION_STATE_LOCKED or REVISION_STATE_DRAFT",
                body.state
            ))
        })?;
    let client = c.client(&cell, &user).await?;
    let r = client
        .program_release(&name, &body.revision, state, body.comment.clone())
        .await?;
    Ok(message(&r))
}

#[derive(Deserialize)]
pub struct AdoptBody {
    from: String,
    #[serde(default)]
    revision: String,
    #[serde(default)]
    comment: String,
}

pub async fn adopt(
    State(c): State<Arc<Console>>,
    Path((cell, name)): Path<(String, String)>,
    headers: HeaderMap,
    body: Json<AdoptBody>,
) -> ApiResult {
    let user = c
        .allowed(
            &headers,
            Permission::ProgramWrite,
            Some((&cell, &name, "program.adopt")),
        )
        .await?;
    let client = c.client(&cell, &user).await?;
    let info = client
        .program_adopt(&name, &body.from, &body.revision, body.comment.clone())
        .await?;
    Ok(message(&info))
}

// ---- PLC -------------------------------------------------------------------------------------

pub async fn plc(
    State(c): State<Arc<Console>>,
    Path((cell, p)): Path<(String, String)>,
    headers: HeaderMap,
) -> ApiResult {
    let user = c.allowed(&headers, Permission::StatusRead, None).await?;
    let client = c.client(&cell, &user).await?;
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
pub struct TagBody {
    value: f64,
}

pub async fn tag_set(
    State(c): State<Arc<Console>>,
    Path((cell, p, tag)): Path<(String, String, String)>,
    headers: HeaderMap,
    body: Json<TagBody>,
) -> ApiResult {
    let target = format!("{p}/{tag}");
    let user = c
        .allowed(
            &headers,
            Permission::PlcTag,
            Some((&cell, &target, "plc.tag")),
        )
        .await?;
    let client = c.client(&cell, &user).await?;
    Ok(message(&client.tag_set(&target, body.value).await?))
}

#[derive(Deserialize)]
pub struct CountQuery {
    count: Option<usize>,
}

pub async fn mem(
    State(c): State<Arc<Console>>,
    Path((cell, p, station, module, address)): Path<(String, String, u8, String, u16)>,
    Query(q): Query<CountQuery>,
    headers: HeaderMap,
) -> ApiResult {
    let user = c.allowed(&headers, Permission::PlcMem, None).await?;
    let client = c.client(&cell, &user).await?;
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

/// A history page as CSV: time, number, machine, kind, and the record's JSON.
fn csv(page: &pb::HistoryPage) -> Response {
    let mut out = String::from("unix_ms,utc,seq,machine,kind,record\n");
    for r in &page.records {
        let record = serde_json::to_value(r)
            .ok()
            .map(|mut v| {
                for k in ["unix_ms", "seq", "machine", "kind"] {
                    if let Some(o) = v.as_object_mut() {
                        o.remove(k);
                    }
                }
                v.to_string()
            })
            .unwrap_or_default();
        out.push_str(&format!(
            "{},{},{},{},{},{}\n",
            r.unix_ms,
            crate::client::render::date_time(r.unix_ms),
            r.seq,
            csv_field(&r.machine),
            r.kind().as_str_name(),
            csv_field(&record)
        ));
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
    headers: &HeaderMap,
    raw: Option<String>,
    audit: bool,
) -> ApiResult {
    let p = if audit {
        Permission::AuditRead
    } else {
        Permission::HistoryRead
    };
    let user = c.allowed(headers, p, None).await?;
    let client = c.client(cell, &user).await?;
    let (params, as_csv) = params(raw);
    let page = client.history(audit, &params).await?;
    Ok(if as_csv { csv(&page) } else { message(&page) })
}

pub async fn history(
    State(c): State<Arc<Console>>,
    Path(cell): Path<String>,
    RawQuery(raw): RawQuery,
    headers: HeaderMap,
) -> ApiResult {
    records(&c, &cell, &headers, raw, false).await
}

pub async fn audit(
    State(c): State<Arc<Console>>,
    Path(cell): Path<String>,
    RawQuery(raw): RawQuery,
    headers: HeaderMap,
) -> ApiResult {
    records(&c, &cell, &headers, raw, true).await
}

pub async fn utilisation(
    State(c): State<Arc<Console>>,
    Path(cell): Path<String>,
    RawQuery(raw): RawQuery,
    headers: HeaderMap,
) -> ApiResult {
    let user = c.allowed(&headers, Permission::HistoryRead, None).await?;
    let client = c.client(&cell, &user).await?;
    let (params, _) = params(raw);
    Ok(message(&client.utilisation(&params).await?))
}

// ---- live ------------------------------------------------------------------------------------

pub async fn events(
    State(c): State<Arc<Console>>,
    Path(cell): Path<String>,
    RawQuery(raw): RawQuery,
    headers: HeaderMap,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ApiError> {
    c.allowed(&headers, Permission::StatusRead, None).await?;
    let machines: Vec<String> = form_urlencoded::parse(raw.unwrap_or_default().as_bytes())
        .filter(|(k, _)| k == "machine")
        .map(|(_, v)| v.into_owned())
        .collect();
    let rx = c.live.subscribe();
    // The stream ends with the console, so that a page left open never holds up its stop.
    let state = (rx, cell, machines, c.stop.clone());
    let stream = futures::stream::unfold(state, |(mut rx, cell, machines, stop)| async move {
        loop {
            let got = tokio::select! {
                () = stop.cancelled() => return None,
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
            return Some((Ok::<_, Infallible>(event), (rx, cell, machines, stop)));
        }
    });
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
