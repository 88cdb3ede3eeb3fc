//! `meshstream bench serve`: a load generator against a real server in this process (gRPC
//! streams over loopback), at several concurrency levels.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Args;
use meshstream::engine::{Engine, EngineConfig, Metrics};
use meshstream::mesh::{REFERENCE_POINTS, ReadLimits};
use meshstream::model::{DEFAULT_FACE_BEAM, DEFAULT_TEMPERATURE, checkpoint, parse_device};
use meshstream::server::proto::mesh_generator_client::MeshGeneratorClient;
use meshstream::server::proto::{Options, ReconstructRequest, reconstruct_response};
use meshstream::server::{
    AuthConfig, ImageServeConfig, InputLimits, Listeners, ReadTimeouts, ServeConfig,
    WholeMeshDefaults, serve,
};

use super::bench_requests::{percentile_ms, points_request, test_cloud};
use super::out;

#[derive(Args)]
pub struct ServeBenchArgs {
    /// Model folder.
    #[arg(long, default_value = "models/default")]
    model: PathBuf,
    #[arg(long, default_value = "cpu")]
    device: String,
    /// Concurrent clients, one level per row.
    #[arg(long, value_delimiter = ',', default_values_t = [1, 4, 16])]
    concurrency: Vec<usize>,
    /// Requests each client sends, one after the other.
    #[arg(long, default_value_t = 4)]
    requests_per_client: usize,
    /// Face budget of each request.
    #[arg(long, default_value_t = 200)]
    max_faces: u32,
    /// Sampling temperature of each request (0: greedy decoding with `--face-beam`).
    #[arg(long, default_value_t = DEFAULT_TEMPERATURE)]
    temperature: f32,
    /// Greedy decoding's face beam in each request (1: per-coordinate greedy).
    #[arg(long, default_value_t = DEFAULT_FACE_BEAM as u32)]
    face_beam: u32,
    /// The engine's decode threads (0: one per core).
    #[arg(long, default_value_t = 0)]
    decode_threads: usize,
}

/// What one request saw.
struct Sample {
    faces: usize,
    time_to_first_face: Option<Duration>,
}

pub fn run(args: &ServeBenchArgs) -> anyhow::Result<()> {
    let device = parse_device(&args.device)?;
    let model = checkpoint::load(&args.model, &device)
        .with_context(|| format!("loading the model in {}", args.model.display()))?;
    let max_level = args.concurrency.iter().copied().max().unwrap_or(1);
    let config = EngineConfig {
        max_running: max_level,
        max_queue: max_level * 2,
        decode_threads: args.decode_threads,
        ..EngineConfig::default()
    };
    let engine = Engine::start(model, None, config, Arc::new(Metrics::default()))?;
    let loopback = SocketAddr::from(([127, 0, 0, 1], 0));
    let serve_config = ServeConfig {
        http_addr: loopback,
        grpc_addr: loopback,
        limits: InputLimits {
            max_points: 1 << 20,
            reference_points: REFERENCE_POINTS,
            read: ReadLimits::default(),
        },
        max_body_bytes: 64 << 20,
        read_timeouts: ReadTimeouts::default(),
        whole_mesh: WholeMeshDefaults::default(),
        request_timeout: Duration::from_secs(600),
        shutdown_grace: Duration::from_secs(5),
        image: ImageServeConfig::default(),
        model_dir: args.model.clone(),
        ui: false,
        auth: AuthConfig::default(),
    };
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(async {
        let listeners = Listeners::bind(&serve_config).await?;
        let grpc = listeners.grpc_addr().context("no gRPC address")?;
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let server = tokio::spawn(serve(engine, serve_config, listeners, async {
            let _ = stopped.await;
        }));
        let request = request(args);
        let mut table = super::table();
        table.set_header([
            "clients",
            "requests",
            "faces",
            "throughput (faces/s)",
            "vs 1 client",
            "time to first face p50",
            "p99",
        ]);
        let mut single = None;
        for &clients in &args.concurrency {
            let t0 = Instant::now();
            let tasks: Vec<_> = (0..clients)
                .map(|_| {
                    let request = request.clone();
                    let n = args.requests_per_client;
                    tokio::spawn(async move { client(grpc, request, n).await })
                })
                .collect();
            let mut samples = Vec::new();
            for t in tasks {
                samples.extend(t.await??);
            }
            let wall = t0.elapsed().as_secs_f64();
            let faces: usize = samples.iter().map(|s| s.faces).sum();
            let throughput = faces as f64 / wall;
            let base = *single.get_or_insert(throughput);
            let mut ttff: Vec<Duration> =
                samples.iter().filter_map(|s| s.time_to_first_face).collect();
            ttff.sort();
            table.add_row([
                clients.to_string(),
                samples.len().to_string(),
                faces.to_string(),
                format!("{throughput:.0}"),
                format!("{:.2}x", throughput / base),
                percentile_ms(&ttff, 0.5),
                percentile_ms(&ttff, 0.99),
            ]);
        }
        let _ = stop.send(());
        server.await??;
        out(&table)?;
        anyhow::Ok(())
    })
}

/// The test shape's points, with this run's options.
fn request(args: &ServeBenchArgs) -> ReconstructRequest {
    let options = Options {
        max_faces: Some(args.max_faces),
        temperature: Some(args.temperature),
        face_beam: Some(args.face_beam),
        ..Options::default()
    };
    points_request(&test_cloud(4096), options)
}

/// Sends `n` requests one after the other and reads each stream to its end.
async fn client(
    addr: SocketAddr,
    request: ReconstructRequest,
    n: usize,
) -> anyhow::Result<Vec<Sample>> {
    let mut grpc = MeshGeneratorClient::connect(format!("http://{addr}")).await?;
    let mut samples = Vec::with_capacity(n);
    for _ in 0..n {
        let t0 = Instant::now();
        let mut stream = grpc.reconstruct(request.clone()).await?.into_inner();
        let mut sample = Sample { faces: 0, time_to_first_face: None };
        while let Some(message) = stream.message().await? {
            if let Some(reconstruct_response::Event::Faces(chunk)) = message.event {
                sample.time_to_first_face.get_or_insert_with(|| t0.elapsed());
                sample.faces += chunk.faces.len();
            }
        }
        samples.push(sample);
    }
    Ok(samples)
}
