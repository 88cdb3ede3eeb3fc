//! `meshstream serve` with API keys: the real binary over HTTP and gRPC, keys from the
//! environment (several, comma-separated) and from a file; open paths; the refusals alike
//! whatever was wrong; counted in the metrics; and no key in the server's log.

mod common;

use std::process::{Command, Stdio};

use common::{Server, points_json, points_request, shape};
use meshstream::server::proto::mesh_generator_client::MeshGeneratorClient;
use serde_json::json;
use tonic::Code;
use tonic::metadata::MetadataValue;

const ENV_KEYS: [&str; 2] = ["env-key-Alpha.0123456789", "env-key-Beta~abcdefghij"];
const FILE_KEY: &str = "file-key-Gamma_9876543210";

/// A server with the two environment keys and the file key, logging everything (trace) to
/// `log`.
fn keyed_server(dir: &tempfile::TempDir, extra: &[&str]) -> (Server, std::path::PathBuf) {
    let key_file = dir.path().join("keys");
    std::fs::write(&key_file, format!("# the file's key\n\n{FILE_KEY}\n# retired-key\n")).unwrap();
    let log = dir.path().join("server.log");
    let mut args = vec!["--api-key-file", key_file.to_str().unwrap(), "--max-faces", "16"];
    args.extend(extra);
    let mut command = Server::command(Server::MODEL, &args);
    command
        .env("MESHSTREAM_API_KEY", ENV_KEYS.join(","))
        .env("MESHSTREAM_LOG", "trace")
        .stderr(std::fs::File::create(&log).unwrap());
    (Server::spawn(command), log)
}

/// A status and body of a response, with its `WWW-Authenticate`.
async fn answer(response: reqwest::Response) -> (u16, Option<String>, String) {
    let status = response.status().as_u16();
    let challenge =
        response.headers().get("www-authenticate").map(|v| v.to_str().unwrap().to_string());
    (status, challenge, response.text().await.unwrap())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn keys_guard_http_and_grpc_alike_and_never_reach_the_log() {
    let dir = tempfile::tempdir().unwrap();
    let (mut server, log) = keyed_server(&dir, &[]);
    let http = reqwest::Client::new();
    let get = |path: &str, authorization: Option<String>| {
        let mut request = http.get(server.url(path));
        if let Some(value) = authorization {
            request = request.header("authorization", value);
        }
        request.send()
    };

    // Refused alike: no header, other schemes, no space, the key alone, a wrong key, a
    // prefix of a right one, a right one with more after it.
    let refusals = [
        None,
        Some(format!("Basic {}", ENV_KEYS[0])),
        Some(format!("Bearer{}", ENV_KEYS[0])),
        Some(ENV_KEYS[0].to_string()),
        Some("Bearer wrong-key".to_string()),
        Some(format!("Bearer {}", &ENV_KEYS[0][..10])),
        Some(format!("Bearer {}x", ENV_KEYS[0])),
        Some("Bearer retired-key".to_string()),
    ];
    let mut answers = Vec::new();
    for authorization in &refusals {
        answers.push(answer(get("/v1/info", authorization.clone()).await.unwrap()).await);
    }
    let first = &answers[0];
    assert_eq!(first.0, 401);
    assert_eq!(first.1.as_deref(), Some("Bearer"));
    let body: serde_json::Value = serde_json::from_str(&first.2).unwrap();
    assert_eq!(body["error"]["code"], "unauthenticated", "{body}");
    for (a, authorization) in answers.iter().zip(&refusals) {
        assert_eq!(a, first, "{authorization:?} was answered differently");
    }

    // Every key works, in the scheme's any case; /v1/info shows none of them.
    for key in [ENV_KEYS[0], ENV_KEYS[1], FILE_KEY] {
        let r = get("/v1/info", Some(format!("Bearer {key}"))).await.unwrap();
        assert_eq!(r.status(), 200, "{key}");
        let info = r.text().await.unwrap();
        assert!(!info.contains(key), "/v1/info shows a key");
    }
    let r = get("/v1/info", Some(format!("bearer {FILE_KEY}"))).await.unwrap();
    assert_eq!(r.status(), 200);

    // Open by default: probes, metrics, the viewer page and its files, the contract.
    for path in ["/healthz", "/readyz", "/metrics", "/", "/ui/app.js", "/openapi.json"] {
        assert_eq!(get(path, None).await.unwrap().status(), 200, "{path}");
    }
    // Closed: the API, and paths that match nothing (no route list for the curious).
    for path in ["/nowhere", "/ui"] {
        assert_eq!(get(path, None).await.unwrap().status(), 401, "{path}");
    }

    // A request with a body: refused before it is read, and the connection closed (saying
    // so, so that the client does not send its next request into it); served with a key.
    let body = points_json(&shape(), json!({"max_faces": 8, "candidates": 1, "fit_rounds": 0}));
    let r = http.post(server.url("/reconstruct")).json(&body).send().await.unwrap();
    assert_eq!(r.headers().get("connection").map(|v| v.to_str().unwrap()), Some("close"));
    assert_eq!(answer(r).await, *first);
    let r = http
        .post(server.url("/reconstruct"))
        .bearer_auth(ENV_KEYS[1])
        .json(&body)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert!(!r.bytes().await.unwrap().is_empty());

    // gRPC: the same keys in the `authorization` metadata; health stays open.
    let channel = tonic::transport::Endpoint::from_shared(server.grpc.clone())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut grpc = MeshGeneratorClient::new(channel.clone());
    let mut grpc_messages = Vec::new();
    for authorization in &refusals {
        let mut request = tonic::Request::new(points_request(8));
        if let Some(value) = authorization {
            let value: MetadataValue<_> = value.parse().unwrap();
            request.metadata_mut().insert("authorization", value);
        }
        let status = grpc.reconstruct(request).await.expect_err("refused");
        assert_eq!(status.code(), Code::Unauthenticated, "{authorization:?}: {status:?}");
        grpc_messages.push(status.message().to_string());
    }
    assert!(grpc_messages.iter().all(|m| *m == grpc_messages[0]), "{grpc_messages:?}");
    for key in [ENV_KEYS[0], FILE_KEY] {
        let mut request = tonic::Request::new(points_request(8));
        let value: MetadataValue<_> = format!("Bearer {key}").parse().unwrap();
        request.metadata_mut().insert("authorization", value);
        let mut stream = grpc.reconstruct(request).await.unwrap().into_inner();
        let mut messages = 0;
        while stream.message().await.unwrap().is_some() {
            messages += 1;
        }
        assert!(messages > 0);
    }
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
    let check = tonic_health::pb::HealthCheckRequest { service: String::new() };
    assert!(health.check(check).await.is_ok());

    // Each refusal counted once: 8 + 2 HTTP GETs, one POST, 8 gRPC calls.
    let refused =
        server.metric(&http, "meshstream_requests_rejected_total{reason=\"unauthenticated\"}");
    assert_eq!(refused.await, 19.0);

    server.terminate();
    assert_eq!(server.wait_exit(std::time::Duration::from_secs(30)), Some(0));
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(text.contains("refused: no valid API key"), "the log is not the server's:\n{text}");
    for key in ENV_KEYS.iter().chain([&FILE_KEY]) {
        assert!(!text.contains(key), "the log shows a key");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_open_paths_are_configurable() {
    let dir = tempfile::tempdir().unwrap();
    let (server, _log) = keyed_server(&dir, &["--auth-open-paths", "/healthz,/ui/*"]);
    let http = reqwest::Client::new();
    for (path, status) in [("/healthz", 200), ("/ui/app.js", 200), ("/readyz", 401), ("/", 401)] {
        let r = http.get(server.url(path)).send().await.unwrap();
        assert_eq!(r.status(), status, "{path}");
    }
    let mut health = tonic_health::pb::health_client::HealthClient::new(
        tonic::transport::Channel::from_shared(server.grpc.clone()).unwrap().connect_lazy(),
    );
    let check = tonic_health::pb::HealthCheckRequest { service: String::new() };
    assert_eq!(health.check(check).await.unwrap_err().code(), Code::Unauthenticated);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_a_key_nothing_is_guarded() {
    let server = Server::start(&["--max-faces", "8"]);
    let r = reqwest::Client::new().get(server.url("/v1/info")).send().await.unwrap();
    assert_eq!(r.status(), 200);
}

/// The server's exit status and error output when started with `args` (and no model load
/// needed: keys are read first).
fn refused_start(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_meshstream"))
        .args(["serve", "--http-addr", "127.0.0.1:0", "--grpc-addr", "127.0.0.1:0"])
        .args(args)
        .env_remove("MESHSTREAM_API_KEY")
        .stdout(Stdio::null())
        .output()
        .unwrap();
    (out.status.success(), String::from_utf8_lossy(&out.stderr).into_owned())
}

#[test]
fn bad_keys_and_key_files_stop_the_start_with_an_error_that_shows_no_key() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("no-such-file");
    let (ok, err) = refused_start(&["--api-key-file", missing.to_str().unwrap()]);
    assert!(!ok && err.contains(missing.to_str().unwrap()), "{err}");

    let empty = dir.path().join("empty");
    std::fs::write(&empty, "# only a comment\n\n").unwrap();
    let (ok, err) = refused_start(&["--api-key-file", empty.to_str().unwrap()]);
    assert!(!ok && err.contains(empty.to_str().unwrap()) && err.contains("no key"), "{err}");

    let (ok, err) = refused_start(&["--api-key", "good-key", "--api-key", "secret with space"]);
    assert!(!ok && err.contains("API key 2"), "{err}");
    assert!(!err.contains("secret with space"), "{err}");
}
