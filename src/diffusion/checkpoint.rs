//! Diffusion checkpoints: `config.json` (a [`DitConfig`]) + `model.safetensors` (the DiT under
//! `dit.`, the patch encoder under `image_encoder.`), in the face model's format and with its
//! checks: a missing, misshapen or unexpected tensor is named. A DINOv2 backbone is frozen and
//! not part of the checkpoint; its weights file is passed to [`load`].

use std::path::Path;

use candle_core::{DType, Device};
use candle_nn::{VarBuilder, VarMap};

use super::config::{DitConfig, ImageEncoderConfig};
use super::image_encoder::Dinov2Encoder;
use super::latent_model::DiffusionModel;
use crate::model::checkpoint::{
    build_checked, copy_into_varmap, detached_weights, encoder_fingerprint, read_config,
    save_checkpoint,
};
use crate::model::{ModelError, Result};

/// A `VarBuilder` over detached copies of a training `VarMap`'s weights: a model built from it
/// runs candle's fused kernels and records no autograd graph.
pub fn inference_weights(varmap: &VarMap, device: &Device) -> VarBuilder<'static> {
    VarBuilder::from_tensors(detached_weights(varmap), DType::F32, device)
}

/// An inference model sharing the current weights of a training `VarMap`.
pub fn inference_model(
    cfg: &DitConfig,
    varmap: &VarMap,
    device: &Device,
    dinov2: Option<Dinov2Encoder>,
) -> Result<DiffusionModel> {
    DiffusionModel::new(cfg, inference_weights(varmap, device), dinov2)
}

/// Writes `config.json` and `model.safetensors` into `dir` (created if needed).
pub fn save(dir: &Path, cfg: &DitConfig, varmap: &VarMap) -> Result<()> {
    save_checkpoint(dir, cfg, varmap)
}

/// Reads and validates `config.json`.
pub fn load_config(dir: &Path) -> Result<DitConfig> {
    let cfg: DitConfig = read_config(dir)?;
    cfg.validate()?;
    Ok(cfg)
}

/// Loads an inference model from `dir`; `dinov2_weights` is required exactly when the config
/// uses a DINOv2 encoder.
pub fn load(dir: &Path, device: &Device, dinov2_weights: Option<&Path>) -> Result<DiffusionModel> {
    let cfg = load_config(dir)?;
    let dinov2 = match (&cfg.image_encoder, dinov2_weights) {
        (ImageEncoderConfig::Dinov2(d), Some(path)) => Some(Dinov2Encoder::load(d, path, device)?),
        (ImageEncoderConfig::Dinov2(_), None) => {
            return Err(ModelError::InvalidConfig(format!(
                "{}: the model uses a DINOv2 encoder; pass its weights file",
                dir.display()
            )));
        }
        (ImageEncoderConfig::Patch(_), _) => None,
    };
    build_checked(dir, device, |vb| DiffusionModel::new(&cfg, vb, dinov2))
}

/// Refuses the image model in `dir` beside the face model in `face_model` when it recorded
/// another encoder than that model's: its latents would mean nothing to the decoder.
pub fn check_encoder(cfg: &DitConfig, dir: &Path, face_model: &Path) -> Result<()> {
    let Some(expected) = &cfg.encoder_fingerprint else { return Ok(()) };
    let found = encoder_fingerprint(face_model)?;
    if *expected == found {
        return Ok(());
    }
    Err(ModelError::ForeignEncoder {
        image_model: dir.to_path_buf(),
        face_model: face_model.to_path_buf(),
        expected: expected.clone(),
        found,
    })
}

/// Copies a checkpoint's weights into a training `VarMap` built for the same config (to resume
/// training), with the same checks as [`load`].
pub fn load_into_varmap(dir: &Path, varmap: &VarMap, device: &Device) -> Result<DitConfig> {
    let cfg = load_config(dir)?;
    copy_into_varmap(dir, varmap, device)?;
    Ok(cfg)
}

/// A training `VarMap` with every weight random (also the zero-initialized adaLN layers, so
/// outputs are non-trivial), and an inference model on it. Patch-encoder configs only.
#[cfg(test)]
pub(crate) fn random_varmap(cfg: &DitConfig) -> (VarMap, DiffusionModel) {
    let varmap = VarMap::new();
    DiffusionModel::new(cfg, VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu), None)
        .unwrap();
    for var in varmap.all_vars() {
        var.set(&var.randn_like(0.0, 0.1).unwrap()).unwrap();
    }
    let model = inference_model(cfg, &varmap, &Device::Cpu, None).unwrap();
    (varmap, model)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::checkpoint::WEIGHTS_FILE;
    use crate::model::testing::max_abs_diff;
    use candle_core::Tensor;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn sample(model: &DiffusionModel) -> Tensor {
        let images = Tensor::full(0.5f32, (2, 3, 16, 16), &Device::Cpu).unwrap();
        model.generate(&images, vec![1.0, 2.5], 3, &mut ChaCha8Rng::seed_from_u64(1)).unwrap()
    }

    #[test]
    fn save_load_gives_identical_outputs() {
        let mut cfg = DitConfig::micro();
        cfg.latent_stats.mean = vec![0.5, 0.0, -0.5, 1.0];
        cfg.latent_stats.std = vec![1.0, 2.0, 0.5, 1.0];
        let (varmap, model) = random_varmap(&cfg);
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &cfg, &varmap).unwrap();
        let loaded = load(dir.path(), &Device::Cpu, None).unwrap();
        assert_eq!(loaded.config(), &cfg);
        assert_eq!(max_abs_diff(&sample(&model), &sample(&loaded)), 0.0);

        let (fresh, _) = random_varmap(&cfg);
        load_into_varmap(dir.path(), &fresh, &Device::Cpu).unwrap();
        let resumed = inference_model(&cfg, &fresh, &Device::Cpu, None).unwrap();
        assert_eq!(max_abs_diff(&sample(&model), &sample(&resumed)), 0.0);
    }

    #[test]
    fn bad_checkpoints_are_named_errors() {
        let cfg = DitConfig::micro();
        let (varmap, _) = random_varmap(&cfg);
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &cfg, &varmap).unwrap();
        let path = dir.path().join(WEIGHTS_FILE);
        let mut tensors = candle_core::safetensors::load(&path, &Device::Cpu).unwrap();
        let name = "dit.blocks.1.modulation.weight";
        tensors.insert(name.into(), Tensor::zeros((3, 4), DType::F32, &Device::Cpu).unwrap());
        candle_core::safetensors::save(&tensors, &path).unwrap();
        let err = load(dir.path(), &Device::Cpu, None).unwrap_err();
        assert!(matches!(&err, ModelError::ShapeMismatch { name: n, .. } if n == name), "{err}");

        tensors.remove(name);
        candle_core::safetensors::save(&tensors, &path).unwrap();
        let err = load(dir.path(), &Device::Cpu, None).unwrap_err();
        assert!(matches!(&err, ModelError::MissingTensor { name: n, .. } if n == name), "{err}");

        // A DINOv2 config without its weights file.
        let mut dino = DitConfig::micro();
        dino.image_encoder = ImageEncoderConfig::Dinov2(super::super::Dinov2Config {
            image_size: 28,
            depth: 1,
            embed_dim: 16,
            heads: 2,
        });
        save(dir.path(), &dino, &varmap).unwrap();
        assert!(matches!(load(dir.path(), &Device::Cpu, None), Err(ModelError::InvalidConfig(_))));
    }

    #[test]
    fn parameter_count_matches_an_instantiated_model() {
        for cfg in [DitConfig::micro(), DitConfig::tiny()] {
            let (varmap, _) = random_varmap(&cfg);
            let n: usize = varmap.all_vars().iter().map(|v| v.elem_count()).sum();
            assert_eq!(n, cfg.parameter_count());
        }
    }

    #[test]
    fn an_image_model_is_refused_beside_another_encoder() {
        let face = tempfile::tempdir().unwrap();
        let face_cfg = crate::model::FaceConfig::micro();
        let (face_vars, _) = crate::model::testing::random_model(&face_cfg);
        crate::model::checkpoint::save(face.path(), &face_cfg, &face_vars).unwrap();
        let dir = Path::new("dit");
        let mut cfg = DitConfig::micro();
        // Made before fingerprints were recorded: paired unchecked.
        check_encoder(&cfg, dir, face.path()).unwrap();
        cfg.encoder_fingerprint = Some(encoder_fingerprint(face.path()).unwrap());
        check_encoder(&cfg, dir, face.path()).unwrap();
        cfg.encoder_fingerprint = Some("0123456789abcdef".into());
        let err = check_encoder(&cfg, dir, face.path()).unwrap_err();
        assert!(matches!(err, ModelError::ForeignEncoder { .. }), "{err}");
        assert!(err.to_string().contains("meshstream-train dit --ae"), "{err}");
    }

    #[test]
    fn the_shipped_image_model_is_for_the_shipped_encoder() {
        let face = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default");
        let dir = face.join("dit");
        let cfg = load_config(&dir).unwrap();
        assert!(cfg.encoder_fingerprint.is_some(), "models/default/dit records no encoder");
        check_encoder(&cfg, &dir, &face).unwrap();
    }
}
