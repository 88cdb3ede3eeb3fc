//! The viewer page at `GET /` and the files it loads under `/ui/`: web/src (plain ES modules,
//! bundled with three.js by `npm run build` into the committed web/dist/app.js, beside
//! three.js's Draco decoder in web/dist/draco/), embedded in the binary so that serving it
//! needs no files on disk and no network.

use axum::Router;
use axum::extract::Path;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;

use super::error::ApiError;

const PAGE: &str = include_str!("../../web/src/index.html");

/// What the page loads: (path under `/ui/`, media type, bytes).
const FILES: &[(&str, &str, &[u8])] = &[
    ("app.js", "text/javascript; charset=utf-8", include_bytes!("../../web/dist/app.js")),
    ("style.css", "text/css; charset=utf-8", include_bytes!("../../web/src/style.css")),
    (
        "examples/mug-points.ply",
        "application/ply",
        include_bytes!("../../web/examples/mug-points.ply"),
    ),
    (
        "examples/table-points.ply",
        "application/ply",
        include_bytes!("../../web/examples/table-points.ply"),
    ),
    (
        "examples/pine-tree.ply",
        "application/ply",
        include_bytes!("../../web/examples/pine-tree.ply"),
    ),
    ("examples/chest.png", "image/png", include_bytes!("../../web/examples/chest.png")),
    (
        "draco/draco_wasm_wrapper.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../web/dist/draco/draco_wasm_wrapper.js"),
    ),
    (
        "draco/draco_decoder.wasm",
        "application/wasm",
        include_bytes!("../../web/dist/draco/draco_decoder.wasm"),
    ),
];

/// The page's routes, for a router that serves the API beside them.
pub fn routes<S: Clone + Send + Sync + 'static>() -> Router<S> {
    Router::new().route("/", get(page)).route("/ui/{*file}", get(file))
}

async fn page() -> Response {
    embedded("text/html; charset=utf-8", PAGE.as_bytes())
}

async fn file(Path(path): Path<String>) -> Response {
    match FILES.iter().find(|(name, ..)| *name == path) {
        Some((_, media_type, bytes)) => embedded(media_type, bytes),
        None => ApiError::new(StatusCode::NOT_FOUND, "not_found", format!("no file ui/{path}"))
            .into_response(),
    }
}

/// A response with the bytes; `no-cache` so that a browser revalidates after an upgrade.
fn embedded(media_type: &'static str, bytes: &'static [u8]) -> Response {
    let mut response = ([(header::CONTENT_TYPE, media_type)], bytes).into_response();
    response.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    response
}
