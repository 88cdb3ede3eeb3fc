//! The HTTP interface (axum): `POST /reconstruct` and `POST /generate` (a mesh, or events
//! streamed as SSE or NDJSON), health, readiness, metrics, model information and the OpenAPI
//! document.

use std::convert::Infallible;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::{Body, Bytes};
use axum::extract::{Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, Uri, header};
use axum::response::sse::{Event as SseEvent, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use futures_util::{Stream, StreamExt, stream};
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::trace::TraceLayer;
use utoipa::OpenApi;

use crate::engine::{Conditioning, DecodeOptions, Engine, Event, Request, RequestStream};
use crate::mesh::{Format, write_mesh};
use crate::metrics::MeshQuality;

use super::auth::AuthLayer;
use super::error::{ApiError, ErrorBody};
use super::events::{DoneEvent, FaceEvent, Line, ProgressEvent};
use super::image_input::{GenerateOptions, ImageDefaults, read_upload};
use super::input::{InputLimits, ParsedRequest, PointsBody, ReconstructOptions, parse_body};
use super::unread_body::close_if_body_unread;
use super::{WholeMeshDefaults, no_image_model, prepare};

#[derive(Clone)]
pub struct AppState {
    pub engine: Engine,
    pub limits: InputLimits,
    pub max_body_bytes: usize,
    /// The whole body must have arrived by then.
    pub body_read_timeout: Duration,
    /// How a points request answered with a whole mesh ends when it does not say.
    pub whole_mesh: WholeMeshDefaults,
    pub request_timeout: Duration,
    /// How images are prepared and sampled; `None` when the engine has no image model.
    pub image: Option<ImageDefaults>,
    /// The `/v1/info` document, made once at start.
    pub info: Arc<serde_json::Value>,
}

#[derive(OpenApi)]
#[openapi(
    info(
        title = "meshstream",
        description = "Point clouds and meshes to artist-style meshes \
        with the FACE method, streamed face by face."
    ),
    paths(reconstruct, generate, healthz, readyz, metrics, info),
    components(schemas(PointsBody, ErrorBody, ProgressEvent, FaceEvent, DoneEvent, MeshQuality)),
    modifiers(&BearerKeys)
)]
struct ApiDoc;

/// The API keys' scheme; operations list it beside "none", as a server may require no key.
struct BearerKeys;

impl utoipa::Modify for BearerKeys {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
        let scheme = HttpBuilder::new().scheme(HttpAuthScheme::Bearer).description(Some(
            "An API key, when the server is started with --api-key or --api-key-file",
        ));
        openapi
            .components
            .get_or_insert_with(Default::default)
            .add_security_scheme("api_key", SecurityScheme::Http(scheme.build()));
    }
}

/// A file's bytes, in a request or a response.
#[derive(utoipa::ToSchema)]
#[schema(value_type = String, format = Binary)]
#[allow(dead_code)] // a schema only
struct Binary(Vec<u8>);

/// `POST /generate` as `multipart/form-data`: the image, and the options (those of the query
/// form) as further fields.
#[derive(utoipa::ToSchema)]
#[allow(dead_code)] // a schema only
struct GenerateForm {
    #[schema(value_type = String, format = Binary)]
    image: Vec<u8>,
}

/// The API's routes, and the viewer page's when `ui` is set; `auth` refuses requests without
/// a key (inside the request-id and trace layers, so that refusals carry an id and are traced);
/// an answer that leaves a request's body unread closes its connection (`unread_body`).
pub fn router(state: AppState, ui: bool, auth: AuthLayer) -> Router {
    let page = if ui { super::ui::routes() } else { Router::new() };
    Router::new()
        .merge(page)
        .route("/reconstruct", post(reconstruct))
        .route("/generate", post(generate))
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .route("/v1/info", get(info))
        .route("/openapi.json", get(openapi))
        .fallback(|| async { ApiError::new(StatusCode::NOT_FOUND, "not_found", "no such route") })
        .with_state(state)
        .layer(auth)
        .layer(PropagateRequestIdLayer::x_request_id())
        .layer(TraceLayer::new_for_http().make_span_with(|req: &axum::http::Request<Body>| {
            let id = req.headers().get("x-request-id").and_then(|v| v.to_str().ok());
            tracing::info_span!("http", method = %req.method(), uri = %req.uri(), request_id = id)
        }))
        .layer(SetRequestIdLayer::x_request_id(MakeRequestUuid))
        .layer(axum::middleware::from_fn(close_if_body_unread))
}

/// Reconstructs a mesh from points (JSON) or a point cloud or mesh file (raw body).
///
/// The mesh comes back in the request's coordinates, in `format` (GLB by default). With
/// `Accept: text/event-stream` the response is SSE: one `face` event per face as it is
/// decoded, then a `done` event (or an `error` event); with `Accept: application/x-ndjson`,
/// the same as JSON lines with a `type` field.
#[utoipa::path(
    post,
    path = "/reconstruct",
    params(ReconstructOptions),
    security((), ("api_key" = [])),
    request_body(
        content(
            (PointsBody = "application/json"),
            (Binary = "application/octet-stream"),
            (Binary = "model/gltf-binary"),
            (Binary = "application/ply"),
            (Binary = "model/obj"),
            (Binary = "model/stl"),
        ),
        description = "Points as JSON (options in the body), or a file (options as query \
            parameters); a mesh is sampled to points, missing normals are estimated"
    ),
    responses(
        (status = 200, description = "The mesh, or the event stream", headers(
            ("x-request-id" = String, description = "Given or generated"),
            ("x-meshstream-faces" = usize, description = "Faces in the mesh"),
            ("x-meshstream-time-ms" = f64, description = "Time in the engine"),
            ("x-meshstream-finish-reason" = String, description = "end_of_mesh, max_faces or dead_end; convex_hull when a fitted answer is the convex hull of the input points, which ended at least 10% closer to them than every decoded candidate"),
            ("x-meshstream-parts" = usize, description = "Connected parts of the mesh"),
            ("x-meshstream-edges" = usize, description = "Distinct edges, corners welded by position"),
            ("x-meshstream-boundary-edges" = usize, description = "Edges used by one face (holes, open borders)"),
            ("x-meshstream-non-manifold-edges" = usize, description = "Edges used by three or more faces"),
            ("x-meshstream-watertight" = bool, description = "Every edge shared by exactly two faces"),
            ("x-meshstream-input-chamfer" = f64, description = "Chamfer distance between the mesh \
                and the input points, the input's longest side spanning 2"),
        ), content(
            (Binary = "model/gltf-binary"),
            (Binary = "model/obj"),
            (Binary = "application/ply"),
            (Binary = "model/stl"),
            (String = "text/event-stream"),
            (String = "application/x-ndjson"),
        )),
        (status = 400, description = "Malformed body or unknown format", body = ErrorBody),
        (status = 401, description = "An API key is required and none valid was given", body = ErrorBody,
            headers(("www-authenticate" = String, description = "Bearer"))),
        (status = 408, description = "The body did not arrive within the body read timeout", body = ErrorBody),
        (status = 413, description = "Body over the size limit", body = ErrorBody),
        (status = 422, description = "Invalid points or options, or a whole mesh with no faces (`no_faces`)", body = ErrorBody),
        (status = 429, description = "The queue is full: retry after Retry-After", body = ErrorBody),
        (status = 503, description = "Shutting down, or waited too long in the queue", body = ErrorBody),
    )
)]
async fn reconstruct(
    State(state): State<AppState>,
    uri: Uri,
    headers: HeaderMap,
    body: Body,
) -> Response {
    let prepared = async {
        let query = query_options::<ReconstructOptions>(&uri)?;
        let bytes = read_body(body, state.max_body_bytes, state.body_read_timeout).await?;
        let (limits, engine, headers) = (state.limits, state.engine.clone(), headers.clone());
        let whole_mesh = state.whole_mesh;
        off_runtime(move || {
            let mut parsed: ParsedRequest = parse_body(&headers, query, &bytes, &limits)?;
            if streaming(&headers).is_none() {
                parsed.decode.candidates.get_or_insert(whole_mesh.candidates);
                parsed.decode.weld_radius.get_or_insert(whole_mesh.weld_radius);
                parsed.decode.fit_rounds.get_or_insert(whole_mesh.fit_rounds);
                // Nobody watches a whole mesh being made.
                parsed.decode.drafts = false;
            }
            let draws = parsed.decode.candidates.unwrap_or(1);
            let conditioning =
                prepare(&engine, &parsed.input, &limits, parsed.seed, draws, parsed.up)?;
            Ok(Prepared { conditioning, decode: parsed.decode, format: parsed.format })
        })
        .await
    };
    run(&state, headers.clone(), prepared.await).await
}

/// Generates a mesh from an image.
///
/// The body is the image (PNG, JPEG or WebP; options as query parameters), or a
/// `multipart/form-data` form with an `image` part and the options as fields. The answer is
/// as for `/reconstruct`: the mesh (in the model's frame, centred in [-1, 1]), or with
/// `Accept: text/event-stream` / `application/x-ndjson` a stream of `progress` events (step k
/// of N of the diffusion stage), then `face` events, then `done`.
#[utoipa::path(
    post,
    path = "/generate",
    params(GenerateOptions),
    security((), ("api_key" = [])),
    request_body(
        content(
            (Binary = "image/png"),
            (Binary = "image/jpeg"),
            (Binary = "image/webp"),
            (GenerateForm = "multipart/form-data"),
        ),
        description = "An image, raw or as the `image` part of a form"
    ),
    responses(
        (status = 200, description = "The mesh, or the event stream", content(
            (Binary = "model/gltf-binary"),
            (Binary = "model/obj"),
            (Binary = "application/ply"),
            (Binary = "model/stl"),
            (String = "text/event-stream"),
            (String = "application/x-ndjson"),
        )),
        (status = 400, description = "Not a usable image, or a malformed form", body = ErrorBody),
        (status = 401, description = "An API key is required and none valid was given", body = ErrorBody,
            headers(("www-authenticate" = String, description = "Bearer"))),
        (status = 408, description = "The body did not arrive within the body read timeout", body = ErrorBody),
        (status = 413, description = "Body over the size limit", body = ErrorBody),
        (status = 422, description = "Invalid options, a picture with nothing on its backdrop to frame (`no_object`; `framing=centre_crop` takes it as it is), or a whole mesh with no faces (`no_faces`)", body = ErrorBody),
        (status = 429, description = "The queue is full: retry after Retry-After", body = ErrorBody),
        (status = 501, description = "This server has no image model", body = ErrorBody),
        (status = 503, description = "Shutting down, or waited too long in the queue", body = ErrorBody),
    )
)]
async fn generate(
    State(state): State<AppState>,
    uri: Uri,
    headers: HeaderMap,
    body: Body,
) -> Response {
    let prepared = async {
        let defaults = state.image.clone().ok_or_else(no_image_model)?;
        let query = query_options::<GenerateOptions>(&uri)?;
        let bytes = read_body(body, state.max_body_bytes, state.body_read_timeout).await?;
        let upload = read_upload(&headers, query, bytes).await?;
        off_runtime(move || {
            let parsed = upload.parse(&defaults)?;
            let conditioning = Conditioning::Image(parsed.prompt);
            Ok(Prepared { conditioning, decode: parsed.decode, format: parsed.format })
        })
        .await
    };
    run(&state, headers.clone(), prepared.await).await
}

/// A request ready for the engine.
struct Prepared {
    conditioning: Conditioning,
    decode: DecodeOptions,
    format: Format,
}

fn query_options<T: serde::de::DeserializeOwned>(uri: &Uri) -> Result<T, ApiError> {
    Query::<T>::try_from_uri(uri)
        .map(|q| q.0)
        .map_err(|e| ApiError::invalid(format!("query parameters: {}", e.body_text())))
}

/// Runs CPU work (parsing, sampling points, decoding images) on the blocking pool.
async fn off_runtime(
    work: impl FnOnce() -> Result<Prepared, ApiError> + Send + 'static,
) -> Result<Prepared, ApiError> {
    tokio::task::spawn_blocking(work)
        .await
        .map_err(|e| ApiError::internal(format!("request preparation stopped: {e}")))?
}

/// Queues a prepared request and answers with its mesh or its stream.
async fn run(
    state: &AppState,
    headers: HeaderMap,
    prepared: Result<Prepared, ApiError>,
) -> Response {
    let id =
        headers.get("x-request-id").and_then(|v| v.to_str().ok()).unwrap_or_default().to_string();
    // The engine counts its own refusals; these are the ones before it.
    let prepared = prepared.inspect_err(|e| state.engine.metrics().reject(e.code));
    let submitted = prepared.and_then(|p| {
        let request = Request {
            id: id.clone(),
            conditioning: p.conditioning,
            options: p.decode,
            deadline: Some(Instant::now() + state.request_timeout),
        };
        Ok((state.engine.submit(request)?, p.format))
    });
    match submitted {
        Ok((stream, format)) => respond(stream, format, &headers, id).await,
        Err(e) => {
            tracing::info!(code = e.code, status = e.status.as_u16(), "refused: {}", e.message);
            e.into_response()
        }
    }
}

/// The whole body; 413 `too_large` when it is over `limit` bytes, 408 `body_timeout` when it
/// has not all arrived within `timeout` (a client trickling its upload holds a connection and
/// a buffer only that long).
async fn read_body(body: Body, limit: usize, timeout: Duration) -> Result<Bytes, ApiError> {
    tokio::time::timeout(timeout, read_body_within(body, limit)).await.map_err(|_| {
        ApiError::new(
            StatusCode::REQUEST_TIMEOUT,
            "body_timeout",
            format!("the body did not arrive within {} s", timeout.as_secs_f64()),
        )
    })?
}

async fn read_body_within(body: Body, limit: usize) -> Result<Bytes, ApiError> {
    let mut chunks = body.into_data_stream();
    let mut bytes = Vec::new();
    let mut over = 0usize;
    while let Some(chunk) = chunks.next().await {
        let chunk =
            chunk.map_err(|e| ApiError::malformed(format!("reading the body failed: {e}")))?;
        if over == 0 && bytes.len() + chunk.len() <= limit {
            bytes.extend_from_slice(&chunk);
            continue;
        }
        // Past the limit, read on and drop up to one more limit's worth before answering:
        // closing a connection with unread bytes in it resets it, and the client would lose
        // the 413 (a lingering close, as nginx does).
        over += chunk.len();
        if over > limit {
            break;
        }
    }
    if over > 0 {
        return Err(ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "too_large",
            format!("the body is over this server's limit of {limit} bytes"),
        ));
    }
    Ok(Bytes::from(bytes))
}

enum Streaming {
    Sse,
    Ndjson,
}

fn streaming(headers: &HeaderMap) -> Option<Streaming> {
    let accept = headers.get(header::ACCEPT).and_then(|v| v.to_str().ok()).unwrap_or("");
    if accept.contains("text/event-stream") {
        Some(Streaming::Sse)
    } else if accept.contains("application/x-ndjson") {
        Some(Streaming::Ndjson)
    } else {
        None
    }
}

async fn respond(
    stream: RequestStream,
    format: Format,
    headers: &HeaderMap,
    id: String,
) -> Response {
    match streaming(headers) {
        Some(Streaming::Sse) => {
            let events = lines(stream, id).map(|line| {
                let event = match &line {
                    Line::Progress(_) => "progress",
                    Line::Face(_) => "face",
                    Line::Draft(_) => "draft",
                    Line::Done(_) => "done",
                    Line::Error(_) => "error",
                };
                let data = match line {
                    Line::Progress(p) => serde_json::to_string(&p),
                    Line::Face(f) | Line::Draft(f) => serde_json::to_string(&f),
                    Line::Done(d) => serde_json::to_string(&d),
                    Line::Error(e) => serde_json::to_string(&e),
                };
                Ok::<_, Infallible>(SseEvent::default().event(event).data(data.unwrap_or_default()))
            });
            Sse::new(events).keep_alive(KeepAlive::default()).into_response()
        }
        Some(Streaming::Ndjson) => {
            let body = lines(stream, id).map(|line| {
                let mut text = serde_json::to_vec(&line).unwrap_or_default();
                text.push(b'\n');
                Ok::<_, Infallible>(Bytes::from(text))
            });
            ([(header::CONTENT_TYPE, "application/x-ndjson")], Body::from_stream(body))
                .into_response()
        }
        None => mesh_response(stream, format, id).await.unwrap_or_else(IntoResponse::into_response),
    }
}

/// The request's events as stream lines; ends after the final one. Dropping it (the client
/// went away) drops the request's stream, which cancels it.
fn lines(stream: RequestStream, id: String) -> impl Stream<Item = Line> {
    stream::unfold(Some(stream), move |state| {
        let id = id.clone();
        async move {
            let mut s = state?;
            let line = match s.next().await? {
                Event::Progress { step, steps } => {
                    return Some((Line::Progress(ProgressEvent { step, steps }), Some(s)));
                }
                Event::Face(f) => return Some((Line::Face(FaceEvent::from(&f)), Some(s))),
                Event::Draft(f) => return Some((Line::Draft(FaceEvent::from(&f)), Some(s))),
                Event::Finished(summary) => {
                    tracing::info!(request_id = %id, faces = summary.faces, "streamed");
                    Line::Done(DoneEvent::new(&id, &summary))
                }
                Event::Failed(e) => Line::Error(ApiError::from(e).body()),
            };
            Some((line, None))
        }
    })
}

async fn mesh_response(
    stream: RequestStream,
    format: Format,
    id: String,
) -> Result<Response, ApiError> {
    let done = stream.collect().await?;
    if done.mesh.faces.is_empty() {
        // Not every format can hold an empty mesh (glTF refuses empty accessors); none is a
        // useful answer. Streams report it in their done event instead.
        return Err(ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "no_faces",
            format!(
                "the model produced no faces for this input ({}); another seed may",
                done.summary.finish.name()
            ),
        ));
    }
    let bytes = write_mesh(&done.mesh, format).map_err(|e| {
        ApiError::internal(format!(
            "the result ({} faces, {}) cannot be written: {e}",
            done.summary.faces,
            done.summary.finish.name()
        ))
    })?;
    let done_event = DoneEvent::new(&id, &done.summary);
    tracing::info!(request_id = %id, faces = done_event.faces, total_ms = done_event.total_ms, "reconstructed");
    let mut response =
        ([(header::CONTENT_TYPE, format.content_type())], Bytes::from(bytes)).into_response();
    let h = response.headers_mut();
    let mut set = |name: &'static str, value: String| {
        if let Ok(v) = HeaderValue::from_str(&value) {
            h.insert(name, v);
        }
    };
    set("x-meshstream-faces", done_event.faces.to_string());
    set("x-meshstream-time-ms", format!("{:.1}", done_event.total_ms));
    set("x-meshstream-finish-reason", done_event.finish_reason.to_string());
    if let Some(q) = &done_event.quality {
        set("x-meshstream-parts", q.parts.to_string());
        set("x-meshstream-edges", q.edges.to_string());
        set("x-meshstream-boundary-edges", q.boundary_edges.to_string());
        set("x-meshstream-non-manifold-edges", q.non_manifold_edges.to_string());
        set("x-meshstream-watertight", q.watertight.to_string());
        if let Some(cd) = q.input_chamfer {
            set("x-meshstream-input-chamfer", format!("{cd:.5}"));
        }
    }
    Ok(response)
}

/// Live: the process answers.
#[utoipa::path(get, path = "/healthz", responses(
    (status = 200, description = "Alive", body = String, content_type = "text/plain"),
))]
async fn healthz() -> &'static str {
    "ok"
}

/// Ready: the model is loaded and the engine accepts requests.
#[utoipa::path(get, path = "/readyz", responses(
    (status = 200, description = "Ready", body = String, content_type = "text/plain"),
    (status = 503, description = "Shutting down or stopped", body = ErrorBody),
))]
async fn readyz(State(state): State<AppState>) -> Response {
    let status = state.engine.status();
    if status.alive && status.accepting {
        "ready".into_response()
    } else {
        ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "not_ready",
            "the engine is not accepting requests",
        )
        .into_response()
    }
}

/// Prometheus metrics: queue depth, running sequences, faces, time to first face and between
/// faces, request duration, batch size, rejections and failures by reason.
#[utoipa::path(get, path = "/metrics", responses(
    (status = 200, description = "The OpenMetrics text format", body = String,
        content_type = "application/openmetrics-text"),
))]
async fn metrics(State(state): State<AppState>) -> Response {
    (
        [(header::CONTENT_TYPE, "application/openmetrics-text; version=1.0.0; charset=utf-8")],
        state.engine.metrics().render(),
    )
        .into_response()
}

/// The model's configuration and version, the engine's settings and the request limits.
#[utoipa::path(get, path = "/v1/info", security((), ("api_key" = [])), responses(
    (status = 200, description = "Server information", body = Object, content_type = "application/json"),
        (status = 401, description = "An API key is required and none valid was given", body = ErrorBody,
            headers(("www-authenticate" = String, description = "Bearer"))),
))]
async fn info(State(state): State<AppState>) -> Json<serde_json::Value> {
    Json((*state.info).clone())
}

async fn openapi() -> Json<utoipa::openapi::OpenApi> {
    Json(ApiDoc::openapi())
}
