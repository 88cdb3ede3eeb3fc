//! `meshstream bench serve`: a load generator against a real server in this process over
//! loopback, at several concurrency levels: whole meshes over HTTP (as a client that does not
//! ask for a stream gets them, with the server's defaults: candidates, welding, fitting) and
//! face streams over gRPC. Running servers (another build, say) can be measured in the same
//! run, level by level in turn with this one.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};
use meshstream::engine::{Engine, EngineConfig, Metrics};
use meshstream::mesh::{Mesh, REFERENCE_POINTS, ReadLimits, primitives, sample_surface};
use meshstream::model::{DEFAULT_FACE_BEAM, DEFAULT_TEMPERATURE, checkpoint, parse_device};
use meshstream::server::proto::mesh_generator_client::MeshGeneratorClient;
use meshstream::server::proto::{
    Options, PointCloud, ReconstructRequest, reconstruct_request, reconstruct_response,
};
use meshstream::server::{
    ImageServeConfig, InputLimits, Listeners, ServeConfig, WholeMeshDefaults, serve,
};

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
    /// What clients ask for.
    #[arg(long, value_delimiter = ',', default_values_t = [Interface::Whole, Interface::Stream])]
    interface: Vec<Interface>,
    /// Requests each client sends, one after the other.
    #[arg(long, default_value_t = 4)]
    requests_per_client: usize,
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
    /// A running server's HTTP address (host:port) whose whole meshes are measured too, at
    /// each level right after this build's; repeat for more. Start it with the same model
    /// and a long --queue-timeout.
    #[arg(long = "also-http")]
    also_http: Vec<SocketAddr>,
}

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
    fn faces_per_second(&self) -> f64 {
        self.samples.iter().map(|s| s.faces).sum::<usize>() as f64 / self.wall.as_secs_f64()
    }
}

pub fn run(args: &ServeBenchArgs) -> anyhow::Result<()> {
    let device = parse_device(&args.device)?;
    let model = checkpoint::load(&args.model, &device)
        .with_context(|| format!("loading the model in {}", args.model.display()))?;
    // The shipped engine settings: a level past `max_running` queues, as a server's would,
    // but for as long as it takes (a loaded machine is measured, not refused).
    let config = EngineConfig {
        decode_threads: args.decode_threads,
        queue_timeout: Duration::from_secs(600),
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
        whole_mesh: WholeMeshDefaults::default(),
        request_timeout: Duration::from_secs(600),
        shutdown_grace: Duration::from_secs(5),
        image: ImageServeConfig::default(),
        model_dir: args.model.clone(),
        ui: false,
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
        let cloud = test_cloud();
        let mut table = super::table();
        table.set_header([
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
        ]);
        for &interface in &args.interface {
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
                    let level = match interface {
                        Interface::Whole => whole_level(*addr, &cloud, args, clients).await?,
                        Interface::Stream => stream_level(*addr, &cloud, args, clients).await?,
                    };
                    let throughput = level.faces_per_second();
                    let one = *single[i].get_or_insert(throughput);
                    let this = *this_build.get_or_insert(throughput);
                    let mut row = vec![
                        interface.to_string(),
                        name.clone(),
                        clients.to_string(),
                        level.samples.len().to_string(),
                        level.samples.iter().map(|s| s.faces).sum::<usize>().to_string(),
                        format!("{throughput:.0}"),
                        format!("{:.2}x", throughput / one),
                        format!("{:.2}x", throughput / this),
                    ];
                    let first: Vec<Duration> =
                        level.samples.iter().filter_map(|s| s.time_to_first_face).collect();
                    let total: Vec<Duration> = level.samples.iter().map(|s| s.total).collect();
                    row.extend([percentile(first.clone(), 0.5), percentile(first, 0.99)]);
                    row.push(percentile(total, 0.5));
                    table.add_row(row);
                }
            }
        }
        let _ = stop.send(());
        server.await??;
        out(&table)?;
        anyhow::Ok(())
    })
}

/// The `p` quantile of `times` in milliseconds, "-" for none.
fn percentile(mut times: Vec<Duration>, p: f64) -> String {
    times.sort();
    times
        .get(((times.len() as f64 - 1.0) * p).round() as usize)
        .map_or("-".to_string(), |d| format!("{:.0} ms", d.as_secs_f64() * 1e3))
}

/// A fixed test shape (a box with a sphere on top), sampled to points with normals.
fn test_cloud() -> Mesh {
    let mut shape = primitives::cuboid([1.0, 0.6, 0.8]);
    shape.append(&primitives::uv_sphere(0.4, 8, 5).translated([0.0, 0.6, 0.0]));
    sample_surface(&shape, 4096, 0).unwrap_or_default()
}

/// `clients` clients each asking `addr` over gRPC for streams, one after the other.
async fn stream_level(
    addr: SocketAddr,
    cloud: &Mesh,
    args: &ServeBenchArgs,
    clients: usize,
) -> anyhow::Result<Level> {
    let request = ReconstructRequest {
        input: Some(reconstruct_request::Input::Points(PointCloud {
            positions: cloud.vertices.iter().flatten().copied().collect(),
            normals: cloud.normals.iter().flatten().flatten().copied().collect(),
        })),
        options: Some(Options {
            max_faces: Some(args.max_faces),
            temperature: Some(args.temperature),
            face_beam: Some(args.face_beam),
            ..Options::default()
        }),
    };
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
    let body: Arc<[u8]> = serde_json::to_vec(&serde_json::json!({
        "points": cloud.vertices,
        "normals": cloud.normals,
        "max_faces": args.max_faces,
        "temperature": args.temperature,
        "face_beam": args.face_beam,
    }))?
    .into();
    let n = args.requests_per_client;
    let t0 = Instant::now();
    let tasks: Vec<_> = (0..clients)
        .map(|_| {
            let body = body.clone();
            tokio::task::spawn_blocking(move || {
                (0..n).map(|_| whole_mesh(addr, &body)).collect::<anyhow::Result<Vec<_>>>()
            })
        })
        .collect();
    let mut samples = Vec::new();
    for t in tasks {
        samples.extend(t.await??);
    }
    Ok(Level { samples, wall: t0.elapsed() })
}

/// One `POST /reconstruct` of `body` (JSON points) answered with a whole mesh, over a
/// connection of its own (HTTP/1.1, closed by the server after the answer).
fn whole_mesh(addr: SocketAddr, body: &[u8]) -> anyhow::Result<Sample> {
    let t0 = Instant::now();
    let mut connection =
        TcpStream::connect(addr).with_context(|| format!("connecting to {addr}"))?;
    write!(
        connection,
        "POST /reconstruct HTTP/1.1\r\nhost: {addr}\r\ncontent-type: application/json\r\n\
         content-length: {}\r\nconnection: close\r\n\r\n",
        body.len()
    )?;
    connection.write_all(body)?;
    let mut answer = Vec::new();
    connection.read_to_end(&mut answer)?;
    let total = t0.elapsed();
    let head_end = answer.windows(4).position(|w| w == b"\r\n\r\n").context("no HTTP head")?;
    let head = String::from_utf8_lossy(&answer[..head_end]);
    let status = head.lines().next().unwrap_or_default();
    if !status.contains(" 200 ") {
        let body = String::from_utf8_lossy(&answer[head_end..]);
        bail!("{addr} answered {status}: {}", body.trim());
    }
    let faces = head
        .lines()
        .find_map(|line| {
            let (name, value) = line.split_once(':')?;
            name.eq_ignore_ascii_case("x-meshstream-faces").then(|| value.trim().parse().ok())?
        })
        .context("the answer has no x-meshstream-faces header")?;
    Ok(Sample { faces, time_to_first_face: Some(total), total })
}
