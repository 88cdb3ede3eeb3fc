//! The one-shot GPU run's two scripts, on the CPU with a tiny budget: `device-pack.sh` packs
//! the trainer, a mesh folder and the shipped weights; `device-run.sh` unpacks them, checks the
//! device against the CPU, trains within its budget, and leaves sharded weights that load,
//! a summary and its logs, in at most the 8 files that come back from a GPU machine.

mod training;

use std::path::{Path, PathBuf};
use std::process::Command;

use meshstream::mesh::{ReadLimits, read_mesh_file};
use training::train_bin;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Procedural shapes in a folder with a manifest like the shared data set's (file, faces,
/// split): the test needs nothing outside the repository.
fn mesh_folder(dir: &Path) -> PathBuf {
    let data = dir.join("meshes");
    let status = train_bin()
        .args(["shapes", "-n", "8", "--seed", "3", "--max-faces", "60", "-o"])
        .arg(&data)
        .status()
        .unwrap();
    assert!(status.success());
    let mut manifest = String::from("file,faces,split\n");
    let mut names: Vec<_> = std::fs::read_dir(&data)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    for (i, name) in names.iter().enumerate() {
        let faces = read_mesh_file(&data.join(name), &ReadLimits::default()).unwrap().faces.len();
        let split = if i < 6 { "train" } else { "dev" };
        manifest.push_str(&format!("{name},{faces},{split}\n"));
    }
    std::fs::write(data.join("manifest.csv"), manifest).unwrap();
    data
}

fn script(name: &str) -> Command {
    Command::new(repo().join("scripts").join(name))
}

fn assert_ran(output: &std::process::Output, what: &str) -> String {
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(
        output.status.success(),
        "{what} failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    stdout
}

#[test]
fn the_packed_run_trains_on_the_cpu_and_its_weights_load() {
    let dir = tempfile::tempdir().unwrap();
    let data = mesh_folder(dir.path());
    let bundle = dir.path().join("bundle");
    let pack = script("device-pack.sh")
        .args(["--binary", env!("CARGO_BIN_EXE_meshstream-train"), "--compression", "0"])
        .arg("--data")
        .arg(&data)
        .arg("--out")
        .arg(&bundle)
        .args(["--reference", "none", "--limit", "100000"])
        .output()
        .unwrap();
    assert_ran(&pack, "device-pack.sh");
    for packed in ["meshstream-train.xz", "data/meshes.tar.xz", "data/manifest.csv"] {
        assert!(bundle.join(packed).is_file(), "{packed} was not packed");
    }
    assert!(bundle.join("init/config.json").is_file());

    let out = dir.path().join("out");
    let run = script("device-run.sh")
        .arg(&bundle)
        .arg(&out)
        .env("DEVICE", "cpu")
        .env("BUDGET", "90")
        .env("EXPORT_RESERVE", "15")
        .env("BATCH_FACES", "300")
        .env("STEPS", "50")
        .env("CHECK_MESHES", "2")
        .env("BENCH_POSITIONS", "200")
        .env("TRAIN_ARGS", "--eval-meshes 1 --eval-procedural 1 --eval-samples 2000")
        .current_dir(repo())
        .output()
        .unwrap();
    let stdout = assert_ran(&run, "device-run.sh");
    assert!(stdout.contains("check: {"), "no device check in:\n{stdout}");
    assert!(stdout.contains("faces/s median"), "no throughput in:\n{stdout}");
    assert!(stdout.contains("backward ms"), "no phase timing in:\n{stdout}");
    assert!(stdout.contains("causal attention core"), "no block timing in:\n{stdout}");
    // The shipped weights are evaluated before the first step, so the best of the run is
    // never worse than them.
    assert!(stdout.contains("evaluation CD by step: 0: "), "no first evaluation in:\n{stdout}");
    assert!(stdout.contains("exported: the weights of step "), "no best step in:\n{stdout}");

    // What comes back from a GPU machine: at most 8 files.
    let files: Vec<_> = walk(&out);
    assert!(files.len() <= 8, "{} files: {files:?}", files.len());
    assert!(out.join("logs.tar.gz").is_file() && out.join("summary.txt").is_file());
    let model = meshstream::model::checkpoint::load(&out.join("model"), &candle_core::Device::Cpu)
        .expect("the exported weights load");
    let shipped =
        meshstream::model::checkpoint::load_config(&repo().join("models/default")).unwrap();
    assert_eq!(model.config().max_faces, shipped.max_faces, "the face limit is kept");
    assert_eq!(
        model.config().point_oversampling,
        shipped.point_oversampling,
        "the point drawing is kept"
    );
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() { files.extend(walk(&path)) } else { files.push(path) }
    }
    files
}
