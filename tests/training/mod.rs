//! What the `meshstream-train` tests share: the binary, a slice of the shared data set, how a
//! run starts, and export.

#![allow(dead_code)] // each test binary uses part of it

use std::path::{Path, PathBuf};
use std::process::Command;

pub fn train_bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_meshstream-train"))
}

/// The named meshes of the shared low-poly set with a manifest giving each its split, copied into
/// a temporary folder; `None` (and a message) when the data set is absent.
pub fn data_slice(dir: &Path, meshes: &[(&str, &str)]) -> Option<PathBuf> {
    let shared = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/lowpoly");
    if !shared.is_dir() {
        eprintln!(
            "SKIPPED (data slice): {} is absent; training on procedural shapes only",
            shared.display()
        );
        return None;
    }
    let slice = dir.join("slice");
    std::fs::create_dir_all(&slice).unwrap();
    let mut manifest = String::from("file,split\n");
    for (name, split) in meshes {
        std::fs::copy(shared.join(name), slice.join(name)).unwrap();
        manifest.push_str(&format!("{name},{split}\n"));
    }
    std::fs::write(slice.join("manifest.csv"), manifest).unwrap();
    Some(slice)
}

/// How a run starts: fresh random weights, the weights of an exported model, or a resume.
pub enum Start<'a> {
    Fresh,
    Init(&'a Path),
    Resume,
}

impl Start<'_> {
    /// Adds `--resume` or `--init` to `cmd`; true when the run is new and so needs its settings
    /// (a resume takes them from the run folder).
    pub fn add_to(&self, cmd: &mut Command) -> bool {
        match self {
            Start::Resume => {
                cmd.arg("--resume");
                return false;
            }
            Start::Init(model) => {
                cmd.args(["--init", model.to_str().unwrap()]);
            }
            Start::Fresh => {}
        }
        true
    }
}

pub fn export(from: &Path, to: &Path, dtype: &str) {
    let status = train_bin()
        .args(["export", from.to_str().unwrap(), "-o", to.to_str().unwrap(), "--dtype", dtype])
        .status()
        .unwrap();
    assert!(status.success());
}

/// `meshstream-train plot` draws the run's log as a PNG.
pub fn assert_plots(run: &Path, png: &Path) {
    let status = train_bin()
        .args(["plot", run.join("log.jsonl").to_str().unwrap(), "-o", png.to_str().unwrap()])
        .status()
        .unwrap();
    assert!(status.success());
    assert!(std::fs::read(png).unwrap().starts_with(b"\x89PNG"));
}
