//! Checkpoints: `config.json` + `model.safetensors` in one directory. Loading checks every
//! tensor against the config and names the first one that is missing or has the wrong shape.

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{Init, VarBuilder, VarMap};

use super::{FaceConfig, FaceModel, ModelError, Result};

pub const CONFIG_FILE: &str = "config.json";
pub const WEIGHTS_FILE: &str = "model.safetensors";

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
