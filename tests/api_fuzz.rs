//! The HTTP API fuzzed from its own contract: schemathesis generates requests from the
//! server's `/openapi.json` (valid and invalid ones) and checks every answer against it: no
//! 5xx, documented status codes, content types, headers and bodies. Once without keys and once
//! with one (given as a header), on a server with small limits so that each request is quick.
//!
//! schemathesis comes from PyPI (`.ci/run` installs it into target/fuzz-tools); without it the
//! test skips, except under MESHSTREAM_REQUIRE_SCHEMATHESIS=1 (CI), where it fails.

mod common;

use std::path::PathBuf;
use std::process::Command;

use common::Server;

/// The version `.ci/run` installs.
const VERSION: &str = "4.32.5";

/// target/fuzz-tools/bin/schemathesis, else one on the PATH.
fn schemathesis() -> Option<PathBuf> {
    let venv = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/fuzz-tools/bin/schemathesis");
    let found = if venv.exists() { venv } else { PathBuf::from("schemathesis") };
    let version = Command::new(&found).arg("--version").output().ok()?;
    let text = String::from_utf8_lossy(&version.stdout);
    if !text.contains(VERSION) {
        eprintln!("schemathesis {VERSION} wanted, {} found", text.trim());
    }
    version.status.success().then_some(found)
}

fn required() -> bool {
    std::env::var("MESHSTREAM_REQUIRE_SCHEMATHESIS").is_ok_and(|v| v == "1")
}

/// Runs schemathesis against `server` with `extra` options; panics with its report on a
/// failure.
fn fuzz(tool: &PathBuf, server: &Server, extra: &[&str]) {
    let config = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/api_fuzz/schemathesis.toml");
    let reports = tempfile::tempdir().unwrap();
    let out = Command::new(tool)
        .args(["--config-file", config, "run", &server.url("/openapi.json")])
        // Bounded and reproducible: 20 examples an operation, a fixed seed, no example
        // database carried between runs.
        .args(["--max-examples", "20", "--seed", "42", "--generation-database", "none"])
        .args(["--workers", "2", "--no-color", "--continue-on-failure"])
        .arg("--report-dir")
        .arg(reports.path())
        .args(extra)
        .current_dir(reports.path())
        .output()
        .unwrap();
    let report = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "schemathesis found responses that break the contract:\n{report}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // It tested every operation (a schema it cannot read would test none and pass).
    assert!(report.contains("Tested: 6"), "{report}");
}

/// Small limits: few faces, one diffusion step.
const SMALL: [&str; 6] =
    ["--max-faces", "16", "--diffusion-steps", "1", "--max-diffusion-steps", "2"];

#[test]
fn the_api_keeps_its_contract_under_schemathesis() {
    let Some(tool) = schemathesis() else {
        assert!(!required(), "schemathesis is required (MESHSTREAM_REQUIRE_SCHEMATHESIS=1)");
        eprintln!(
            "skipped: schemathesis is not installed (pip install schemathesis=={VERSION}, \
             as .ci/run does into target/fuzz-tools)"
        );
        return;
    };
    let server = Server::start(&SMALL);
    fuzz(&tool, &server, &[]);

    let key = "fuzz-key-0123456789";
    let mut keyed = SMALL.to_vec();
    keyed.extend(["--api-key", key]);
    let server = Server::start(&keyed);
    fuzz(&tool, &server, &["--header", &format!("Authorization: Bearer {key}")]);
}
