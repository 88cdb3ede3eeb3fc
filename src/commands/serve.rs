use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use clap::{Args, ValueEnum};
use meshstream::candidates::{
    DEFAULT_CANDIDATES, DEFAULT_HULL_FACES, DEFAULT_WELD_RADIUS, MAX_WELD_RADIUS,
};
use meshstream::diffusion::Framing;
use meshstream::engine::{Engine, EngineConfig, Metrics};
use meshstream::mesh::{FitOptions, MAX_FIT_ROUNDS, REFERENCE_POINTS, ReadLimits};
use meshstream::model::{Quantize, parse_device};
use meshstream::server::{
    ApiKeys, AuthConfig, DEFAULT_OPEN_PATHS, ImageServeConfig, InputLimits, Listeners, OpenPath,
    ReadTimeouts, ServeConfig, WholeMeshDefaults, serve,
};
use tracing_subscriber::EnvFilter;

use super::out;

use super::{candidate_count, image_model_dir, load_face_model, load_image_model, point_count};

#[derive(Clone, Copy, ValueEnum)]
enum LogFormat {
    Text,
    Json,
}

/// Every setting is a flag and a `MESHSTREAM_*` environment variable.
#[derive(Args)]
pub struct ServeArgs {
    /// Model folder (config.json + model.safetensors).
    #[arg(long, env = "MESHSTREAM_MODEL", default_value = "models/default")]
    model: PathBuf,
    /// cpu or cuda:N (with --features cuda).
    #[arg(long, env = "MESHSTREAM_DEVICE", default_value = "cpu")]
    device: String,
    #[arg(long, env = "MESHSTREAM_HTTP_ADDR", default_value = "0.0.0.0:8080")]
    http_addr: SocketAddr,
    #[arg(long, env = "MESHSTREAM_GRPC_ADDR", default_value = "0.0.0.0:50051")]
    grpc_addr: SocketAddr,
    #[arg(long, env = "MESHSTREAM_LOG_FORMAT", value_enum, default_value = "text")]
    log_format: LogFormat,
    /// Sequences decoded together.
    #[arg(long, env = "MESHSTREAM_MAX_RUNNING", default_value_t = EngineConfig::default().max_running)]
    max_running: usize,
    /// Requests waiting to start; more are refused with 429.
    #[arg(long, env = "MESHSTREAM_MAX_QUEUE", default_value_t = 64)]
    max_queue: usize,
    /// Face budget of one request (the model's own limit applies too).
    #[arg(long, env = "MESHSTREAM_MAX_FACES", default_value_t = 4096)]
    max_faces: usize,
    /// Sum of the running sequences' face budgets (bounds cache memory).
    #[arg(long, env = "MESHSTREAM_MAX_BATCH_FACES", default_value_t = 65536)]
    max_batch_faces: usize,
    /// Requests sent to the encoder, as one batch, per scheduler iteration.
    #[arg(long, env = "MESHSTREAM_MAX_ENCODES_PER_ITERATION", default_value_t = 4)]
    max_encodes_per_iteration: usize,
    /// Seconds a request may wait in the queue.
    #[arg(long, env = "MESHSTREAM_QUEUE_TIMEOUT", default_value_t = 30.0)]
    queue_timeout: f64,
    /// Seconds after which a waiting request is no longer overtaken by smaller ones.
    #[arg(long, env = "MESHSTREAM_AGING", default_value_t = 2.0)]
    aging: f64,
    /// Events buffered per client before its sequence waits for it.
    #[arg(long, env = "MESHSTREAM_STREAM_BUFFER", default_value_t = 256)]
    stream_buffer: usize,
    /// Seconds a stream's client may leave its buffer full (read nothing) before its request
    /// is cancelled and its slot given to another.
    #[arg(long, env = "MESHSTREAM_STREAM_IDLE_TIMEOUT", default_value_t = 30.0)]
    stream_idle_timeout: f64,
    /// Seconds an HTTP client may take to send a request's headers (and an idle keep-alive
    /// connection stays open).
    #[arg(long, env = "MESHSTREAM_HEADER_READ_TIMEOUT", default_value_t = 30.0)]
    header_read_timeout: f64,
    /// Seconds an HTTP client may take to send a request's body (408 after).
    #[arg(long, env = "MESHSTREAM_BODY_READ_TIMEOUT", default_value_t = 60.0)]
    body_read_timeout: f64,
    /// Number format of the model's linear layers: f32, q8_0 or q4k (quantized when the model
    /// loads; the encoder and layers whose inputs do not fit the blocks stay f32).
    #[arg(long, env = "MESHSTREAM_QUANTIZE", default_value_t = Quantize::F32)]
    quantize: Quantize,
    /// Threads stepping the running batch (0: one per core).
    #[arg(long, env = "MESHSTREAM_DECODE_THREADS", default_value_t = 0)]
    decode_threads: usize,
    /// Seconds a request may take in all.
    #[arg(long, env = "MESHSTREAM_REQUEST_TIMEOUT", default_value_t = 300.0)]
    request_timeout: f64,
    /// Seconds accepted requests may still take after SIGTERM.
    #[arg(long, env = "MESHSTREAM_SHUTDOWN_GRACE", default_value_t = 30.0)]
    shutdown_grace: f64,
    /// Largest request body in bytes.
    #[arg(long, env = "MESHSTREAM_MAX_BODY_BYTES", default_value_t = 64 << 20)]
    max_body_bytes: usize,
    /// Most points (or mesh vertices) in one request.
    #[arg(long, env = "MESHSTREAM_MAX_POINTS", default_value_t = 2_000_000)]
    max_points: usize,
    /// Most triangles in an uploaded mesh.
    #[arg(long, env = "MESHSTREAM_MAX_MESH_FACES", default_value_t = 4_000_000)]
    max_mesh_faces: usize,
    /// Candidates of a reconstruction answered with a whole mesh that does not say (see
    /// `reconstruct --candidates`); streamed answers take 1 unless they say, so that their faces
    /// arrive as they are decoded.
    #[arg(long, env = "MESHSTREAM_CANDIDATES", default_value_t = DEFAULT_CANDIDATES,
          value_parser = candidate_count())]
    candidates: usize,
    /// The most input points a reconstruction's candidates are judged and its corners fitted
    /// against (see `reconstruct --reference-points`): fewer make fitting cheaper and coarser.
    #[arg(long, env = "MESHSTREAM_REFERENCE_POINTS", default_value_t = REFERENCE_POINTS,
          value_parser = point_count())]
    reference_points: usize,
    /// Fitting rounds of a reconstruction answered with a whole mesh that does not say (see
    /// `reconstruct --fit-rounds`; at most 200); streamed answers take 0 unless they say.
    #[arg(long, env = "MESHSTREAM_FIT_ROUNDS", default_value_t = FitOptions::default().rounds as u16,
          value_parser = clap::value_parser!(u16).range(..=MAX_FIT_ROUNDS as i64))]
    fit_rounds: u16,
    /// Grid cells within which a reconstruction answered with a whole mesh that does not say
    /// merges its candidates' corners, before fitting (see `reconstruct --weld-radius`; at
    /// most 4); streamed answers take 0 unless they say.
    #[arg(long, env = "MESHSTREAM_WELD_RADIUS", default_value_t = DEFAULT_WELD_RADIUS,
          value_parser = clap::value_parser!(u16).range(..=i64::from(MAX_WELD_RADIUS)))]
    weld_radius: u16,
    /// A fitted reconstruction judges the convex hull of its input points, with at most this many
    /// faces (and its face budget), beside its decoded candidates, and answers with it when it ends
    /// at least 10% closer to the points, its finish reason then `convex_hull` (see `reconstruct
    /// --hull-faces`); 0 never. A request that is not fitted (`fit_rounds=0`, streams unless they
    /// ask) gets the model's faces only.
    #[arg(long, env = "MESHSTREAM_HULL_FACES", default_value_t = DEFAULT_HULL_FACES)]
    hull_faces: usize,
    /// Image model folder (the diffusion transformer); default: the model folder's `dit/`,
    /// when it has one. Without one, image requests are answered 501 / UNIMPLEMENTED.
    #[arg(long, env = "MESHSTREAM_IMAGE_MODEL")]
    image_model: Option<PathBuf>,
    /// DINOv2 weights (safetensors), for an image model configured with a DINOv2 encoder.
    #[arg(long, env = "MESHSTREAM_IMAGE_ENCODER")]
    image_encoder: Option<PathBuf>,
    /// Euler steps of an image request that does not say.
    #[arg(long, env = "MESHSTREAM_DIFFUSION_STEPS", default_value_t = ImageServeConfig::default().steps)]
    diffusion_steps: usize,
    /// Most Euler steps an image request may ask for.
    #[arg(long, env = "MESHSTREAM_MAX_DIFFUSION_STEPS", default_value_t = EngineConfig::default().max_diffusion_steps)]
    max_diffusion_steps: usize,
    /// Samples an image request may take: one whose mesh comes out empty is sampled again from
    /// the next seed, up to this many times in all (1: never).
    #[arg(long, env = "MESHSTREAM_IMAGE_ATTEMPTS", default_value_t = EngineConfig::default().image_attempts)]
    image_attempts: usize,
    /// Guidance scale of an image request that does not say.
    #[arg(long, env = "MESHSTREAM_GUIDANCE", default_value_t = ImageServeConfig::default().guidance)]
    guidance: f32,
    /// How an image request that does not say is framed: object (found, centred and scaled
    /// as in the image model's training renders, backdrop painted white) or centre_crop (the
    /// largest centred square, as given).
    #[arg(long, env = "MESHSTREAM_IMAGE_FRAMING", default_value_t = ImageServeConfig::default().framing)]
    image_framing: Framing,
    /// Largest width and height of an uploaded image, in pixels.
    #[arg(long, env = "MESHSTREAM_MAX_IMAGE_SIDE", default_value_t = ImageServeConfig::default().max_side)]
    max_image_side: u32,
    /// Do not serve the viewer page at `GET /` (the API only).
    #[arg(long, env = "MESHSTREAM_NO_UI", value_parser = clap::builder::BoolishValueParser::new())]
    no_ui: bool,
    /// An API key that requests must carry (HTTP `Authorization: Bearer KEY`, gRPC metadata
    /// `authorization: Bearer KEY`); repeat the flag, or comma-separate keys in the variable,
    /// for several. Without any key, no request needs one.
    #[arg(
        long = "api-key",
        value_name = "KEY",
        env = "MESHSTREAM_API_KEY",
        value_delimiter = ',',
        hide_env_values = true
    )]
    api_keys: Vec<String>,
    /// A file of API keys, one a line (blank lines and # comments skipped), read at start.
    #[arg(long, env = "MESHSTREAM_API_KEY_FILE")]
    api_key_file: Option<PathBuf>,
    /// Paths that need no key, comma-separated: exact, or a prefix ending in `*`; HTTP paths
    /// and gRPC methods (`/package.Service/Method`) alike.
    #[arg(long, env = "MESHSTREAM_AUTH_OPEN_PATHS", value_delimiter = ',',
          default_value = DEFAULT_OPEN_PATHS)]
    auth_open_paths: Vec<OpenPath>,
}

fn seconds(name: &str, value: f64) -> anyhow::Result<Duration> {
    Duration::try_from_secs_f64(value).with_context(|| format!("--{name} {value}"))
}

pub fn run(args: &ServeArgs) -> anyhow::Result<()> {
    let filter =
        EnvFilter::try_from_env("MESHSTREAM_LOG").unwrap_or_else(|_| EnvFilter::new("info"));
    let logs = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr);
    match args.log_format {
        LogFormat::Text => logs.init(),
        LogFormat::Json => logs.json().init(),
    }
    let keys = ApiKeys::new(&args.api_keys, args.api_key_file.as_deref())?;
    if !keys.is_empty() {
        tracing::info!(keys = keys.len(), "requests need an API key");
    }
    let device = parse_device(&args.device)?;
    let (model, report) = load_face_model(&args.model, &device, args.quantize)?;
    tracing::info!("model weights: {report}");
    let image_model = match image_model_dir(&args.model, args.image_model.as_deref()) {
        Some(dir) => {
            Some(load_image_model(&dir, &args.model, args.image_encoder.as_deref(), &device)?)
        }
        None => {
            tracing::info!("no image model: image requests are off");
            None
        }
    };
    let config = EngineConfig {
        max_running: args.max_running,
        max_queue: args.max_queue,
        max_faces_per_request: args.max_faces,
        max_batch_faces: args.max_batch_faces,
        max_encodes_per_iteration: args.max_encodes_per_iteration,
        queue_timeout: seconds("queue-timeout", args.queue_timeout)?,
        aging: seconds("aging", args.aging)?,
        stream_buffer: args.stream_buffer,
        stream_idle_timeout: seconds("stream-idle-timeout", args.stream_idle_timeout)?,
        decode_threads: args.decode_threads,
        max_diffusion_steps: args.max_diffusion_steps,
        image_attempts: args.image_attempts,
        hull_faces: args.hull_faces,
    };
    let engine = Engine::start(model, image_model, config, Arc::new(Metrics::default()))?;
    let serve_config = ServeConfig {
        http_addr: args.http_addr,
        grpc_addr: args.grpc_addr,
        limits: InputLimits {
            max_points: args.max_points,
            reference_points: args.reference_points,
            read: ReadLimits {
                max_bytes: args.max_body_bytes as u64,
                max_vertices: args.max_points,
                max_faces: args.max_mesh_faces,
            },
        },
        max_body_bytes: args.max_body_bytes,
        read_timeouts: ReadTimeouts {
            header: seconds("header-read-timeout", args.header_read_timeout)?,
            body: seconds("body-read-timeout", args.body_read_timeout)?,
        },
        whole_mesh: WholeMeshDefaults {
            candidates: args.candidates,
            weld_radius: args.weld_radius,
            fit_rounds: usize::from(args.fit_rounds),
        },
        request_timeout: seconds("request-timeout", args.request_timeout)?,
        shutdown_grace: seconds("shutdown-grace", args.shutdown_grace)?,
        model_dir: args.model.clone(),
        image: ImageServeConfig {
            steps: args.diffusion_steps,
            guidance: args.guidance,
            framing: args.image_framing,
            max_side: args.max_image_side,
        },
        ui: !args.no_ui,
        auth: AuthConfig { keys, open_paths: args.auth_open_paths.clone() },
    };
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(async {
        let listeners = Listeners::bind(&serve_config).await?;
        // Tests and scripts read the ports from this line.
        let addr = |a: Option<SocketAddr>| a.map_or_else(|| "?".into(), |a| a.to_string());
        let listening = format!(
            "meshstream listening: http={} grpc={}",
            addr(listeners.http_addr()),
            addr(listeners.grpc_addr())
        );
        if let Err(e) = out(&listening) {
            tracing::warn!("{listening} (not on stdout: {e:#})");
        }
        serve(engine, serve_config, listeners, termination()).await
    })?;
    Ok(())
}

/// SIGTERM (Kubernetes, docker stop) or SIGINT (Ctrl-C).
async fn termination() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = term.recv() => {}
                    _ = tokio::signal::ctrl_c() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}
