//! Where a training step's time goes (`meshstream-train bench`): the step of `ae` taken apart,
//! each phase waited out on the device before the next, so that a GPU's slow kernels are found
//! by the phase that holds them. The totals are slower than training's own (it waits between
//! phases); compare phases and faces/s measured in one run.

use std::path::Path;
use std::time::{Duration, Instant};

use candle_core::Device;
use serde::Serialize;

use crate::model::TrainBatch;

use super::TrainError;
use super::augment::AugmentConfig;
use super::batch::{BatchConfig, BatchSource, CurriculumStage, SampleConfig};
use super::checkpoint::trainable_model;
use super::dataset::FolderData;
use super::evaluate::example;
use super::optim::{OptimConfig, Optimizer, clip_grad_norm, default_rule};

/// Seconds per step, by phase, averaged over the timed steps.
#[derive(Debug, Clone, Default, Serialize)]
pub struct StepPhases {
    /// Face positions per step (faces plus end of mesh), and forward/backward passes.
    pub positions: usize,
    pub passes: f64,
    pub faces_per_s: f64,
    /// Copying the batch to the device.
    pub upload_s: f64,
    pub encoder_s: f64,
    /// The decoder stack's hidden states (teacher-forced).
    pub decoder_s: f64,
    /// The 9 sub-heads' logits.
    pub head_s: f64,
    pub loss_s: f64,
    pub backward_s: f64,
    /// Gradient clipping and the optimizer.
    pub update_s: f64,
}

/// Times `steps` training steps of `positions` face positions (after one untimed step) of the
/// model in `model_dir`, on procedural shapes and, with `folder`, its meshes half the time.
pub fn bench_train_step(
    model_dir: &Path,
    folder: Option<std::sync::Arc<FolderData>>,
    positions: usize,
    steps: usize,
    max_padding: f64,
    device: &Device,
) -> Result<StepPhases, TrainError> {
    let (cfg, varmap, model) = trainable_model(model_dir, device)?;
    let mut optimizer = Optimizer::new(&varmap, OptimConfig::default(), default_rule)?;
    let vars = varmap.all_vars();
    let batch_cfg = BatchConfig {
        sample: SampleConfig::for_model(&cfg, AugmentConfig::default())?,
        faces_per_batch: positions,
        procedural_ratio: if folder.is_some() { 0.5 } else { 1.0 },
        procedural_weights: Default::default(),
        curriculum: vec![CurriculumStage { from_step: 0, max_faces: cfg.max_faces }],
        max_faces: cfg.max_faces,
        seed: 0,
        max_padding,
    };
    let source = BatchSource::new(folder, batch_cfg);
    let mut total = StepPhases::default();
    let mut timed = Duration::ZERO;
    for index in 0..=steps {
        let batch = source.batch(index as u64)?;
        let groups = batch.length_groups(max_padding);
        let mut phases = StepPhases {
            positions: batch.positions(),
            passes: groups.len() as f64,
            ..StepPhases::default()
        };
        let started = Instant::now();
        let mut clock = PhaseClock::new(device);
        let mut grads = Vec::new();
        for group in groups {
            let examples: Vec<_> = group.iter().map(|s| example(s)).collect();
            let tensors = TrainBatch::new(&examples, device)?;
            clock.lap(&mut phases.upload_s)?;
            let enc =
                model.encode_train(&tensors.points, &tensors.normals, &tensors.query_indices)?;
            let latents = enc.sample()?;
            clock.lap(&mut phases.encoder_s)?;
            let hidden = model.hidden_states(&latents, &tensors.faces)?;
            clock.lap(&mut phases.decoder_s)?;
            let logits = model.teacher_forced_logits(&hidden, &tensors.faces)?;
            clock.lap(&mut phases.head_s)?;
            let loss = tensors.cross_entropy(&logits, cfg.quant_levels)?;
            clock.lap(&mut phases.loss_s)?;
            grads.push(loss.backward()?);
            clock.lap(&mut phases.backward_s)?;
        }
        // The last pass's gradients stand for the step's: the optimizer's cost does not
        // depend on which it is given.
        if let Some(mut grads) = grads.pop() {
            clip_grad_norm(&mut grads, &vars, 1.0)?;
            optimizer.step(&grads, 1e-4)?;
        }
        clock.lap(&mut phases.update_s)?;
        if index == 0 {
            continue; // kernels compiled, caches and pools warmed
        }
        timed += started.elapsed();
        total.add(&phases);
    }
    let n = steps.max(1) as f64;
    total.scale(1.0 / n);
    total.faces_per_s = total.positions as f64 / (timed.as_secs_f64() / n).max(f64::EPSILON);
    Ok(total)
}

impl StepPhases {
    fn add(&mut self, other: &StepPhases) {
        self.positions += other.positions;
        self.passes += other.passes;
        for (a, b) in self.times_mut().into_iter().zip(other.times()) {
            *a += b;
        }
    }

    fn scale(&mut self, factor: f64) {
        self.positions = (self.positions as f64 * factor).round() as usize;
        self.passes *= factor;
        for t in self.times_mut() {
            *t *= factor;
        }
    }

    /// The phases' names and seconds, in step order.
    pub fn times(&self) -> [f64; 7] {
        [
            self.upload_s,
            self.encoder_s,
            self.decoder_s,
            self.head_s,
            self.loss_s,
            self.backward_s,
            self.update_s,
        ]
    }

    pub const PHASES: [&str; 7] =
        ["upload", "encoder", "decoder", "head", "loss", "backward", "update"];

    fn times_mut(&mut self) -> [&mut f64; 7] {
        [
            &mut self.upload_s,
            &mut self.encoder_s,
            &mut self.decoder_s,
            &mut self.head_s,
            &mut self.loss_s,
            &mut self.backward_s,
            &mut self.update_s,
        ]
    }
}

/// Waits for the device at each lap and adds the lap's time to a phase.
struct PhaseClock<'a> {
    device: &'a Device,
    last: Instant,
}

impl<'a> PhaseClock<'a> {
    fn new(device: &'a Device) -> Self {
        Self { device, last: Instant::now() }
    }

    fn lap(&mut self, phase: &mut f64) -> Result<(), TrainError> {
        self.device.synchronize()?;
        let now = Instant::now();
        *phase += (now - self.last).as_secs_f64();
        self.last = now;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::FaceConfig;
    use crate::model::checkpoint;
    use crate::model::testing::random_model;

    #[test]
    fn every_phase_of_a_step_is_timed() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = FaceConfig { quant_levels: 128, max_faces: 60, ..FaceConfig::micro() };
        let (varmap, _) = random_model(&cfg);
        checkpoint::save(dir.path(), &cfg, &varmap).unwrap();
        let phases = bench_train_step(dir.path(), None, 200, 2, 0.25, &Device::Cpu).unwrap();
        assert!(phases.positions > 0 && phases.positions <= 200, "{phases:?}");
        assert!(phases.passes >= 1.0 && phases.faces_per_s > 0.0);
        assert!(phases.times().iter().all(|&t| t > 0.0), "{phases:?}");
    }
}
