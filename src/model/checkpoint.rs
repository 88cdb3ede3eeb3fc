//! Checkpoints: `config.json` + `model.safetensors` (or its shards, see [`read_model_weights`])
//! in one directory. Loading checks every tensor against the config and names the first one
//! that is missing or has the wrong shape.

mod shards;

use std::collections::{HashMap, HashSet};
use std::path::Path;
use std::sync::Mutex;

use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{Init, VarBuilder, VarMap};

use super::{ENCODER_SCOPE, FaceConfig, FaceModel, ModelError, Result};

pub use shards::{
    DEFAULT_MAX_SHARD_BYTES, ModelWeights, WEIGHTS_FILE, WEIGHTS_INDEX_FILE, read_model_weights,
    weight_files,
};

pub const CONFIG_FILE: &str = "config.json";

/// Detached copies of a `VarMap`'s tensors: an inference model built from them runs candle's
/// fused kernels and records no autograd graph.
pub fn detached_weights(varmap: &VarMap) -> HashMap<String, Tensor> {
    let data = varmap.data().lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    data.iter().map(|(name, var)| (name.clone(), var.as_tensor().detach())).collect()
}

/// An inference model sharing the current weights of a training `VarMap`.
pub fn inference_model(cfg: &FaceConfig, varmap: &VarMap, device: &Device) -> Result<FaceModel> {
    let vb = VarBuilder::from_tensors(detached_weights(varmap), DType::F32, device);
    FaceModel::new(cfg, vb)
}

pub(crate) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> ModelError + '_ {
    move |error| ModelError::Io { path: path.to_path_buf(), error }
}

/// Writes `config.json` and `model.safetensors` into `dir` (created if needed).
pub fn save(dir: &Path, cfg: &FaceConfig, varmap: &VarMap) -> Result<()> {
    save_checkpoint(dir, cfg, varmap)
}

/// [`save`] for any serializable config (the diffusion model's checkpoints share the format).
pub(crate) fn save_checkpoint<C: serde::Serialize>(
    dir: &Path,
    cfg: &C,
    varmap: &VarMap,
) -> Result<()> {
    write_model_dir(dir, cfg, &detached_weights(varmap))
}

/// Writes `config.json` and one `model.safetensors` into `dir` (created if needed), removing
/// any shards there: checkpoints and a run's best weights stay on the machine that trains, so
/// only exports, which travel, are sharded.
pub(crate) fn write_model_dir<C: serde::Serialize>(
    dir: &Path,
    cfg: &C,
    weights: &HashMap<String, Tensor>,
) -> Result<()> {
    write_sharded_model_dir(dir, cfg, weights, u64::MAX)
}

/// Writes `config.json` and the weights into `dir` (created if needed), in shards when their
/// data passes `max_shard_bytes` (see [`read_model_weights`]), the weights readable by whoever
/// may read the config. safetensors 0.8 writes through a temporary file, always mode 0600, so
/// a model exported by one user (root in a build container, say) would be unreadable to the
/// user that serves it (safetensors issue #782); the config's mode is what the umask gives.
pub(crate) fn write_sharded_model_dir<C: serde::Serialize>(
    dir: &Path,
    cfg: &C,
    weights: &HashMap<String, Tensor>,
    max_shard_bytes: u64,
) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(io_err(dir))?;
    let cfg_path = dir.join(CONFIG_FILE);
    let json = serde_json::to_string_pretty(cfg).map_err(|e| ModelError::BadCheckpoint {
        path: cfg_path.clone(),
        message: e.to_string(),
    })?;
    std::fs::write(&cfg_path, json).map_err(io_err(&cfg_path))?;
    let written = shards::write_weights(dir, weights, max_shard_bytes)?;
    let permissions = std::fs::metadata(&cfg_path).map_err(io_err(&cfg_path))?.permissions();
    for path in written {
        std::fs::set_permissions(&path, permissions.clone()).map_err(io_err(&path))?;
    }
    Ok(())
}

/// Reads and validates `config.json`.
pub fn load_config(dir: &Path) -> Result<FaceConfig> {
    let cfg: FaceConfig = read_config(dir)?;
    cfg.validate()?;
    Ok(cfg)
}

/// Parses `config.json` (without validating it).
pub(crate) fn read_config<C: serde::de::DeserializeOwned>(dir: &Path) -> Result<C> {
    let path = dir.join(CONFIG_FILE);
    let text = std::fs::read_to_string(&path).map_err(io_err(&path))?;
    serde_json::from_str(&text)
        .map_err(|e| ModelError::BadCheckpoint { path: path.clone(), message: e.to_string() })
}

/// A fingerprint of the shape encoder's weights in `dir`: an image model generates the latents
/// of one encoder only, and records this to refuse being paired with another. The weights are
/// hashed as f16 values, so the f16 and f32 exports of one encoder agree (an encoder frozen
/// since an f16 export is bit for bit that export). Names and values are hashed in name order,
/// so a sharded export has the fingerprint of the single file.
pub fn encoder_fingerprint(dir: &Path) -> Result<String> {
    let ModelWeights { path, tensors } = read_model_weights(dir, &Device::Cpu)?;
    let prefix = format!("{ENCODER_SCOPE}.");
    let mut names: Vec<&String> = tensors.keys().filter(|n| n.starts_with(&prefix)).collect();
    if names.is_empty() {
        return Err(ModelError::MissingTensor { path, name: format!("{prefix}*") });
    }
    names.sort();
    let mut hash = Fnv1a::default();
    for name in names {
        let t = &tensors[name];
        hash.write(name.as_bytes());
        for d in t.dims() {
            hash.write(&(*d as u64).to_le_bytes());
        }
        let values =
            t.to_dtype(DType::F16)?.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
        values.iter().for_each(|v| hash.write(&v.to_le_bytes()));
    }
    Ok(hash.hex())
}

/// FNV-1a (64 bit): a content fingerprint, not a security hash; it only has to notice changed
/// weights.
pub(crate) struct Fnv1a(u64);

impl Default for Fnv1a {
    fn default() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }
}

impl Fnv1a {
    pub fn write(&mut self, bytes: &[u8]) {
        self.0 =
            bytes.iter().fold(self.0, |h, &b| (h ^ u64::from(b)).wrapping_mul(0x100_0000_01b3));
    }

    pub fn hex(&self) -> String {
        format!("{:016x}", self.0)
    }
}

/// A problem with one tensor, recorded while the model is built.
#[derive(Debug, Clone)]
enum TensorProblem {
    Missing(String),
    Shape { name: String, expected: Vec<usize>, found: Vec<usize> },
}

impl TensorProblem {
    fn into_error(self, path: &Path) -> ModelError {
        let path = path.to_path_buf();
        match self {
            Self::Missing(name) => ModelError::MissingTensor { path, name },
            Self::Shape { name, expected, found } => {
                ModelError::ShapeMismatch { path, name, expected, found }
            }
        }
    }
}

fn check(
    tensors: &HashMap<String, Tensor>,
    name: &str,
    expected: &Shape,
) -> std::result::Result<Tensor, TensorProblem> {
    let t = tensors.get(name).ok_or_else(|| TensorProblem::Missing(name.to_string()))?;
    if t.shape() != expected {
        return Err(TensorProblem::Shape {
            name: name.to_string(),
            expected: expected.dims().to_vec(),
            found: t.dims().to_vec(),
        });
    }
    Ok(t.clone())
}

/// Loaded tensors plus what the model asked for and the first problem, so the error can name
/// the tensor with both shapes.
struct CheckedTensors {
    tensors: HashMap<String, Tensor>,
    used: Mutex<HashSet<String>>,
    problem: Mutex<Option<TensorProblem>>,
}

/// The `VarBuilder` backend; shared so that `load` can read the record after the build.
struct CheckedBackend(std::sync::Arc<CheckedTensors>);

impl SimpleBackend for CheckedBackend {
    fn get(
        &self,
        s: Shape,
        name: &str,
        _: Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let this = &self.0;
        match check(&this.tensors, name, &s) {
            Ok(t) => {
                this.used.lock().unwrap_or_else(|p| p.into_inner()).insert(name.to_string());
                t.to_dtype(dtype)?.to_device(dev)
            }
            Err(problem) => {
                let msg = format!("{problem:?}");
                this.problem.lock().unwrap_or_else(|p| p.into_inner()).get_or_insert(problem);
                Err(candle_core::Error::Msg(msg))
            }
        }
    }

    fn get_unchecked(&self, name: &str, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        let t = self
            .0
            .tensors
            .get(name)
            .ok_or_else(|| candle_core::Error::CannotFindTensor { path: name.to_string() })?;
        t.to_dtype(dtype)?.to_device(dev)
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.0.tensors.contains_key(name)
    }
}

/// Loads an inference model from `dir`. Every tensor the config needs must be there with the
/// right shape, and no other tensor may be.
/// A folder with a quantized model file (`model.gguf`, see [`super::quantize`]) loads with its
/// linear layers quantized as they were written.
pub fn load(dir: &Path, device: &Device) -> Result<FaceModel> {
    if super::quantize::is_quantized_dir(dir) {
        return Ok(super::quantize::load_quantized(dir, device, Default::default())?.0);
    }
    let cfg = load_config(dir)?;
    load_with_config(dir, &cfg, device)
}

/// [`load`] of the f32 weights in `dir` with a config edited by the caller (a longer
/// `max_faces`, say: the rotary positions are computed, not learned).
pub fn load_with_config(dir: &Path, cfg: &FaceConfig, device: &Device) -> Result<FaceModel> {
    cfg.validate()?;
    build_checked(dir, device, |vb| FaceModel::new(cfg, vb))
}

/// Runs `build` on the weights in `dir` with the checks of [`load`]: the first missing or
/// misshapen tensor is named, and so are tensors `build` did not use.
pub(crate) fn build_checked<M>(
    dir: &Path,
    device: &Device,
    build: impl FnOnce(VarBuilder) -> Result<M>,
) -> Result<M> {
    let ModelWeights { path, tensors } = read_model_weights(dir, device)?;
    build_from_tensors(&path, tensors, device, build)
}

/// [`build_checked`] on tensors already read from `path`.
pub(crate) fn build_from_tensors<M>(
    path: &Path,
    tensors: HashMap<String, Tensor>,
    device: &Device,
    build: impl FnOnce(VarBuilder) -> Result<M>,
) -> Result<M> {
    let path = path.to_path_buf();
    let names: Vec<String> = tensors.keys().cloned().collect();
    let backend = std::sync::Arc::new(CheckedTensors {
        tensors,
        used: Mutex::new(HashSet::new()),
        problem: Mutex::new(None),
    });
    let vb = VarBuilder::from_backend(
        Box::new(CheckedBackend(backend.clone())),
        DType::F32,
        device.clone(),
    );
    let built = build(vb);
    let problem = backend.problem.lock().unwrap_or_else(|p| p.into_inner()).take();
    if let Some(problem) = problem {
        return Err(problem.into_error(&path));
    }
    let model = built?;
    let used = backend.used.lock().unwrap_or_else(|p| p.into_inner());
    let mut unused: Vec<String> = names.into_iter().filter(|n| !used.contains(n)).collect();
    if !unused.is_empty() {
        unused.sort();
        return Err(ModelError::UnexpectedTensors { path, names: unused });
    }
    Ok(model)
}

/// Copies a checkpoint's weights into a training `VarMap` built for the same config (to resume
/// training), with the same checks as [`load`].
pub fn load_into_varmap(dir: &Path, varmap: &VarMap, device: &Device) -> Result<FaceConfig> {
    let cfg = load_config(dir)?;
    copy_into_varmap(dir, varmap, device)?;
    Ok(cfg)
}

/// The weights part of [`load_into_varmap`], for any model.
pub(crate) fn copy_into_varmap(dir: &Path, varmap: &VarMap, device: &Device) -> Result<()> {
    let ModelWeights { path, tensors } = read_model_weights(dir, device)?;
    let data = varmap.data().lock().unwrap_or_else(|p| p.into_inner());
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    for name in names {
        let var = &data[name];
        let t = check(&tensors, name, var.shape()).map_err(|p| p.into_error(&path))?;
        var.set(&t.to_dtype(var.dtype())?)?;
    }
    let mut unused: Vec<String> =
        tensors.keys().filter(|n| !data.contains_key(*n)).cloned().collect();
    if !unused.is_empty() {
        unused.sort();
        return Err(ModelError::UnexpectedTensors { path, names: unused });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::testing::{max_abs_diff, random_latents, random_model, seeded_model};

    fn outputs(model: &FaceModel, latents: &Tensor) -> Tensor {
        let mut s = model.start_sequence(latents).unwrap();
        model.step(&mut [&mut s]).unwrap()
    }

    #[test]
    fn save_load_gives_identical_outputs() {
        let cfg = FaceConfig::micro();
        let (varmap, model) = random_model(&cfg);
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &cfg, &varmap).unwrap();
        let loaded = load(dir.path(), &Device::Cpu).unwrap();
        assert_eq!(loaded.config(), &cfg);
        let latents = random_latents(&cfg, 1, 5);
        assert_eq!(max_abs_diff(&outputs(&model, &latents), &outputs(&loaded, &latents)), 0.0);

        // Resume path: a fresh VarMap takes the saved weights.
        let (fresh, _) = seeded_model(&cfg, 1);
        load_into_varmap(dir.path(), &fresh, &Device::Cpu).unwrap();
        let resumed = inference_model(&cfg, &fresh, &Device::Cpu).unwrap();
        assert_eq!(max_abs_diff(&outputs(&model, &latents), &outputs(&resumed, &latents)), 0.0);
    }

    #[test]
    fn the_encoder_fingerprint_follows_the_encoder_only() {
        let cfg = FaceConfig::micro();
        let (varmap, _) = random_model(&cfg);
        let saved = |edit: &dyn Fn(&str, &Tensor) -> Tensor, dtype: DType| {
            let dir = tempfile::tempdir().unwrap();
            let data = varmap.data().lock().unwrap();
            let weights: HashMap<String, Tensor> = data
                .iter()
                .map(|(name, var)| {
                    // Values an f16 file holds exactly, as after an f16 export.
                    let t = var.as_tensor().to_dtype(DType::F16).unwrap();
                    let t = edit(name, &t.to_dtype(DType::F32).unwrap());
                    (name.clone(), t.to_dtype(dtype).unwrap())
                })
                .collect();
            write_model_dir(dir.path(), &cfg, &weights).unwrap();
            encoder_fingerprint(dir.path()).unwrap()
        };
        let keep = |_: &str, t: &Tensor| t.clone();
        let fingerprint = saved(&keep, DType::F32);
        assert_eq!(saved(&keep, DType::F16), fingerprint, "f16 and f32 copies differ");
        let nudge = |prefix: &'static str| {
            move |name: &str, t: &Tensor| {
                if name.starts_with(prefix) { (t + 0.25).unwrap() } else { t.clone() }
            }
        };
        assert_eq!(saved(&nudge("decoder."), DType::F32), fingerprint);
        assert_ne!(saved(&nudge("encoder."), DType::F32), fingerprint);
    }

    #[test]
    fn a_sharded_model_loads_and_fingerprints_as_the_single_file() {
        let cfg = FaceConfig::micro();
        let (varmap, model) = random_model(&cfg);
        let weights = detached_weights(&varmap);
        let single = tempfile::tempdir().unwrap();
        write_model_dir(single.path(), &cfg, &weights).unwrap();
        let sharded = tempfile::tempdir().unwrap();
        write_sharded_model_dir(sharded.path(), &cfg, &weights, 64 * 1024).unwrap();
        assert!(!sharded.path().join(WEIGHTS_FILE).exists());
        assert!(weight_files(sharded.path()).unwrap().len() > 1);

        let loaded = load(sharded.path(), &Device::Cpu).unwrap();
        let latents = random_latents(&cfg, 1, 5);
        assert_eq!(max_abs_diff(&outputs(&model, &latents), &outputs(&loaded, &latents)), 0.0);
        let (fresh, _) = seeded_model(&cfg, 1);
        load_into_varmap(sharded.path(), &fresh, &Device::Cpu).unwrap();
        let resumed = inference_model(&cfg, &fresh, &Device::Cpu).unwrap();
        assert_eq!(max_abs_diff(&outputs(&model, &latents), &outputs(&resumed, &latents)), 0.0);
        assert_eq!(
            encoder_fingerprint(sharded.path()).unwrap(),
            encoder_fingerprint(single.path()).unwrap()
        );
    }

    #[cfg(unix)]
    #[test]
    fn shards_and_index_are_as_readable_as_the_config() {
        use std::os::unix::fs::PermissionsExt;
        let cfg = FaceConfig::micro();
        let (varmap, _) = random_model(&cfg);
        let dir = tempfile::tempdir().unwrap();
        write_sharded_model_dir(dir.path(), &cfg, &detached_weights(&varmap), 64 * 1024).unwrap();
        let mode = |path: &Path| std::fs::metadata(path).unwrap().permissions().mode() & 0o777;
        let config = mode(&dir.path().join(CONFIG_FILE));
        for path in weight_files(dir.path()).unwrap() {
            assert_eq!(mode(&path), config, "{}", path.display());
        }
        assert_eq!(mode(&dir.path().join(WEIGHTS_INDEX_FILE)), config);
    }

    #[cfg(unix)]
    #[test]
    fn the_weights_are_as_readable_as_the_config() {
        use std::os::unix::fs::PermissionsExt;
        let cfg = FaceConfig::micro();
        let (varmap, _) = random_model(&cfg);
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &cfg, &varmap).unwrap();
        let mode = |file: &str| {
            std::fs::metadata(dir.path().join(file)).unwrap().permissions().mode() & 0o777
        };
        assert_eq!(mode(WEIGHTS_FILE), mode(CONFIG_FILE));
    }

    #[test]
    fn a_wrong_shape_names_the_tensor() {
        let cfg = FaceConfig::micro();
        let (varmap, _) = random_model(&cfg);
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &cfg, &varmap).unwrap();
        let mut tensors =
            candle_core::safetensors::load(dir.path().join(WEIGHTS_FILE), &Device::Cpu).unwrap();
        let name = "decoder.layers.1.mlp.fc1.weight";
        tensors.insert(name.to_string(), Tensor::zeros((3, 4), DType::F32, &Device::Cpu).unwrap());
        candle_core::safetensors::save(&tensors, dir.path().join(WEIGHTS_FILE)).unwrap();
        let err = load(dir.path(), &Device::Cpu).unwrap_err();
        match &err {
            ModelError::ShapeMismatch { name: n, expected, found, .. } => {
                assert_eq!(n, name);
                assert_eq!(expected, &vec![64, 32]);
                assert_eq!(found, &vec![3, 4]);
            }
            other => panic!("unexpected {other}"),
        }
        assert!(err.to_string().contains(name), "{err}");
        let (fresh, _) = random_model(&cfg);
        assert!(matches!(
            load_into_varmap(dir.path(), &fresh, &Device::Cpu),
            Err(ModelError::ShapeMismatch { .. })
        ));
    }

    #[test]
    fn missing_and_extra_tensors_are_named() {
        let cfg = FaceConfig::micro();
        let (varmap, _) = random_model(&cfg);
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &cfg, &varmap).unwrap();
        let path = dir.path().join(WEIGHTS_FILE);
        let mut tensors = candle_core::safetensors::load(&path, &Device::Cpu).unwrap();
        tensors.remove("head.sub.3.fc2.bias");
        candle_core::safetensors::save(&tensors, &path).unwrap();
        let err = load(dir.path(), &Device::Cpu).unwrap_err();
        assert!(
            matches!(&err, ModelError::MissingTensor { name, .. } if name == "head.sub.3.fc2.bias"),
            "{err}"
        );

        let mut tensors = candle_core::safetensors::load(&path, &Device::Cpu).unwrap();
        tensors.insert(
            "head.sub.3.fc2.bias".into(),
            Tensor::zeros(16, DType::F32, &Device::Cpu).unwrap(),
        );
        tensors.insert("stray".into(), Tensor::zeros(1, DType::F32, &Device::Cpu).unwrap());
        candle_core::safetensors::save(&tensors, &path).unwrap();
        let err = load(dir.path(), &Device::Cpu).unwrap_err();
        assert!(
            matches!(&err, ModelError::UnexpectedTensors { names, .. } if names == &["stray"]),
            "{err}"
        );

        assert!(matches!(load(&dir.path().join("nope"), &Device::Cpu), Err(ModelError::Io { .. })));
    }
}
