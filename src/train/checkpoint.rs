//! Training checkpoints: everything a run needs to continue exactly (weights, optimizer
//! state, step, best score), written atomically; and exports with just what inference needs.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use serde::{Deserialize, Serialize};

use crate::model::checkpoint as model_checkpoint;
use crate::model::{FaceConfig, FaceModel};

use super::TrainError;
use super::optim::Optimizer;

const OPTIMIZER_FILE: &str = "optimizer.safetensors";
const STATE_FILE: &str = "state.json";
/// A checkpoint's subfolder with the run's weight average, a model folder of its own.
const AVERAGE_DIR: &str = "average";

/// Where a checkpoint written by [`save`] keeps the run's weight average, when it has one.
pub fn average_dir(checkpoint: &Path) -> PathBuf {
    checkpoint.join(AVERAGE_DIR)
}

/// Where a run keeps its files.
#[derive(Debug, Clone)]
pub struct RunDir(pub PathBuf);

impl RunDir {
    /// The run's full configuration (model, data, schedule).
    pub fn config(&self) -> PathBuf {
        self.0.join("train.json")
    }
    /// The latest checkpoint, for `--resume`.
    pub fn checkpoint(&self) -> PathBuf {
        self.0.join("checkpoint")
    }
    /// The exported weights with the best evaluation Chamfer distance so far.
    pub fn best(&self) -> PathBuf {
        self.0.join("best")
    }
    /// One JSON object per line: every step's metrics and every evaluation.
    pub fn log(&self) -> PathBuf {
        self.0.join("log.jsonl")
    }
    /// The diffusion runs' latent cache (latents and rendered views, with their description).
    pub fn latent_cache(&self) -> PathBuf {
        self.0.join("latent-cache")
    }
}

/// Progress that is not in the tensors.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct TrainState {
    pub step: u64,
    pub best_chamfer: Option<f64>,
    /// Wall time spent training before this session, in seconds.
    pub elapsed_s: f64,
}

impl TrainState {
    /// Records `chamfer` as the best so far when it is lower than every earlier one (an
    /// evaluation without a Chamfer distance never is); says whether it was.
    pub fn record_best(&mut self, chamfer: Option<f64>) -> bool {
        let better = match (chamfer, self.best_chamfer) {
            (Some(cd), Some(best)) => cd < best,
            (Some(_), None) => true,
            (None, _) => false,
        };
        if better {
            self.best_chamfer = chamfer;
        }
        better
    }
}

/// Writes a checkpoint into `dir`: to a sibling temporary folder first, then renamed, so an
/// interrupted save never leaves a half-written checkpoint behind. A run's weight average,
/// when it keeps one, goes into [`average_dir`].
pub fn save(
    dir: &Path,
    cfg: &impl Serialize,
    varmap: &VarMap,
    optimizer: &Optimizer,
    state: &TrainState,
    average: Option<&HashMap<String, Tensor>>,
) -> Result<(), TrainError> {
    let tmp = dir.with_extension("tmp");
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(TrainError::io(&tmp))?;
    }
    model_checkpoint::save_checkpoint(&tmp, cfg, varmap)?;
    if let Some(average) = average {
        model_checkpoint::write_model_dir(&average_dir(&tmp), cfg, average)?;
    }
    candle_core::safetensors::save(&optimizer.state()?, tmp.join(OPTIMIZER_FILE))?;
    let state_path = tmp.join(STATE_FILE);
    let json = serde_json::to_string_pretty(state).map_err(|e| TrainError::Json(e.to_string()))?;
    std::fs::write(&state_path, json).map_err(TrainError::io(&state_path))?;
    if dir.exists() {
        std::fs::remove_dir_all(dir).map_err(TrainError::io(dir))?;
    }
    std::fs::rename(&tmp, dir).map_err(TrainError::io(dir))?;
    Ok(())
}

/// Restores weights, optimizer state and progress from a checkpoint written by [`save`].
pub fn restore(
    dir: &Path,
    varmap: &VarMap,
    optimizer: &mut Optimizer,
    device: &Device,
) -> Result<TrainState, TrainError> {
    load_weights(dir, varmap, device)?;
    let opt_path = dir.join(OPTIMIZER_FILE);
    let state = candle_core::safetensors::load(&opt_path, device)?;
    optimizer.load_state(&state)?;
    let state_path = dir.join(STATE_FILE);
    let text = std::fs::read_to_string(&state_path).map_err(TrainError::io(&state_path))?;
    serde_json::from_str(&text)
        .map_err(|e| TrainError::Json(format!("{}: {e}", state_path.display())))
}

/// Sets every variable of `varmap` from the weights of a model directory (a checkpoint or an
/// export in any float type). Every variable must be there with its shape.
pub fn load_weights(dir: &Path, varmap: &VarMap, device: &Device) -> Result<(), TrainError> {
    let vars =
        varmap.data().lock().map_err(|_| TrainError::Json("variable map poisoned".into()))?;
    let shapes = vars.iter().map(|(name, var)| (name.clone(), var.dims().to_vec())).collect();
    for (name, tensor) in read_weights(dir, &shapes, device)? {
        if let Some(var) = vars.get(&name) {
            var.set(&tensor)?;
        }
    }
    Ok(())
}

/// The f32 weights of a model directory named in `shapes`, each checked to be there with its
/// shape.
pub fn read_weights(
    dir: &Path,
    shapes: &HashMap<String, Vec<usize>>,
    device: &Device,
) -> Result<HashMap<String, Tensor>, TrainError> {
    let model_checkpoint::ModelWeights { path, mut tensors } =
        model_checkpoint::read_model_weights(dir, device)?;
    let mut weights = HashMap::with_capacity(shapes.len());
    for (name, dims) in shapes {
        let t = tensors.remove(name).ok_or_else(|| TrainError::Weights {
            path: path.clone(),
            message: format!("no tensor '{name}'"),
        })?;
        if t.dims() != dims.as_slice() {
            return Err(TrainError::Weights {
                path: path.clone(),
                message: format!("tensor '{name}': expected shape {dims:?}, found {:?}", t.dims()),
            });
        }
        weights.insert(name.clone(), t.to_dtype(DType::F32)?);
    }
    Ok(weights)
}

/// A trained model's weights in a training `VarMap` on `device`: what a run started with
/// `--init` trains.
pub fn trainable_model(
    dir: &Path,
    device: &Device,
) -> Result<(FaceConfig, VarMap, FaceModel), TrainError> {
    let cfg = model_checkpoint::load_config(dir)?;
    let varmap = VarMap::new();
    let model = FaceModel::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F32, device))?;
    model_checkpoint::load_into_varmap(dir, &varmap, device)?;
    Ok((cfg, varmap, model))
}

/// Writes what inference needs (`config.json` + `model.safetensors`, no optimizer state) from
/// a checkpoint or model directory of a face autoencoder or a diffusion model, with the
/// weights stored as `dtype` (F16 halves the size). Weights with more than `max_shard_bytes`
/// of data are written as shards plus `model.safetensors.index.json`, so that every file fits
/// a transfer limit; the folder keeps no weight files of an earlier export.
pub fn export(
    from: &Path,
    to: &Path,
    dtype: DType,
    max_shard_bytes: u64,
) -> Result<(), TrainError> {
    let cfg = match model_checkpoint::load_config(from) {
        Ok(face) => AnyConfig::Face(face),
        Err(face_err) => match crate::diffusion::checkpoint::load_config(from) {
            Ok(dit) => AnyConfig::Dit(Box::new(dit)),
            Err(_) => return Err(face_err.into()),
        },
    };
    let tensors = model_checkpoint::read_model_weights(from, &Device::Cpu)?.tensors;
    let converted = tensors
        .into_iter()
        .map(|(name, t)| Ok((name, t.to_dtype(dtype)?)))
        .collect::<Result<HashMap<_, _>, candle_core::Error>>()?;
    model_checkpoint::write_sharded_model_dir(to, &cfg, &converted, max_shard_bytes)?;
    Ok(())
}

/// Parses a shard size for `--max-shard-size`: a positive number of bytes, optionally with a
/// unit (B, KB, MB, GB in powers of 1000; KiB, MiB, GiB in powers of 1024), e.g. `15MiB`.
pub fn parse_shard_size(text: &str) -> Result<u64, String> {
    let text = text.trim();
    let split = text.find(|c: char| !c.is_ascii_digit()).unwrap_or(text.len());
    let (number, unit) = text.split_at(split);
    let number: u64 = number.parse().map_err(|_| format!("{text:?} is not a byte count"))?;
    let scale: u64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1,
        "kb" => 1000,
        "mb" => 1000 * 1000,
        "gb" => 1000 * 1000 * 1000,
        "kib" => 1 << 10,
        "mib" => 1 << 20,
        "gib" => 1 << 30,
        other => {
            return Err(format!(
                "unknown unit {other:?} in {text:?} (B, KB, MB, GB, KiB, MiB, GiB)"
            ));
        }
    };
    match number.checked_mul(scale) {
        Some(0) => Err("the shard size must be positive".into()),
        Some(bytes) => Ok(bytes),
        None => Err(format!("{text:?} is too large")),
    }
}

/// The configuration of either kind of model, written as the model's own.
#[derive(Serialize)]
#[serde(untagged)]
enum AnyConfig {
    Face(FaceConfig),
    Dit(Box<crate::diffusion::DitConfig>),
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::FaceConfig;
    use crate::model::checkpoint::{WEIGHTS_FILE, WEIGHTS_INDEX_FILE, weight_files};
    use crate::model::testing::random_model;

    /// A run's model folder (f32) and the weights in it.
    fn model_dir() -> tempfile::TempDir {
        let cfg = FaceConfig::micro();
        let (varmap, _) = random_model(&cfg);
        let dir = tempfile::tempdir().unwrap();
        model_checkpoint::save(dir.path(), &cfg, &varmap).unwrap();
        dir
    }

    fn f32_weights(dir: &Path) -> HashMap<String, Vec<f32>> {
        let tensors = model_checkpoint::read_model_weights(dir, &Device::Cpu).unwrap().tensors;
        tensors
            .into_iter()
            .map(|(name, t)| {
                let values = t.to_dtype(DType::F32).unwrap().flatten_all().unwrap();
                (name, values.to_vec1().unwrap())
            })
            .collect()
    }

    #[test]
    fn a_sharded_export_holds_the_weights_of_the_single_file() {
        let run = model_dir();
        let out = tempfile::tempdir().unwrap();
        let single = out.path().join("single");
        export(run.path(), &single, DType::F16, model_checkpoint::DEFAULT_MAX_SHARD_BYTES).unwrap();
        assert!(single.join(WEIGHTS_FILE).is_file());
        assert!(!single.join(WEIGHTS_INDEX_FILE).exists());

        let sharded = out.path().join("sharded");
        export(run.path(), &sharded, DType::F16, 32 * 1024).unwrap();
        assert!(!sharded.join(WEIGHTS_FILE).exists());
        assert!(weight_files(&sharded).unwrap().len() > 1);
        assert_eq!(f32_weights(&sharded), f32_weights(&single));
        crate::model::checkpoint::load(&sharded, &Device::Cpu).unwrap();

        // Exporting from a sharded folder, and over one, gives the single file again.
        export(&sharded, &sharded, DType::F16, model_checkpoint::DEFAULT_MAX_SHARD_BYTES).unwrap();
        let bytes = |dir: &Path| std::fs::read(dir.join(WEIGHTS_FILE)).unwrap();
        assert_eq!(bytes(&sharded), bytes(&single));
        let mut left: Vec<_> = std::fs::read_dir(&sharded)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        left.sort();
        assert_eq!(left, vec!["config.json", WEIGHTS_FILE]);
    }

    #[test]
    fn read_weights_takes_shards() {
        let run = model_dir();
        let out = tempfile::tempdir().unwrap();
        export(run.path(), out.path(), DType::F32, 32 * 1024).unwrap();
        let (varmap, _) = random_model(&FaceConfig::micro());
        load_weights(out.path(), &varmap, &Device::Cpu).unwrap();
        let expected = f32_weights(run.path());
        for (name, var) in varmap.data().lock().unwrap().iter() {
            let values: Vec<f32> = var.as_tensor().flatten_all().unwrap().to_vec1().unwrap();
            assert_eq!(values, expected[name], "{name}");
        }
    }

    #[test]
    fn shard_sizes_take_units() {
        assert_eq!(parse_shard_size("15MiB"), Ok(15 << 20));
        assert_eq!(parse_shard_size(" 16 MB "), Ok(16_000_000));
        assert_eq!(parse_shard_size("1048576"), Ok(1 << 20));
        assert_eq!(parse_shard_size("2gib"), Ok(2 << 30));
        assert_eq!(parse_shard_size("512KB"), Ok(512_000));
        assert!(parse_shard_size("0MiB").is_err());
        assert!(parse_shard_size("MiB").is_err());
        assert!(parse_shard_size("1.5MiB").is_err());
        assert!(parse_shard_size("3 parsecs").is_err());
        assert!(parse_shard_size("99999999999999GiB").is_err());
    }

    #[test]
    fn only_a_lower_chamfer_distance_is_the_new_best() {
        let mut state = TrainState::default();
        assert!(!state.record_best(None), "an evaluation without CD is never the best");
        assert!(state.record_best(Some(0.5)), "the first CD is the best so far");
        assert!(!state.record_best(Some(0.5)), "a tie keeps the earlier weights");
        assert!(!state.record_best(Some(0.7)));
        assert!(!state.record_best(None));
        assert!(state.record_best(Some(0.3)));
        assert_eq!(state.best_chamfer, Some(0.3));
    }
}
