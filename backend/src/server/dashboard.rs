//! The dashboard's static files (Trunk's `dist/`) behind the API routes:
//! served without following symbolic links, or a note on how to build it.

use std::path::PathBuf;
use std::sync::Arc;

use axum::extract::State;
use axum::http::StatusCode;
use axum::response::{Html, IntoResponse, Response};
use axum::Router;
use tower_http::services::ServeDir;

/// `api` with the dashboard in `dist` as its fallback: the files (symbolic
/// links inside `dist` are not followed: 404; only the files really in the
/// directory are served), or, if `dist` has no `index.html`, a note on how
/// to build it.
pub(super) fn fallback(api: Router, dist: PathBuf) -> Router {
    if dist.join("index.html").is_file() {
        let root = std::fs::canonicalize(&dist).unwrap_or_else(|_| dist.clone());
        let files = Router::new().fallback_service(ServeDir::new(&root)).layer(
            axum::middleware::from_fn_with_state(Arc::new(root), refuse_links),
        );
        api.fallback_service(files)
    } else {
        let note = dashboard_missing_note(&dist);
        api.fallback(move || {
            let note = note.clone();
            async move { Html(note) }
        })
    }
}

/// 404 for a dashboard path that passes through a symbolic link inside
/// `root` (or resolves outside it); otherwise on to `ServeDir`, which reads
/// the path the same way (percent-decoded, `.` skipped, `..` refused).
async fn refuse_links(
    State(root): State<Arc<PathBuf>>,
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
    match dist_path_is_plain(&root, request.uri().path()).await {
        true => next.run(request).await,
        false => (StatusCode::NOT_FOUND, "not found").into_response(),
    }
}

/// Whether every component of the file `path` names under `root` (and
/// `index.html` of a directory) is a plain file or directory, and the file
/// lies inside `root`. A path that does not exist is plain (`ServeDir`
/// answers 404).
async fn dist_path_is_plain(root: &std::path::Path, path: &str) -> bool {
    let Some(decoded) = percent_decode(path.trim_start_matches('/')) else {
        return false;
    };
    let mut here = root.to_path_buf();
    for component in std::path::Path::new(&decoded).components() {
        match component {
            std::path::Component::Normal(c) => here.push(c),
            std::path::Component::CurDir => continue,
            _ => return false,
        }
        match tokio::fs::symlink_metadata(&here).await {
            Ok(m) if m.file_type().is_symlink() => return false,
            Ok(_) => {}
            Err(_) => return true,
        }
    }
    if tokio::fs::metadata(&here).await.is_ok_and(|m| m.is_dir()) {
        here.push("index.html");
        if tokio::fs::symlink_metadata(&here)
            .await
            .is_ok_and(|m| m.file_type().is_symlink())
        {
            return false;
        }
    }
    match tokio::fs::canonicalize(&here).await {
        Ok(real) => real.starts_with(root),
        Err(_) => true,
    }
}

/// `%XX`-decode a URL path (as `ServeDir` does); `None` if it is not UTF-8.
fn percent_decode(s: &str) -> Option<String> {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let hex = |b: u8| (b as char).to_digit(16);
        if bytes[i] == b'%' && i + 2 < bytes.len() {
            if let (Some(h), Some(l)) = (hex(bytes[i + 1]), hex(bytes[i + 2])) {
                out.push((h * 16 + l) as u8);
                i += 3;
                continue;
            }
        }
        out.push(bytes[i]);
        i += 1;
    }
    String::from_utf8(out).ok()
}

fn dashboard_missing_note(dist: &std::path::Path) -> String {
    format!(
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>spintune</title></head><body>\
<h1>spintune server</h1>\
<p>The dashboard is not built: <code>{}</code> has no <code>index.html</code>.</p>\
<p>Build it from the repository root with <code>trunk build --release</code> \
(see README.md), or start the server with <code>--dist DIR</code>.</p>\
<p>The API works regardless: <a href=\"/api/runs\">/api/runs</a>.</p></body></html>",
        html_escape(&dist.display().to_string())
    )
}

fn html_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}
