//! The console's pages, compiled into the binary: nothing is fetched from anywhere else
//! (the Content-Security-Policy says so to the browser too).

use axum::extract::{Path, Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

/// The files under `assets/`.
static FILES: include_dir::Dir<'_> =
    include_dir::include_dir!("$CARGO_MANIFEST_DIR/src/console/assets");

fn kind(name: &str) -> &'static str {
    match name.rsplit_once('.').map(|(_, e)| e) {
        Some("html") => "text/html; charset=utf-8",
        Some("js") => "text/javascript; charset=utf-8",
        Some("css") => "text/css; charset=utf-8",
        Some("svg") => "image/svg+xml",
        Some("png") => "image/png",
        _ => "application/octet-stream",
    }
}

fn serve(name: &str) -> Response {
    // One level only: a name with a separator is no asset.
    if name.contains(['/', '\\']) {
        return (StatusCode::NOT_FOUND, "no such file\n").into_response();
    }
    match FILES.get_file(name) {
        Some(f) => ([(header::CONTENT_TYPE, kind(name))], f.contents()).into_response(),
        None => (StatusCode::NOT_FOUND, "no such file\n").into_response(),
    }
}

/// `/`: the single page.
pub async fn index() -> Response {
    serve("index.html")
}

/// `/assets/FILE`.
pub async fn file(Path(name): Path<String>) -> Response {
    serve(&name)
}

/// Headers every answer carries: only this origin's scripts, styles and connections; no
/// framing, no opener or embedding from elsewhere; no caching of the API's answers; under
/// TLS, HTTPS only from now on (HSTS).
pub async fn headers(State(https): State<bool>, req: Request, next: Next) -> Response {
    let api = req.uri().path().starts_with("/api/");
    let mut r = next.run(req).await;
    add_headers(r.headers_mut(), https, api);
    r
}

fn add_headers(h: &mut axum::http::HeaderMap, https: bool, api: bool) {
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(
            "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; \
             connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'self'",
        ),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    h.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    h.insert(
        "cross-origin-opener-policy",
        HeaderValue::from_static("same-origin"),
    );
    h.insert(
        "cross-origin-resource-policy",
        HeaderValue::from_static("same-origin"),
    );
    h.insert(
        "permissions-policy",
        HeaderValue::from_static("camera=(), microphone=(), geolocation=(), usb=(), serial=()"),
    );
    if https {
        h.insert(
            header::STRICT_TRANSPORT_SECURITY,
            HeaderValue::from_static("max-age=31536000"),
        );
    }
    if api {
        h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hsts_under_tls_only_and_the_usual_headers_always() {
        for https in [false, true] {
            let mut h = axum::http::HeaderMap::new();
            add_headers(&mut h, https, true);
            assert_eq!(h.contains_key(header::STRICT_TRANSPORT_SECURITY), https);
            for name in [
                "content-security-policy",
                "x-content-type-options",
                "x-frame-options",
                "referrer-policy",
                "cross-origin-opener-policy",
                "cross-origin-resource-policy",
                "cache-control",
            ] {
                assert!(h.contains_key(name), "{name}");
            }
        }
    }
}
