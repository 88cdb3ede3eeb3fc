//! Training of the image-to-latent diffusion model (`meshstream-train dit`, paper section
//! 3.4): a [`cache`] of autoencoder latents paired with rendered [`views`], the training loop
//! in [`trainer`] (mirroring the autoencoder's: checkpoints, exact resume, JSONL log, best
//! export) and the end-to-end [`evaluate`] (image -> DiT -> greedy decoding -> CD/HD).

pub mod cache;
pub mod evaluate;
pub mod trainer;
pub mod views;

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::diffusion::DitConfig;

use self::evaluate::DitEvalOptions;
use super::optim::OptimConfig;
use super::run_loop;
use cache::CacheSpec;

/// Everything that defines a DiT run; saved as `train.json` in the run folder, so `--resume`
/// continues with exactly the same settings.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct DitTrainConfig {
    /// The diffusion model, with the latent statistics of the run's cache.
    pub model: DitConfig,
    /// The frozen autoencoder's model folder.
    pub autoencoder: PathBuf,
    /// What the latent cache is built from (its description is checked on resume).
    pub cache: CacheSpec,
    pub eval_split: String,
    /// Held-aside meshes from the folder's eval split, and held-aside procedural shapes.
    pub eval_folder_meshes: usize,
    pub eval_procedural: usize,
    pub eval: DitEvalOptions,
    /// (latent, view) pairs per step.
    pub batch: usize,
    pub optim: OptimConfig,
    /// Muon for the 2-D matrices of the transformer blocks (as the paper), else AdamW only.
    pub muon: bool,
    #[serde(flatten)]
    pub plan: run_loop::Plan,
    /// Seed of the initial weights, the batches and the flow-matching noise (the cache has its
    /// own in `cache`).
    pub seed: u64,
}

/// The smallest latent std the normalization divides by: a dead channel stays finite.
pub const MIN_LATENT_STD: f32 = 1e-3;
