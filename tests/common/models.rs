//! Models with random weights (the same on every run), saved as trained ones are.

use std::path::Path;

use candle_core::{Device, Tensor};
use candle_nn::VarMap;
use meshstream::diffusion::{DiffusionModel, DitConfig};
use meshstream::model::{FaceConfig, FaceModel, checkpoint, seeded_var_builder};

/// A `tiny` image model.
pub fn random_image_model(dir: &Path) {
    let cfg = DitConfig::tiny();
    let varmap = VarMap::new();
    DiffusionModel::new(&cfg, seeded_var_builder(&varmap, 0, &Device::Cpu), None).unwrap();
    meshstream::diffusion::checkpoint::save(dir, &cfg, &varmap).unwrap();
}

/// A `tiny` face model whose first coordinate always says end of mesh: every mesh it decodes
/// is empty.
pub fn model_that_ends_at_once(dir: &Path) {
    let cfg = FaceConfig::tiny();
    let varmap = VarMap::new();
    FaceModel::new(&cfg, seeded_var_builder(&varmap, 0, &Device::Cpu)).unwrap();
    {
        let vars = varmap.data().lock().unwrap();
        let bias = &vars["head.sub.0.fc2.bias"];
        let mut values = bias.to_vec1::<f32>().unwrap();
        values[cfg.quant_levels] = 1e4;
        bias.set(&Tensor::new(values, &Device::Cpu).unwrap()).unwrap();
    }
    checkpoint::save(dir, &cfg, &varmap).unwrap();
}
