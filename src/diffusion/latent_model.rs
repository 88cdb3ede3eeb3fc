//! The image-to-latent model: image encoder + DiT + the latent normalization, with the
//! training loss and a step-by-step batched sampler.
//!
//! ```text
//! let mut run = model.start(&images, scales, 100, &mut rng)?;   // encodes images once
//! while !run.is_done() { model.step(&mut run)?; }              // "step k of N": run.rows()
//! let latents = model.latents(&run)?;                           // (B, K, latent_dim), raw scale
//! ```
//! The latents go to the unchanged FACE decoder.

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use rand::Rng;

use super::config::{DitConfig, ImageEncoderConfig};
use super::dit::{Dit, DitCondition};
use super::flow::{self, Guidance, RowStep};
use super::image_encoder::{Dinov2Encoder, ImageEncoder, PatchEncoder};
use crate::model::{ModelError, Result};

#[derive(Debug)]
pub struct DiffusionModel {
    cfg: DitConfig,
    dit: Dit,
    encoder: ImageEncoder,
    /// (1, 1, latent_dim) each.
    mean: Tensor,
    std: Tensor,
}

impl DiffusionModel {
    /// Builds the DiT (weights under `dit.`) and, for a patch encoder, the image encoder
    /// (under `image_encoder.`) from `vb`. A DINOv2 config needs its frozen backbone in
    /// `dinov2` (see [`Dinov2Encoder::load`]).
    pub fn new(cfg: &DitConfig, vb: VarBuilder, dinov2: Option<Dinov2Encoder>) -> Result<Self> {
        cfg.validate()?;
        let encoder = match (&cfg.image_encoder, dinov2) {
            (ImageEncoderConfig::Patch(p), None) => {
                ImageEncoder::Patch(PatchEncoder::new(p, cfg.norm_eps, vb.pp("image_encoder"))?)
            }
            (ImageEncoderConfig::Dinov2(_), Some(d)) => ImageEncoder::Dinov2(d),
            (ImageEncoderConfig::Patch(_), Some(_)) => {
                return Err(ModelError::InvalidConfig(
                    "a DINOv2 backbone was given, but the config uses the patch encoder".into(),
                ));
            }
            (ImageEncoderConfig::Dinov2(_), None) => {
                return Err(ModelError::InvalidConfig(
                    "the config uses a DINOv2 encoder: its weights must be supplied".into(),
                ));
            }
        };
        if !encoder.matches(&cfg.image_encoder) {
            return Err(ModelError::InvalidConfig(
                "the DINOv2 backbone does not match the config's image encoder".into(),
            ));
        }
        let d = cfg.latent_dim;
        let device = vb.device().clone();
        Ok(Self {
            cfg: cfg.clone(),
            dit: Dit::new(cfg, vb.pp("dit"))?,
            encoder,
            mean: Tensor::from_slice(&cfg.latent_stats.mean, (1, 1, d), &device)?,
            std: Tensor::from_slice(&cfg.latent_stats.std, (1, 1, d), &device)?,
        })
    }

    pub fn config(&self) -> &DitConfig {
        &self.cfg
    }

    pub fn dit(&self) -> &Dit {
        &self.dit
    }

    pub fn encoder(&self) -> &ImageEncoder {
        &self.encoder
    }

    /// Raw autoencoder latents -> the DiT's space: (x - mean) / std per channel.
    pub fn normalize(&self, latents: &Tensor) -> Result<Tensor> {
        Ok(latents.broadcast_sub(&self.mean)?.broadcast_div(&self.std)?)
    }

    /// The inverse of [`DiffusionModel::normalize`].
    pub fn denormalize(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.broadcast_mul(&self.std)?.broadcast_add(&self.mean)?)
    }

    /// The flow-matching loss on raw latents (B, K, latent_dim) paired with images
    /// (B, 3, S, S) in [0, 1]. Each row's image is replaced by the null condition with the
    /// config's `condition_dropout` probability.
    pub fn training_loss(
        &self,
        latents: &Tensor,
        images: &Tensor,
        rng: &mut impl Rng,
    ) -> Result<Tensor> {
        let b = latents.dim(0)?;
        if images.dim(0)? != b {
            return Err(ModelError::bad_input(format!(
                "{b} latent sets but {} images",
                images.dim(0)?
            )));
        }
        let p = self.cfg.condition_dropout;
        let keep: Vec<f32> = (0..b).map(|_| f32::from(u8::from(!rng.random_bool(p)))).collect();
        let keep = Tensor::from_vec(keep, b, latents.device())?;
        let tokens = self.encoder.encode(images)?;
        let cond = self.dit.condition(&tokens, Some(&keep))?;
        flow::loss(&self.dit, &self.normalize(latents)?, &cond, rng)
    }

    /// Starts sampling latents for images (B, 3, S, S) in [0, 1], one guidance scale per row,
    /// with `steps` Euler steps from noise drawn from `rng`.
    pub fn start(
        &self,
        images: &Tensor,
        scales: Vec<f32>,
        steps: usize,
        rng: &mut impl Rng,
    ) -> Result<LatentSampling> {
        let b = images.dim(0)?;
        if steps == 0 || scales.len() != b {
            return Err(ModelError::bad_input(format!(
                "sampling needs steps > 0 (got {steps}) and one guidance scale per image \
                 ({} for {b})",
                scales.len()
            )));
        }
        let tokens = self.encoder.encode(images)?;
        let cond = self.dit.condition(&tokens, None)?;
        let uncond = self.dit.null_condition(b)?;
        let shape = [b, self.cfg.num_latents, self.cfg.latent_dim];
        let x = flow::gaussian_noise(&shape, rng, images.device())?;
        Ok(LatentSampling { cond, uncond, scales, x, rows: vec![RowStep { step: 0, steps }; b] })
    }

    /// One Euler step for every unfinished row of a sampling run; finished rows stay as they
    /// are.
    pub fn step(&self, run: &mut LatentSampling) -> Result<()> {
        let active: Vec<u32> =
            (0..run.len()).filter(|&i| !run.rows[i].is_done()).map(|i| i as u32).collect();
        if active.len() == run.len() {
            run.x = self.step_rows(&run.x, &run.cond, &run.uncond, &run.scales, &run.rows)?;
        } else if !active.is_empty() {
            let part = run.select(&active)?;
            let stepped =
                self.step_rows(&part.x, &part.cond, &part.uncond, &part.scales, &part.rows)?;
            // Reassemble in row order: stepped rows in turn, finished rows unchanged.
            let mut next_stepped = 0;
            let mut rows = Vec::with_capacity(run.len());
            for (i, row) in run.rows.iter().enumerate() {
                if row.is_done() {
                    rows.push(run.x.narrow(0, i, 1)?);
                } else {
                    rows.push(stepped.narrow(0, next_stepped, 1)?);
                    next_stepped += 1;
                }
            }
            run.x = Tensor::cat(&rows, 0)?;
        }
        for &i in &active {
            run.rows[i as usize].step += 1;
        }
        Ok(())
    }

    fn step_rows(
        &self,
        x: &Tensor,
        cond: &DitCondition,
        uncond: &DitCondition,
        scales: &[f32],
        rows: &[RowStep],
    ) -> Result<Tensor> {
        let guidance = Guidance { cond, uncond, scales: scales.to_vec() };
        flow::euler_step_rows(&self.dit, x, rows, &guidance)
    }

    /// The run's current latents in the autoencoder's scale (B, K, latent_dim).
    pub fn latents(&self, run: &LatentSampling) -> Result<Tensor> {
        self.denormalize(&run.x)
    }

    /// All steps at once: images to latents for the face decoder.
    pub fn generate(
        &self,
        images: &Tensor,
        scales: Vec<f32>,
        steps: usize,
        rng: &mut impl Rng,
    ) -> Result<Tensor> {
        let mut run = self.start(images, scales, steps, rng)?;
        while !run.is_done() {
            self.step(&mut run)?;
        }
        self.latents(&run)
    }
}

/// A batched sampling run in progress: conditions prepared once, the current x_t, and where
/// each row is on its schedule. Runs can be joined and rows dropped between steps, so a
/// scheduler can keep one batch while requests come and go.
#[derive(Debug, Clone)]
pub struct LatentSampling {
    cond: DitCondition,
    uncond: DitCondition,
    scales: Vec<f32>,
    x: Tensor,
    rows: Vec<RowStep>,
}

impl LatentSampling {
    pub fn len(&self) -> usize {
        self.rows.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// Each row's progress: steps done and total steps.
    pub fn rows(&self) -> &[RowStep] {
        &self.rows
    }

    pub fn is_done(&self) -> bool {
        self.rows.iter().all(|r| r.is_done())
    }

    /// Adds the rows of `other` after this run's rows.
    pub fn append(&mut self, other: LatentSampling) -> Result<()> {
        self.cond = self.cond.concat(&other.cond)?;
        self.uncond = self.uncond.concat(&other.uncond)?;
        self.x = Tensor::cat(&[&self.x, &other.x], 0)?;
        self.scales.extend(other.scales);
        self.rows.extend(other.rows);
        Ok(())
    }

    /// Keeps the rows where `keep` is true, in order. Keeping none is an error: drop the run.
    pub fn retain(&mut self, keep: &[bool]) -> Result<()> {
        if keep.len() != self.len() {
            return Err(ModelError::bad_input(format!(
                "{} flags for a run of {} rows",
                keep.len(),
                self.len()
            )));
        }
        let rows: Vec<u32> = (0..self.len()).filter(|&i| keep[i]).map(|i| i as u32).collect();
        if rows.is_empty() {
            return Err(ModelError::bad_input("a sampling run cannot keep zero rows"));
        }
        if rows.len() < self.len() {
            *self = self.select(&rows)?;
        }
        Ok(())
    }

    fn select(&self, rows: &[u32]) -> Result<Self> {
        let idx = Tensor::from_slice(rows, rows.len(), self.x.device())?;
        Ok(Self {
            cond: self.cond.select(rows)?,
            uncond: self.uncond.select(rows)?,
            scales: rows.iter().map(|&i| self.scales[i as usize]).collect(),
            x: self.x.index_select(&idx, 0)?,
            rows: rows.iter().map(|&i| self.rows[i as usize]).collect(),
        })
    }
}

/// Per-channel mean and std of raw latents (B, K, latent_dim) over all rows and vectors, for
/// [`super::LatentStats`]. A std below `min_std` is raised to it so that a dead channel does
/// not blow up the normalization.
pub fn latent_stats(latents: &Tensor, min_std: f32) -> Result<super::LatentStats> {
    let d = latents.dim(candle_core::D::Minus1)?;
    let flat = latents.to_dtype(DType::F32)?.reshape(((), d))?;
    let mean = flat.mean(0)?;
    let var = flat.broadcast_sub(&mean)?.sqr()?.mean(0)?;
    let std: Vec<f32> = var.sqrt()?.to_vec1::<f32>()?.into_iter().map(|s| s.max(min_std)).collect();
    Ok(super::LatentStats { mean: mean.to_vec1()?, std })
}

/// (B, 3, S, S) zeros: a placeholder batch of images, e.g. for warming up.
pub fn blank_images(cfg: &DitConfig, batch: usize, device: &Device) -> Result<Tensor> {
    let s = cfg.image_encoder.image_size();
    Ok(Tensor::zeros((batch, 3, s, s), DType::F32, device)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diffusion::checkpoint::{inference_model, random_varmap};
    use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarMap};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn randn(shape: &[usize], seed: u64) -> Tensor {
        flow::gaussian_noise(shape, &mut ChaCha8Rng::seed_from_u64(seed), &Device::Cpu).unwrap()
    }

    #[test]
    fn normalization_round_trips_and_stats_are_per_channel() {
        let mut cfg = DitConfig::micro();
        cfg.latent_stats.mean = vec![1.0, -2.0, 0.5, 0.0];
        cfg.latent_stats.std = vec![2.0, 0.5, 1.0, 4.0];
        let (_, model) = random_varmap(&cfg);
        let x = randn(&[2, cfg.num_latents, cfg.latent_dim], 1);
        let back = model.denormalize(&model.normalize(&x).unwrap()).unwrap();
        assert!(crate::model::testing::max_abs_diff(&x, &back) < 1e-5);

        let raw = model.denormalize(&randn(&[64, cfg.num_latents, cfg.latent_dim], 2)).unwrap();
        let stats = latent_stats(&raw, 1e-3).unwrap();
        for c in 0..4 {
            assert!(
                (stats.mean[c] - cfg.latent_stats.mean[c]).abs() < 0.15 * cfg.latent_stats.std[c]
            );
            assert!((stats.std[c] / cfg.latent_stats.std[c] - 1.0).abs() < 0.1, "{stats:?}");
        }
    }

    #[test]
    fn a_gradient_step_reduces_the_loss_on_a_fixed_batch() {
        let cfg = DitConfig::micro();
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let model = DiffusionModel::new(&cfg, vb, None).unwrap();
        let latents = randn(&[4, cfg.num_latents, cfg.latent_dim], 3);
        let images = Tensor::rand(0f32, 1.0, (4, 3, 16, 16), &Device::Cpu).unwrap();
        // The same seed each time: the same noise, times and dropout, so only the weights move.
        let loss_at = |m: &DiffusionModel| {
            m.training_loss(&latents, &images, &mut ChaCha8Rng::seed_from_u64(9)).unwrap()
        };
        let params = ParamsAdamW { lr: 1e-3, weight_decay: 0.0, ..Default::default() };
        let mut opt = AdamW::new(varmap.all_vars(), params).unwrap();
        let before = loss_at(&model);
        for _ in 0..5 {
            opt.backward_step(&loss_at(&model)).unwrap();
        }
        let after = loss_at(&model).to_scalar::<f32>().unwrap();
        let before = before.to_scalar::<f32>().unwrap();
        assert!(after < before * 0.98, "loss {before} -> {after}");
    }

    #[test]
    fn sampling_runs_step_by_step_and_reports_progress() {
        let cfg = DitConfig::micro();
        let (varmap, _) = random_varmap(&cfg);
        let model = inference_model(&cfg, &varmap, &Device::Cpu, None).unwrap();
        let images = blank_images(&cfg, 3, &Device::Cpu).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let mut run = model.start(&images, vec![1.0, 3.0, 0.0], 4, &mut rng).unwrap();
        assert_eq!(run.rows()[2], RowStep { step: 0, steps: 4 });
        model.step(&mut run).unwrap();
        assert_eq!(run.rows()[2], RowStep { step: 1, steps: 4 });
        while !run.is_done() {
            model.step(&mut run).unwrap();
        }
        let stepped = model.latents(&run).unwrap();
        assert_eq!(stepped.dims(), &[3, cfg.num_latents, cfg.latent_dim]);
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let all = model.generate(&images, vec![1.0, 3.0, 0.0], 4, &mut rng).unwrap();
        assert_eq!(crate::model::testing::max_abs_diff(&stepped, &all), 0.0);
        assert!(model.start(&images, vec![1.0], 4, &mut rng).is_err());
        assert!(model.start(&images, vec![1.0; 3], 0, &mut rng).is_err());
    }

    /// A scheduler joins runs started at different times, with different step counts, and
    /// drops rows as they finish or are cancelled: each row must come out as if sampled alone.
    #[test]
    fn joined_runs_match_runs_alone() {
        let cfg = DitConfig::micro();
        let (_, model) = random_varmap(&cfg);
        let image = |v: f32| Tensor::full(v, (1, 3, 16, 16), &Device::Cpu).unwrap();
        let alone = |v: f32, scale: f32, steps: usize, seed: u64| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            model.generate(&image(v), vec![scale], steps, &mut rng).unwrap()
        };
        let start = |v: f32, scale: f32, steps: usize, seed: u64| {
            model
                .start(&image(v), vec![scale], steps, &mut ChaCha8Rng::seed_from_u64(seed))
                .unwrap()
        };
        let mut run = start(0.2, 1.0, 5, 1);
        model.step(&mut run).unwrap();
        model.step(&mut run).unwrap();
        run.append(start(0.7, 3.0, 3, 2)).unwrap();
        run.append(start(0.9, 0.0, 4, 3)).unwrap();
        model.step(&mut run).unwrap();
        // The third request is cancelled after one step.
        run.retain(&[true, true, false]).unwrap();
        while !run.rows()[0].is_done() || !run.rows()[1].is_done() {
            model.step(&mut run).unwrap();
        }
        assert_eq!(run.rows(), &[RowStep { step: 5, steps: 5 }, RowStep { step: 3, steps: 3 }]);
        let joined = model.latents(&run).unwrap();
        for (row, expect) in [alone(0.2, 1.0, 5, 1), alone(0.7, 3.0, 3, 2)].iter().enumerate() {
            let got = joined.narrow(0, row, 1).unwrap();
            assert!(crate::model::testing::max_abs_diff(&got, expect) < 1e-4, "row {row}");
        }
        assert!(run.retain(&[false, false]).is_err());
        assert!(run.retain(&[true]).is_err());
    }
}
