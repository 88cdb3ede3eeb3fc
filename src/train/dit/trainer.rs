//! The training loop of the diffusion model (`meshstream-train dit`), mirroring the
//! autoencoder's: warm-up + cosine schedule, gradient clipping, checkpoints with optimizer
//! state, exact resume, a JSONL log, periodic evaluation and a `best/` export.
//!
//! Batches are a pure function of (seed, step): a resumed run draws exactly the (latent, view)
//! pairs and the flow-matching noise it would have drawn, so no RNG state is saved.

use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{Device, Tensor};
use candle_nn::VarMap;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::diffusion::{DiffusionModel, checkpoint as dit_checkpoint};
use crate::model::{FaceModel, checkpoint as model_checkpoint, seeded_var_builder};
use crate::tokenize::Quantizer;

use super::super::TrainError;
use super::super::checkpoint::{self, RunDir, TrainState};
use super::super::dataset::load_folder;
use super::super::log::{LogRecord, LogWriter};
use super::super::optim::{Optimizer, Rule, default_rule};
use super::super::run_loop;
use super::cache::{AutoencoderId, LatentCache};
use super::evaluate::{DitEvalReport, DitEvalSet, evaluate};
use super::views::images_tensor;
use super::{DitTrainConfig, MIN_LATENT_STD};

/// Keeps the batch stream apart from the cache's streams, which use the same seed.
const BATCH_STREAM_OFFSET: u64 = 1 << 40;

pub struct DitTrainer {
    cfg: DitTrainConfig,
    dir: RunDir,
    device: Device,
    varmap: VarMap,
    model: DiffusionModel,
    optimizer: Optimizer,
    state: TrainState,
    cache: LatentCache,
    autoencoder: FaceModel,
    eval_set: DitEvalSet,
    log: LogWriter,
}

impl DitTrainer {
    /// A new run in `dir`: builds (or reuses, when its description matches) the latent cache,
    /// writes the cache's latent statistics into the model configuration, saves `train.json`,
    /// and optionally starts from the weights of an exported diffusion model (`init`).
    pub fn create(
        mut cfg: DitTrainConfig,
        dir: PathBuf,
        init: Option<&Path>,
        device: Device,
        progress: bool,
    ) -> Result<Self, TrainError> {
        let dir = RunDir(dir);
        std::fs::create_dir_all(&dir.0).map_err(TrainError::io(&dir.0))?;
        let autoencoder = load_autoencoder(&cfg, &device)?;
        let cache = match LatentCache::load(&dir.latent_cache())? {
            Some(cache) if cache.info.spec == cfg.cache => cache,
            _ => {
                let cache = LatentCache::build(&cfg.cache, &autoencoder, progress)?;
                cache.save(&dir.latent_cache())?;
                cache
            }
        };
        cfg.model.latent_stats = cache.stats(MIN_LATENT_STD)?;
        cfg.model.encoder_fingerprint =
            Some(model_checkpoint::encoder_fingerprint(&cfg.autoencoder)?);
        cfg.model.validate()?;
        let json =
            serde_json::to_string_pretty(&cfg).map_err(|e| TrainError::Json(e.to_string()))?;
        std::fs::write(dir.config(), json).map_err(TrainError::io(&dir.config()))?;
        let trainer = Self::build(cfg, dir, device, autoencoder, cache)?;
        if let Some(init) = init {
            let mut init_cfg = dit_checkpoint::load_config(init)?;
            // The statistics and the encoder belong to the data; the weights only need the same
            // architecture.
            init_cfg.latent_stats = trainer.cfg.model.latent_stats.clone();
            init_cfg.encoder_fingerprint = trainer.cfg.model.encoder_fingerprint.clone();
            if init_cfg != trainer.cfg.model {
                return Err(TrainError::Config(format!(
                    "{} has a different diffusion model configuration than this run",
                    init.display()
                )));
            }
            checkpoint::load_weights(init, &trainer.varmap, &trainer.device)?;
        }
        Ok(trainer)
    }

    /// Continues the run in `dir` exactly where its last checkpoint left it; the autoencoder
    /// and the latent cache must be the ones the run started with.
    pub fn resume(dir: PathBuf, device: Device, steps: Option<u64>) -> Result<Self, TrainError> {
        let dir = RunDir(dir);
        let text = std::fs::read_to_string(dir.config()).map_err(TrainError::io(&dir.config()))?;
        let mut cfg: DitTrainConfig =
            serde_json::from_str(&text).map_err(|e| TrainError::Json(e.to_string()))?;
        if let Some(steps) = steps {
            cfg.plan.steps = steps;
        }
        let autoencoder = load_autoencoder(&cfg, &device)?;
        let cache = match LatentCache::load(&dir.latent_cache())? {
            Some(cache) if cache.info.spec == cfg.cache => cache,
            Some(_) => {
                return Err(TrainError::Config(format!(
                    "{}: the latent cache was built from other settings than train.json's",
                    dir.latent_cache().display()
                )));
            }
            None => {
                return Err(TrainError::Config(format!(
                    "{}: the latent cache is missing",
                    dir.latent_cache().display()
                )));
            }
        };
        let mut trainer = Self::build(cfg, dir, device, autoencoder, cache)?;
        trainer.state = checkpoint::restore(
            &trainer.dir.checkpoint(),
            &trainer.varmap,
            &mut trainer.optimizer,
            &trainer.device,
        )?;
        Ok(trainer)
    }

    fn build(
        cfg: DitTrainConfig,
        dir: RunDir,
        device: Device,
        autoencoder: FaceModel,
        cache: LatentCache,
    ) -> Result<Self, TrainError> {
        let varmap = VarMap::new();
        // Drawn from the run's seed: candle's own initializer cannot be seeded.
        let model =
            DiffusionModel::new(&cfg.model, seeded_var_builder(&varmap, cfg.seed, &device), None)?;
        let optimizer = if cfg.muon {
            Optimizer::new(&varmap, cfg.optim, default_rule)?
        } else {
            Optimizer::new(&varmap, cfg.optim, adamw_rule)?
        };
        let ae = autoencoder.config();
        let eval_folder = match &cfg.cache.data {
            Some(path) if cfg.eval_folder_meshes > 0 => {
                let q = Quantizer::new(u16::try_from(ae.quant_levels).unwrap_or(u16::MAX))?;
                Some(load_folder(path, Some(&cfg.eval_split), ae.max_faces, q, &cfg.cache.up_axes)?)
            }
            _ => None,
        };
        let eval_set = DitEvalSet::build(
            eval_folder.as_ref(),
            cfg.eval_folder_meshes,
            cfg.eval_procedural,
            &cfg.cache.view,
            &autoencoder,
        )?;
        let log = LogWriter::append(&dir.log())?;
        Ok(Self {
            cfg,
            dir,
            device,
            varmap,
            model,
            optimizer,
            state: TrainState::default(),
            cache,
            autoencoder,
            eval_set,
            log,
        })
    }

    pub fn config(&self) -> &DitTrainConfig {
        &self.cfg
    }

    /// What the cache holds and what it skipped, for the start banner.
    pub fn data_summary(&self) -> String {
        let info = &self.cache.info;
        let s = &info.skipped;
        format!(
            "latent cache: {} copies of {} meshes x {} views (built in {:.0} s; skipped: {} \
             unreadable, {} without faces, {} over the face limit, {} copies); {} evaluation \
             meshes",
            info.entries,
            info.meshes,
            info.spec.views,
            info.build_seconds,
            s.unreadable,
            s.no_faces,
            s.over_face_limit,
            s.copies,
            self.eval_set.len()
        )
    }

    pub fn parameter_counts(&self) -> std::collections::HashMap<&'static str, usize> {
        self.optimizer.counts()
    }

    /// The (latents, images) batch of `step` and the random stream its loss continues with.
    fn batch(&self, step: u64) -> Result<(Tensor, Tensor, ChaCha8Rng), TrainError> {
        let mut rng = ChaCha8Rng::seed_from_u64(self.cfg.seed);
        rng.set_stream(BATCH_STREAM_OFFSET + step);
        let (n, views) = (self.cache.len(), self.cache.info.spec.views);
        let mut latents = Vec::new();
        let mut images = Vec::with_capacity(self.cfg.batch);
        for _ in 0..self.cfg.batch.max(1) {
            let (i, v) = (rng.random_range(0..n), rng.random_range(0..views));
            let (Some(latent), Some(image)) = (self.cache.latent(i), self.cache.image(i, v)) else {
                return Err(TrainError::Config(format!("latent cache entry {i} is missing")));
            };
            latents.extend_from_slice(latent);
            images.push(image);
        }
        let (k, d) = (self.cfg.model.num_latents, self.cfg.model.latent_dim);
        let latents = Tensor::from_vec(latents, (images.len(), k, d), &self.device)?;
        let size = self.cache.info.spec.view.size as usize;
        Ok((latents, images_tensor(&images, size, &self.device)?, rng))
    }

    /// Evaluates the current weights (none when the evaluation set is empty), logs the report,
    /// and exports them to `best/` when their Chamfer distance is the lowest so far.
    pub fn evaluate_and_keep_best(&mut self) -> Result<Option<DitEvalReport>, TrainError> {
        if self.eval_set.is_empty() {
            return Ok(None);
        }
        let model =
            dit_checkpoint::inference_model(&self.cfg.model, &self.varmap, &self.device, None)?;
        let report = evaluate(&model, &self.autoencoder, &self.eval_set, &self.cfg.eval)?;
        self.log.write(&LogRecord::DitEval {
            step: self.state.step,
            split: self.cfg.eval_split.clone(),
            report: report.clone(),
            elapsed_s: self.state.elapsed_s,
        })?;
        if self.state.record_best(report.chamfer_mean) {
            dit_checkpoint::save(&self.dir.best(), &self.cfg.model, &self.varmap)?;
        }
        Ok(Some(report))
    }
}

/// What one `dit` session keeps between steps.
pub struct DitSession {
    clock: run_loop::SessionClock,
}

impl run_loop::Steps for DitTrainer {
    type Session = DitSession;
    type Report = DitEvalReport;

    fn state(&self) -> &TrainState {
        &self.state
    }

    fn plan(&self) -> &run_loop::Plan {
        &self.cfg.plan
    }

    fn begin(&mut self) -> Result<DitSession, TrainError> {
        Ok(DitSession { clock: run_loop::SessionClock::new(self.varmap.all_vars(), &self.state) })
    }

    fn train_step(&mut self, session: &mut DitSession) -> Result<String, TrainError> {
        let t0 = Instant::now();
        let (latents, images, mut rng) = self.batch(self.state.step)?;
        let loss_t = self.model.training_loss(&latents, &images, &mut rng)?;
        let loss = f64::from(loss_t.to_scalar::<f32>()?);
        let grads = loss_t.backward()?;
        let (lr, grad_norm) = run_loop::update(
            loss,
            grads,
            &mut self.optimizer,
            &mut self.state,
            &self.cfg.plan,
            &session.clock,
        )?;
        let samples = latents.dim(0)?;
        let samples_per_s = samples as f64 / t0.elapsed().as_secs_f64();
        self.log.write(&LogRecord::DitStep {
            step: self.state.step,
            loss,
            lr,
            grad_norm,
            samples,
            samples_per_s,
            elapsed_s: self.state.elapsed_s,
        })?;
        Ok(format!("loss {loss:.4}  {samples_per_s:.1} samples/s"))
    }

    fn evaluate(&mut self) -> Result<Option<DitEvalReport>, TrainError> {
        self.evaluate_and_keep_best()
    }

    fn report_line(step: u64, report: &DitEvalReport) -> String {
        super::evaluate::eval_line(step, report)
    }

    fn save_checkpoint(&self) -> Result<(), TrainError> {
        checkpoint::save(
            &self.dir.checkpoint(),
            &self.cfg.model,
            &self.varmap,
            &self.optimizer,
            &self.state,
            None,
        )
    }
}

/// AdamW for every parameter: with decay on matrices other than embeddings, without on the
/// rest (the autoencoder's split, minus Muon).
fn adamw_rule(name: &str, rank: usize) -> Rule {
    match default_rule(name, rank) {
        Rule::Muon => Rule::AdamW,
        other => other,
    }
}

/// The frozen autoencoder of a run, refused when its weights are not the ones the cache was
/// built from.
fn load_autoencoder(cfg: &DitTrainConfig, device: &Device) -> Result<FaceModel, TrainError> {
    let id = AutoencoderId::of(&cfg.autoencoder)?;
    if id != cfg.cache.autoencoder {
        return Err(TrainError::Config(format!(
            "{}: the autoencoder differs from the one this run's latent cache was built with",
            cfg.autoencoder.display()
        )));
    }
    let ae = &id.config;
    if (ae.num_latents, ae.latent_dim) != (cfg.model.num_latents, cfg.model.latent_dim) {
        return Err(TrainError::Config(format!(
            "the diffusion model generates {} x {} latents but the autoencoder has {} x {}",
            cfg.model.num_latents, cfg.model.latent_dim, ae.num_latents, ae.latent_dim
        )));
    }
    Ok(model_checkpoint::load(&cfg.autoencoder, device)?)
}
