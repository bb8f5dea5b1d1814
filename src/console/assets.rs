//! The console's pages, compiled into the binary: nothing is fetched from anywhere else
//! (the Content-Security-Policy says so to the browser too).

use axum::extract::Path;
use axum::http::{StatusCode, header};
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
        Some("ico") => "image/x-icon",
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

/// `/favicon.ico`: where a browser looks for the icon when a page names none (the pages
/// name `/assets/favicon.svg`), so that the request never ends in a 404.
pub async fn favicon() -> Response {
    serve("favicon.ico")
}

/// `/assets/FILE`.
pub async fn file(Path(name): Path<String>) -> Response {
    serve(&name)
}
