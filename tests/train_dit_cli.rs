//! `meshstream-train dit` end to end with a very small diffusion model against the repository's
//! autoencoder: latent cache, a checkpoint, a resume that continues exactly, evaluation,
//! export in the diffusion checkpoint format, and a plot.

mod training;

use std::path::{Path, PathBuf};

use meshstream::train::log::{LogRecord, read_log};
use training::{Start, assert_plots, data_slice, export, train_bin};

/// Two small training meshes and one to evaluate on.
const SLICE: [(&str, &str); 3] = [
    ("kaykit-city-builder__box_A.ply", "train"),
    ("kaykit-city-builder__bench.ply", "train"),
    ("kaykit-city-builder__base.ply", "dev"),
];

fn autoencoder() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default")
}

fn run(out: &Path, data: Option<&Path>, stop_at: u64, start: Start) -> String {
    let mut cmd = train_bin();
    cmd.args(["dit", "--no-progress", "--steps", "8", "--stop-at", &stop_at.to_string()])
        .args(["--out", out.to_str().unwrap()]);
    if start.add_to(&mut cmd) {
        cmd.args(["--ae", autoencoder().to_str().unwrap(), "--width", "32", "--layers", "1"])
            .args(["--procedural", "3", "--augmentations", "2", "--views", "2", "--batch", "4"])
            .args(["--lr", "1e-3", "--warmup", "2", "--checkpoint-every", "3"])
            .args(["--eval-every", "1000", "--eval-meshes", "1", "--eval-procedural", "1"])
            .args(["--eval-steps", "2", "--eval-max-faces", "12", "--eval-samples", "1000"]);
        if let Some(data) = data {
            cmd.args(["--data", data.to_str().unwrap()]);
        }
    }
    let output = cmd.output().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert!(output.status.success(), "meshstream-train dit failed:\n{stderr}");
    stderr
}

fn step_losses(log: &Path) -> Vec<(u64, f64)> {
    read_log(log)
        .unwrap()
        .into_iter()
        .filter_map(|r| match r {
            LogRecord::DitStep { step, loss, .. } => Some((step, loss)),
            _ => None,
        })
        .collect()
}

fn train_json(run: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(run.join("train.json")).unwrap()).unwrap()
}

#[test]
fn trains_checkpoints_resumes_exactly_evaluates_exports_and_plots() {
    let tmp = tempfile::tempdir().unwrap();
    let data = data_slice(tmp.path(), &SLICE);

    // Both runs start from one exported set of random weights (a run of 0 steps, exported at
    // full precision).
    let init_run = tmp.path().join("init-run");
    let banner = run(&init_run, data.as_deref(), 0, Start::Fresh);
    assert!(banner.contains("latent cache:"), "{banner}");
    let init = tmp.path().join("init");
    export(&init_run, &init, "f32");
    // They are drawn from the run's seed: a run started again draws the same.
    let again = tmp.path().join("init-run-again");
    run(&again, data.as_deref(), 0, Start::Fresh);
    let weights = |run: &Path| std::fs::read(run.join("checkpoint/model.safetensors")).unwrap();
    assert!(weights(&init_run) == weights(&again), "the same seed drew other weights");

    let straight = tmp.path().join("straight");
    run(&straight, data.as_deref(), 8, Start::Init(&init));
    let resumed = tmp.path().join("resumed");
    run(&resumed, data.as_deref(), 4, Start::Init(&init));
    assert!(resumed.join("checkpoint/optimizer.safetensors").is_file());
    assert!(resumed.join("latent-cache/cache.safetensors").is_file());
    run(&resumed, None, 8, Start::Resume);

    // The cache is a function of its settings: both runs built the same one, and its latent
    // statistics went into the model configuration.
    let cache = |run: &Path| std::fs::read(run.join("latent-cache/cache.safetensors")).unwrap();
    assert!(cache(&straight) == cache(&resumed), "caches differ");
    let stats = &train_json(&resumed)["model"]["latent_stats"];
    assert_eq!(stats, &train_json(&straight)["model"]["latent_stats"]);
    let stds = stats["std"].as_array().unwrap();
    assert_eq!(stds.len(), 64);
    assert!(stds.iter().any(|s| (s.as_f64().unwrap() - 1.0).abs() > 1e-3), "identity stats");

    // Same cache, weights, optimizer state, batches and noise: the resumed run continues
    // exactly.
    let a = step_losses(&straight.join("log.jsonl"));
    let b = step_losses(&resumed.join("log.jsonl"));
    assert_eq!(a.iter().map(|s| s.0).collect::<Vec<_>>(), (1..=8).collect::<Vec<_>>());
    assert_eq!(b.iter().map(|s| s.0).collect::<Vec<_>>(), (1..=8).collect::<Vec<_>>());
    for ((step, la), (_, lb)) in a.iter().zip(&b) {
        assert!((la - lb).abs() <= 1e-3 * la.abs(), "step {step}: {la} straight vs {lb} resumed");
    }

    // The run ends with an evaluation of the held-aside meshes (data slice and procedural).
    let records = read_log(&resumed.join("log.jsonl")).unwrap();
    let eval = records.iter().find_map(|r| match r {
        LogRecord::DitEval { step: 8, report, .. } => Some(report.clone()),
        _ => None,
    });
    let eval = eval.expect("an evaluation at step 8");
    // The weights from --init were evaluated before the first step.
    assert!(records.iter().any(|r| matches!(r, LogRecord::DitEval { step: 0, .. })));
    assert_eq!(eval.meshes, if data.is_some() { 2 } else { 1 });
    assert!(eval.loss.is_finite() && eval.mean_faces <= 12.0);
    // Every mesh is either scored or counted as a failure, and the topology of every one
    // with faces is summed up.
    assert!(eval.chamfer_mean.is_some() || eval.failures == eval.meshes);
    let topology = eval.topology.expect("the topology of what it decoded");
    assert!(topology.meshes <= eval.meshes && topology.meshes + eval.failures >= eval.meshes);

    // Exported in the diffusion checkpoint format, loadable by the library.
    let model = tmp.path().join("model");
    export(&resumed, &model, "f16");
    let loaded =
        meshstream::diffusion::checkpoint::load(&model, &candle_core::Device::Cpu, None).unwrap();
    assert_eq!(loaded.config().width, 32);
    let trained: meshstream::diffusion::LatentStats =
        serde_json::from_value(stats.clone()).unwrap();
    assert_eq!(loaded.config().latent_stats, trained);
    // It records the encoder it was trained for, and so pairs with its autoencoder.
    let encoder = meshstream::model::checkpoint::encoder_fingerprint(&autoencoder()).unwrap();
    assert_eq!(loaded.config().encoder_fingerprint.as_ref(), Some(&encoder));

    assert_plots(&resumed, &tmp.path().join("curves.png"));
}

#[test]
fn refuses_to_overwrite_a_run_and_needs_an_autoencoder() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("run");
    std::fs::create_dir_all(out.join("checkpoint")).unwrap();
    let ae = autoencoder();
    let output = train_bin()
        .args(["dit", "--ae", ae.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("--resume"));

    let output = train_bin()
        .args(["dit", "--out", tmp.path().join("x").to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("--ae"));

    // The base preset needs a DINOv2 backbone: refused before any cache is built.
    let out = tmp.path().join("base");
    let output = train_bin()
        .args(["dit", "--ae", ae.to_str().unwrap(), "--preset", "base"])
        .args(["--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("DINOv2"));
    assert!(!out.join("latent-cache").exists());
}

#[test]
fn resume_refuses_an_autoencoder_that_changed_since_the_cache_was_built() {
    let tmp = tempfile::tempdir().unwrap();
    let ae = tmp.path().join("ae");
    std::fs::create_dir_all(&ae).unwrap();
    for file in ["config.json", "model.safetensors"] {
        std::fs::copy(autoencoder().join(file), ae.join(file)).unwrap();
    }
    let out = tmp.path().join("run");
    let create = train_bin()
        .args(["dit", "--no-progress", "--stop-at", "0", "--ae", ae.to_str().unwrap()])
        .args(["--out", out.to_str().unwrap(), "--width", "32", "--layers", "1"])
        .args(["--procedural", "2", "--augmentations", "1", "--views", "1"])
        .output()
        .unwrap();
    assert!(create.status.success(), "{}", String::from_utf8_lossy(&create.stderr));

    let weights = ae.join("model.safetensors");
    let mut bytes = std::fs::read(&weights).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    std::fs::write(&weights, bytes).unwrap();
    let resume = train_bin()
        .args(["dit", "--no-progress", "--resume", "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!resume.status.success());
    let stderr = String::from_utf8_lossy(&resume.stderr);
    assert!(stderr.contains("autoencoder differs"), "{stderr}");
}
