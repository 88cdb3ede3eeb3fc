//! `serve` under sustained and excessive load and against clients that are slow on purpose:
//! `bench soak` in CI size, overload against a short queue, a stalled stream reader, headers
//! and bodies sent too slowly, and connections that send nothing when the server stops.

mod common;

use std::process::Command;
use std::time::{Duration, Instant};

use common::{Server, points_request};
use meshstream::server::proto::mesh_generator_client::MeshGeneratorClient;
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// `meshstream bench KIND --model (the shipped one) ARGS`: its standard output, after checking
/// that it exited 0.
fn bench(kind: &str, args: &[&str]) -> String {
    let model = concat!(env!("CARGO_MANIFEST_DIR"), "/models/default");
    let out = Command::new(env!("CARGO_BIN_EXE_meshstream"))
        .args(["bench", kind, "--model", model])
        .args(args)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{kind} {args:?}: {}\n{stdout}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// `meshstream bench soak ARGS --json`: the report.
fn soak(args: &[&str]) -> Value {
    let stdout = bench("soak", &[args, &["--json"]].concat());
    serde_json::from_str(stdout.trim()).unwrap_or_else(|e| panic!("{e}: {stdout}"))
}

fn count(report: &Value, prefix: &str) -> u64 {
    let outcomes = report["outcomes"].as_object().unwrap();
    outcomes.iter().filter(|(k, _)| k.starts_with(prefix)).map(|(_, v)| v.as_u64().unwrap()).sum()
}

#[test]
fn a_ci_sized_soak_loses_nothing_and_gives_its_memory_back() {
    let r = soak(&["--requests", "160", "--concurrency", "8", "--garbage-share", "0.1"]);
    assert_eq!(r["lost"], 0, "{r}");
    assert_eq!(r["accepted_garbage"], 0, "{r}");
    // Every kind of request was sent and answered as it should be.
    for kind in ["completed: HTTP whole mesh", "completed: HTTP stream", "completed: gRPC stream"] {
        assert!(count(&r, kind) > 0, "no {kind}: {r}");
    }
    assert!(count(&r, "refused: HTTP 4") > 0, "no garbage refused over HTTP: {r}");
    assert!(count(&r, "refused: gRPC InvalidArgument") > 0, "no garbage refused over gRPC: {r}");
    assert!(count(&r, "left after the first face") > 0, "no client left early: {r}");
    let done = count(&r, "completed") + count(&r, "refused") + count(&r, "left");
    assert_eq!(done, 160, "{r}");
    assert_eq!(r["server_exit"], "exit status: 0", "{r}");
    // Memory at the end within 25% of the warm level, both read after the server's idle trim
    // (the 10,000-request run is held to 10%).
    let rss = &r["rss_bytes"];
    let (start, end) = (rss["start"].as_f64().unwrap(), rss["end"].as_f64().unwrap());
    assert!(end <= start * 1.25, "RSS {start} at the start, {end} at the end: {r}");
}

#[test]
fn bench_serve_rounds_take_turns_and_summarize_each_ratio() {
    let sweep = ["--concurrency", "1,2", "--interface", "whole", "--requests-per-client", "1"];
    let stdout = bench("serve", &[&sweep[..], &["--max-faces", "20", "--rounds", "2"]].concat());
    let lines: Vec<Vec<&str>> = stdout
        .lines()
        .map(|line| line.split('|').map(str::trim).filter(|c| !c.is_empty()).collect())
        .collect();
    // Round by round, each level in turn, one client first: its ratio is its own.
    let levels: Vec<(&str, &str, &str, &str)> = lines
        .iter()
        .filter(|cells| cells.first().is_some_and(|c| c.parse::<u32>().is_ok()))
        .map(|r| (r[0], r[3], r[7], r[13]))
        .collect();
    assert_eq!(levels.len(), 4, "{stdout}");
    for (i, &(round, clients, vs_one, rows_a_step)) in levels.iter().enumerate() {
        assert_eq!(round, ["1", "2"][i / 2], "{stdout}");
        assert_eq!(clients, ["1", "2"][i % 2], "{stdout}");
        if clients == "1" {
            assert_eq!(vs_one, "1.00x", "{stdout}");
            // A whole mesh's 4 candidates step together, however soon some of them end.
            let rows: f64 = rows_a_step.parse().unwrap_or_else(|e| panic!("{e}: {stdout}"));
            assert!(rows > 1.0 && rows <= 4.0, "{stdout}");
        }
    }
    // Then the summary: the two-client level's ratio over both rounds, between its two values.
    let summary = lines
        .iter()
        .find(|c| c.len() == 7 && c[0] == "whole" && c[2] == "2")
        .unwrap_or_else(|| panic!("no summary row: {stdout}"));
    let ratio = |c: &str| c.trim_end_matches('x').parse::<f64>().unwrap();
    let seen: Vec<f64> = levels.iter().filter(|l| l.1 == "2").map(|l| ratio(l.2)).collect();
    let (lowest, highest) = (seen[0].min(seen[1]), seen[0].max(seen[1]));
    assert_eq!(summary[6], "2", "{stdout}");
    assert!((ratio(summary[4]) - lowest).abs() < 0.006, "{stdout}");
    assert!((ratio(summary[5]) - highest).abs() < 0.006, "{stdout}");
    assert!((ratio(summary[3]) - (lowest + highest) / 2.0).abs() < 0.011, "{stdout}");
}

#[test]
fn bench_serve_sends_a_given_meshs_points_and_names_a_file_it_cannot_read() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = dir.path().join("tetrahedron.obj");
    let faces = "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n";
    std::fs::write(&mesh, format!("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n{faces}")).unwrap();
    let level = ["--concurrency", "1", "--interface", "whole", "--requests-per-client", "1"];
    let input = mesh.to_str().unwrap();
    let args = [&level[..], &["--max-faces", "20", "--input", input, "--points", "1500"]].concat();
    let stdout = bench("serve", &args);
    assert!(stdout.starts_with(&format!("input: {input}, 1500 points a request\n")), "{stdout}");
    assert!(stdout.lines().any(|l| l.starts_with("| 1 ")), "no level measured: {stdout}");

    let missing = dir.path().join("missing.ply");
    let out = Command::new(env!("CARGO_BIN_EXE_meshstream"))
        .args(["bench", "serve", "--input", missing.to_str().unwrap()])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && stderr.contains("missing.ply"), "{stderr}");
}

#[test]
fn overload_is_refused_at_once_and_admitted_requests_keep_their_pace() {
    // As many clients as the server runs and queues (16 + 16; both set here, whatever the
    // defaults): nobody is refused.
    let at_capacity = soak(&[
        "--requests",
        "64",
        "--concurrency",
        "32",
        "--garbage-share",
        "0",
        "--leave-share",
        "0",
        "--serve-arg=--max-queue=16",
        "--serve-arg=--max-running=16",
    ]);
    // Twice that: the rest are refused with 429 and come back after Retry-After.
    let overloaded = soak(&[
        "--requests",
        "128",
        "--concurrency",
        "64",
        "--garbage-share",
        "0",
        "--leave-share",
        "0",
        "--serve-arg=--max-queue=16",
        "--serve-arg=--max-running=16",
    ]);
    // Nothing lost; each request completed or, after 30 tries, was refused as the queue was
    // full (a client may keep arriving when others have just taken the room).
    for r in [&at_capacity, &overloaded] {
        assert_eq!(r["lost"], 0, "{r}");
        let refused = count(r, "refused: queue_full");
        assert_eq!(count(r, "completed") + refused, r["requests"].as_u64().unwrap(), "{r}");
        assert!(refused * 10 <= r["requests"].as_u64().unwrap(), "{r}");
    }
    assert!(overloaded["retried_429"].as_u64().unwrap() > 0, "nothing refused: {overloaded}");
    // Refusals come at once: no queueing, no reading of more than the body.
    let refusal_p99 = overloaded["answer_429_ms"]["p99"].as_f64().unwrap();
    assert!(refusal_p99 < 1000.0, "429 after {refusal_p99} ms: {overloaded}");
    // Admitted requests take about what they take at capacity (shared CI machines are noisy:
    // a generous bound that refusals queueing in front of them would still break).
    let p99 = |r: &Value| r["latency_ms"]["p99"].as_f64().unwrap();
    assert!(
        p99(&overloaded) < 2.0 * p99(&at_capacity) + 1000.0,
        "p99 {} ms under overload, {} ms at capacity",
        p99(&overloaded),
        p99(&at_capacity)
    );
    // Memory stays flat: refused requests are not kept.
    let peak = |r: &Value| r["rss_bytes"]["peak"].as_f64().unwrap();
    assert!(peak(&overloaded) < 1.25 * peak(&at_capacity), "{overloaded} vs {at_capacity}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stalled_stream_reader_is_cancelled_and_frees_its_slot() {
    let server = Server::start(&[
        "--max-running",
        "1",
        "--stream-buffer",
        "4",
        "--stream-idle-timeout",
        "1",
    ]);
    // A client whose HTTP/2 window takes a few faces: once it stops reading, the server
    // cannot send, the stream's buffer fills and its sequence waits.
    let channel = tonic::transport::Endpoint::from_shared(server.grpc.clone())
        .unwrap()
        .initial_stream_window_size(Some(256))
        .initial_connection_window_size(Some(256))
        .connect()
        .await
        .unwrap();
    let mut grpc = MeshGeneratorClient::new(channel);
    let mut stalled = grpc.reconstruct(points_request(400)).await.unwrap().into_inner();
    assert!(stalled.message().await.unwrap().is_some());
    let c = reqwest::Client::new();
    let t0 = Instant::now();
    assert_eq!(server.metric(&c, "meshstream_running_sequences").await, 1.0);
    while server.metric(&c, "meshstream_running_sequences").await > 0.0 {
        assert!(t0.elapsed() < Duration::from_secs(10), "the stalled stream still holds its slot");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // The only slot is free: another request runs to its end.
    let body = common::points_json(&common::shape(), serde_json::json!({"max_faces": 20}));
    let r = c.post(server.url("/reconstruct")).json(&body).send().await.unwrap();
    assert_eq!(r.status(), 200);
    // The stalled reader, reading again, finds its faces and then why it was cancelled.
    let end = loop {
        match stalled.message().await {
            Ok(Some(_)) => continue,
            other => break other,
        }
    };
    let status = end.unwrap_err();
    assert_eq!(status.code(), tonic::Code::Cancelled, "{status:?}");
    assert!(status.message().starts_with("stream_idle"), "{status:?}");
    assert_eq!(
        server.metric(&c, "meshstream_requests_failed_total{reason=\"stream_idle\"}").await,
        1.0
    );
}

/// Whether the server closed `stream` within `limit`, writing `bytes` one at a time
/// `every` so often meanwhile; and what it answered before closing.
async fn trickle(
    mut stream: TcpStream,
    bytes: &[u8],
    every: Duration,
    limit: Duration,
) -> (bool, String) {
    let (mut read, mut write) = stream.split();
    let mut answer = Vec::new();
    let t0 = Instant::now();
    let mut sent = 0;
    while t0.elapsed() < limit {
        if sent < bytes.len() && write.write_all(&bytes[sent..=sent]).await.is_ok() {
            sent += 1;
        }
        let mut buf = [0u8; 4096];
        match tokio::time::timeout(every, read.read(&mut buf)).await {
            Ok(Ok(0)) | Ok(Err(_)) => return (true, String::from_utf8_lossy(&answer).into()),
            Ok(Ok(n)) => answer.extend_from_slice(&buf[..n]),
            Err(_) => {}
        }
    }
    (false, String::from_utf8_lossy(&answer).into())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn headers_sent_too_slowly_or_not_at_all_are_cut_off() {
    let server = Server::start(&["--header-read-timeout", "1"]);
    let addr = server.http.trim_start_matches("http://").to_string();
    let headers = b"POST /reconstruct HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n\
        Content-Length: 2\r\nX-Padding: aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa\r\n\r\n{}";
    // A byte every 100 ms: the headers would take 13 s.
    let t0 = Instant::now();
    let stream = TcpStream::connect(&addr).await.unwrap();
    let (closed, _) =
        trickle(stream, headers, Duration::from_millis(100), Duration::from_secs(6)).await;
    assert!(closed, "a client sending its headers byte by byte still holds its connection");
    assert!(t0.elapsed() < Duration::from_secs(4), "closed after {:?}", t0.elapsed());
    // A client that connects and says nothing is closed too.
    let t0 = Instant::now();
    let stream = TcpStream::connect(&addr).await.unwrap();
    let (closed, _) =
        trickle(stream, b"", Duration::from_millis(100), Duration::from_secs(6)).await;
    assert!(closed && t0.elapsed() < Duration::from_secs(4), "a silent client held on");
    // Clients that send at a normal pace are served as before.
    let r = reqwest::Client::new().get(server.url("/healthz")).send().await.unwrap();
    assert_eq!(r.status(), 200);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_does_not_wait_for_connections_that_send_nothing() {
    // The header read timeout (30 s by default) is far beyond the wait allowed below.
    let mut server = Server::start(&["--shutdown-grace", "60"]);
    let addr = server.http.trim_start_matches("http://").to_string();
    // One connection that has said nothing yet (as an HTTP client's spare one), one idle
    // between requests.
    let _silent = TcpStream::connect(&addr).await.unwrap();
    let mut idle = TcpStream::connect(&addr).await.unwrap();
    idle.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n").await.unwrap();
    let mut buf = [0u8; 1024];
    assert!(idle.read(&mut buf).await.unwrap() > 0);
    let t0 = Instant::now();
    server.terminate();
    assert_eq!(server.wait_exit(Duration::from_secs(20)), Some(0));
    assert!(t0.elapsed() < Duration::from_secs(10), "exited after {:?}", t0.elapsed());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_body_that_trickles_is_cut_off_with_408() {
    let server = Server::start(&["--body-read-timeout", "1"]);
    let addr = server.http.trim_start_matches("http://").to_string();
    let mut stream = TcpStream::connect(&addr).await.unwrap();
    stream
        .write_all(
            b"POST /reconstruct HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n\
              Content-Length: 100000\r\n\r\n",
        )
        .await
        .unwrap();
    let body = vec![b' '; 100];
    let t0 = Instant::now();
    let (closed, answer) =
        trickle(stream, &body, Duration::from_millis(100), Duration::from_secs(6)).await;
    assert!(closed, "the trickling upload is still going: {answer}");
    assert!(t0.elapsed() < Duration::from_secs(4), "cut off after {:?}", t0.elapsed());
    assert!(answer.starts_with("HTTP/1.1 408"), "{answer}");
    assert!(answer.contains("\"body_timeout\""), "{answer}");
}
