//! The training loop of the autoencoder (`meshstream-train ae`).

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use serde::{Deserialize, Serialize};

use crate::metrics::MetricOptions;
use crate::model::checkpoint::detached_weights;
use crate::model::{
    ENCODER_SCOPE, EncoderTraining, FaceConfig, FaceModel, TrainBatch,
    checkpoint as model_checkpoint, seeded_var_builder,
};
use crate::tokenize::Quantizer;

use super::TrainError;
use super::average::WeightAverage;
use super::batch::{BatchConfig, BatchSource, Prefetcher};
use super::checkpoint::{self, RunDir, TrainState};
use super::dataset::{FolderData, UpAxes, load_folder};
use super::evaluate::{EvalReport, EvalSet, evaluate};
use super::log::{LogRecord, LogWriter, StepTiming};
use super::optim::{OptimConfig, Optimizer, default_rule};
use super::run_loop;

/// Everything that defines a run; saved as `train.json` in the run folder, so `--resume`
/// continues with exactly the same settings.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TrainConfig {
    pub model: FaceConfig,
    /// A folder of meshes (with an optional `manifest.csv`); none: procedural shapes only.
    pub data: Option<PathBuf>,
    pub train_split: String,
    pub eval_split: String,
    /// The folder's meshes that stand on another axis than y, stood on y when loaded. Runs
    /// from before it had none.
    #[serde(default, skip_serializing_if = "UpAxes::is_empty")]
    pub up_axes: UpAxes,
    pub batch: BatchConfig,
    pub optim: OptimConfig,
    #[serde(flatten)]
    pub plan: run_loop::Plan,
    /// Batches whose gradients are summed into one optimizer step.
    pub accumulate: usize,
    /// Held-aside meshes from the folder's eval split, and held-aside procedural shapes.
    pub eval_folder_meshes: usize,
    pub eval_procedural: usize,
    /// Points per surface for the evaluation's Chamfer and Hausdorff distances.
    pub eval_metric_samples: usize,
    /// Frozen: only the decoder and head learn (runs from before the option: trained).
    #[serde(default)]
    pub encoder: EncoderTraining,
    /// A trained encoder's learning rate as a share of the schedule's: below 1 its latent
    /// space moves less than the decoder (runs from before the option: 1).
    #[serde(default = "full_rate")]
    pub encoder_lr_scale: f64,
    /// The decay of an exponential moving average of the weights, which the run then
    /// evaluates, keeps as best and checkpoints (see [`WeightAverage`]); none: the raw weights
    /// (runs from before the option).
    #[serde(default)]
    pub weight_average: Option<f64>,
}

fn full_rate() -> f64 {
    1.0
}

pub struct Trainer {
    cfg: TrainConfig,
    dir: RunDir,
    device: Device,
    varmap: VarMap,
    model: FaceModel,
    optimizer: Optimizer,
    average: Option<WeightAverage>,
    state: TrainState,
    train_data: Option<Arc<FolderData>>,
    eval_set: EvalSet,
    log: LogWriter,
}

impl Trainer {
    /// A new run in `dir` (its config written there), optionally starting from the weights of
    /// an exported model (`init`); the optimizer starts fresh, so keep a warm-up.
    pub fn create(
        cfg: TrainConfig,
        dir: PathBuf,
        init: Option<&std::path::Path>,
        device: Device,
    ) -> Result<Self, TrainError> {
        if cfg.encoder == EncoderTraining::Frozen && init.is_none() {
            return Err(TrainError::Config(
                "a frozen encoder needs trained weights to keep: start from --init".into(),
            ));
        }
        let dir = RunDir(dir);
        std::fs::create_dir_all(&dir.0).map_err(TrainError::io(&dir.0))?;
        let json =
            serde_json::to_string_pretty(&cfg).map_err(|e| TrainError::Json(e.to_string()))?;
        std::fs::write(dir.config(), json).map_err(TrainError::io(&dir.config()))?;
        let mut trainer = Self::build(cfg, dir, device)?;
        if let Some(init) = init {
            let init_cfg = model_checkpoint::load_config(init)?;
            if !init_cfg.same_weights(&trainer.cfg.model) {
                return Err(TrainError::Config(format!(
                    "{} has a different model configuration than this run",
                    init.display()
                )));
            }
            checkpoint::load_weights(init, &trainer.varmap, &trainer.device)?;
        }
        trainer.average = trainer.start_average()?;
        Ok(trainer)
    }

    /// Continues the run in `dir` exactly where its last checkpoint left it.
    pub fn resume(dir: PathBuf, device: Device, steps: Option<u64>) -> Result<Self, TrainError> {
        let dir = RunDir(dir);
        let text = std::fs::read_to_string(dir.config()).map_err(TrainError::io(&dir.config()))?;
        let mut cfg: TrainConfig =
            serde_json::from_str(&text).map_err(|e| TrainError::Json(e.to_string()))?;
        if let Some(steps) = steps {
            cfg.plan.steps = steps;
        }
        let mut trainer = Self::build(cfg, dir, device)?;
        trainer.state = checkpoint::restore(
            &trainer.dir.checkpoint(),
            &trainer.varmap,
            &mut trainer.optimizer,
            &trainer.device,
        )?;
        trainer.average = trainer.start_average()?;
        if let Some(average) = &mut trainer.average {
            average
                .restore(&checkpoint::average_dir(&trainer.dir.checkpoint()), &trainer.device)?;
        }
        Ok(trainer)
    }

    /// The weight average of the run's configuration, starting at the current weights.
    fn start_average(&self) -> Result<Option<WeightAverage>, TrainError> {
        self.cfg.weight_average.map(|decay| WeightAverage::start(decay, &self.varmap)).transpose()
    }

    fn build(cfg: TrainConfig, dir: RunDir, device: Device) -> Result<Self, TrainError> {
        let varmap = VarMap::new();
        // Drawn from the run's seed: candle's own initializer cannot be seeded.
        let model =
            FaceModel::new(&cfg.model, seeded_var_builder(&varmap, cfg.batch.seed, &device))?;
        let mut optimizer = Optimizer::new(&varmap, cfg.optim, default_rule)?;
        if cfg.encoder_lr_scale != 1.0 {
            if cfg.encoder == EncoderTraining::Frozen
                || !(cfg.encoder_lr_scale > 0.0 && cfg.encoder_lr_scale <= 1.0)
            {
                return Err(TrainError::Config(format!(
                    "an encoder learning-rate scale of {} needs a trained encoder and a share in (0, 1]",
                    cfg.encoder_lr_scale
                )));
            }
            let prefix = format!("{ENCODER_SCOPE}.");
            if optimizer.scale_learning_rate(&prefix, cfg.encoder_lr_scale) == 0 {
                return Err(TrainError::Config(format!("the model has no {prefix}* weights")));
            }
        }
        let q = Quantizer::new(
            u16::try_from(cfg.model.quant_levels)
                .map_err(|_| TrainError::Config("quant_levels too large".into()))?,
        )?;
        let (max_faces, up) = (cfg.model.max_faces, &cfg.up_axes);
        let (train_data, eval_data) = match &cfg.data {
            Some(path) => (
                Some(Arc::new(load_folder(path, Some(&cfg.train_split), max_faces, q, up)?)),
                Some(load_folder(path, Some(&cfg.eval_split), max_faces, q, up)?),
            ),
            None => (None, None),
        };
        let eval_set = EvalSet::build(
            eval_data.as_ref(),
            cfg.eval_folder_meshes,
            cfg.eval_procedural,
            &cfg.batch.sample,
            max_faces,
        )?;
        let log = LogWriter::append(&dir.log())?;
        Ok(Self {
            cfg,
            dir,
            device,
            varmap,
            model,
            optimizer,
            average: None,
            state: TrainState::default(),
            train_data,
            eval_set,
            log,
        })
    }

    /// Training meshes available (after skips) and what was skipped, for the start banner.
    pub fn data_summary(&self) -> String {
        let data = match &self.train_data {
            Some(d) => format!(
                "{} training meshes ({} unreadable, {} without faces, {} over the face limit skipped); {} evaluation meshes",
                d.meshes.len(),
                d.skipped.unreadable.len(),
                d.skipped.no_faces,
                d.skipped.over_face_limit,
                self.eval_set.items.len()
            ),
            None => {
                format!("procedural shapes only; {} evaluation meshes", self.eval_set.items.len())
            }
        };
        match self.cfg.encoder {
            EncoderTraining::Trained if self.cfg.encoder_lr_scale != 1.0 => {
                format!("{data}; the encoder learns at {} x the lr", self.cfg.encoder_lr_scale)
            }
            EncoderTraining::Trained => data,
            EncoderTraining::Frozen => format!("{data}; the encoder is frozen"),
        }
    }

    pub fn parameter_counts(&self) -> std::collections::HashMap<&'static str, usize> {
        self.optimizer.counts()
    }

    /// Evaluates the current weights (their average, when the run keeps one), logs the
    /// report, and exports them to `best/` when their Chamfer distance is the lowest so far.
    pub fn evaluate_and_keep_best(&mut self) -> Result<EvalReport, TrainError> {
        let weights = match &self.average {
            Some(average) => average.weights().clone(),
            None => detached_weights(&self.varmap),
        };
        let model = FaceModel::new(
            &self.cfg.model,
            VarBuilder::from_tensors(weights.clone(), DType::F32, &self.device),
        )?;
        let metric =
            MetricOptions { samples: self.cfg.eval_metric_samples, ..MetricOptions::default() };
        let report = evaluate(&model, &self.eval_set, 16, &metric)?;
        self.log.write(&LogRecord::Eval {
            step: self.state.step,
            split: self.cfg.eval_split.clone(),
            report: report.clone(),
            elapsed_s: self.state.elapsed_s,
        })?;
        if self.state.record_best(report.chamfer_mean) {
            model_checkpoint::write_model_dir(&self.dir.best(), &self.cfg.model, &weights)?;
        }
        Ok(report)
    }
}

/// Adds the gradients of `more` into `acc`, variable by variable.
fn add_grads(acc: &mut GradStore, more: &GradStore, vars: &[Var]) -> Result<(), TrainError> {
    for var in vars {
        if let Some(g) = more.get(var.as_tensor()) {
            let sum = match acc.remove(var.as_tensor()) {
                Some(prev) => (prev + g)?,
                None => g.clone(),
            };
            acc.insert(var.as_tensor(), sum);
        }
    }
    Ok(())
}

/// Threads that make batches: on the CPU the model needs the cores itself, so one; beside a
/// GPU every core but the one that drives it, since sampling, augmentation and tokenization
/// of tens of thousands of face positions per step would otherwise leave the GPU waiting.
fn data_workers(device: &Device) -> usize {
    if device.is_cpu() {
        return 1;
    }
    std::thread::available_parallelism().map_or(1, |n| n.get().saturating_sub(1).max(1))
}

/// What one `ae` session keeps between steps.
pub struct AeSession {
    prefetch: Prefetcher,
    clock: run_loop::SessionClock,
}

impl run_loop::Steps for Trainer {
    type Session = AeSession;
    type Report = EvalReport;

    fn state(&self) -> &TrainState {
        &self.state
    }

    fn plan(&self) -> &run_loop::Plan {
        &self.cfg.plan
    }

    fn begin(&mut self) -> Result<AeSession, TrainError> {
        let source = BatchSource::new(self.train_data.clone(), self.cfg.batch.clone());
        let accumulate = self.cfg.accumulate.max(1) as u64;
        Ok(AeSession {
            prefetch: Prefetcher::spawn(
                source,
                self.state.step * accumulate,
                4,
                data_workers(&self.device),
            ),
            clock: run_loop::SessionClock::new(self.varmap.all_vars(), &self.state),
        })
    }

    fn train_step(&mut self, session: &mut AeSession) -> Result<String, TrainError> {
        let accumulate = self.cfg.accumulate.max(1) as u64;
        let t0 = Instant::now();
        let mut grads: Option<GradStore> = None;
        // The step's losses stay on the device until the step ends: one copy to the host per
        // step, not one per group, so the GPU is never made to wait mid-step.
        let mut losses: Option<Tensor> = None;
        let (mut positions, mut meshes) = (0, 0);
        let mut timing = StepTiming::default();
        for _ in 0..accumulate {
            let waiting = Instant::now();
            let batch = session.prefetch.next_batch().ok_or(TrainError::DataStopped)??;
            timing.data_wait_s += waiting.elapsed().as_secs_f64();
            let batch_positions = batch.positions();
            let groups = batch.length_groups(self.cfg.batch.max_padding);
            timing.groups += groups.len();
            for group in groups {
                let examples: Vec<_> = group.iter().map(|s| super::evaluate::example(s)).collect();
                let tensors = TrainBatch::new(&examples, &self.device)?;
                let out = self.model.loss(&tensors, self.cfg.encoder)?;
                // Each group's loss is a mean over its positions; weighted by its share,
                // the sum is the mean over the whole step's positions.
                let group_positions: usize = group.iter().map(|s| s.faces.len() + 1).sum();
                let weight = group_positions as f64 / batch_positions as f64 / accumulate as f64;
                let pair =
                    (Tensor::stack(&[out.total.detach(), out.coords.detach()], 0)? * weight)?;
                losses = Some(match losses {
                    None => pair,
                    Some(sum) => (sum + pair)?,
                });
                let step_grads = (out.total * weight)?.backward()?;
                grads = Some(match grads {
                    None => step_grads,
                    Some(mut acc) => {
                        add_grads(&mut acc, &step_grads, &session.clock.vars)?;
                        acc
                    }
                });
            }
            positions += batch_positions;
            meshes += batch.samples.len();
        }
        // Copying the losses back waits for every pass the step queued on the device.
        let losses = losses.ok_or(TrainError::DataStopped)?.to_vec1::<f32>()?;
        let (loss, coord_loss) = (f64::from(losses[0]), f64::from(losses[1]));
        timing.compute_s = t0.elapsed().as_secs_f64() - timing.data_wait_s;
        let phase = Instant::now();
        let grads = grads.ok_or(TrainError::DataStopped)?;
        let (lr, grad_norm) = run_loop::update(
            loss,
            grads,
            &mut self.optimizer,
            &mut self.state,
            &self.cfg.plan,
            &session.clock,
        )?;
        self.device.synchronize()?;
        timing.update_s = phase.elapsed().as_secs_f64();
        if let Some(average) = &mut self.average {
            let phase = Instant::now();
            average.update(&self.varmap, self.state.step)?;
            self.device.synchronize()?;
            timing.average_s = phase.elapsed().as_secs_f64();
        }
        let faces_per_s = positions as f64 / t0.elapsed().as_secs_f64();
        self.log.write(&LogRecord::Step {
            step: self.state.step,
            loss,
            coord_loss,
            lr,
            grad_norm,
            positions,
            meshes,
            faces_per_s,
            timing,
            elapsed_s: self.state.elapsed_s,
        })?;
        Ok(format!("loss {coord_loss:.2}  {faces_per_s:.0} faces/s"))
    }

    fn evaluate(&mut self) -> Result<Option<EvalReport>, TrainError> {
        self.evaluate_and_keep_best().map(Some)
    }

    fn report_line(step: u64, report: &EvalReport) -> String {
        eval_line(step, report)
    }

    fn save_checkpoint(&self) -> Result<(), TrainError> {
        checkpoint::save(
            &self.dir.checkpoint(),
            &self.cfg.model,
            &self.varmap,
            &self.optimizer,
            &self.state,
            self.average.as_ref().map(WeightAverage::weights),
        )
    }
}

pub fn eval_line(step: u64, r: &EvalReport) -> String {
    let opt = |v: Option<f64>| v.map_or_else(|| "-".into(), |v| format!("{v:.4}"));
    let by_source = r.by_source.as_ref().map_or_else(String::new, |b| {
        format!(
            "; folder / procedural: loss {} / {}, CD {} / {}",
            opt(b.loss_folder),
            opt(b.loss_procedural),
            opt(b.chamfer_folder),
            opt(b.chamfer_procedural)
        )
    });
    let topology = r.topology.map_or_else(String::new, |t| format!("; {t}"));
    format!(
        "eval @ {step}: loss {:.3} ({} with other meshes' points), CD {}, HD {}, failures {}/{}, \
         exact {}, faces right {}, face-count error {:.2}{topology}{by_source}",
        r.loss,
        r.loss_other_points.map_or_else(|| "-".into(), |v| format!("{v:.3}")),
        opt(r.chamfer_mean),
        opt(r.hausdorff_mean),
        r.failures,
        r.meshes,
        r.exact,
        r.faces_right.map_or_else(|| "-".into(), |v| format!("{:.1}%", 100.0 * v)),
        r.face_count_error
    )
}

/// Stops the run at the next step boundary on Ctrl-C (the run then checkpoints and exits).
pub fn stop_flag_on_ctrl_c() -> Arc<AtomicBool> {
    let flag = Arc::new(AtomicBool::new(false));
    let f = flag.clone();
    // If a handler is already set (tests), the run simply cannot be interrupted that way.
    let _ = ctrlc::set_handler(move || f.store(true, Ordering::SeqCst));
    flag
}
