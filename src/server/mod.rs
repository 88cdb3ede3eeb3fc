//! `meshstream serve`: HTTP (axum) and gRPC (tonic) in one process, on one engine.

mod auth;
mod connections;
mod error;
mod events;
mod grpc;
mod http;
mod image_input;
mod input;
mod ui;
mod unread_body;

/// The gRPC API's messages, client and server (`proto/meshstream/v1/meshstream.proto`).
pub mod proto {
    tonic::include_proto!("meshstream.v1");

    /// Encoded descriptors of the API, for server reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        include_bytes!(concat!(env!("OUT_DIR"), "/meshstream_descriptor.bin"));
}

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use serde_json::json;
use thiserror::Error;
use tokio::net::TcpListener;
use tokio::sync::watch;
use tokio_stream::wrappers::TcpListenerStream;

use crate::diffusion::{Framing, ImageOptions};
use crate::engine::{Conditioning, Engine, EngineError, PreparedPoints, Stage};
use crate::mesh::{Mesh, UpAxis};
use crate::model::DEFAULT_TEMPERATURE;

pub use auth::{ApiKeys, AuthConfig, AuthError, DEFAULT_OPEN_PATHS, OpenPath};
pub use connections::ReadTimeouts;
pub use error::ApiError;
use image_input::ImageDefaults;
pub use input::InputLimits;

use proto::mesh_generator_server::MeshGeneratorServer;

#[derive(Debug, Error)]
pub enum ServerError {
    /// The I/O error is in the message, not a source: a chain printer would repeat it.
    #[error("cannot listen on {addr}: {error}")]
    Bind { addr: SocketAddr, error: std::io::Error },
    #[error("the {what} server failed: {message}")]
    Serve { what: &'static str, message: String },
}

#[derive(Debug, Clone)]
pub struct ServeConfig {
    pub http_addr: SocketAddr,
    pub grpc_addr: SocketAddr,
    pub limits: InputLimits,
    pub max_body_bytes: usize,
    /// Slow HTTP clients: how long headers and bodies may take to arrive.
    pub read_timeouts: ReadTimeouts,
    /// How a points request answered with a whole mesh ends when it does not say.
    pub whole_mesh: WholeMeshDefaults,
    /// A request not finished by then fails (504, DEADLINE_EXCEEDED).
    pub request_timeout: Duration,
    /// After SIGTERM: how long accepted requests may still take.
    pub shutdown_grace: Duration,
    /// Shown by `/v1/info`.
    pub model_dir: PathBuf,
    pub image: ImageServeConfig,
    /// Serve the viewer page at `GET /`.
    pub ui: bool,
    /// API keys, and the paths that need none.
    pub auth: AuthConfig,
}

/// How a points request answered with a whole mesh ends when it does not say: a stream's
/// faces arrive as they are decoded (1 candidate, no weld, no fit) unless it asks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WholeMeshDefaults {
    pub candidates: usize,
    pub weld_radius: u16,
    pub fit_rounds: usize,
}

impl Default for WholeMeshDefaults {
    fn default() -> Self {
        Self {
            candidates: crate::candidates::DEFAULT_CANDIDATES,
            weld_radius: crate::candidates::DEFAULT_WELD_RADIUS,
            fit_rounds: crate::mesh::FitOptions::default().rounds,
        }
    }
}

/// Image requests' defaults and limits (used when the engine has an image model).
#[derive(Debug, Clone, PartialEq)]
pub struct ImageServeConfig {
    /// Euler steps when a request does not say.
    pub steps: usize,
    /// Guidance scale when a request does not say.
    pub guidance: f32,
    /// Framing when a request does not say.
    pub framing: Framing,
    /// Largest width and height of an uploaded image, in pixels.
    pub max_side: u32,
}

impl Default for ImageServeConfig {
    /// 25 Euler steps (the paper uses 100; 25, 50 and 100 scored the same on the dev pictures,
    /// and the diffusion takes half the time of 50) and the guidance scale that gave the
    /// shipped model its lowest dev CD (docs/decisions.md, "Image requests").
    fn default() -> Self {
        Self { steps: 25, guidance: 8.0, framing: Framing::Object, max_side: 4096 }
    }
}

impl ImageServeConfig {
    /// The defaults for the engine's image model, if it has one.
    fn defaults(&self, engine: &Engine) -> Option<ImageDefaults> {
        let size = engine.diffusion_config()?.image_encoder.image_size();
        let decode = ImageOptions {
            max_width: self.max_side,
            max_height: self.max_side,
            framing: self.framing,
            ..ImageOptions::new(u32::try_from(size).ok()?)
        };
        Some(ImageDefaults { steps: self.steps, guidance: self.guidance, decode })
    }
}

/// The answer to an image request on a server without an image model.
pub(crate) fn no_image_model() -> ApiError {
    ApiError::from(EngineError::Unsupported(
        "this server has no image model: start it with a model folder that has a dit/ \
         subfolder"
            .into(),
    ))
}

/// The encoder's input for a mesh or point cloud in the caller's coordinates (`up` their up
/// axis), a draw for each of its `candidates`, and the reference points they are judged
/// against. CPU work.
pub(crate) fn prepare(
    engine: &Engine,
    input: &Mesh,
    limits: &InputLimits,
    seed: u64,
    candidates: usize,
    up: UpAxis,
) -> Result<Conditioning, ApiError> {
    let cfg = engine.model_config();
    let points = engine.metrics().time(Stage::Prepare, || {
        PreparedPoints::from_mesh(input, cfg, limits.reference_points, seed, candidates, up)
    })?;
    Ok(Conditioning::Points(points))
}

fn info_document(engine: &Engine, cfg: &ServeConfig) -> serde_json::Value {
    let model = engine.model_config();
    json!({
        "service": "meshstream",
        "version": env!("CARGO_PKG_VERSION"),
        "model": {
            "dir": cfg.model_dir.display().to_string(),
            "parameters": model.parameter_count(),
            "config": model,
        },
        "image_model": engine.diffusion_config().map(|d| json!({
            "parameters": d.parameter_count(),
            "config": d,
            "default_steps": cfg.image.steps,
            "default_guidance": cfg.image.guidance,
            "default_framing": cfg.image.framing.name(),
            "max_image_side": cfg.image.max_side,
        })),
        "engine": engine.config(),
        "defaults": {
            "candidates": { "whole_mesh": cfg.whole_mesh.candidates, "stream": 1 },
            "weld_radius": { "whole_mesh": cfg.whole_mesh.weld_radius, "stream": 0 },
            "fit_rounds": { "whole_mesh": cfg.whole_mesh.fit_rounds, "stream": 0 },
            "max_hole_edges": crate::mesh::DEFAULT_MAX_HOLE_EDGES,
            "reference_points": cfg.limits.reference_points,
            "temperature": DEFAULT_TEMPERATURE,
        },
        "limits": {
            "max_faces": engine.face_limit(),
            "max_points": cfg.limits.max_points,
            "max_body_bytes": cfg.max_body_bytes,
            "request_timeout_s": cfg.request_timeout.as_secs_f64(),
        },
    })
}

/// The two listening sockets, bound before serving so that callers can learn the ports
/// (a port of 0 picks a free one).
pub struct Listeners {
    http: TcpListener,
    grpc: TcpListener,
}

impl Listeners {
    pub async fn bind(cfg: &ServeConfig) -> Result<Self, ServerError> {
        let bind = |addr: SocketAddr| async move {
            TcpListener::bind(addr).await.map_err(|error| ServerError::Bind { addr, error })
        };
        Ok(Self { http: bind(cfg.http_addr).await?, grpc: bind(cfg.grpc_addr).await? })
    }

    pub fn http_addr(&self) -> Option<SocketAddr> {
        self.http.local_addr().ok()
    }

    pub fn grpc_addr(&self) -> Option<SocketAddr> {
        self.grpc.local_addr().ok()
    }
}

/// Serves until `shutdown` resolves, then stops accepting, lets accepted requests finish for
/// the grace period, and returns once the engine has stopped.
pub async fn serve(
    engine: Engine,
    cfg: ServeConfig,
    listeners: Listeners,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    let state = http::AppState {
        engine: engine.clone(),
        limits: cfg.limits,
        max_body_bytes: cfg.max_body_bytes,
        body_read_timeout: cfg.read_timeouts.body,
        whole_mesh: cfg.whole_mesh,
        request_timeout: cfg.request_timeout,
        image: cfg.image.defaults(&engine),
        info: Arc::new(info_document(&engine, &cfg)),
    };
    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<MeshGeneratorServer<grpc::GrpcService>>().await;
    // v1 and the older v1alpha, which some clients still ask for first.
    let reflection_builder = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    let reflection_error = |e: tonic_reflection::server::Error| ServerError::Serve {
        what: "gRPC reflection",
        message: e.to_string(),
    };
    let reflection = reflection_builder().build_v1().map_err(reflection_error)?;
    let reflection_alpha = reflection_builder().build_v1alpha().map_err(reflection_error)?;
    let generator = MeshGeneratorServer::new(grpc::GrpcService {
        engine: engine.clone(),
        limits: cfg.limits,
        image: cfg.image.defaults(&engine),
        request_timeout: cfg.request_timeout,
    })
    .max_decoding_message_size(cfg.max_body_bytes);
    tracing::info!(http_addr = ?listeners.http_addr(), grpc_addr = ?listeners.grpc_addr(), "listening");

    let (closing_tx, closing_rx) = watch::channel(false);
    let grace = cfg.shutdown_grace;
    let signal_engine = engine.clone();
    tokio::spawn(async move {
        shutdown.await;
        tracing::info!(grace_s = grace.as_secs_f64(), "shutting down: finishing accepted requests");
        signal_engine.shutdown(grace);
        health.set_not_serving::<MeshGeneratorServer<grpc::GrpcService>>().await;
        let _ = closing_tx.send(true);
    });
    let closed = |mut rx: watch::Receiver<bool>| async move {
        let _ = rx.wait_for(|closing| *closing).await;
    };
    let auth = auth::AuthLayer::new(cfg.auth.clone(), engine.metrics().clone());
    let http_server = connections::serve_http(
        listeners.http,
        http::router(state, cfg.ui, auth.clone()),
        cfg.read_timeouts,
        closed(closing_rx.clone()),
    );
    let grpc_server = tonic::transport::Server::builder()
        .layer(auth)
        .add_service(health_service)
        .add_service(reflection)
        .add_service(reflection_alpha)
        .add_service(generator)
        .serve_with_incoming_shutdown(
            TcpListenerStream::new(listeners.grpc),
            closed(closing_rx.clone()),
        );
    let servers = async {
        let ((), grpc) = tokio::join!(http_server, grpc_server);
        grpc.map_err(|e| ServerError::Serve { what: "gRPC", message: e.to_string() })
    };
    // Connections that outlive the grace period (a client that never reads) do not hold the
    // process: the engine has failed their requests by then.
    let deadline = async {
        closed(closing_rx.clone()).await;
        tokio::time::sleep(grace + Duration::from_secs(2)).await;
    };
    let result = tokio::select! {
        r = servers => r,
        () = deadline => {
            tracing::warn!("connections still open after the grace period: closing them");
            Ok(())
        }
    };
    let joining = engine.clone();
    let _ = tokio::task::spawn_blocking(move || joining.join()).await;
    tracing::info!("stopped");
    result
}
