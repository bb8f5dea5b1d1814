//! What a request brings, checked before a handler sees it, and before its body is read:
//! who sends it and whether they may ([`Caller`]: the session, the permission, and for a
//! write the origin and the CSRF token), the names in its path ([`Names`]: one key chunk
//! each, so a path never becomes a wildcard or a selector), its query ([`Params`]) and its
//! JSON body ([`JsonObject`]: an object of the documented fields, nothing else). Every
//! refusal is an [`ApiError`], the API's `{code, message}`.

use std::marker::PhantomData;
use std::sync::Arc;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{FromRequest, FromRequestParts, Path, Query, RawPathParams, Request};
use axum::http::request::Parts;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::de::DeserializeOwned;
use serde_json::json;

use super::Console;
use super::auth::{Auth, COOKIE, User};
use crate::bus::keys::is_plain_chunk;
use cellgate_core::config::Permission;
use cellgate_core::pb;

/// Longest name a path may carry (a program name's bound).
const MAX_NAME: usize = 128;

/// A refusal as the API answers it.
#[derive(Debug)]
pub struct ApiError {
    pub status: StatusCode,
    pub code: pb::ErrorCode,
    pub message: String,
    /// Seconds to wait (`Retry-After`), for 429.
    pub retry_after: Option<u64>,
}

impl ApiError {
    pub fn new(status: StatusCode, code: pb::ErrorCode, message: impl Into<String>) -> Self {
        ApiError {
            status,
            code,
            message: message.into(),
            retry_after: None,
        }
    }

    pub fn login() -> Self {
        Self::new(
            StatusCode::UNAUTHORIZED,
            pb::ErrorCode::NotPermitted,
            "log in first",
        )
    }

    pub fn forbidden(p: Permission) -> Self {
        Self::new(
            StatusCode::FORBIDDEN,
            pb::ErrorCode::NotPermitted,
            format!("your roles do not allow {}", p.name()),
        )
    }

    pub fn bad(message: impl Into<String>) -> Self {
        Self::new(
            StatusCode::BAD_REQUEST,
            pb::ErrorCode::InvalidRequest,
            message,
        )
    }

    pub fn too_large(limit: u64) -> Self {
        Self::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            pb::ErrorCode::InvalidRequest,
            format!("the body is over this request's limit of {limit} bytes"),
        )
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut r = (
            self.status,
            Json(json!({ "code": self.code.as_str_name(), "message": self.message })),
        )
            .into_response();
        if let Some(s) = self.retry_after
            && let Ok(v) = HeaderValue::from_str(&s.to_string())
        {
            r.headers_mut().insert(header::RETRY_AFTER, v);
        }
        // Refused for its size or type before its body was read: the body may still be on
        // the way, so the connection ends here, and the client is told not to send its next
        // request on it (it would find it closed).
        if matches!(
            self.status,
            StatusCode::PAYLOAD_TOO_LARGE | StatusCode::UNSUPPORTED_MEDIA_TYPE
        ) {
            r.headers_mut()
                .insert(header::CONNECTION, HeaderValue::from_static("close"));
        }
        r
    }
}

/// The session cookie of a request.
pub fn session_id(headers: &HeaderMap) -> Option<String> {
    cookie(headers, COOKIE)
}

/// The cookie `name` of a request, from any of its `Cookie` headers.
pub fn cookie(headers: &HeaderMap, name: &str) -> Option<String> {
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|h| h.to_str().ok())
        .flat_map(|h| h.split(';'))
        .find_map(|c| {
            let (k, v) = c.trim().split_once('=')?;
            (k == name).then(|| v.to_string())
        })
}

/// The host names the console answers to, so that a page of another site whose name was
/// pointed at this console's address (DNS rebinding) is not served: a request's `Host` must
/// be an address literal (no name can be re-pointed there), `localhost`, or one of
/// `console.host_names`, with the port the console listens on.
#[derive(Debug, Clone)]
pub struct Hosts {
    pub https: bool,
    pub port: u16,
    /// Lower case.
    pub names: Vec<String>,
}

impl Hosts {
    pub fn new(https: bool, port: u16, names: &[String]) -> Self {
        Hosts {
            https,
            port,
            names: names.iter().map(|n| n.to_ascii_lowercase()).collect(),
        }
    }

    /// Whether `host` (a `Host` header: `NAME[:PORT]`, `IP[:PORT]`, `[IPv6][:PORT]`) is one
    /// this console answers to.
    pub fn admits(&self, host: &str) -> bool {
        let default_port = if self.https { 443 } else { 80 };
        let (name, port) = match host.rsplit_once(':') {
            Some((n, p)) if !p.contains(']') && (n.starts_with('[') || !n.contains(':')) => {
                (n, p.parse::<u16>().ok())
            }
            _ => (host, Some(default_port)),
        };
        if port != Some(self.port) {
            return false;
        }
        let name = name.to_ascii_lowercase();
        let literal = name
            .strip_prefix('[')
            .and_then(|n| n.strip_suffix(']'))
            .map_or_else(
                || name.parse::<std::net::Ipv4Addr>().is_ok(),
                |v6| v6.parse::<std::net::Ipv6Addr>().is_ok(),
            );
        literal || name == "localhost" || self.names.contains(&name)
    }

    /// Why a request's `Host` is not one this console answers to, if it is not.
    pub fn check(&self, headers: &HeaderMap) -> Result<(), String> {
        let host = headers
            .get(header::HOST)
            .and_then(|h| h.to_str().ok())
            .unwrap_or("");
        if self.admits(host) {
            Ok(())
        } else {
            Err(format!(
                "this console does not answer to the host {host:?}: reach it by its address, \
                 localhost, or a name listed in console.host_names (port {})",
                self.port
            ))
        }
    }
}

/// Every request: refused with 421 (Misdirected Request) unless its `Host` is one the console
/// answers to ([`Hosts`]), before anything else reads it.
pub async fn host(
    axum::extract::State(hosts): axum::extract::State<Arc<Hosts>>,
    req: Request,
    next: axum::middleware::Next,
) -> Response {
    match hosts.check(req.headers()) {
        Ok(()) => next.run(req).await,
        Err(why) => ApiError::new(
            StatusCode::MISDIRECTED_REQUEST,
            pb::ErrorCode::InvalidRequest,
            why,
        )
        .into_response(),
    }
}

/// Whether a state-changing request comes from the console's own pages: a browser says
/// where a request comes from (`Sec-Fetch-Site`, `Origin`), and a page of another site may
/// not act here even with a token it somehow holds. A client that is no browser sends
/// neither and is judged by its session and token alone. The `Host` the origin is compared
/// with is one the console answers to ([`Hosts`]).
pub fn same_origin(headers: &HeaderMap, hosts: &Hosts) -> Result<(), String> {
    if let Some(site) = headers.get("sec-fetch-site") {
        let site = site.to_str().unwrap_or("?");
        if site != "same-origin" && site != "none" {
            return Err(format!(
                "a request from another site (Sec-Fetch-Site: {site}) may not act here"
            ));
        }
    }
    hosts.check(headers)?;
    if let Some(origin) = headers.get(header::ORIGIN) {
        let origin = origin.to_str().unwrap_or("?");
        let host = headers
            .get(header::HOST)
            .and_then(|h| h.to_str().ok())
            .unwrap_or("");
        let own = format!("{}://{host}", if hosts.https { "https" } else { "http" });
        if host.is_empty() || !origin.eq_ignore_ascii_case(&own) {
            return Err(format!(
                "a request from {origin} may not act here: only this console's own pages may"
            ));
        }
    }
    Ok(())
}

/// What a route needs of its caller: a permission, and for a write the action the audit
/// trail names it by.
pub trait Need: Send + Sync + 'static {
    const PERMISSION: Permission;
    /// `Some(action)` for a write: then the origin and the CSRF token are checked too, and
    /// a refusal goes to the cell's audit trail.
    const WRITE: Option<&'static str>;
}

macro_rules! needs {
    ($($(#[$doc:meta])* $name:ident = $p:ident, $write:expr;)*) => {$(
        $(#[$doc])*
        pub struct $name;
        impl Need for $name {
            const PERMISSION: Permission = Permission::$p;
            const WRITE: Option<&'static str> = $write;
        }
    )*};
}

needs! {
    /// Read the cell's state.
    ReadStatus = StatusRead, None;
    /// Read the program library.
    ReadPrograms = ProgramRead, None;
    /// Read the history and utilisation.
    ReadHistory = HistoryRead, None;
    /// Read the audit trail.
    ReadAudit = AuditRead, None;
    /// Read PLC memory.
    ReadPlcMemory = PlcMem, None;
    /// Submit a job.
    SubmitJob = JobSubmit, Some("job.submit");
    /// Cancel a job.
    CancelJob = JobCancel, Some("job.cancel");
    /// Output DO.
    OutputDo = IoDo, Some("io.do");
    /// Store a program.
    StoreProgram = ProgramWrite, Some("program.store");
    /// Remove a program.
    RemoveProgram = ProgramWrite, Some("program.remove");
    /// Adopt a revision of another program.
    AdoptProgram = ProgramWrite, Some("program.adopt");
    /// Release, lock or unlock a revision.
    ReleaseProgram = ProgramRelease, Some("program.release");
    /// Write a PLC tag.
    SetTag = PlcTag, Some("plc.tag");
}

/// The user of a request that may do what `N` needs: checked from the request's head, so
/// a refused request's body is never read.
pub struct Caller<N> {
    pub user: User,
    /// The session's id.
    pub session: String,
    need: PhantomData<N>,
}

impl<N: Need> FromRequestParts<Arc<Console>> for Caller<N> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, c: &Arc<Console>) -> Result<Self, ApiError> {
        let session = session_id(&parts.headers).unwrap_or_default();
        let user = c.auth.user(&session).ok_or_else(ApiError::login)?;
        let p = N::PERMISSION;
        let refusal = if !user.may(p) {
            Some(ApiError::forbidden(p))
        } else if N::WRITE.is_none() {
            None
        } else if let Err(why) = same_origin(&parts.headers, &c.hosts) {
            Some(ApiError::new(
                StatusCode::FORBIDDEN,
                pb::ErrorCode::NotPermitted,
                why,
            ))
        } else if !Auth::csrf_ok(
            &user,
            parts
                .headers
                .get("x-csrf-token")
                .and_then(|v| v.to_str().ok()),
        ) {
            Some(ApiError::new(
                StatusCode::FORBIDDEN,
                pb::ErrorCode::NotPermitted,
                "missing or wrong X-CSRF-Token: reload the page",
            ))
        } else {
            None
        };
        if let Some(e) = refusal {
            if let Some(action) = N::WRITE {
                let (cell, target) = cell_and_target(parts, c).await;
                tracing::warn!(user = %user.name, cell, target, action, error = %e.message, "console: request refused");
                c.note_refusal(&cell, &user.name, action, p, &target, &e.message);
            }
            return Err(e);
        }
        Ok(Caller {
            user,
            session,
            need: PhantomData,
        })
    }
}

/// The cell a request's path names, and what it acts on (the path's other names).
async fn cell_and_target(parts: &mut Parts, c: &Arc<Console>) -> (String, String) {
    let mut cell = String::new();
    let mut target = Vec::new();
    if let Ok(raw) = RawPathParams::from_request_parts(parts, c).await {
        for (k, v) in &raw {
            if k == "cell" {
                cell = v.to_string();
            } else {
                target.push(v.to_string());
            }
        }
    }
    (cell, target.join("/"))
}

/// The names of a request's path, each one key chunk of at most 128 characters: a name
/// with `/`, `*`, `$`, `?` or `#` is refused (400), so a path never becomes a wildcard or
/// a selector on the bus.
pub struct Names<T>(pub T);

impl<T: DeserializeOwned + Send, S: Send + Sync> FromRequestParts<S> for Names<T> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ApiError> {
        let raw = RawPathParams::from_request_parts(parts, state)
            .await
            .map_err(|e| ApiError::bad(e.body_text()))?;
        for (k, v) in &raw {
            if !is_plain_chunk(v) || v.chars().count() > MAX_NAME {
                return Err(ApiError::bad(format!(
                    "{k} {v:?} is not a name: at most {MAX_NAME} characters, without '/', '*', \
                     '$', '?' or '#'"
                )));
            }
        }
        let Path(t) = Path::<T>::from_request_parts(parts, state)
            .await
            .map_err(|e| ApiError::bad(e.body_text()))?;
        Ok(Names(t))
    }
}

/// A request's query string as `T`; one that does not read is refused (400).
pub struct Params<T>(pub T);

impl<T: DeserializeOwned + Send, S: Send + Sync> FromRequestParts<S> for Params<T> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ApiError> {
        let Query(t) = Query::<T>::from_request_parts(parts, state)
            .await
            .map_err(|e| ApiError::bad(e.body_text()))?;
        Ok(Params(t))
    }
}

/// A JSON object body read as `T` (whose fields deny unknown ones): another content type is
/// refused with 415, anything but an object (an array, a number) with 400, a body over the
/// route's limit with 413.
pub struct JsonObject<T>(pub T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequest<S> for JsonObject<T> {
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, ApiError> {
        let json = req
            .headers()
            .get(header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.split(';').next())
            .is_some_and(|m| m.trim().eq_ignore_ascii_case("application/json"));
        if !json {
            return Err(ApiError::new(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                pb::ErrorCode::InvalidRequest,
                "the body must be JSON (Content-Type: application/json)",
            ));
        }
        let bytes = Bytes::from_request(req, state).await.map_err(|e| {
            let status = e.status();
            ApiError::new(status, pb::ErrorCode::InvalidRequest, e.body_text())
        })?;
        // Read straight into the body's type, never through a map: a field given twice is
        // refused ("duplicate field"), not taken at its last value.
        if bytes.iter().find(|b| !b.is_ascii_whitespace()) != Some(&b'{') {
            return Err(ApiError::bad(
                "the body must be a JSON object with the documented fields",
            ));
        }
        serde_json::from_slice::<T>(&bytes)
            .map(JsonObject)
            .map_err(|e| match e.classify() {
                serde_json::error::Category::Data => ApiError::bad(format!("the body: {e}")),
                _ => ApiError::bad(format!("the body is not JSON: {e}")),
            })
    }
}

/// Unknown paths and methods: the API answers in its own shape, the pages in plain text.
pub async fn not_found(req: Request) -> Response {
    if req.uri().path().starts_with("/api/") {
        ApiError::new(
            StatusCode::NOT_FOUND,
            pb::ErrorCode::NotFound,
            format!("no such API path: {}", req.uri().path()),
        )
        .into_response()
    } else {
        (StatusCode::NOT_FOUND, "no such page\n").into_response()
    }
}

/// A method the path does not take.
pub async fn method_not_allowed(req: Request) -> Response {
    ApiError::new(
        StatusCode::METHOD_NOT_ALLOWED,
        pb::ErrorCode::InvalidRequest,
        format!("{} is not taken on {}", req.method(), req.uri().path()),
    )
    .into_response()
}
