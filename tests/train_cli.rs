//! The `meshstream-train` binary end to end: a short run on a small slice of the data set,
//! a checkpoint, a resume that continues exactly, an export and a plot.

mod training;

use std::path::Path;

use meshstream::train::log::{LogRecord, read_log};
use training::{Start, assert_plots, data_slice, export, train_bin};

/// Three small training meshes and one to evaluate on.
const SLICE: [(&str, &str); 4] = [
    ("kaykit-city-builder__box_A.ply", "train"),
    ("kaykit-city-builder__box_B.ply", "train"),
    ("kaykit-city-builder__bench.ply", "train"),
    ("kaykit-city-builder__base.ply", "dev"),
];

/// Runs `meshstream-train ae` to success; returns what it printed on stderr.
fn run(out: &Path, data: Option<&Path>, steps: u64, stop_at: u64, start: Start) -> String {
    run_with(out, data, steps, stop_at, start, &[])
}

fn run_with(
    out: &Path,
    data: Option<&Path>,
    steps: u64,
    stop_at: u64,
    start: Start,
    extra: &[&str],
) -> String {
    let mut cmd = train_bin();
    cmd.args(["ae", "--preset", "tiny", "--no-progress", "--steps", &steps.to_string()]).args([
        "--stop-at",
        &stop_at.to_string(),
        "--out",
        out.to_str().unwrap(),
    ]);
    cmd.args(extra);
    if start.add_to(&mut cmd) {
        cmd.args(["--max-faces", "60", "--curriculum", "0:60", "--batch-faces", "120"])
            .args(["--warmup", "4", "--checkpoint-every", "4", "--eval-every", "1000"])
            .args(["--eval-meshes", "1", "--eval-procedural", "1", "--eval-samples", "2000"]);
        if let Some(data) = data {
            cmd.args(["--data", data.to_str().unwrap(), "--procedural-ratio", "0.5"]);
        }
    }
    let output = cmd.output().unwrap();
    assert!(
        output.status.success(),
        "meshstream-train failed:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stderr).into_owned()
}

fn step_losses(log: &Path) -> Vec<(u64, f64)> {
    read_log(log)
        .unwrap()
        .into_iter()
        .filter_map(|r| match r {
            LogRecord::Step { step, loss, .. } => Some((step, loss)),
            _ => None,
        })
        .collect()
}

#[test]
fn trains_checkpoints_resumes_exactly_exports_and_plots() {
    let tmp = tempfile::tempdir().unwrap();
    let data = data_slice(tmp.path(), &SLICE);

    // A run of 0 steps, exported at full precision: the random weights the runs below start
    // from.
    let init_run = tmp.path().join("init-run");
    run(&init_run, data.as_deref(), 16, 0, Start::Fresh);
    let init = tmp.path().join("init");
    export(&init_run, &init, "f32");
    let weights = |dir: &Path| {
        meshstream::model::checkpoint::read_model_weights(dir, &candle_core::Device::Cpu)
            .unwrap()
            .tensors
    };
    let largest_difference = |a: &candle_core::Tensor, b: &candle_core::Tensor| {
        (a - b).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap()
    };
    let same = |a: &Path, b: &Path| {
        let (a, b) = (weights(a), weights(b));
        a.len() == b.len()
            && a.iter()
                .all(|(name, t)| b.get(name).is_some_and(|u| largest_difference(t, u) == 0.0))
    };
    // The initial weights are drawn from the run's seed: the same seed draws them again.
    let again = tmp.path().join("init-run-again");
    run(&again, data.as_deref(), 16, 0, Start::Fresh);
    assert!(same(&init_run.join("checkpoint"), &again.join("checkpoint")));
    let other_seed = tmp.path().join("init-run-seed-1");
    run_with(&other_seed, data.as_deref(), 16, 0, Start::Fresh, &["--seed", "1"]);
    assert!(!same(&init_run.join("checkpoint"), &other_seed.join("checkpoint")));

    // A frozen encoder keeps the init's encoder weights bit for bit while the rest learns.
    // (It also turns every sample by a quarter turn and stands a kit's meshes on y, which its
    // train.json records.)
    let frozen = tmp.path().join("frozen");
    // (And weights its procedural mix, and spreads its points, which train.json records too:
    // the init drew them independently, which does not change what its weights fit.)
    let extra = [
        "--freeze-encoder",
        "--any-angle-share",
        "0",
        "--procedural-weights",
        "box=3,l-extrusion=0",
        "--point-oversampling",
        "4",
        "--up-axis",
        "kenney-road=z",
    ];
    run_with(&frozen, data.as_deref(), 4, 4, Start::Init(&init), &extra);
    let config: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(frozen.join("train.json")).unwrap()).unwrap();
    assert_eq!(config["batch"]["sample"]["augment"]["any_angle_share"], 0.0);
    let mix = &config["batch"]["procedural_weights"];
    assert_eq!((&mix["Box"], &mix["LExtrusion"]), (&3.into(), &0.into()));
    assert_eq!(config["batch"]["sample"]["point_oversampling"], 4);
    assert_eq!(config["model"]["point_oversampling"], 4);
    assert_eq!(config["up_axes"], serde_json::json!([{"prefix": "kenney-road", "up": "z"}]));
    // The f32 export passes the default shard size: `--init` read it from shards.
    let (before, after) = (weights(&init), weights(&frozen.join("checkpoint")));
    let unchanged = |name: &String| largest_difference(&before[name], &after[name]) == 0.0;
    assert!(before.keys().filter(|n| n.starts_with("encoder.")).all(unchanged));
    assert!(!before.keys().filter(|n| n.starts_with("decoder.layers.")).any(unchanged));

    // A run from trained weights keeps their point drawing unless told otherwise, and
    // refuses a preset of other layers.
    let spread = tmp.path().join("spread");
    export(&frozen, &spread, "f32");
    let kept = tmp.path().join("kept");
    let printed = run(&kept, data.as_deref(), 4, 0, Start::Init(&spread));
    // Without a progress bar every evaluation is printed as it comes.
    assert!(printed.contains("eval @ 0: ") && printed.contains("open edges"), "{printed}");
    let config: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(kept.join("train.json")).unwrap()).unwrap();
    assert_eq!(config["model"]["point_oversampling"], 4);
    let output = train_bin()
        .args(["ae", "--preset", "base", "--init", spread.to_str().unwrap(), "--out"])
        .arg(tmp.path().join("other-layers"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success() && stderr.contains("other layers than the \"base\" preset"));

    // One run straight through, and one stopped halfway and resumed, both keeping a weight
    // average.
    let average = ["--weight-average", "0.9"];
    let straight = tmp.path().join("straight");
    run_with(&straight, data.as_deref(), 16, 16, Start::Init(&init), &average);
    let resumed = tmp.path().join("resumed");
    run_with(&resumed, data.as_deref(), 16, 8, Start::Init(&init), &average);
    assert!(resumed.join("checkpoint/model.safetensors").is_file());
    assert!(resumed.join("checkpoint/optimizer.safetensors").is_file());
    assert!(resumed.join("checkpoint/average/model.safetensors").is_file());
    run(&resumed, None, 16, 16, Start::Resume);

    let a = step_losses(&straight.join("log.jsonl"));
    let b = step_losses(&resumed.join("log.jsonl"));
    assert_eq!(a.iter().map(|s| s.0).collect::<Vec<_>>(), (1..=16).collect::<Vec<_>>());
    assert_eq!(b.iter().map(|s| s.0).collect::<Vec<_>>(), (1..=16).collect::<Vec<_>>());
    // Same data, weights, optimizer state and schedule: the resumed run continues exactly.
    for ((step, la), (_, lb)) in a.iter().zip(&b) {
        assert!((la - lb).abs() <= 1e-3 * la.abs(), "step {step}: {la} straight vs {lb} resumed");
    }
    // The average resumes too, and it is not the raw weights.
    let (raw, straight_average, resumed_average) = (
        weights(&straight.join("checkpoint")),
        weights(&straight.join("checkpoint/average")),
        weights(&resumed.join("checkpoint/average")),
    );
    let name = "decoder.layers.0.mlp.fc1.weight";
    let spread = largest_difference(&raw[name], &straight_average[name]);
    let off = largest_difference(&resumed_average[name], &straight_average[name]);
    // (A resume that restarted the average at the raw weights would be 7% of it off.)
    assert!(off <= 1e-3 * spread, "resumed average {off} off, {spread} from the raw weights");
    for (name, t) in &straight_average {
        let off = largest_difference(t, &resumed_average[name]);
        assert!(off < 1e-3, "{name}: the resumed average is {off} off");
    }
    let first: f64 = a[..4].iter().map(|s| s.1).sum::<f64>() / 4.0;
    let last: f64 = a[12..].iter().map(|s| s.1).sum::<f64>() / 4.0;
    assert!(last < first, "loss did not fall: {first} -> {last}");

    // A run from --init evaluates those weights before its first step, and every session
    // ends with an evaluation, which exports the best weights; a resumed session does not
    // evaluate again where it starts.
    let evaluated = |run: &Path| -> Vec<u64> {
        let records = read_log(&run.join("log.jsonl")).unwrap();
        records
            .into_iter()
            .filter_map(|r| match r {
                LogRecord::Eval { step, .. } => Some(step),
                _ => None,
            })
            .collect()
    };
    assert_eq!(evaluated(&straight), [0, 16]);
    assert_eq!(evaluated(&resumed), [0, 8, 16]);
    // Each evaluation reports the topology of what it rebuilt.
    let records = read_log(&straight.join("log.jsonl")).unwrap();
    assert!(records.iter().all(|r| match r {
        LogRecord::Eval { report, .. } => report.topology.is_some(),
        _ => true,
    }));
    let model = tmp.path().join("model");
    export(&resumed, &model, "f16");
    let loaded = meshstream::model::checkpoint::load(&model, &candle_core::Device::Cpu).unwrap();
    assert_eq!(loaded.config().max_faces, 60);
    #[cfg(unix)]
    {
        // Whoever may read the config may read the weights (safetensors alone writes 0600).
        use std::os::unix::fs::PermissionsExt;
        let mode = |f: &Path| std::fs::metadata(f).unwrap().permissions().mode();
        let config = mode(&model.join("config.json"));
        for file in meshstream::model::checkpoint::weight_files(&model).unwrap() {
            assert_eq!(mode(&file), config, "{}", file.display());
        }
    }

    assert_plots(&resumed, &tmp.path().join("curves.png"));
    assert_scores_meshes(&model, tmp.path());
}

/// `meshstream-train loss` scores every mesh it can read and prepare, and reports the others.
fn assert_scores_meshes(model: &Path, tmp: &Path) {
    let shapes = tmp.join("shapes");
    let status = train_bin()
        .args(["shapes", "-o", shapes.to_str().unwrap(), "-n", "3", "--max-faces", "60"])
        .status()
        .unwrap();
    assert!(status.success());
    std::fs::write(shapes.join("broken.obj"), "f 1 2 3\n").unwrap();
    std::fs::write(shapes.join("a-point.obj"), "v 1 1 1\nv 1 1 1\nv 1 1 1\nf 1 2 3\n").unwrap();
    let output = train_bin()
        .args(["loss", "--json", "--model", model.to_str().unwrap(), shapes.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let meshes = report["meshes"].as_array().unwrap();
    assert_eq!(meshes.len(), 3, "{report}");
    for mesh in meshes {
        let loss = mesh["loss"].as_f64().unwrap();
        assert!(loss.is_finite() && loss > 0.0, "{mesh}");
        assert!(mesh["faces"].as_u64().unwrap() > 0);
    }
    assert_eq!(report["unreadable"].as_array().unwrap().len(), 1, "{report}");
    let left_out = report["left_out"].as_array().unwrap();
    assert_eq!(left_out.len(), 1, "{report}");
    assert!(left_out[0].as_str().unwrap().starts_with("a-point: "), "{report}");

    // Split by coordinate, each mesh's 9 means and its end of mesh add up to its loss; and
    // each mesh's greedy decode is scored from the same points.
    let output = train_bin()
        .args(["loss", "--json", "--per-coordinate", "--greedy"])
        .args(["--model", model.to_str().unwrap()])
        .arg(&shapes)
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    for mesh in report["meshes"].as_array().unwrap() {
        let faces = mesh["faces"].as_f64().unwrap();
        let coordinates: Vec<f64> =
            mesh["coordinates"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        assert_eq!(coordinates.len(), 9, "{mesh}");
        let summed = coordinates.iter().sum::<f64>() * faces + mesh["end"].as_f64().unwrap();
        let loss = mesh["loss"].as_f64().unwrap() * (faces + 1.0);
        assert!((summed - loss).abs() < 1e-3 * loss, "{mesh}");
        let greedy = &mesh["greedy"];
        assert!(greedy["faces"].as_u64().unwrap() <= 60, "{mesh}");
        let greedy_loss = greedy["loss"].as_f64().unwrap();
        assert!(greedy_loss.is_finite() && greedy_loss > 0.0, "{mesh}");
        if greedy["same"].as_bool().unwrap() {
            assert!((greedy_loss - mesh["loss"].as_f64().unwrap()).abs() < 1e-4, "{mesh}");
        }
    }
}

#[test]
fn refuses_to_overwrite_a_run_and_reports_bad_arguments() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("run");
    std::fs::create_dir_all(out.join("checkpoint")).unwrap();
    let output = train_bin().args(["ae", "--out", out.to_str().unwrap()]).output().unwrap();
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("--resume"));

    // Each bad argument is refused with a message that names what is wrong.
    let refusals: [(&[&str], &str); 8] = [
        (&["--curriculum", "ten:5"], "ten:5"),
        (&["--any-angle-share", "1.5"], "between 0 and 1"),
        // Freezing needs trained weights to keep.
        (&["--freeze-encoder"], "--init"),
        (&["--encoder-lr-scale", "0"], "not in (0, 1]"),
        // A frozen encoder has no learning rate to scale.
        (
            &["--init", "models/default", "--freeze-encoder", "--encoder-lr-scale", "0.5"],
            "cannot be used with",
        ),
        (&["--procedural-weights", "blob=2"], "unknown shape kind 'blob'"),
        (&["--procedural-weights", "box=2000"], "at most 1000"),
        (&["--point-oversampling", "0"], "point_oversampling 0 not in 1..=64"),
    ];
    for (i, (args, says)) in refusals.into_iter().enumerate() {
        let run = tmp.path().join(format!("refused-{i}"));
        let output =
            train_bin().args(["ae", "--out", run.to_str().unwrap()]).args(args).output().unwrap();
        assert!(!output.status.success(), "{args:?}");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(stderr.contains(says), "{args:?}: {stderr}");
    }
}

#[test]
fn shapes_writes_the_held_aside_set_reproducibly() {
    let dir = tempfile::tempdir().unwrap();
    let write = |out: &Path, extra: &[&str]| {
        let status = train_bin()
            .args(["shapes", "-o", out.to_str().unwrap(), "-n", "6"])
            .args(extra)
            .status()
            .unwrap();
        assert!(status.success());
        let mut names: Vec<String> = std::fs::read_dir(out)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    };
    let primitives = write(&dir.path().join("a"), &["--primitives"]);
    assert_eq!(primitives.len(), 6);
    let kinds = ["Box", "Prism", "Pyramid", "Wedge", "Frustum", "Cone"];
    assert!(primitives.iter().all(|n| kinds.iter().any(|k| n.ends_with(&format!("-{k}.ply")))));
    assert_eq!(write(&dir.path().join("b"), &["--primitives"]), primitives);
    let a = std::fs::read(dir.path().join("a").join(&primitives[0])).unwrap();
    let b = std::fs::read(dir.path().join("b").join(&primitives[0])).unwrap();
    assert_eq!(a, b, "the same seed gives the same shapes");
    let mesh = meshstream::mesh::read_mesh_file(
        &dir.path().join("a").join(&primitives[0]),
        &meshstream::mesh::ReadLimits::default(),
    )
    .unwrap();
    assert!(!mesh.faces.is_empty());

    // A grid the tokenizer does not support is refused, naming the option.
    let output = train_bin()
        .args(["shapes", "-o", dir.path().join("c").to_str().unwrap(), "--levels", "64"])
        .output()
        .unwrap();
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("--levels"));
}
