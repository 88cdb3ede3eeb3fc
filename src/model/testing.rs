//! Helpers shared by the model's unit tests.

use candle_core::{Device, Tensor};
use candle_nn::VarMap;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::{FaceConfig, FaceModel, FaceToken, checkpoint, seeded_var_builder};

/// A randomly initialized model, the same on every run: its training `VarMap` and an inference
/// copy.
pub fn random_model(cfg: &FaceConfig) -> (VarMap, FaceModel) {
    seeded_model(cfg, 0)
}

/// A model initialized as training would, from `seed` (see [`seeded_var_builder`]).
pub fn seeded_model(cfg: &FaceConfig, seed: u64) -> (VarMap, FaceModel) {
    let dev = Device::Cpu;
    let varmap = VarMap::new();
    FaceModel::new(cfg, seeded_var_builder(&varmap, seed, &dev)).unwrap();
    let model = checkpoint::inference_model(cfg, &varmap, &dev).unwrap();
    (varmap, model)
}

pub fn random_latents(cfg: &FaceConfig, batch: usize, seed: u64) -> Tensor {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let n = batch * cfg.num_latents * cfg.latent_dim;
    let v: Vec<f32> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
    Tensor::from_vec(v, (batch, cfg.num_latents, cfg.latent_dim), &Device::Cpu).unwrap()
}

/// Arbitrary (not canonical) face tokens: the network does not care.
pub fn random_faces(cfg: &FaceConfig, n: usize, seed: u64) -> Vec<FaceToken> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n).map(|_| std::array::from_fn(|_| rng.random_range(0..cfg.quant_levels as u16))).collect()
}

pub fn faces_tensor(faces: &[FaceToken]) -> Tensor {
    let flat: Vec<u32> = faces.iter().flatten().map(|&c| u32::from(c)).collect();
    Tensor::from_vec(flat, (1, faces.len(), 9), &Device::Cpu).unwrap()
}

pub fn max_abs_diff(a: &Tensor, b: &Tensor) -> f32 {
    (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar().unwrap()
}
