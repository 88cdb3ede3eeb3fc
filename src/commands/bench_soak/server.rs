//! The server under load: a `meshstream serve` child process on ephemeral ports (so that its
//! memory can be read and a crash is seen), or one somewhere else given by its address.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use anyhow::{Context, bail};

/// Where to send requests, and the child process when it was started here.
pub struct Target {
    pub http: String,
    /// `None`: no gRPC endpoint, the gRPC share goes over HTTP.
    pub grpc: Option<String>,
    pub child: Option<Child>,
}

impl Target {
    /// Starts `meshstream serve` (this binary) with `model`, `defaults` and then `extra` flags
    /// (a later flag overrides an earlier one); waits until it listens.
    pub fn start(model: &Path, defaults: &[&str], extra: &[String]) -> anyhow::Result<Self> {
        let exe = std::env::current_exe().context("finding this program")?;
        let mut child = crate::kernel_threads::as_called(&mut Command::new(exe))
            .arg("serve")
            .arg("--model")
            .arg(model)
            .args(["--http-addr", "127.0.0.1:0", "--grpc-addr", "127.0.0.1:0"])
            .args(defaults)
            .args(extra)
            .env("MESHSTREAM_LOG", std::env::var("MESHSTREAM_LOG").unwrap_or("warn".into()))
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .context("starting meshstream serve")?;
        let mut line = String::new();
        if let Some(stdout) = child.stdout.take() {
            BufReader::new(stdout).read_line(&mut line).context("reading the server's address")?;
        }
        // "meshstream listening: http=ADDR grpc=ADDR"
        let field = |name: &str| {
            line.split_whitespace().find_map(|w| w.strip_prefix(name).map(str::to_string))
        };
        let (Some(http), Some(grpc)) = (field("http="), field("grpc=")) else {
            let status = child.wait().ok();
            bail!("meshstream serve did not start (exit status {status:?})");
        };
        Ok(Self {
            http: format!("http://{http}"),
            grpc: Some(format!("http://{grpc}")),
            child: Some(child),
        })
    }

    /// The child's resident memory in bytes, when there is a child and Linux says.
    pub fn rss(&self) -> Option<u64> {
        self.child.as_ref().and_then(|c| rss_of(c.id()))
    }

    /// Fails if the child has exited (crashed) while it should be serving.
    pub fn check_alive(&mut self) -> anyhow::Result<()> {
        if let Some(child) = &mut self.child
            && let Some(status) = child.try_wait()?
        {
            bail!("the server exited during the run: {status}");
        }
        Ok(())
    }

    /// SIGTERM, then the exit status once it has drained (killed after `grace`).
    pub fn stop(&mut self, grace: Duration) -> anyhow::Result<Option<String>> {
        let Some(child) = &mut self.child else {
            return Ok(None);
        };
        let pid = child.id().to_string();
        Command::new("kill").args(["-TERM", &pid]).status().context("sending SIGTERM")?;
        let t0 = std::time::Instant::now();
        while t0.elapsed() < grace {
            if let Some(status) = child.try_wait()? {
                return Ok(Some(status.to_string()));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        child.kill()?;
        Ok(Some(format!("killed after {grace:?} without exiting: {}", child.wait()?)))
    }
}

impl Drop for Target {
    fn drop(&mut self) {
        if let Some(child) = &mut self.child {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// `VmRSS` of `/proc/PID/status`, in bytes.
fn rss_of(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// The highest resident memory seen while a run lasts, sampled every 50 ms.
pub struct PeakRss {
    peak: Arc<AtomicU64>,
    sampler: tokio::task::JoinHandle<()>,
}

impl PeakRss {
    pub fn watch(pid: Option<u32>) -> Self {
        let peak = Arc::new(AtomicU64::new(0));
        let seen = Arc::clone(&peak);
        let sampler = tokio::spawn(async move {
            let Some(pid) = pid else { return };
            loop {
                if let Some(rss) = rss_of(pid) {
                    seen.fetch_max(rss, Ordering::Relaxed);
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        });
        Self { peak, sampler }
    }

    pub fn stop(self) -> Option<u64> {
        self.sampler.abort();
        Some(self.peak.load(Ordering::Relaxed)).filter(|&p| p > 0)
    }
}
