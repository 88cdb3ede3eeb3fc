//! `meshstream bench serve`: a load generator against a real server in this process over
//! loopback, at several concurrency levels: whole meshes over HTTP (as a client that does not
//! ask for a stream gets them, with the server's defaults: candidates, welding, fitting) and
//! face streams over gRPC. Running servers (another build, say) can be measured in the same
//! run, level by level in turn with this one.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};
use meshstream::engine::{Engine, EngineConfig, Metrics, Stage};
use meshstream::mesh::{Mesh, REFERENCE_POINTS, ReadLimits};
use meshstream::metrics::median;
use meshstream::model::{DEFAULT_FACE_BEAM, DEFAULT_TEMPERATURE, Quantize, parse_device};
use meshstream::server::proto::mesh_generator_client::MeshGeneratorClient;
use meshstream::server::proto::{Options, ReconstructRequest, reconstruct_response};
use meshstream::server::{
    AuthConfig, ImageServeConfig, InputLimits, Listeners, ReadTimeouts, ServeConfig,
    WholeMeshDefaults, serve,
};

use super::bench_requests::{file_cloud, percentile_ms, points_request, test_cloud};
use super::out;

#[derive(Args)]
pub struct ServeBenchArgs {
    /// Model folder.
    #[arg(long, default_value = "models/default")]
    model: PathBuf,
    #[arg(long, default_value = "cpu")]
    device: String,
    /// Number format of the model's linear layers, as `serve --quantize`.
    #[arg(long, default_value_t = Quantize::F32)]
    quantize: Quantize,
    /// Concurrent clients, one level per row.
    #[arg(long, value_delimiter = ',', default_values_t = [1, 4, 16])]
    concurrency: Vec<usize>,
    /// What clients ask for.
    #[arg(long, value_delimiter = ',', default_values_t = [Interface::Whole, Interface::Stream])]
    interface: Vec<Interface>,
    /// Requests each client sends, one after the other.
    #[arg(long, default_value_t = 4)]
    requests_per_client: usize,
    /// Times every level is measured, the levels taking turns: a level's ratio against one
    /// client is taken within its round, and with more than one round a second table gives
    /// each ratio's median and range (a machine's speed drifts between runs).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    rounds: u32,
    /// A mesh or point cloud file whose points every request sends, instead of the built-in
    /// test shape (a box with a sphere on top): how fast the server is depends on what it
    /// decodes for the input.
    #[arg(long)]
    input: Option<PathBuf>,
    /// Points in each request: the input's (a mesh's sampled on its surface), at most this many.
    #[arg(long, default_value_t = 4096, value_parser = clap::value_parser!(u32).range(1..))]
    points: u32,
    /// Face budget of each request.
    #[arg(long, default_value_t = 300)]
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
    /// Sequences the engine decodes together, as `serve --max-running`.
    #[arg(long, default_value_t = EngineConfig::default().max_running)]
    max_running: usize,
    /// A running server's HTTP address (host:port) whose whole meshes are measured too, at
    /// each level right after this build's; repeat for more. Start it with the same model
    /// and a long --queue-timeout.
    #[arg(long = "also-http")]
    also_http: Vec<SocketAddr>,
}

/// The stages whose work a level reports (see [`Metrics::add_work`]); the server measured has
/// no image model.
const WORK_STAGES: [Stage; 4] = [Stage::Prepare, Stage::Encode, Stage::Decode, Stage::End];

/// What a client asks for.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Interface {
    /// `POST /reconstruct` answered with a whole mesh (GLB): every face comes at the end.
    Whole,
    /// gRPC `Reconstruct`: faces streamed as they are decoded.
    Stream,
}

impl std::fmt::Display for Interface {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Whole => "whole",
            Self::Stream => "stream",
        })
    }
}

/// What one request saw.
struct Sample {
    faces: usize,
    time_to_first_face: Option<Duration>,
    total: Duration,
}

/// One level of one server and interface.
struct Level {
    samples: Vec<Sample>,
    wall: Duration,
}

impl Level {
    fn faces(&self) -> usize {
        self.samples.iter().map(|s| s.faces).sum()
    }

    fn faces_per_second(&self) -> f64 {
        self.faces() as f64 / self.wall.as_secs_f64()
    }
}

/// Each level's faces/s against one client's in the same round, over the rounds, in the order
/// the levels were first measured.
#[derive(Default)]
struct Ratios(Vec<((Interface, String, usize), Vec<f64>)>);

impl Ratios {
    fn add(&mut self, level: (Interface, String, usize), ratio: f64) {
        match self.0.iter_mut().find(|(l, _)| *l == level) {
            Some((_, seen)) => seen.push(ratio),
            None => self.0.push((level, vec![ratio])),
        }
    }

    fn table(&self) -> comfy_table::Table {
        let mut table = super::table();
        table.set_header([
            "interface",
            "server",
            "clients",
            "vs 1 client: median",
            "lowest",
            "highest",
            "rounds",
        ]);
        for ((interface, server, clients), seen) in &self.0 {
            let lowest = seen.iter().copied().fold(f64::INFINITY, f64::min);
            let highest = seen.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            table.add_row([
                interface.to_string(),
                server.clone(),
                clients.to_string(),
                median(seen.clone()).map_or("-".into(), |m| format!("{m:.2}x")),
                format!("{lowest:.2}x"),
                format!("{highest:.2}x"),
                seen.len().to_string(),
            ]);
        }
        table
    }
}

/// The CPU time this process has used so far (user and system, all its threads: the server
/// and, in a level, its clients), in seconds; `None` where it cannot be read.
///
/// Why: faces per CPU second at one client and at many tell how much batching saves per
/// request, apart from how many cores the one client's path keeps busy.
fn process_cpu_seconds() -> Option<f64> {
    #[cfg(unix)]
    {
        let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
        // SAFETY: getrusage fills the rusage it is given; a zeroed one is valid either way.
        let read = unsafe { libc::getrusage(libc::RUSAGE_SELF, usage.as_mut_ptr()) } == 0;
        // SAFETY: zero-initialized, and filled when read.
        let usage = unsafe { usage.assume_init() };
        let seconds = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
        read.then(|| seconds(usage.ru_utime) + seconds(usage.ru_stime))
    }
    #[cfg(not(unix))]
    None
}

pub fn run(args: &ServeBenchArgs) -> anyhow::Result<()> {
    let points = args.points as usize;
    let (cloud, source) = match &args.input {
        Some(input) => (file_cloud(input, points)?, input.display().to_string()),
        None => (test_cloud(points), "the built-in box and sphere".into()),
    };
    out(format_args!("input: {source}, {} points a request", cloud.vertices.len()))?;
    let device = parse_device(&args.device)?;
    let (model, _) = super::load_face_model(&args.model, &device, args.quantize)?;
    // The shipped engine settings: a level past `max_running` queues, as a server's would,
    // but for as long as it takes (a loaded machine is measured, not refused).
    let config = EngineConfig {
        decode_threads: args.decode_threads,
        max_running: args.max_running,
        queue_timeout: Duration::from_secs(600),
        ..EngineConfig::default()
    };
    let metrics = Arc::new(Metrics::default());
    let engine = Engine::start(model, None, config, Arc::clone(&metrics))?;
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
        let http = listeners.http_addr().context("no HTTP address")?;
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let server = tokio::spawn(serve(engine, serve_config, listeners, async {
            let _ = stopped.await;
        }));
        let mut table = super::table();
        table.set_header([
            "round",
            "interface",
            "server",
            "clients",
            "requests",
            "faces",
            "faces/s",
            "vs 1 client",
            "vs this build",
            "first face p50",
            "p99",
            "answer p50",
            "faces a CPU s",
            "rows a step",
            "work s: prepare, encode, decode, end",
        ]);
        let mut ratios = Ratios::default();
        for (round, &interface) in
            (1..=args.rounds).flat_map(|r| args.interface.iter().map(move |i| (r, i)))
        {
            let servers: Vec<(String, SocketAddr)> = match interface {
                Interface::Whole => std::iter::once(("this build".to_string(), http))
                    .chain(args.also_http.iter().map(|a| (a.to_string(), *a)))
                    .collect(),
                Interface::Stream => vec![("this build".to_string(), grpc)],
            };
            let mut single: Vec<Option<f64>> = vec![None; servers.len()];
            for &clients in &args.concurrency {
                let mut this_build = None;
                for (i, (name, addr)) in servers.iter().enumerate() {
                    let work_before = WORK_STAGES.map(|s| metrics.work_seconds(s));
                    let steps_before = metrics.decode_steps();
                    let cpu_before = process_cpu_seconds();
                    let level = match interface {
                        Interface::Whole => whole_level(*addr, &cloud, args, clients).await?,
                        Interface::Stream => stream_level(*addr, &cloud, args, clients).await?,
                    };
                    let throughput = level.faces_per_second();
                    let one = *single[i].get_or_insert(throughput);
                    let this = *this_build.get_or_insert(throughput);
                    ratios.add((interface, name.clone(), clients), throughput / one);
                    let mut row = vec![
                        round.to_string(),
                        interface.to_string(),
                        name.clone(),
                        clients.to_string(),
                        level.samples.len().to_string(),
                        level.faces().to_string(),
                        format!("{throughput:.0}"),
                        format!("{:.2}x", throughput / one),
                        format!("{:.2}x", throughput / this),
                    ];
                    let mut first: Vec<Duration> =
                        level.samples.iter().filter_map(|s| s.time_to_first_face).collect();
                    let mut total: Vec<Duration> = level.samples.iter().map(|s| s.total).collect();
                    first.sort();
                    total.sort();
                    row.extend([percentile_ms(&first, 0.5), percentile_ms(&first, 0.99)]);
                    row.push(percentile_ms(&total, 0.5));
                    // Only this build's engine is in this process.
                    let cpu = cpu_before.zip(process_cpu_seconds()).map(|(a, b)| b - a);
                    row.push(match cpu {
                        Some(seconds) if i == 0 && seconds > 0.0 => {
                            format!("{:.0}", level.faces() as f64 / seconds)
                        }
                        _ => "-".into(),
                    });
                    // How well decoding batched: sequences stepped together, on average.
                    let (steps, rows) = metrics.decode_steps();
                    row.push(match steps - steps_before.0 {
                        steps if i == 0 && steps > 0 => {
                            format!("{:.1}", (rows - steps_before.1) as f64 / steps as f64)
                        }
                        _ => "-".into(),
                    });
                    row.push(if i == 0 {
                        let work = WORK_STAGES.map(|s| metrics.work_seconds(s));
                        let spent =
                            work.iter().zip(work_before).map(|(a, b)| format!("{:.1}", a - b));
                        spent.collect::<Vec<_>>().join(", ")
                    } else {
                        "-".into()
                    });
                    table.add_row(row);
                }
            }
        }
        let _ = stop.send(());
        server.await??;
        out(&table)?;
        if args.rounds > 1 {
            out(ratios.table())?;
        }
        anyhow::Ok(())
    })
}

/// `clients` clients each asking `addr` over gRPC for streams, one after the other.
async fn stream_level(
    addr: SocketAddr,
    cloud: &Mesh,
    args: &ServeBenchArgs,
    clients: usize,
) -> anyhow::Result<Level> {
    let options = Options {
        max_faces: Some(args.max_faces),
        temperature: Some(args.temperature),
        face_beam: Some(args.face_beam),
        ..Options::default()
    };
    let request = points_request(cloud, options);
    let t0 = Instant::now();
    let tasks: Vec<_> = (0..clients)
        .map(|_| tokio::spawn(stream_client(addr, request.clone(), args.requests_per_client)))
        .collect();
    let mut samples = Vec::new();
    for t in tasks {
        samples.extend(t.await??);
    }
    Ok(Level { samples, wall: t0.elapsed() })
}

/// Sends `n` requests one after the other and reads each stream to its end.
async fn stream_client(
    addr: SocketAddr,
    request: ReconstructRequest,
    n: usize,
) -> anyhow::Result<Vec<Sample>> {
    let mut grpc = MeshGeneratorClient::connect(format!("http://{addr}")).await?;
    let mut samples = Vec::with_capacity(n);
    for _ in 0..n {
        let t0 = Instant::now();
        let mut stream = grpc.reconstruct(request.clone()).await?.into_inner();
        let (mut faces, mut time_to_first_face) = (0, None);
        while let Some(message) = stream.message().await? {
            if let Some(reconstruct_response::Event::Faces(chunk)) = message.event {
                time_to_first_face.get_or_insert_with(|| t0.elapsed());
                faces += chunk.faces.len();
            }
        }
        samples.push(Sample { faces, time_to_first_face, total: t0.elapsed() });
    }
    Ok(samples)
}

/// `clients` clients each asking `addr` over HTTP for whole meshes, one after the other.
async fn whole_level(
    addr: SocketAddr,
    cloud: &Mesh,
    args: &ServeBenchArgs,
    clients: usize,
) -> anyhow::Result<Level> {
    let body = serde_json::to_vec(&serde_json::json!({
        "points": cloud.vertices,
        "normals": cloud.normals,
        "max_faces": args.max_faces,
        "temperature": args.temperature,
        "face_beam": args.face_beam,
    }))?;
    let url = format!("http://{addr}/reconstruct");
    // A connection per client, as separate clients have.
    let n = args.requests_per_client;
    let t0 = Instant::now();
    let tasks: Vec<_> = (0..clients)
        .map(|_| {
            let (url, body) = (url.clone(), body.clone());
            tokio::spawn(async move {
                let client = reqwest::Client::new();
                let mut samples = Vec::with_capacity(n);
                for _ in 0..n {
                    samples.push(whole_mesh(&client, &url, body.clone()).await?);
                }
                anyhow::Ok(samples)
            })
        })
        .collect();
    let mut samples = Vec::new();
    for t in tasks {
        samples.extend(t.await??);
    }
    Ok(Level { samples, wall: t0.elapsed() })
}

/// One `POST /reconstruct` of `body` (JSON points) answered with a whole mesh.
async fn whole_mesh(client: &reqwest::Client, url: &str, body: Vec<u8>) -> anyhow::Result<Sample> {
    let t0 = Instant::now();
    let answer = client
        .post(url)
        .header("content-type", "application/json")
        .body(body)
        .send()
        .await
        .with_context(|| format!("asking {url}"))?;
    let status = answer.status();
    let faces = answer.headers().get("x-meshstream-faces").cloned();
    let bytes = answer.bytes().await?;
    let total = t0.elapsed();
    if !status.is_success() {
        bail!("{url} answered {status}: {}", String::from_utf8_lossy(&bytes).trim());
    }
    let faces = faces
        .and_then(|v| v.to_str().ok()?.parse().ok())
        .context("the answer has no x-meshstream-faces header")?;
    Ok(Sample { faces, time_to_first_face: Some(total), total })
}
