//! The container image, the compose stack and the Kubernetes manifests, built and run for real.
//!
//! Needs a Docker daemon (one that answers, or Debian's `dockerd` to start as root), what
//! `scripts/local-base-images.sh` needs where no base image can be pulled (debootstrap), a
//! compose client (`docker compose` or `docker-compose`), and for the validators `hadolint`,
//! `kubectl` (for its kustomize) and `kubernetes-validate` on PATH. Where one is missing a test
//! skips, saying so, unless MESHSTREAM_REQUIRE_CONTAINER=1 (set by .ci/run) makes it a failure.
//! Every container, compose network and daemon a test starts, it removes or stops by id.

mod common;

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use common::{points_json, points_request, shape, stream_through};
use meshstream::engine::Metrics;
use meshstream::mesh::{Format, ReadLimits, read_mesh};
use meshstream::server::proto::mesh_generator_client::MeshGeneratorClient;
use meshstream::server::proto::reconstruct_response;
use serde_json::{Value, json};

const ROOT: &str = env!("CARGO_MANIFEST_DIR");
const IMAGE: &str = "meshstream:container-test";
/// The name scripts/local-base-images.sh gives the Prometheus image it makes or pulls.
const PROMETHEUS_IMAGE: &str = "meshstream-local/prometheus:debian";

/// Skips (returning true) with a message, or fails under MESHSTREAM_REQUIRE_CONTAINER=1.
fn unavailable(what: &str) -> bool {
    if std::env::var("MESHSTREAM_REQUIRE_CONTAINER").is_ok_and(|v| v == "1") {
        panic!("{what} (MESHSTREAM_REQUIRE_CONTAINER=1: required here)");
    }
    eprintln!("skipping: {what}");
    true
}

fn on_path(tool: &str) -> bool {
    std::env::var_os("PATH")
        .is_some_and(|paths| std::env::split_paths(&paths).any(|dir| dir.join(tool).is_file()))
}

/// Runs `command`, panicking with its output unless it succeeds; its stdout.
fn checked(command: &mut Command) -> String {
    let out = command.output().unwrap_or_else(|e| panic!("{command:?}: {e}"));
    assert!(out.status.success(), "{command:?}: {}", report(&out));
    String::from_utf8_lossy(&out.stdout).trim().to_string()
}

fn report(out: &Output) -> String {
    format!(
        "{}\n--- stdout\n{}\n--- stderr\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

fn read(path: &str) -> String {
    std::fs::read_to_string(Path::new(ROOT).join(path)).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// The number after `key` (then `=`, `:` or spaces, and an optional quote) on its first line.
fn number_after(text: &str, key: &str) -> f64 {
    let rest = text.split_once(key).unwrap_or_else(|| panic!("no {key}")).1;
    let digits: String = rest
        .trim_start_matches(|c: char| c == '=' || c == ':' || c == '"' || c.is_whitespace())
        .chars()
        .take_while(|c| c.is_ascii_digit() || *c == '.')
        .collect();
    digits.parse().unwrap_or_else(|_| panic!("no number after {key}"))
}

#[test]
fn shutdown_grace_matches_serve_everywhere() {
    // serve's default, which the image, compose and the ConfigMap keep.
    let help = checked(Command::new(env!("CARGO_BIN_EXE_meshstream")).args(["help", "serve"]));
    let serve_default = number_after(help.split_once("--shutdown-grace").unwrap().1, "default:");
    let dockerfile = read("Dockerfile");
    let image = number_after(&dockerfile, "MESHSTREAM_SHUTDOWN_GRACE=");
    let config =
        number_after(&read("deploy/k8s/base/meshstream.env"), "MESHSTREAM_SHUTDOWN_GRACE=");
    assert_eq!((image, config), (serve_default, serve_default));
    // After the grace, serve takes up to 2 s more to close what is left: SIGKILL must wait.
    let closing = serve_default + 2.0;
    let compose = number_after(&read("deploy/compose.yaml"), "stop_grace_period");
    assert!(compose > closing, "compose stop_grace_period {compose} s <= {closing} s");
    let docker_run = number_after(&dockerfile, "--stop-timeout");
    assert!(docker_run > closing, "the Dockerfile's docker run --stop-timeout {docker_run}");
    let deployment = read("deploy/k8s/base/deployment.yaml");
    let pod = number_after(&deployment, "terminationGracePeriodSeconds");
    let pre_stop = number_after(&deployment, "command: [\"sleep\", ");
    assert!(
        pod > pre_stop + closing,
        "terminationGracePeriodSeconds {pod} <= {pre_stop} + {closing}"
    );
}

#[test]
fn the_dashboard_charts_metrics_the_server_exports() {
    // Families by reason have no lines until they count something.
    let metrics = Metrics::default();
    metrics.reject("queue_full");
    metrics.fail("deadline");
    metrics.finish("end_of_mesh");
    let exported: Vec<String> = metrics
        .render()
        .lines()
        .filter_map(|l| l.strip_prefix("# TYPE ")?.split_whitespace().next().map(str::to_string))
        .collect();
    let dashboard: Value = serde_json::from_str(&read("deploy/grafana/dashboards/meshstream.json"))
        .expect("the dashboard is JSON");
    let panels = dashboard["panels"].as_array().expect("panels");
    let titles: Vec<&str> = panels.iter().filter_map(|p| p["title"].as_str()).collect();
    for wanted in ["Queue depth", "Running sequences", "Faces per second", "Time to first face"] {
        assert!(titles.contains(&wanted), "no {wanted} panel in {titles:?}");
    }
    assert!(titles.iter().any(|t| t.starts_with("Rejections by reason")));
    for panel in panels {
        let targets = panel["targets"].as_array().expect("targets");
        assert!(!targets.is_empty(), "{} has no query", panel["title"]);
        for expr in targets.iter().map(|t| t["expr"].as_str().expect("expr")) {
            for name in metric_names(expr) {
                let base = ["_bucket", "_total", "_count", "_sum"]
                    .iter()
                    .find_map(|s| name.strip_suffix(s))
                    .unwrap_or(&name);
                assert!(exported.iter().any(|e| e == base), "{expr}: {name} is not exported");
            }
        }
    }
}

fn metric_names(expr: &str) -> Vec<String> {
    let mut names = Vec::new();
    let mut rest = expr;
    while let Some(i) = rest.find("meshstream_") {
        let name: String =
            rest[i..].chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '_').collect();
        rest = &rest[i + name.len()..];
        names.push(name);
    }
    assert!(!names.is_empty(), "{expr} charts no meshstream metric");
    names
}

/// The image builds from a context `.dockerignore` cuts down to a list; a file the binary
/// embeds and the list leaves out breaks only `docker build`, which needs Docker. Checked here
/// without it: every `include_bytes!` of the viewer is named (or its folder is).
#[test]
fn the_build_context_holds_every_file_the_binary_embeds() {
    let kept: Vec<String> = read(".dockerignore")
        .lines()
        .filter_map(|l| l.strip_prefix('!'))
        .map(|l| l.trim().to_string())
        .collect();
    let ui = read("src/server/ui.rs");
    let embedded: Vec<&str> = ui
        .split("include_bytes!(\"../../")
        .skip(1)
        .filter_map(|rest| rest.split('"').next())
        .collect();
    assert!(embedded.len() >= 5, "{embedded:?}");
    for path in embedded {
        assert!(Path::new(ROOT).join(path).is_file(), "{path} is embedded but missing");
        let named = kept.iter().any(|k| k == path || (k.ends_with('/') && path.starts_with(k)));
        assert!(named, "{path} is embedded but .dockerignore leaves it out of the image's build");
    }
}

#[test]
fn dockerfiles_and_manifests_pass_their_validators() {
    for tool in ["hadolint", "kubectl", "kubernetes-validate"] {
        if !on_path(tool) && unavailable(&format!("{tool} is not on PATH")) {
            return;
        }
    }
    // .hadolint.yaml in the root holds the rules it ignores, with why.
    checked(Command::new("hadolint").current_dir(ROOT).args(["Dockerfile", "Dockerfile.cuda"]));
    let scratch = tempfile::tempdir().unwrap();
    for dir in ["base", "overlays/cpu", "overlays/gpu", "overlays/cpu-ingress"] {
        let rendered = checked(
            Command::new("kubectl")
                .current_dir(ROOT)
                .args(["kustomize", &format!("deploy/k8s/{dir}")]),
        );
        let file = scratch.path().join(format!("{}.yaml", dir.replace('/', "-")));
        std::fs::write(&file, &rendered).unwrap();
        checked(Command::new("kubernetes-validate").args(["--strict", "--quiet"]).arg(&file));
        for kind in [
            "Deployment",
            "Service",
            "HorizontalPodAutoscaler",
            "PodDisruptionBudget",
            "ConfigMap",
            "NetworkPolicy",
        ] {
            assert!(rendered.contains(&format!("kind: {kind}\n")), "{dir}: no {kind}");
        }
        assert!(rendered.contains("clusterIP: None"), "{dir}: no headless gRPC Service");
        assert!(rendered.contains("path: /readyz") && rendered.contains("path: /healthz"));
        // API keys from an optional Secret.
        assert!(
            rendered.contains("name: meshstream-api-keys") && rendered.contains("optional: true")
        );
        if dir == "overlays/cpu-ingress" {
            assert_eq!(rendered.matches("kind: Ingress\n").count(), 2, "{dir}: HTTP and gRPC");
            assert!(rendered.contains("nginx.ingress.kubernetes.io/backend-protocol: GRPC"));
            assert!(rendered.contains("secretName: meshstream-tls"));
        }
        if dir == "overlays/gpu" {
            assert!(rendered.contains("nvidia.com/gpu: \"1\""));
            assert!(rendered.contains("MESHSTREAM_DEVICE: cuda:0"));
            assert!(rendered.contains("name: meshstream_queue_depth"));
        }
    }
}

/// A Docker client and daemon: the one that answers, or a `dockerd` this test started (and
/// stops when dropped).
struct Docker {
    client: String,
    host: Option<String>,
    daemon: Option<Daemon>,
}

/// A `dockerd` this test started: the process, its scratch folder, and whether the default
/// bridge (docker0), which dockerd makes and leaves, was there before it.
struct Daemon {
    process: Child,
    _run: tempfile::TempDir,
    bridge_existed: bool,
}

impl Docker {
    fn connect() -> Option<Docker> {
        // Docker's own client builds with BuildKit through its buildx plug-in; Debian's docker.io
        // client has BuildKit built in.
        let client = std::env::var("DOCKER").ok().unwrap_or_else(|| {
            let buildx = Command::new("docker").args(["buildx", "version"]).output();
            if buildx.is_ok_and(|o| o.status.success()) || !Path::new("/usr/bin/docker").exists() {
                "docker".into()
            } else {
                "/usr/bin/docker".into()
            }
        });
        let docker = Docker { client, host: None, daemon: None };
        if docker.command().arg("info").output().is_ok_and(|o| o.status.success()) {
            return Some(docker);
        }
        let root = checked(Command::new("id").arg("-u")) == "0";
        if !root || !on_path("dockerd") {
            return None;
        }
        docker.start_daemon()
    }

    /// A daemon of our own: its socket and run state in a scratch folder, its images in the
    /// target folder (kept between runs, as a build cache; see `prune`).
    fn start_daemon(mut self) -> Option<Docker> {
        let run = tempfile::Builder::new().prefix("meshstream-docker").tempdir_in("/tmp").unwrap();
        let data = Path::new(env!("CARGO_TARGET_TMPDIR")).join("docker");
        let socket = format!("unix://{}", run.path().join("docker.sock").display());
        let log = std::fs::File::create(run.path().join("dockerd.log")).unwrap();
        let bridge_existed = Path::new("/sys/class/net/docker0").exists();
        let process = Command::new("dockerd")
            .arg("--host")
            .arg(&socket)
            .arg("--data-root")
            .arg(&data)
            .arg("--exec-root")
            .arg(run.path().join("exec"))
            .arg("--pidfile")
            .arg(run.path().join("dockerd.pid"))
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .ok()?;
        eprintln!("started dockerd (pid {}) on {socket}", process.id());
        let log = run.path().join("dockerd.log");
        self.host = Some(socket);
        self.daemon = Some(Daemon { process, _run: run, bridge_existed });
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(30) {
            if self.command().arg("info").output().is_ok_and(|o| o.status.success()) {
                return Some(self);
            }
            std::thread::sleep(Duration::from_millis(200));
        }
        let log = std::fs::read_to_string(log).unwrap_or_default();
        panic!("dockerd did not answer within 30 s:\n{log}");
    }

    fn command(&self) -> Command {
        let mut command = Command::new(&self.client);
        self.environment(&mut command);
        command
    }

    /// What this daemon's clients (docker, compose, the base-image script) need to reach it.
    fn environment(&self, command: &mut Command) {
        command.env("DOCKER", &self.client).env("DOCKER_BUILDKIT", "1");
        if let Some(host) = &self.host {
            command.env("DOCKER_HOST", host);
        }
    }

    fn run(&self, args: &[&str]) -> String {
        checked(self.command().args(args))
    }

    /// Bounds what a daemon this test started keeps between runs: every source change adds a
    /// builder layer holding a release target folder, and unpruned its data root had grown to
    /// 7.8 GB on a developer's machine. The images a rebuild left untagged go, and the build
    /// cache beyond the 4 GB used last (the latest build's layers). A user's own daemon is
    /// left alone: its images and cache are not ours to delete. Housekeeping after the checks,
    /// so a failure is reported, not failed on: a daemon killed mid-build leaves its build
    /// cache naming snapshots it no longer has ("failed to get usage ... not found"), and the
    /// image itself built and served.
    fn prune(&self) {
        if self.daemon.is_some() {
            for args in [
                &["image", "prune", "--force"][..],
                &["builder", "prune", "--force", "--keep-storage", "4GB"],
            ] {
                let out = self.command().args(args).output();
                match out {
                    Ok(out) if out.status.success() => {}
                    Ok(out) => eprintln!("docker {args:?} did not prune: {}", report(&out)),
                    Err(e) => eprintln!("docker {args:?} did not run: {e}"),
                }
            }
        }
    }

    /// `docker compose`, or the standalone docker-compose.
    fn compose(&self) -> Option<Command> {
        let plugin = self.command().args(["compose", "version"]).output();
        if plugin.is_ok_and(|o| o.status.success()) {
            let mut command = self.command();
            command.arg("compose");
            return Some(command);
        }
        on_path("docker-compose").then(|| {
            let mut command = Command::new("docker-compose");
            self.environment(&mut command);
            command
        })
    }
}

impl Drop for Docker {
    fn drop(&mut self) {
        let Some(mut daemon) = self.daemon.take() else {
            return;
        };
        let pid = daemon.process.id().to_string();
        let _ = Command::new("kill").args(["-TERM", &pid]).status();
        let t0 = Instant::now();
        while !matches!(daemon.process.try_wait(), Ok(Some(_))) {
            if t0.elapsed() > Duration::from_secs(20) {
                let _ = daemon.process.kill();
                let _ = daemon.process.wait();
                break;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        eprintln!("stopped dockerd (pid {pid})");
        if !daemon.bridge_existed {
            let _ = Command::new("ip").args(["link", "delete", "docker0"]).status();
        }
    }
}

/// A container, removed by id when dropped.
struct Container<'a> {
    docker: &'a Docker,
    id: String,
}

impl Drop for Container<'_> {
    fn drop(&mut self) {
        let _ = self.docker.command().args(["rm", "--force", "--volumes", &self.id]).output();
    }
}

impl Container<'_> {
    /// `http://127.0.0.1:PORT` for a published container port.
    fn published(&self, port: &str) -> String {
        let mapping = self.docker.run(&["port", &self.id, port]);
        let addr = mapping.lines().find(|l| l.starts_with("127.0.0.1:")).expect("a loopback port");
        format!("http://{addr}")
    }

    fn inspect(&self, format: &str) -> String {
        self.docker.run(&["inspect", "--format", format, &self.id])
    }
}

/// A compose project, taken down (containers, network) when dropped.
struct ComposeStack<'a> {
    docker: &'a Docker,
    project: String,
    env: Vec<(&'static str, String)>,
}

impl ComposeStack<'_> {
    fn command(&self) -> Command {
        let mut command = self.docker.compose().expect("a compose client");
        command.current_dir(ROOT).args(["-p", &self.project, "-f", "deploy/compose.yaml"]);
        command.envs(self.env.iter().map(|(k, v)| (k, v)));
        command
    }
}

impl Drop for ComposeStack<'_> {
    fn drop(&mut self) {
        let down =
            self.command().args(["down", "--volumes", "--remove-orphans", "-t", "5"]).output();
        match down {
            Ok(out) if !out.status.success() => eprintln!("compose down failed: {}", report(&out)),
            Err(e) => eprintln!("compose down: {e}"),
            Ok(_) => {}
        }
        // Whatever down left, by id.
        let label = format!("label=com.docker.compose.project={}", self.project);
        let ids = |args: &[&str]| -> Vec<String> {
            let out = self.docker.command().args(args).args(["--filter", &label]).output();
            out.map(|o| {
                String::from_utf8_lossy(&o.stdout).split_whitespace().map(String::from).collect()
            })
            .unwrap_or_default()
        };
        for id in ids(&["container", "ls", "-aq"]) {
            let _ = self.docker.command().args(["container", "rm", "--force", &id]).output();
        }
        for id in ids(&["network", "ls", "-q"]) {
            let _ = self.docker.command().args(["network", "rm", &id]).output();
        }
    }
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// Polls `probe` every 100 ms until it gives a value, failing after `limit`.
async fn poll<T, F, Fut>(limit: Duration, what: &str, mut probe: F) -> T
where
    F: FnMut() -> Fut,
    Fut: Future<Output = Option<T>>,
{
    let t0 = Instant::now();
    loop {
        if let Some(value) = probe().await {
            return value;
        }
        assert!(t0.elapsed() < limit, "{what}: not within {limit:?}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

async fn status_of(http: &reqwest::Client, url: &str) -> Option<u16> {
    Some(http.get(url).send().await.ok()?.status().as_u16())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_image_serves_drains_on_sigterm_and_compose_scrapes_it() {
    let Some(docker) = Docker::connect() else {
        unavailable("no Docker daemon answers and none can be started (dockerd as root)");
        return;
    };
    if docker.compose().is_none()
        && unavailable("no compose client (docker compose, docker-compose)")
    {
        return;
    }
    let mut base = Command::new(Path::new(ROOT).join("scripts/local-base-images.sh"));
    docker.environment(&mut base);
    checked(base.env("PROMETHEUS_IMAGE", PROMETHEUS_IMAGE).current_dir(ROOT));

    let t0 = Instant::now();
    let build_log = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("container-build.log");
    let build = docker
        .command()
        .current_dir(ROOT)
        .args(["build", "--progress=plain", "--network", "host", "-t", IMAGE, "."])
        .output()
        .unwrap();
    std::fs::write(&build_log, [&build.stdout[..], &build.stderr[..]].concat()).unwrap();
    assert!(build.status.success(), "docker build: {}", report(&build));
    docker.prune();
    let size: f64 =
        docker.run(&["image", "inspect", "--format", "{{.Size}}", IMAGE]).parse().unwrap();
    eprintln!(
        "built {IMAGE} in {:.1} s ({}), {:.1} MB",
        t0.elapsed().as_secs_f64(),
        build_log.display(),
        size / 1e6
    );
    assert_eq!(
        docker.run(&["image", "inspect", "--format", "{{.Config.User}}", IMAGE]),
        "10001:10001"
    );

    let http = reqwest::Client::new();
    let started = Instant::now();
    // Read-only, as the Kubernetes manifests run it; published on loopback, ephemeral ports.
    let id = docker.run(&[
        "run",
        "--detach",
        "--read-only",
        "--stop-timeout",
        "40",
        "--publish",
        "127.0.0.1::8080",
        "--publish",
        "127.0.0.1::50051",
        IMAGE,
    ]);
    let container = Container { docker: &docker, id };
    let base_url = container.published("8080/tcp");
    let grpc_url = container.published("50051/tcp");
    let readyz = format!("{base_url}/readyz");
    poll(Duration::from_secs(120), "/readyz", || async {
        (status_of(&http, &readyz).await == Some(200)).then_some(())
    })
    .await;
    eprintln!("container start to ready (/readyz 200): {:.2} s", started.elapsed().as_secs_f64());
    // The image's HEALTHCHECK: `meshstream healthcheck` inside the container.
    poll(Duration::from_secs(90), "health turning healthy", || async {
        let health = container.inspect("{{.State.Health.Status}}");
        assert_ne!(health, "unhealthy", "{}", container.inspect("{{json .State.Health}}"));
        (health == "healthy").then_some(())
    })
    .await;
    eprintln!("container start to healthy: {:.2} s", started.elapsed().as_secs_f64());
    // PID 1 is meshstream, not a shell, and it runs as the image's user.
    let status = docker.run(&["exec", &container.id, "cat", "/proc/1/status"]);
    let uid = status.lines().find(|l| l.starts_with("Uid:")).unwrap();
    assert_eq!(uid.split_whitespace().nth(1), Some("10001"), "{uid}");
    assert!(status.starts_with("Name:\tmeshstream"), "{status}");

    // A real reconstruction over HTTP, and one over gRPC.
    let body = points_json(&shape(), json!({"max_faces": 200, "candidates": 1, "fit_rounds": 0}));
    let r = http.post(format!("{base_url}/reconstruct")).json(&body).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let mesh = read_mesh(&r.bytes().await.unwrap(), Format::Gltf, &ReadLimits::default()).unwrap();
    assert!(!mesh.faces.is_empty());
    let mut grpc = MeshGeneratorClient::connect(grpc_url).await.unwrap();
    let mut stream = grpc.reconstruct(points_request(100)).await.unwrap().into_inner();
    let (mut faces, mut done) = (0, None);
    while let Some(message) = stream.message().await.unwrap() {
        match message.event.unwrap() {
            reconstruct_response::Event::Faces(chunk) => faces += chunk.faces.len(),
            reconstruct_response::Event::Done(stats) => done = Some(stats),
            reconstruct_response::Event::Progress(p) => panic!("progress {p:?} for points"),
            reconstruct_response::Event::Drafts(d) => panic!("drafts {d:?} not asked for"),
        }
    }
    assert!(faces > 0 && done.expect("a final stats message").faces as usize == faces);

    // SIGTERM, as `docker stop` and Kubernetes send it, during a stream: the stream finishes,
    // the container exits 0.
    let last = stream_through(&base_url, || {
        docker.run(&["kill", "--signal", "TERM", &container.id]);
    })
    .await;
    assert_eq!(last["type"], "done", "{last}");
    assert_eq!(docker.run(&["wait", &container.id]), "0");
    drop(container);

    compose_scrapes_the_service(&docker, &http).await;
}

/// `compose up` of meshstream and Prometheus; Prometheus's own API says it scrapes meshstream,
/// and every dashboard query runs on it.
async fn compose_scrapes_the_service(docker: &Docker, http: &reqwest::Client) {
    let (service_port, prometheus_port) = (free_port(), free_port());
    let stack = ComposeStack {
        docker,
        project: format!("meshstream-test-{}", std::process::id()),
        env: vec![
            ("MESHSTREAM_IMAGE", IMAGE.into()),
            ("PROMETHEUS_IMAGE", PROMETHEUS_IMAGE.into()),
            ("MESHSTREAM_HTTP_PORT", service_port.to_string()),
            ("MESHSTREAM_GRPC_PORT", free_port().to_string()),
            ("PROMETHEUS_PORT", prometheus_port.to_string()),
        ],
    };
    // Grafana has no image here: its dashboard is checked against Prometheus below.
    checked(stack.command().args(["up", "--detach", "--no-build", "meshstream", "prometheus"]));

    let body = points_json(&shape(), json!({"max_faces": 100, "candidates": 1, "fit_rounds": 0}));
    let service = format!("http://127.0.0.1:{service_port}");
    let r = http.post(format!("{service}/reconstruct")).json(&body).send().await.unwrap();
    assert_eq!(r.status(), 200);

    let prometheus = format!("http://127.0.0.1:{prometheus_port}");
    let query = |expr: String| {
        let url = format!("{prometheus}/api/v1/query?query={}", urlencoding::encode(&expr));
        async move {
            let answer: Value = http.get(url).send().await.ok()?.json().await.ok()?;
            Some(answer)
        }
    };
    poll(Duration::from_secs(90), "Prometheus: up{job=\"meshstream\"} == 1", || async {
        let answer = query("up{job=\"meshstream\"}".into()).await?;
        (answer["data"]["result"][0]["value"][1] == "1").then_some(())
    })
    .await;
    poll(Duration::from_secs(30), "Prometheus: faces counted", || async {
        let answer = query("meshstream_faces_generated_total".into()).await?;
        let faces: f64 = answer["data"]["result"][0]["value"][1].as_str()?.parse().ok()?;
        (faces > 0.0).then_some(())
    })
    .await;
    let dashboard: Value =
        serde_json::from_str(&read("deploy/grafana/dashboards/meshstream.json")).unwrap();
    for target in dashboard["panels"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|p| p["targets"].as_array().unwrap())
    {
        let expr = target["expr"].as_str().unwrap().replace("$__rate_interval", "1m");
        let answer = query(expr.clone()).await.expect("an answer");
        assert_eq!(answer["status"], "success", "{expr}: {answer}");
    }

    let label = format!("label=com.docker.compose.project={}", stack.project);
    checked(stack.command().args(["down", "--volumes", "--remove-orphans", "-t", "5"]));
    assert_eq!(docker.run(&["container", "ls", "-aq", "--filter", &label]), "", "containers left");
    assert_eq!(docker.run(&["network", "ls", "-q", "--filter", &label]), "", "networks left");
}
