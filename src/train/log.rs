//! The run's JSONL log: one record per optimizer step and one per evaluation.

use std::io::{BufRead, Write};
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::TrainError;
use super::dit::evaluate::DitEvalReport;
use super::evaluate::EvalReport;

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum LogRecord {
    Step {
        step: u64,
        /// The objective (coordinate loss plus the weighted KL term, if any).
        loss: f64,
        /// Summed cross-entropy of the 9 coordinates per face position (nats).
        coord_loss: f64,
        lr: f64,
        grad_norm: f64,
        /// Face positions (faces plus end of mesh) in the step's batches.
        positions: usize,
        meshes: usize,
        faces_per_s: f64,
        /// Where the step's wall time went (runs from before the field: zeros).
        #[serde(default)]
        timing: StepTiming,
        elapsed_s: f64,
    },
    Eval {
        step: u64,
        split: String,
        #[serde(flatten)]
        report: EvalReport,
        elapsed_s: f64,
    },
    /// One optimizer step of the diffusion model.
    DitStep {
        step: u64,
        /// Flow-matching loss (mean squared velocity error on normalized latents).
        loss: f64,
        lr: f64,
        grad_norm: f64,
        /// (latent, view) pairs in the step.
        samples: usize,
        samples_per_s: f64,
        elapsed_s: f64,
    },
    DitEval {
        step: u64,
        split: String,
        #[serde(flatten)]
        report: DitEvalReport,
        elapsed_s: f64,
    },
}

/// Where one optimizer step's wall time went, each phase waited out on the device before the
/// next begins: what holds training back on a GPU.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq)]
pub struct StepTiming {
    /// Forward and backward passes: one per group of similar lengths.
    pub groups: usize,
    /// Waiting for batches: above zero, data preparation is the bottleneck.
    pub data_wait_s: f64,
    /// The groups' copies to the device, forward and backward passes.
    pub compute_s: f64,
    /// Gradient clipping and the optimizer's update.
    pub update_s: f64,
    /// The weight average's update (zero without one).
    pub average_s: f64,
}

/// Appends records to the log, one line each, flushed so a crash loses nothing written.
pub struct LogWriter(std::fs::File);

impl LogWriter {
    pub fn append(path: &Path) -> Result<Self, TrainError> {
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .map_err(TrainError::io(path))?;
        Ok(Self(file))
    }

    pub fn write(&mut self, record: &LogRecord) -> Result<(), TrainError> {
        let line = serde_json::to_string(record).map_err(|e| TrainError::Json(e.to_string()))?;
        writeln!(self.0, "{line}")
            .and_then(|()| self.0.flush())
            .map_err(|error| TrainError::Io { path: "log".into(), error })
    }
}

/// Every record of a log; lines that do not parse (a line cut by a crash) are skipped.
pub fn read_log(path: &Path) -> Result<Vec<LogRecord>, TrainError> {
    let file = std::fs::File::open(path).map_err(TrainError::io(path))?;
    Ok(std::io::BufReader::new(file)
        .lines()
        .map_while(Result::ok)
        .filter_map(|line| serde_json::from_str(&line).ok())
        .collect())
}
