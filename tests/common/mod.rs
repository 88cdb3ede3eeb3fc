//! A real `meshstream serve` process on ephemeral ports, for the interface tests.

#![allow(dead_code)] // each test binary uses part of it

pub mod models;

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use meshstream::mesh::Mesh;
use meshstream::mesh::primitives::{cuboid, uv_sphere};
use meshstream::server::proto::{Options, PointCloud, ReconstructRequest, reconstruct_request};

pub struct Server {
    pub child: Child,
    pub http: String,
    pub grpc: String,
}

impl Server {
    /// Starts the server with the shipped model and `extra` flags; waits until it listens.
    pub fn start(extra: &[&str]) -> Server {
        Self::start_with_model(Self::MODEL, extra)
    }

    /// Starts the server with the model in `model`.
    pub fn start_with_model(model: &str, extra: &[&str]) -> Server {
        Self::start_at(model, "127.0.0.1:0", "127.0.0.1:0", extra)
    }

    /// Starts the server with the model in `model` on the HTTP and gRPC addresses given.
    pub fn start_at(model: &str, http: &str, grpc: &str, extra: &[&str]) -> Server {
        let mut command = Self::command_at(model, http, grpc, extra);
        command.stderr(Stdio::inherit());
        Self::spawn(command)
    }

    /// The command that [`Server::start_with_model`] runs, for a test to add to (environment,
    /// where its log goes) before [`Server::spawn`].
    pub fn command(model: &str, extra: &[&str]) -> Command {
        Self::command_at(model, "127.0.0.1:0", "127.0.0.1:0", extra)
    }

    fn command_at(model: &str, http: &str, grpc: &str, extra: &[&str]) -> Command {
        let mut command = Command::new(env!("CARGO_BIN_EXE_meshstream"));
        command
            .args(["serve", "--model", model, "--http-addr", http, "--grpc-addr", grpc])
            .args(extra)
            .env("MESHSTREAM_LOG", "warn")
            .stdout(Stdio::piped());
        command
    }

    /// Runs a server command; waits until it listens.
    pub fn spawn(mut command: Command) -> Server {
        let mut child = command.spawn().unwrap();
        let stdout = child.stdout.take().unwrap();
        let mut line = String::new();
        BufReader::new(stdout).read_line(&mut line).unwrap();
        // "meshstream listening: http=ADDR grpc=ADDR"
        let field = |name: &str| {
            line.split_whitespace()
                .find_map(|w| w.strip_prefix(&format!("{name}=")).map(str::to_string))
        };
        let http = field("http").unwrap_or_else(|| panic!("no address in {line:?}"));
        let grpc = field("grpc").unwrap_or_else(|| panic!("no gRPC address in {line:?}"));
        Server { child, http: format!("http://{http}"), grpc: format!("http://{grpc}") }
    }

    /// The shipped model's folder.
    pub const MODEL: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/models/default");

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.http)
    }

    /// SIGTERM, as Kubernetes sends it.
    pub fn terminate(&self) {
        let pid = self.child.id().to_string();
        assert!(Command::new("kill").args(["-TERM", &pid]).status().unwrap().success());
    }

    pub fn wait_exit(&mut self, limit: Duration) -> Option<i32> {
        let t0 = Instant::now();
        while t0.elapsed() < limit {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status.code();
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        None
    }

    /// A metric's value from `/metrics`: the sum of the samples whose lines start with `prefix`
    /// (one sample, or all of a metric's labels when the prefix leaves them open).
    pub async fn metric(&self, client: &reqwest::Client, prefix: &str) -> f64 {
        let text = client.get(self.url("/metrics")).send().await.unwrap().text().await.unwrap();
        let values: Vec<f64> = text
            .lines()
            .filter(|l| l.starts_with(prefix))
            .filter_map(|l| l.rsplit(' ').next()?.parse().ok())
            .collect();
        assert!(!values.is_empty(), "no {prefix} in\n{text}");
        values.iter().sum()
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A small test shape: a box on a sphere, as a point cloud with normals sampled from it.
pub fn shape() -> Mesh {
    let mut m = cuboid([1.0, 0.6, 0.8]);
    m.append(&uv_sphere(0.4, 8, 5).translated([0.0, 0.6, 0.0]));
    meshstream::mesh::sample_surface(&m, 3000, 7).unwrap()
}

pub fn points_json(m: &Mesh, extra: serde_json::Value) -> serde_json::Value {
    let mut body = serde_json::json!({
        "points": m.vertices,
        "normals": m.normals,
    });
    if let (Some(b), Some(e)) = (body.as_object_mut(), extra.as_object()) {
        b.extend(e.clone());
    }
    body
}

/// The gRPC request for [`shape`]'s points.
pub fn points_request(max_faces: u32) -> ReconstructRequest {
    let cloud = shape();
    ReconstructRequest {
        input: Some(reconstruct_request::Input::Points(PointCloud {
            positions: cloud.vertices.iter().flatten().copied().collect(),
            normals: cloud.normals.unwrap().iter().flatten().copied().collect(),
        })),
        options: Some(Options { max_faces: Some(max_faces), ..Options::default() }),
    }
}

/// Starts an NDJSON stream of [`shape`] reconstructed at `base_url` (`http://HOST:PORT`), calls
/// `signal` once its first bytes have arrived (to stop the server under it), reads the rest and
/// gives the last event.
pub async fn stream_through(base_url: &str, signal: impl FnOnce()) -> serde_json::Value {
    let body = points_json(&shape(), serde_json::json!({"max_faces": 300}));
    let r = reqwest::Client::new()
        .post(format!("{base_url}/reconstruct"))
        .header("accept", "application/x-ndjson")
        .json(&body)
        .send()
        .await
        .unwrap();
    let mut chunks = r.bytes_stream();
    let _first = chunks.next().await.unwrap().unwrap();
    signal();
    let mut text = String::new();
    while let Some(chunk) = chunks.next().await {
        text.push_str(std::str::from_utf8(&chunk.unwrap()).unwrap());
    }
    serde_json::from_str(text.trim().lines().last().unwrap()).unwrap()
}
