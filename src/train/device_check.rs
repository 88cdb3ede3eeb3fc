//! Does a device compute what the CPU computes? A trained model's loss and gradient norm on
//! the same batch, on both, before a training run trusts the device (a GPU build with a wrong
//! kernel would otherwise train garbage for its whole slot).

use std::path::Path;
use std::time::Instant;

use candle_core::Device;
use serde::Serialize;

use crate::metrics::MetricOptions;
use crate::model::{EncoderTraining, TrainBatch, checkpoint};

use super::TrainError;
use super::augment::AugmentConfig;
use super::batch::SampleConfig;
use super::checkpoint::trainable_model;
use super::evaluate::{EvalSet, evaluate, example};
use super::optim::clip_grad_norm;

/// What one device computed for the check's batch.
#[derive(Debug, Clone, Serialize)]
pub struct DeviceResult {
    pub device: String,
    pub loss: f64,
    pub grad_norm: f64,
    /// Wall time of one forward and backward pass after a first, warming one.
    pub step_ms: f64,
    /// The batch's meshes decoded greedily, as a training run's evaluation does it: their mean
    /// Chamfer distance (near ties may decode differently, so this is reported, not compared).
    pub decoded_chamfer: Option<f64>,
    pub decode_ms: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct DeviceCheck {
    pub meshes: usize,
    pub positions: usize,
    pub reference: DeviceResult,
    pub checked: DeviceResult,
    /// |checked - reference| / |reference|, for the loss and the gradient norm.
    pub loss_rel_diff: f64,
    pub grad_rel_diff: f64,
    pub tolerance: f64,
}

impl DeviceCheck {
    pub fn passed(&self) -> bool {
        self.loss_rel_diff <= self.tolerance && self.grad_rel_diff <= self.tolerance
    }
}

/// Runs the model in `model_dir` on `meshes` held-aside procedural shapes, on `reference` and
/// on `checked`, and compares the loss and the gradient norm (relative `tolerance`).
pub fn check_device(
    model_dir: &Path,
    meshes: usize,
    reference: &Device,
    checked: &Device,
    tolerance: f64,
) -> Result<DeviceCheck, TrainError> {
    let cfg = checkpoint::load_config(model_dir)?;
    let sample = SampleConfig::for_model(&cfg, AugmentConfig::OFF)?;
    let set = EvalSet::build(None, 0, meshes.max(1), &sample, cfg.max_faces)?;
    let positions = set.items.iter().map(|(_, s)| s.faces.len() + 1).sum();
    let run = |device: &Device| -> Result<DeviceResult, TrainError> {
        let (_, varmap, model) = trainable_model(model_dir, device)?;
        let examples: Vec<_> = set.items.iter().map(|(_, s)| example(s)).collect();
        let batch = TrainBatch::new(&examples, device)?;
        let step = || -> Result<(f64, f64), TrainError> {
            let loss = model.loss(&batch, EncoderTraining::Trained)?.total;
            let mut grads = loss.backward()?;
            let grad_norm = clip_grad_norm(&mut grads, &varmap.all_vars(), 0.0)?;
            Ok((f64::from(loss.to_scalar::<f32>()?), grad_norm))
        };
        step()?;
        let t0 = Instant::now();
        let (loss, grad_norm) = step()?;
        let step_ms = t0.elapsed().as_secs_f64() * 1e3;
        let t0 = Instant::now();
        let inference = checkpoint::inference_model(&cfg, &varmap, device)?;
        let metric = MetricOptions { samples: 10_000, ..MetricOptions::default() };
        let decoded = evaluate(&inference, &set, set.items.len(), &metric)?;
        Ok(DeviceResult {
            device: format!("{device:?}"),
            loss,
            grad_norm,
            step_ms,
            decoded_chamfer: decoded.chamfer_mean,
            decode_ms: t0.elapsed().as_secs_f64() * 1e3,
        })
    };
    let reference = run(reference)?;
    let checked = run(checked)?;
    let rel = |a: f64, b: f64| (a - b).abs() / b.abs().max(f64::EPSILON);
    Ok(DeviceCheck {
        meshes: set.items.len(),
        positions,
        loss_rel_diff: rel(checked.loss, reference.loss),
        grad_rel_diff: rel(checked.grad_norm, reference.grad_norm),
        reference,
        checked,
        tolerance,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::FaceConfig;
    use crate::model::testing::random_model;

    #[test]
    fn the_cpu_agrees_with_itself_and_the_report_says_so() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = FaceConfig { quant_levels: 128, ..FaceConfig::micro() };
        let (varmap, _) = random_model(&cfg);
        checkpoint::save(dir.path(), &cfg, &varmap).unwrap();
        let report = check_device(dir.path(), 3, &Device::Cpu, &Device::Cpu, 1e-6).unwrap();
        assert_eq!(report.meshes, 3);
        assert!(report.reference.loss.is_finite() && report.reference.grad_norm > 0.0);
        assert_eq!(report.loss_rel_diff, 0.0);
        assert!(report.passed());
    }
}
