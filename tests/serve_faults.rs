//! `serve` through faults: killed with SIGKILL mid-stream and restarted, stopped with SIGTERM
//! under load, started with a damaged model.

mod common;

use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use common::{Server, points_json, points_request, shape, stream_through};
use futures_util::StreamExt;
use meshstream::server::proto::mesh_generator_client::MeshGeneratorClient;
use meshstream::server::proto::reconstruct_response;
use serde_json::{Value, json};

const MODEL: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/models/default");

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_kill_9_mid_stream_a_restart_on_the_same_ports_serves_at_once() {
    let mut first = Server::start(&[]);
    let http = first.http.trim_start_matches("http://").to_string();
    let grpc = first.grpc.trim_start_matches("http://").to_string();
    let r = reqwest::Client::new()
        .post(first.url("/reconstruct"))
        .header("accept", "application/x-ndjson")
        .json(&points_json(&shape(), json!({"max_faces": 300})))
        .send()
        .await
        .unwrap();
    let mut chunks = r.bytes_stream();
    assert!(chunks.next().await.is_some());
    first.child.kill().unwrap(); // SIGKILL
    first.child.wait().unwrap();
    // The stream stops where it was; the client sees it cut (it has no `done`).
    let mut rest = String::new();
    while let Some(Ok(chunk)) = chunks.next().await {
        rest.push_str(&String::from_utf8_lossy(&chunk));
    }
    assert!(!rest.contains("\"type\":\"done\""), "the killed server finished: {rest}");

    // Nothing to recover: the new process binds the same ports and is ready as it listens.
    let t0 = Instant::now();
    let second = Server::start_at(MODEL, &http, &grpc, &[]);
    let started = t0.elapsed();
    let c = reqwest::Client::new();
    assert_eq!(c.get(second.url("/readyz")).send().await.unwrap().status(), 200);
    let last = stream_through(&second.http, || {}).await;
    assert_eq!(last["type"], "done", "{last}");
    let mut client = MeshGeneratorClient::connect(second.grpc.clone()).await.unwrap();
    let mut stream = client.reconstruct(points_request(20)).await.unwrap().into_inner();
    let mut done = false;
    while let Some(m) = stream.message().await.unwrap() {
        done |= matches!(m.event, Some(reconstruct_response::Event::Done(_)));
    }
    assert!(done);
    eprintln!("restarted and listening after {started:?}");
}

/// How one request under SIGTERM ended: `Ok` with its terminal answer (a whole answer, or a
/// clean refusal), `Err` when it was cut without one.
async fn http_stream(url: String) -> Result<String, String> {
    let body = points_json(&shape(), json!({"max_faces": 400, "temperature": 1.0}));
    let r = reqwest::Client::new()
        .post(url)
        .header("accept", "application/x-ndjson")
        .json(&body)
        .send()
        .await
        .map_err(|e| format!("no answer: {e}"))?;
    if r.status() != 200 {
        return Ok(format!("HTTP {}", r.status().as_u16()));
    }
    let text = r.text().await.map_err(|e| format!("the stream broke off: {e}"))?;
    let last: Value = text
        .trim()
        .lines()
        .last()
        .and_then(|l| serde_json::from_str(l).ok())
        .ok_or_else(|| format!("no last line in {text:?}"))?;
    match last["type"].as_str() {
        Some("done") => Ok("done".into()),
        Some("error") => Ok(format!("error {}", last["error"]["code"])),
        _ => Err(format!("the stream ended on {last}")),
    }
}

async fn whole_mesh(url: String) -> Result<String, String> {
    let body = points_json(&shape(), json!({"max_faces": 400, "candidates": 1}));
    let r = reqwest::Client::new().post(url).json(&body).send().await;
    let r = r.map_err(|e| format!("no answer: {e}"))?;
    let status = r.status().as_u16();
    let bytes = r.bytes().await.map_err(|e| format!("the answer broke off: {e}"))?;
    match status {
        200 => Ok("mesh".into()),
        _ => {
            let v: Value = serde_json::from_slice(&bytes).map_err(|e| format!("{status}: {e}"))?;
            Ok(format!("HTTP {status} {}", v["error"]["code"]))
        }
    }
}

async fn grpc_stream(url: String) -> Result<String, String> {
    let mut client = MeshGeneratorClient::connect(url).await.map_err(|e| e.to_string())?;
    let mut stream = match client.reconstruct(points_request(400)).await {
        Ok(r) => r.into_inner(),
        Err(status) => return Ok(format!("gRPC {:?}", status.code())),
    };
    loop {
        match stream.message().await {
            Ok(Some(m)) if matches!(m.event, Some(reconstruct_response::Event::Done(_))) => {
                return Ok("done".into());
            }
            Ok(Some(_)) => {}
            Ok(None) => return Err("the stream ended without its stats".into()),
            Err(s) if s.message().starts_with("shutting_down") => {
                return Ok(format!("gRPC {:?} shutting_down", s.code()));
            }
            Err(s) => return Err(format!("{s:?}")),
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_under_load_finishes_or_cleanly_fails_every_accepted_request() {
    let grace = 3;
    let mut server = Server::start(&["--shutdown-grace", &grace.to_string(), "--max-running", "4"]);
    let mut tasks = Vec::new();
    for i in 0..16 {
        let task = match i % 4 {
            0 => tokio::spawn(whole_mesh(server.url("/reconstruct"))),
            1 => tokio::spawn(grpc_stream(server.grpc.clone())),
            _ => tokio::spawn(http_stream(server.url("/reconstruct"))),
        };
        tasks.push(task);
    }
    // Every request accepted (running, queued or already done) before the signal.
    let c = reqwest::Client::new();
    let t0 = Instant::now();
    loop {
        let running = server.metric(&c, "meshstream_running_sequences").await;
        let queued = server.metric(&c, "meshstream_queue_depth").await;
        let text = c.get(server.url("/metrics")).send().await.unwrap().text().await.unwrap();
        let finished: f64 = text
            .lines()
            .filter(|l| l.starts_with("meshstream_requests_finished_total{"))
            .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
            .sum();
        if running + queued + finished >= 16.0 {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "the requests were never all accepted");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    server.terminate();
    let signalled = Instant::now();
    let mut ends = Vec::new();
    for task in tasks {
        let limit = Duration::from_secs(grace + 5).saturating_sub(signalled.elapsed());
        let end = tokio::time::timeout(limit, task).await;
        let end = end
            .unwrap_or_else(|_| panic!("a request hangs {:?} after SIGTERM", signalled.elapsed()));
        ends.push(end.unwrap());
    }
    let cut: Vec<&String> = ends.iter().filter_map(|e| e.as_ref().err()).collect();
    assert!(cut.is_empty(), "cut without a last event: {cut:?} of {ends:?}");
    // Each finished or was failed as the server shut down (503, UNAVAILABLE, an error event).
    for end in ends.iter().flatten() {
        let clean = ["done", "mesh"].contains(&end.as_str()) || end.contains("shutting_down");
        assert!(clean, "{end} in {ends:?}");
    }
    assert_eq!(server.wait_exit(Duration::from_secs(10)), Some(0));
}

/// `serve --model DIR` until it exits (killed after a minute: it should not start).
fn serve_with(dir: &std::path::Path) -> Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_meshstream"))
        .args(["serve", "--http-addr", "127.0.0.1:0", "--grpc-addr", "127.0.0.1:0", "--model"])
        .arg(dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t0.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.wait_with_output().unwrap()
}

#[test]
fn serve_refuses_a_truncated_or_misshapen_model_naming_the_tensor() {
    let dir = tempfile::tempdir().unwrap();
    let source = std::path::Path::new(MODEL);
    std::fs::copy(source.join("config.json"), dir.path().join("config.json")).unwrap();
    let weights = dir.path().join("model.safetensors");

    let bytes = std::fs::read(source.join("model.safetensors")).unwrap();
    std::fs::write(&weights, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let o = serve_with(dir.path());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && o.stdout.is_empty(), "it served a truncated model: {err}");
    assert!(err.contains("truncated") && err.contains("tensor "), "{err}");

    let device = candle_core::Device::Cpu;
    let mut tensors =
        candle_core::safetensors::load(source.join("model.safetensors"), &device).unwrap();
    let name = "decoder.layers.1.mlp.fc1.weight";
    let wrong = candle_core::Tensor::zeros((3, 4), candle_core::DType::F32, &device).unwrap();
    assert!(tensors.insert(name.to_string(), wrong).is_some(), "no {name} in the model");
    candle_core::safetensors::save(&tensors, &weights).unwrap();
    let o = serve_with(dir.path());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && o.stdout.is_empty(), "it served a misshapen model: {err}");
    assert!(err.contains(name), "{err}");
}
