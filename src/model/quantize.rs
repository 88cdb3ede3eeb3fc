//! Quantized inference: the linear layers of the encoder, the face pooling, the decoder and the
//! head in a GGUF block type (Q8_0 or Q4K), multiplied by candle's quantized CPU kernels. The
//! choice is made when a model is loaded: from its f32 weights, or from a quantized model file
//! (`model.gguf` beside `config.json`) that is used as it is, without quantizing again.
//!
//! A block never spans two rows of a weight, so a layer quantizes only when its input features
//! are a multiple of the block size (32 for Q8_0, 256 for Q4K); the others stay f32, and the
//! [`QuantizeReport`] names them. Norms, embeddings, biases and the start token stay f32.

use std::collections::{BTreeMap, HashMap};
use std::fmt;
use std::path::Path;
use std::str::FromStr;
use std::sync::Arc;

use candle_core::quantized::{GgmlDType, QTensor, gguf_file};
use candle_core::{DType, Device, Tensor};

use super::checkpoint::{self, CONFIG_FILE, ModelWeights, build_from_tensors, io_err};
use super::{FaceModel, ModelError, Result};

/// The weights of a quantized model folder, beside `config.json`.
pub const QUANTIZED_WEIGHTS_FILE: &str = "model.gguf";
/// The GGUF metadata key naming the block type of the quantized layers.
const QUANTIZE_KEY: &str = "meshstream.quantize";

/// The number format of the linear layers' weights at inference.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Hash)]
pub enum Quantize {
    #[default]
    F32,
    /// 8-bit values in blocks of 32 with one f16 scale (8.5 bits a weight).
    Q8_0,
    /// 4-bit values in super-blocks of 256 with 6-bit scales and minimums (4.5 bits a weight).
    Q4K,
}

impl Quantize {
    pub const ALL: [Self; 3] = [Self::F32, Self::Q8_0, Self::Q4K];

    pub fn name(self) -> &'static str {
        match self {
            Self::F32 => "f32",
            Self::Q8_0 => "q8_0",
            Self::Q4K => "q4k",
        }
    }

    /// The GGUF block type; `None` for f32.
    pub fn block_type(self) -> Option<GgmlDType> {
        match self {
            Self::F32 => None,
            Self::Q8_0 => Some(GgmlDType::Q8_0),
            Self::Q4K => Some(GgmlDType::Q4K),
        }
    }
}

impl fmt::Display for Quantize {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Quantize {
    type Err = ModelError;

    fn from_str(s: &str) -> Result<Self> {
        Self::ALL.into_iter().find(|q| q.name() == s.trim().to_ascii_lowercase()).ok_or_else(|| {
            ModelError::bad_input(format!("unknown quantization {s:?}: expected f32, q8_0 or q4k"))
        })
    }
}

/// What a model's linear layers hold after loading.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct QuantizeReport {
    pub quantize: Quantize,
    /// Layers in the quantized block type.
    pub quantized: usize,
    /// Layers kept f32 because their input features are not a multiple of the block size:
    /// (name, input features).
    pub kept: Vec<(String, usize)>,
    /// The encoder's layers kept f32 (see [`FaceModel::quantize`]).
    pub encoder_f32: usize,
}

impl fmt::Display for QuantizeReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let Some(block) = self.quantize.block_type() else {
            let layers = self.kept.len() + self.encoder_f32;
            return write!(f, "f32 weights ({layers} linear layers)");
        };
        write!(f, "{}: {} linear layers quantized", self.quantize, self.quantized)?;
        if self.encoder_f32 > 0 {
            write!(f, ", the encoder's {} kept f32 (faster on its many rows)", self.encoder_f32)?;
        }
        if !self.kept.is_empty() {
            let kept: Vec<String> =
                self.kept.iter().map(|(name, input)| format!("{name} ({input} in)")).collect();
            write!(
                f,
                ", {} kept f32 (input features not a multiple of {}): {}",
                self.kept.len(),
                block.block_size(),
                kept.join(", ")
            )?;
        }
        Ok(())
    }
}

impl FaceModel {
    /// Quantizes every linear layer of the decoding (face pooling, decoder, head) whose input
    /// features fit `quantize`'s block size; f32 leaves the model as it is. The encoder stays
    /// f32: it multiplies every input point (1,024 rows) once per request, where gemm is
    /// faster than candle's quantized kernels, which multiply row by row: q8_0 encoded a cloud
    /// in 62 ms against f32's 21 and doubled the time to first face (docs/decisions.md,
    /// "Quantized inference").
    pub fn quantize(&mut self, quantize: Quantize) -> Result<QuantizeReport> {
        if let Some(block) = quantize.block_type() {
            for layer in self.decoding_dense_mut() {
                layer.quantize(block)?;
            }
        }
        self.quantize_report(quantize)
    }

    fn quantize_report(&mut self, quantize: Quantize) -> Result<QuantizeReport> {
        let mut report =
            QuantizeReport { quantize, quantized: 0, kept: Vec::new(), encoder_f32: 0 };
        for layer in self.encoder_dense_mut() {
            match layer.quantized_weight() {
                Some(_) => report.quantized += 1,
                None => report.encoder_f32 += 1,
            }
        }
        for layer in self.decoding_dense_mut() {
            if layer.quantized_weight().is_some() {
                report.quantized += 1;
            } else {
                let name = layer.name().unwrap_or_default().to_string();
                report.kept.push((name, layer.features()?.0));
            }
        }
        Ok(report)
    }

    /// The quantized weights by tensor name (`{layer}.weight`).
    fn quantized_weights(&mut self) -> HashMap<String, Arc<QTensor>> {
        self.dense_mut()
            .into_iter()
            .filter_map(|l| Some((format!("{}.weight", l.name()?), l.quantized_weight()?.clone())))
            .collect()
    }
}

/// Whether `dir` holds a quantized model file.
pub fn is_quantized_dir(dir: &Path) -> bool {
    dir.join(QUANTIZED_WEIGHTS_FILE).is_file()
}

/// Loads the model in `dir` with its linear layers in `quantize`. A folder with a quantized
/// model file loads as it was written; asking it for another quantization is an error (it
/// would need the f32 weights).
pub fn load_quantized(
    dir: &Path,
    device: &Device,
    quantize: Quantize,
) -> Result<(FaceModel, QuantizeReport)> {
    if is_quantized_dir(dir) {
        if checkpoint::weight_files(dir).is_ok_and(|files| !files.is_empty()) {
            return Err(ModelError::BadCheckpoint {
                path: dir.to_path_buf(),
                message: format!(
                    "holds both f32 weights and {QUANTIZED_WEIGHTS_FILE}; remove one of the two"
                ),
            });
        }
        let (mut model, stored) = load_gguf(dir, device)?;
        if quantize != Quantize::F32 && quantize != stored {
            return Err(ModelError::bad_input(format!(
                "{} holds {stored} weights; {quantize} needs a folder with the f32 weights",
                dir.display()
            )));
        }
        let report = model.quantize_report(stored)?;
        return Ok((model, report));
    }
    let mut model = checkpoint::load(dir, device)?;
    let report = model.quantize(quantize)?;
    Ok((model, report))
}

/// Writes the model in `from` (f32 weights) to `to` as `config.json` and `model.gguf`, its
/// linear layers quantized to `quantize`, every other tensor f32.
pub fn export_quantized(from: &Path, to: &Path, quantize: Quantize) -> Result<QuantizeReport> {
    if quantize == Quantize::F32 {
        return Err(ModelError::bad_input("export a quantized model: q8_0 or q4k, not f32"));
    }
    if is_quantized_dir(from) {
        return Err(ModelError::bad_input(format!(
            "{} is already quantized; export from the f32 weights",
            from.display()
        )));
    }
    if checkpoint::weight_files(to).is_ok_and(|files| !files.is_empty()) {
        return Err(ModelError::bad_input(format!(
            "{} holds f32 weights: write the quantized model to a folder of its own",
            to.display()
        )));
    }
    let device = Device::Cpu;
    let cfg = checkpoint::load_config(from)?;
    let mut model = checkpoint::load(from, &device)?;
    let report = model.quantize(quantize)?;
    let mut quantized = model.quantized_weights();
    let ModelWeights { tensors, .. } = checkpoint::read_model_weights(from, &device)?;
    let tensors: BTreeMap<String, Tensor> = tensors.into_iter().collect();
    let mut stored = Vec::with_capacity(tensors.len());
    for (name, t) in &tensors {
        let q = match quantized.remove(name) {
            Some(q) => q,
            None => Arc::new(QTensor::quantize(&t.to_dtype(DType::F32)?, GgmlDType::F32)?),
        };
        stored.push((name.as_str(), q));
    }
    std::fs::create_dir_all(to).map_err(io_err(to))?;
    let cfg_path = to.join(CONFIG_FILE);
    let json = serde_json::to_string_pretty(&cfg).map_err(|e| ModelError::BadCheckpoint {
        path: cfg_path.clone(),
        message: e.to_string(),
    })?;
    std::fs::write(&cfg_path, json).map_err(io_err(&cfg_path))?;
    let path = to.join(QUANTIZED_WEIGHTS_FILE);
    let mut file = std::fs::File::create(&path).map_err(io_err(&path))?;
    let kind = gguf_file::Value::String(quantize.name().to_string());
    let tensors: Vec<(&str, &QTensor)> = stored.iter().map(|(n, q)| (*n, q.as_ref())).collect();
    gguf_file::write(&mut file, &[(QUANTIZE_KEY, &kind)], &tensors)?;
    Ok(report)
}

/// A quantized model folder: every tensor from `model.gguf` (f32 ones as they are, the others
/// dequantized only to build the model), then the quantized weights put into their layers.
fn load_gguf(dir: &Path, device: &Device) -> Result<(FaceModel, Quantize)> {
    let cfg = checkpoint::load_config(dir)?;
    let path = dir.join(QUANTIZED_WEIGHTS_FILE);
    let bad = |message: String| ModelError::BadCheckpoint { path: path.clone(), message };
    let mut file = std::fs::File::open(&path).map_err(io_err(&path))?;
    let content = gguf_file::Content::read(&mut file).map_err(|e| bad(e.to_string()))?;
    let quantize: Quantize = content
        .metadata
        .get(QUANTIZE_KEY)
        .and_then(|v| v.to_string().ok())
        .ok_or_else(|| bad(format!("no {QUANTIZE_KEY} metadata")))?
        .parse()?;
    let mut tensors = HashMap::new();
    let mut quantized = HashMap::new();
    for name in content.tensor_infos.keys() {
        let q = content.tensor(&mut file, name, device).map_err(|e| bad(e.to_string()))?;
        tensors.insert(name.clone(), q.dequantize(device)?);
        if q.dtype() != GgmlDType::F32 {
            quantized.insert(name.clone(), Arc::new(q));
        }
    }
    let mut model = build_from_tensors(&path, tensors, device, |vb| FaceModel::new(&cfg, vb))?;
    for layer in model.dense_mut() {
        let Some(name) = layer.name().map(|n| format!("{n}.weight")) else { continue };
        if let Some(weight) = quantized.remove(&name) {
            layer.set_quantized(weight)?;
        }
    }
    if !quantized.is_empty() {
        let mut names: Vec<String> = quantized.into_keys().collect();
        names.sort();
        return Err(bad(format!("quantized tensors that are no linear layer's weight: {names:?}")));
    }
    Ok((model, quantize))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::FaceConfig;
    use crate::model::testing::{max_abs_diff, random_latents, random_model};

    /// A config whose layers partly fit Q4K's 256-wide blocks: the decoder (256 wide) does,
    /// the encoder (64 wide) does not.
    fn mixed_config() -> FaceConfig {
        let mut cfg = FaceConfig::micro();
        cfg.decoder.width = 256;
        cfg.decoder.mlp_hidden = 256;
        cfg.head_hidden = 256;
        cfg.encoder.width = 64;
        cfg.encoder.mlp_hidden = 64;
        cfg.coord_embed_dim = 32;
        cfg.latent_dim = 32;
        cfg
    }

    fn first_step(model: &FaceModel, latents: &Tensor) -> (Tensor, Tensor) {
        let mut s = model.start_sequence(latents).unwrap();
        let hidden = model.step(&mut [&mut s]).unwrap();
        let logits = model.head_logits(0, &hidden).unwrap();
        (hidden, logits)
    }

    /// ||a - b|| / ||b||.
    fn relative_error(a: &Tensor, b: &Tensor) -> f32 {
        let norm = |t: &Tensor| t.sqr().unwrap().sum_all().unwrap().to_scalar::<f32>().unwrap();
        (norm(&(a - b).unwrap()) / norm(b)).sqrt()
    }

    #[test]
    fn quantized_layers_agree_with_f32_within_their_precision() {
        let cfg = mixed_config();
        let (_, model) = random_model(&cfg);
        let latents = random_latents(&cfg, 1, 3);
        let (hidden, logits) = first_step(&model, &latents);
        for (quantize, tolerance) in [(Quantize::Q8_0, 0.06), (Quantize::Q4K, 0.5)] {
            let mut q = model.clone();
            let report = q.quantize(quantize).unwrap();
            assert!(report.quantized > 0, "{report}");
            let (qh, ql) = first_step(&q, &latents);
            let (eh, el) = (relative_error(&qh, &hidden), relative_error(&ql, &logits));
            assert!(eh > 0.0, "{quantize} changed nothing");
            assert!(eh < tolerance && el < tolerance, "{quantize}: hidden {eh}, logits {el}");
        }
    }

    #[test]
    fn layers_that_do_not_fit_the_blocks_stay_f32() {
        let cfg = mixed_config();
        let (_, model) = random_model(&cfg);
        let mut q8 = model.clone();
        let report = q8.quantize(Quantize::Q8_0).unwrap();
        // Every micro decoding layer takes a multiple of 32 inputs; the encoder stays f32.
        assert_eq!(report.kept, [], "{report}");
        let mut f32_model = model.clone();
        assert_eq!(report.encoder_f32, f32_model.encoder_dense_mut().len());
        assert!(report.to_string().contains("encoder's"), "{report}");
        assert!(q8.encoder_dense_mut().iter().all(|l| l.quantized_weight().is_none()));

        let mut q4 = model.clone();
        let report = q4.quantize(Quantize::Q4K).unwrap();
        assert!(report.kept.iter().all(|(_, input)| input % 256 != 0), "{report}");
        assert!(report.kept.iter().all(|(n, _)| !n.starts_with("encoder.")), "{report}");
        assert!(report.kept.iter().all(|(n, _)| !n.starts_with("decoder.layers")), "{report}");
        assert!(report.to_string().contains("not a multiple of 256"), "{report}");
        // Sub-head 1 takes 256 + 1 * coord_embed_dim inputs.
        assert!(report.kept.iter().any(|(n, _)| n == "head.sub.1.fc1"), "{report}");
        assert!(report.kept.iter().all(|(n, _)| n != "head.sub.0.fc1"), "{report}");
    }

    #[test]
    fn a_bad_quantize_value_is_a_clear_error() {
        assert_eq!("Q8_0".parse::<Quantize>().unwrap(), Quantize::Q8_0);
        assert_eq!("q4k".parse::<Quantize>().unwrap(), Quantize::Q4K);
        let err = "q5".parse::<Quantize>().unwrap_err().to_string();
        assert!(err.contains("\"q5\"") && err.contains("f32, q8_0 or q4k"), "{err}");
    }

    #[test]
    fn an_exported_quantized_model_loads_as_quantized_without_quantizing_again() {
        let cfg = mixed_config();
        let (varmap, model) = random_model(&cfg);
        let f32_dir = tempfile::tempdir().unwrap();
        checkpoint::save(f32_dir.path(), &cfg, &varmap).unwrap();
        let q_dir = tempfile::tempdir().unwrap();
        let exported = export_quantized(f32_dir.path(), q_dir.path(), Quantize::Q8_0).unwrap();

        let (loaded, report) = load_quantized(q_dir.path(), &Device::Cpu, Quantize::F32).unwrap();
        assert_eq!(report, exported);
        let mut in_memory = model.clone();
        in_memory.quantize(Quantize::Q8_0).unwrap();
        let latents = random_latents(&cfg, 1, 8);
        let (a, b) = (first_step(&loaded, &latents), first_step(&in_memory, &latents));
        assert_eq!(max_abs_diff(&a.1, &b.1), 0.0);
        // `checkpoint::load` finds the quantized file too.
        let plain = checkpoint::load(q_dir.path(), &Device::Cpu).unwrap();
        assert_eq!(max_abs_diff(&first_step(&plain, &latents).1, &b.1), 0.0);

        let err = load_quantized(q_dir.path(), &Device::Cpu, Quantize::Q4K).unwrap_err();
        assert!(err.to_string().contains("f32 weights"), "{err}");
        assert!(export_quantized(q_dir.path(), f32_dir.path(), Quantize::Q4K).is_err());
        assert!(export_quantized(f32_dir.path(), q_dir.path(), Quantize::F32).is_err());
    }
}
