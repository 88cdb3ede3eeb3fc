//! `meshstream bench soak`: sustained mixed traffic against a `meshstream serve` process,
//! started here as a child (its memory is read from /proc, a crash is seen) or given by
//! `--url`. Reports what completed, what was refused and why, and what was lost (no complete
//! answer and no error): a run that lost any request fails.

mod server;
mod traffic;

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::Args;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde_json::json;

use super::bench_requests::{percentile, percentile_ms, point_cloud, test_cloud};
use super::out;
use server::{PeakRss, Target};
use traffic::{Client, Mix, Outcome, Record, Traffic};

/// The body limit of a server started here: the oversized garbage is one byte over it, so a
/// small limit keeps those requests cheap (a request's points are a few tens of KB).
const CHILD_MAX_BODY_BYTES: &str = "1048576";

/// How long the server is left idle before its memory is read: past its idle trim (one second)
/// and the last connections' closing.
const SETTLE: Duration = Duration::from_secs(2);

#[derive(Args)]
pub struct SoakArgs {
    /// Requests in all (a request refused with 429 and sent again counts once).
    #[arg(long, default_value_t = 10_000)]
    requests: usize,
    /// Clients sending at once, each one request after another.
    #[arg(long, default_value_t = 16)]
    concurrency: usize,
    /// Load this server (http://HOST:PORT) instead of starting one; its memory is not reported.
    #[arg(long)]
    url: Option<String>,
    /// The gRPC endpoint of the `--url` server (http://HOST:PORT); without it, no gRPC requests.
    #[arg(long, requires = "url")]
    grpc_url: Option<String>,
    /// Model folder of the server started here.
    #[arg(long, default_value = "models/default")]
    model: PathBuf,
    /// A flag for the server started here, as `--serve-arg=--max-queue=16` (repeatable; it
    /// overrides this command's own choices, such as a 1 MiB body limit).
    #[arg(long = "serve-arg", allow_hyphen_values = true)]
    serve_args: Vec<String>,
    /// Face budget of each request.
    #[arg(long, default_value_t = 16)]
    max_faces: u32,
    /// Points in each request.
    #[arg(long, default_value_t = 512)]
    points: usize,
    /// Candidates of each whole-mesh request.
    #[arg(long, default_value_t = 1)]
    candidates: u32,
    /// Fitting rounds of each whole-mesh request (0: as decoded; `bench mesh` measures what
    /// fitting costs).
    #[arg(long, default_value_t = 0)]
    fit_rounds: u32,
    /// Share of the requests that are garbage (bad JSON, wrong content type, truncated,
    /// oversized, no points over gRPC).
    #[arg(long, default_value_t = 0.05)]
    garbage_share: f64,
    /// Share of the other requests sent over gRPC (streams).
    #[arg(long, default_value_t = 0.35)]
    grpc_share: f64,
    /// Share of the other HTTP requests answered as a stream (NDJSON) rather than a mesh.
    #[arg(long, default_value_t = 0.5)]
    stream_share: f64,
    /// Share of the streams whose client goes away after the first face.
    #[arg(long, default_value_t = 0.05)]
    leave_share: f64,
    /// Times a request refused with 429 is sent again (after Retry-After) before it counts as
    /// refused.
    #[arg(long, default_value_t = 30)]
    max_retries: u32,
    /// Seconds after which a request without a complete answer counts as lost.
    #[arg(long, default_value_t = 120.0)]
    client_timeout: f64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// The report as JSON instead of a table.
    #[arg(long)]
    json: bool,
}

fn share(name: &str, value: f64) -> anyhow::Result<f64> {
    if (0.0..=1.0).contains(&value) { Ok(value) } else { bail!("--{name} {value}: give 0 to 1") }
}

pub fn run(args: &SoakArgs) -> anyhow::Result<()> {
    if args.requests == 0 || args.concurrency == 0 {
        bail!("--requests and --concurrency must be at least 1");
    }
    let mix = Mix {
        garbage: share("garbage-share", args.garbage_share)?,
        grpc: share("grpc-share", args.grpc_share)?,
        http_stream: share("stream-share", args.stream_share)?,
        leave: share("leave-share", args.leave_share)?,
    };
    let timeout = Duration::try_from_secs_f64(args.client_timeout)
        .with_context(|| format!("--client-timeout {}", args.client_timeout))?;
    let mut target = match &args.url {
        Some(url) => Target {
            http: url.trim_end_matches('/').into(),
            grpc: args.grpc_url.clone(),
            child: None,
        },
        None => Target::start(
            &args.model,
            &["--max-body-bytes", CHILD_MAX_BODY_BYTES],
            &args.serve_args,
        )?,
    };
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    let report = runtime.block_on(soak(args, mix, timeout, &mut target))?;
    let server_exit = target.stop(Duration::from_secs(60))?;
    let lost = report.lost();
    if args.json {
        let mut value = report.json();
        value["server_exit"] = json!(server_exit);
        out(value)?;
    } else {
        out(report.table(server_exit.as_deref()))?;
    }
    if lost > 0 {
        bail!("{lost} requests were lost (no complete answer and no error)");
    }
    if report.accepted_garbage() > 0 {
        bail!("{} garbage requests were answered as valid", report.accepted_garbage());
    }
    Ok(())
}

async fn soak(
    args: &SoakArgs,
    mix: Mix,
    timeout: Duration,
    target: &mut Target,
) -> anyhow::Result<Report> {
    let http = reqwest::Client::new();
    let info: serde_json::Value = http
        .get(format!("{}/v1/info", target.http))
        .send()
        .await
        .and_then(reqwest::Response::error_for_status)
        .context("asking the server for /v1/info")?
        .json()
        .await
        .context("reading /v1/info")?;
    let max_body_bytes = info["limits"]["max_body_bytes"].as_u64().context("no body limit")?;
    let cloud = test_cloud(args.points);
    let traffic = Arc::new(Traffic {
        http,
        base_url: target.http.clone(),
        grpc_url: target.grpc.clone(),
        points: json!({"points": cloud.vertices, "normals": cloud.normals}),
        grpc_points: point_cloud(&cloud),
        max_faces: args.max_faces,
        candidates: args.candidates,
        fit_rounds: args.fit_rounds,
        max_body_bytes: usize::try_from(max_body_bytes)?,
        max_retries: args.max_retries,
        timeout,
    });
    // Warm up: a round of valid requests per client, so that the memory at the start is the
    // server's working level, not its idle one.
    let warm_mix = Mix { garbage: 0.0, leave: 0.0, ..mix };
    run_clients(&traffic, warm_mix, args.concurrency * 2, args.concurrency, args.seed ^ 0xdead)
        .await;
    // Both memory figures are read once the server has been idle long enough to hand freed
    // memory back (`serve` does after a second), so that they compare like with like.
    tokio::time::sleep(SETTLE).await;
    let rss_start = target.rss();
    let peak = PeakRss::watch(target.child.as_ref().map(std::process::Child::id));
    let t0 = Instant::now();
    let records = run_clients(&traffic, mix, args.requests, args.concurrency, args.seed).await;
    let duration = t0.elapsed();
    let rss_peak = peak.stop();
    target.check_alive()?;
    tokio::time::sleep(SETTLE).await;
    let rss_end = target.rss();
    Ok(Report {
        requests: args.requests,
        concurrency: args.concurrency,
        duration,
        records,
        rss: [rss_start, rss_peak, rss_end],
    })
}

/// `n` requests from `clients` clients at once, each taking the next request when it is done.
async fn run_clients(
    traffic: &Arc<Traffic>,
    mix: Mix,
    n: usize,
    clients: usize,
    seed: u64,
) -> Vec<Record> {
    let next = Arc::new(AtomicUsize::new(0));
    let progress = indicatif::ProgressBar::new(n as u64);
    let tasks: Vec<_> = (0..clients)
        .map(|_| {
            let (traffic, next, progress) =
                (Arc::clone(traffic), Arc::clone(&next), progress.clone());
            tokio::spawn(async move {
                let mut client = Client::new(&traffic);
                let mut records = Vec::new();
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    if i >= n {
                        return records;
                    }
                    let request_seed = seed.wrapping_add(i as u64);
                    let mut rng = ChaCha8Rng::seed_from_u64(request_seed);
                    let kind = mix.pick(&mut rng, traffic.grpc_url.is_some());
                    records.push(client.send(kind, request_seed).await);
                    progress.inc(1);
                }
            })
        })
        .collect();
    let mut records = Vec::with_capacity(n);
    for task in tasks {
        match task.await {
            Ok(r) => records.extend(r),
            Err(e) => tracing::error!("a soak client failed: {e}"),
        }
    }
    progress.finish_and_clear();
    records
}

struct Report {
    requests: usize,
    concurrency: usize,
    duration: Duration,
    records: Vec<Record>,
    /// The server's resident memory after the warm-up, at its highest during the run, and
    /// after it.
    rss: [Option<u64>; 3],
}

impl Report {
    /// Clients that panicked left their requests unrecorded: those are lost too.
    fn lost(&self) -> usize {
        let lost = self.records.iter().filter(|r| matches!(r.outcome, Outcome::Lost(_))).count();
        lost + self.requests.saturating_sub(self.records.len())
    }

    fn accepted_garbage(&self) -> usize {
        self.records.iter().filter(|r| matches!(r.outcome, Outcome::Accepted(_))).count()
    }

    /// Counts of outcomes by label: completed by kind, refused by reason, and so on.
    fn outcomes(&self) -> BTreeMap<String, usize> {
        let mut counts = BTreeMap::new();
        for r in &self.records {
            let label = match &r.outcome {
                Outcome::Completed { .. } => format!("completed: {}", r.kind.name()),
                Outcome::Refused(reason) => format!("refused: {reason}"),
                Outcome::Left => format!("left after the first face: {}", r.kind.name()),
                Outcome::Accepted(what) => format!("garbage answered as valid: {what}"),
                Outcome::Lost(why) => format!("LOST: {why}"),
            };
            *counts.entry(label).or_insert(0) += 1;
        }
        counts
    }

    fn times(&self) -> Times {
        let mut t = Times::default();
        for r in &self.records {
            t.busy.extend(&r.busy);
            if let Outcome::Completed { latency, first_face } = r.outcome {
                t.latency.push(latency);
                t.first_face.extend(first_face);
            }
        }
        t.latency.sort();
        t.first_face.sort();
        t.busy.sort();
        t
    }

    fn completed(&self) -> usize {
        self.records.iter().filter(|r| matches!(r.outcome, Outcome::Completed { .. })).count()
    }

    fn json(&self) -> serde_json::Value {
        let t = self.times();
        let ms = |v: &[Duration], p: f64| percentile(v, p).map(|d| d.as_secs_f64() * 1e3);
        json!({
            "requests": self.requests,
            "concurrency": self.concurrency,
            "duration_s": self.duration.as_secs_f64(),
            "completed": self.completed(),
            "lost": self.lost(),
            "accepted_garbage": self.accepted_garbage(),
            "outcomes": self.outcomes(),
            "retried_429": t.busy.len(),
            "latency_ms": {"p50": ms(&t.latency, 0.5), "p99": ms(&t.latency, 0.99)},
            "first_face_ms": {"p50": ms(&t.first_face, 0.5), "p99": ms(&t.first_face, 0.99)},
            "answer_429_ms": {"p50": ms(&t.busy, 0.5), "p99": ms(&t.busy, 0.99)},
            "rss_bytes": {"start": self.rss[0], "peak": self.rss[1], "end": self.rss[2]},
        })
    }

    fn table(&self, server_exit: Option<&str>) -> comfy_table::Table {
        let t = self.times();
        let mut table = super::table();
        table.set_header(["measure", "value"]);
        let secs = self.duration.as_secs_f64();
        let mut row = |k: String, v: String| {
            table.add_row([k, v]);
        };
        row("requests, clients at once".into(), format!("{}, {}", self.requests, self.concurrency));
        row(
            "duration".into(),
            format!("{secs:.1} s ({:.1} requests/s)", self.requests as f64 / secs),
        );
        for (label, n) in self.outcomes() {
            row(label, n.to_string());
        }
        row("lost (no complete answer, no error)".into(), self.lost().to_string());
        row("429 answers retried after Retry-After".into(), t.busy.len().to_string());
        row(
            "429 answer time p50 / p99".into(),
            format!("{} / {}", percentile_ms(&t.busy, 0.5), percentile_ms(&t.busy, 0.99)),
        );
        row(
            "latency of completed p50 / p99".into(),
            format!("{} / {}", percentile_ms(&t.latency, 0.5), percentile_ms(&t.latency, 0.99)),
        );
        row(
            "time to first face (streams) p50 / p99".into(),
            format!(
                "{} / {}",
                percentile_ms(&t.first_face, 0.5),
                percentile_ms(&t.first_face, 0.99)
            ),
        );
        let mib = |b: Option<u64>| {
            b.map_or("-".to_string(), |b| format!("{:.1} MiB", b as f64 / 1048576.0))
        };
        row(
            "server RSS start (warm) / peak / end".into(),
            format!("{} / {} / {}", mib(self.rss[0]), mib(self.rss[1]), mib(self.rss[2])),
        );
        if let [Some(start), _, Some(end)] = self.rss {
            let change = (end as f64 / start as f64 - 1.0) * 100.0;
            row("server RSS end vs start".into(), format!("{change:+.1}%"));
        }
        if let Some(exit) = server_exit {
            row("server exit after SIGTERM".into(), exit.to_string());
        }
        table
    }
}

#[derive(Default)]
struct Times {
    latency: Vec<Duration>,
    first_face: Vec<Duration>,
    busy: Vec<Duration>,
}
