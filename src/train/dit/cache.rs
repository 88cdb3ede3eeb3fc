//! The latent cache: every training mesh, augmented a few times, encoded once by the frozen
//! autoencoder (its latents C, K x d) and rendered from a few random views. Built once per
//! run, stored in the run folder with a description of what it was built from, and checked
//! against that description when the run resumes. A cache is a pure function of its
//! [`CacheSpec`]: each augmented copy draws from its own random stream.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{Device, Tensor};
use indicatif::{ProgressBar, ProgressStyle};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::diffusion::{LatentStats, latent_stats};
use crate::mesh::Mesh;
use crate::model::checkpoint::{Fnv1a, weight_files};
use crate::model::{FaceConfig, FaceModel, TrainBatch};
use crate::tokenize::Quantizer;

use super::super::TrainError;
use super::super::augment::{AugmentConfig, augment};
use super::super::batch::{SampleConfig, TrainingSample, prepare_sample};
use super::super::dataset::{UpAxes, load_folder};
use super::super::evaluate::example;
use super::super::procedural::ProceduralShapes;
use super::views::{ViewConfig, render_rgb};

const TENSORS_FILE: &str = "cache.safetensors";
const INFO_FILE: &str = "cache.json";
/// Augmented copies prepared (in parallel) and then encoded together per progress update.
const CHUNK: usize = 64;
/// Rows per forward pass of the autoencoder's encoder.
const ENCODE_BATCH: usize = 32;

/// Which autoencoder encoded the cache: its configuration and a fingerprint of its weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AutoencoderId {
    pub config: FaceConfig,
    /// Bytes of the weight files.
    pub weights_bytes: u64,
    /// FNV-1a (64 bit) of `model.safetensors` in hex; of a sharded model, of its shards one
    /// after the other in index order (the index itself is not hashed: the shards hold every
    /// name and value). Single-file ids are what they were before shards; the shards of the
    /// same weights hash differently, so a run started on one layout refuses the other.
    pub weights_fnv1a: String,
}

impl AutoencoderId {
    pub fn of(dir: &Path) -> Result<Self, TrainError> {
        let config = crate::model::checkpoint::load_config(dir)?;
        let mut hash = Fnv1a::default();
        let mut weights_bytes = 0;
        for path in weight_files(dir)? {
            let bytes = std::fs::read(&path).map_err(TrainError::io(&path))?;
            hash.write(&bytes);
            weights_bytes += bytes.len() as u64;
        }
        Ok(Self { config, weights_bytes, weights_fnv1a: hash.hex() })
    }
}

/// Everything a cache is built from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CacheSpec {
    pub autoencoder: AutoencoderId,
    /// Folder of meshes (its `split` rows with a manifest); none: procedural shapes only.
    pub data: Option<PathBuf>,
    pub split: String,
    /// The folder's meshes that stand on another axis than y, stood on y when loaded. Caches
    /// from before it had none.
    #[serde(default, skip_serializing_if = "UpAxes::is_empty")]
    pub up_axes: UpAxes,
    /// Procedural shapes added to the folder's meshes (drawn from `seed`).
    pub procedural: usize,
    /// Augmented copies per mesh.
    pub augmentations: usize,
    /// Rendered views per copy.
    pub views: usize,
    pub augment: AugmentConfig,
    pub view: ViewConfig,
    pub seed: u64,
}

/// What was left out while building, and why.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CacheSkips {
    pub unreadable: usize,
    pub no_faces: usize,
    pub over_face_limit: usize,
    /// Augmented copies dropped: over the face limit after augmentation, degenerate, or
    /// unrenderable.
    pub copies: usize,
}

/// The cache's description, stored as `cache.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CacheInfo {
    pub spec: CacheSpec,
    pub meshes: usize,
    /// Augmented copies kept: rows of the cache.
    pub entries: usize,
    pub skipped: CacheSkips,
    pub build_seconds: f64,
}

/// Latents (entries x K x d, f32) and views (entries x views x S x S x 3, u8) in memory.
pub struct LatentCache {
    pub info: CacheInfo,
    latents: Vec<f32>,
    images: Vec<u8>,
}

/// One augmented copy before encoding.
struct Prepared {
    sample: TrainingSample,
    views: Vec<u8>,
}

impl LatentCache {
    /// Builds the cache of `spec` with `autoencoder` (the model `spec.autoencoder` describes).
    pub fn build(
        spec: &CacheSpec,
        autoencoder: &FaceModel,
        progress: bool,
    ) -> Result<Self, TrainError> {
        let start = Instant::now();
        let ae = &spec.autoencoder.config;
        let (sources, mut skipped) = source_meshes(spec)?;
        let copies = sources.len() * spec.augmentations;
        if copies == 0 || spec.views == 0 {
            return Err(TrainError::Config(
                "the latent cache would be empty: no training meshes, augmentations or views"
                    .into(),
            ));
        }
        let sample_cfg = SampleConfig::for_model(ae, AugmentConfig::OFF)?;
        let bar = progress_bar(copies as u64, progress);
        let mut cache = Self {
            info: CacheInfo {
                spec: spec.clone(),
                meshes: sources.len(),
                entries: 0,
                skipped: CacheSkips::default(),
                build_seconds: 0.0,
            },
            latents: Vec::new(),
            images: Vec::new(),
        };
        for chunk_start in (0..copies).step_by(CHUNK) {
            let chunk_end = (chunk_start + CHUNK).min(copies);
            let prepared: Vec<Option<Prepared>> = (chunk_start..chunk_end)
                .into_par_iter()
                .map(|j| {
                    let (name, mesh) = &sources[j / spec.augmentations];
                    prepare_copy(spec, &sample_cfg, name, mesh, j as u64)
                })
                .collect();
            skipped.copies += prepared.iter().filter(|p| p.is_none()).count();
            let kept: Vec<Prepared> = prepared.into_iter().flatten().collect();
            for group in kept.chunks(ENCODE_BATCH) {
                let examples: Vec<_> = group.iter().map(|p| example(&p.sample)).collect();
                let batch = TrainBatch::new(&examples, autoencoder.device())?;
                let latents =
                    autoencoder.encode(&batch.points, &batch.normals, &batch.query_indices)?;
                cache.latents.extend(latents.flatten_all()?.to_vec1::<f32>()?);
                for p in group {
                    cache.images.extend_from_slice(&p.views);
                }
                cache.info.entries += group.len();
            }
            bar.set_position(chunk_end as u64);
        }
        bar.finish_and_clear();
        if cache.info.entries == 0 {
            return Err(TrainError::Config(
                "every augmented copy was skipped: the latent cache is empty".into(),
            ));
        }
        cache.info.skipped = skipped;
        cache.info.build_seconds = start.elapsed().as_secs_f64();
        Ok(cache)
    }

    pub fn len(&self) -> usize {
        self.info.entries
    }

    pub fn is_empty(&self) -> bool {
        self.info.entries == 0
    }

    fn latent_len(&self) -> usize {
        let ae = &self.info.spec.autoencoder.config;
        ae.num_latents * ae.latent_dim
    }

    fn image_len(&self) -> usize {
        let s = self.info.spec.view.size as usize;
        s * s * 3
    }

    /// The latents of entry `i` (K x d, row-major).
    pub fn latent(&self, i: usize) -> Option<&[f32]> {
        let n = self.latent_len();
        self.latents.get(i * n..(i + 1) * n)
    }

    /// View `v` of entry `i` (S x S x 3 bytes, row-major RGB).
    pub fn image(&self, i: usize, v: usize) -> Option<&[u8]> {
        let n = self.image_len();
        let k = i * self.info.spec.views + v;
        if v >= self.info.spec.views {
            return None;
        }
        self.images.get(k * n..(k + 1) * n)
    }

    /// All latents as one (entries, K, d) tensor.
    pub fn latents_tensor(&self, device: &Device) -> candle_core::Result<Tensor> {
        let ae = &self.info.spec.autoencoder.config;
        Tensor::from_slice(&self.latents, (self.len(), ae.num_latents, ae.latent_dim), device)
    }

    /// Per-channel statistics of the cached latents, for the DiT's normalization.
    pub fn stats(&self, min_std: f32) -> Result<LatentStats, TrainError> {
        Ok(latent_stats(&self.latents_tensor(&Device::Cpu)?, min_std)?)
    }

    /// Writes the cache into `dir` (created if needed); the description last, so a folder
    /// with a description always has its tensors.
    pub fn save(&self, dir: &Path) -> Result<(), TrainError> {
        std::fs::create_dir_all(dir).map_err(TrainError::io(dir))?;
        let info_path = dir.join(INFO_FILE);
        if info_path.exists() {
            std::fs::remove_file(&info_path).map_err(TrainError::io(&info_path))?;
        }
        let spec = &self.info.spec;
        let s = spec.view.size as usize;
        let tensors = HashMap::from([
            ("latents".to_string(), self.latents_tensor(&Device::Cpu)?),
            (
                "images".to_string(),
                Tensor::from_slice(&self.images, (self.len(), spec.views, s, s, 3), &Device::Cpu)?,
            ),
        ]);
        candle_core::safetensors::save(&tensors, dir.join(TENSORS_FILE))?;
        let json = serde_json::to_string_pretty(&self.info)
            .map_err(|e| TrainError::Json(e.to_string()))?;
        std::fs::write(&info_path, json).map_err(TrainError::io(&info_path))
    }

    /// The cache in `dir`, if there is one: its description and tensor shapes checked.
    pub fn load(dir: &Path) -> Result<Option<Self>, TrainError> {
        let info_path = dir.join(INFO_FILE);
        if !info_path.is_file() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&info_path).map_err(TrainError::io(&info_path))?;
        let info: CacheInfo = serde_json::from_str(&text)
            .map_err(|e| TrainError::Json(format!("{}: {e}", info_path.display())))?;
        let path = dir.join(TENSORS_FILE);
        let tensors = candle_core::safetensors::load(&path, &Device::Cpu)?;
        let bad = |message: String| TrainError::Weights { path: path.clone(), message };
        let get = |name: &str| tensors.get(name).ok_or_else(|| bad(format!("no tensor '{name}'")));
        let (latents, images) = (get("latents")?, get("images")?);
        let spec = &info.spec;
        let s = spec.view.size as usize;
        let (k, d) = (spec.autoencoder.config.num_latents, spec.autoencoder.config.latent_dim);
        if latents.dims() != [info.entries, k, d]
            || images.dims() != [info.entries, spec.views, s, s, 3]
        {
            return Err(bad(format!(
                "shapes {:?} and {:?} do not match {}",
                latents.dims(),
                images.dims(),
                info_path.display()
            )));
        }
        Ok(Some(Self {
            latents: latents.flatten_all()?.to_vec1::<f32>()?,
            images: images.flatten_all()?.to_vec1::<u8>()?,
            info,
        }))
    }
}

/// The training meshes (normalized): the folder's split, then the procedural shapes.
fn source_meshes(spec: &CacheSpec) -> Result<(Vec<(String, Mesh)>, CacheSkips), TrainError> {
    let ae = &spec.autoencoder.config;
    let q = Quantizer::new(
        u16::try_from(ae.quant_levels)
            .map_err(|_| TrainError::Config("quant_levels too large".into()))?,
    )?;
    let mut sources = Vec::new();
    let mut skipped = CacheSkips::default();
    if let Some(dir) = &spec.data {
        let folder = load_folder(dir, Some(&spec.split), ae.max_faces, q, &spec.up_axes)?;
        skipped.unreadable = folder.skipped.unreadable.len();
        skipped.no_faces = folder.skipped.no_faces;
        skipped.over_face_limit = folder.skipped.over_face_limit;
        sources.extend(folder.meshes.into_iter().map(|r| (r.name, r.mesh)));
    }
    let shapes = ProceduralShapes::new(spec.seed, ae.max_faces).on_grid(q);
    for (i, (kind, mesh)) in shapes.take(spec.procedural).enumerate() {
        match mesh.normalized() {
            Ok((normalized, _)) => {
                sources.push((format!("procedural-{i:05}-{kind:?}"), normalized))
            }
            Err(_) => skipped.no_faces += 1,
        }
    }
    Ok((sources, skipped))
}

/// Augmented copy `index` of a mesh: the encoder's input sampled from it, and its views.
/// `None` when the copy cannot be used (counted by the caller).
fn prepare_copy(
    spec: &CacheSpec,
    sample_cfg: &SampleConfig,
    name: &str,
    mesh: &Mesh,
    index: u64,
) -> Option<Prepared> {
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
    rng.set_stream(index);
    let augmented = augment(mesh, &spec.augment, &mut rng);
    let max_faces = spec.autoencoder.config.max_faces;
    // Sampling normalizes the augmented mesh itself; the views must show that same frame.
    let sample = prepare_sample(name, &augmented, sample_cfg, max_faces, &mut rng).ok()??;
    let (normalized, _) = augmented.normalized().ok()?;
    let mut views = Vec::with_capacity(spec.views * (spec.view.size as usize).pow(2) * 3);
    for _ in 0..spec.views {
        views.extend(render_rgb(&normalized, &spec.view.random(&mut rng)).ok()?);
    }
    Some(Prepared { sample, views })
}

fn progress_bar(total: u64, visible: bool) -> ProgressBar {
    if !visible {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(total);
    if let Ok(style) = ProgressStyle::with_template(
        "latent cache {elapsed_precise} [{bar:30}] {pos}/{len} copies {per_sec} ETA {eta}",
    ) {
        bar.set_style(style.progress_chars("=> "));
    }
    bar
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::checkpoint::WEIGHTS_FILE;

    /// The repository's default autoencoder, with the spec of a small procedural cache.
    fn spec_and_model(seed: u64) -> (CacheSpec, FaceModel) {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default");
        let model = crate::model::checkpoint::load(&dir, &Device::Cpu).unwrap();
        let spec = CacheSpec {
            autoencoder: AutoencoderId::of(&dir).unwrap(),
            data: None,
            split: "train".into(),
            up_axes: UpAxes::default(),
            procedural: 3,
            augmentations: 2,
            views: 2,
            augment: AugmentConfig::default(),
            view: ViewConfig::new(16),
            seed,
        };
        (spec, model)
    }

    #[test]
    fn cache_is_deterministic_has_the_right_shapes_and_round_trips() {
        let (spec, model) = spec_and_model(5);
        let a = LatentCache::build(&spec, &model, false).unwrap();
        let b = LatentCache::build(&spec, &model, false).unwrap();
        assert_eq!(a.info.meshes, 3);
        assert_eq!(a.len() + a.info.skipped.copies, 6);
        assert!(a.len() >= 4, "{:?}", a.info.skipped);
        assert_eq!(a.latents, b.latents);
        assert_eq!(a.images, b.images);
        assert_eq!(a.latent(0).unwrap().len(), 128 * 64);
        assert_eq!(a.image(0, 1).unwrap().len(), 16 * 16 * 3);
        assert!(a.image(0, 2).is_none() && a.latent(a.len()).is_none());
        // Two views of one copy differ (random cameras), as do two copies' latents.
        assert_ne!(a.image(0, 0), a.image(0, 1));
        assert_ne!(a.latent(0), a.latent(1));

        let (other, _) = spec_and_model(6);
        let c = LatentCache::build(&other, &model, false).unwrap();
        assert_ne!(a.latents, c.latents);

        let dir = tempfile::tempdir().unwrap();
        a.save(dir.path()).unwrap();
        let loaded = LatentCache::load(dir.path()).unwrap().unwrap();
        assert_eq!(loaded.info, a.info);
        assert_eq!(loaded.latents, a.latents);
        assert_eq!(loaded.images, a.images);
        assert!(LatentCache::load(&dir.path().join("none")).unwrap().is_none());
    }

    #[test]
    fn stats_are_per_channel_over_every_latent() {
        let (spec, model) = spec_and_model(1);
        let cache = LatentCache::build(&spec, &model, false).unwrap();
        let stats = cache.stats(1e-3).unwrap();
        assert_eq!(stats.mean.len(), 64);
        let channel0: Vec<f32> = cache.latents.iter().step_by(64).copied().collect();
        let mean = channel0.iter().sum::<f32>() / channel0.len() as f32;
        let var = channel0.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / channel0.len() as f32;
        assert!((stats.mean[0] - mean).abs() < 1e-4);
        assert!((stats.std[0] - var.sqrt().max(1e-3)).abs() < 1e-4);
        assert!(stats.std.iter().all(|s| *s >= 1e-3));
    }

    #[test]
    fn autoencoder_id_of_shards_hashes_them_in_order() {
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default");
        let dir = tempfile::tempdir().unwrap();
        crate::train::checkpoint::export(&src, dir.path(), candle_core::DType::F16, 1 << 20)
            .unwrap();
        let shards = weight_files(dir.path()).unwrap();
        assert!(shards.len() > 1);
        let mut hash = Fnv1a::default();
        let mut bytes = 0;
        for shard in &shards {
            let data = std::fs::read(shard).unwrap();
            hash.write(&data);
            bytes += data.len() as u64;
        }
        let id = AutoencoderId::of(dir.path()).unwrap();
        assert_eq!((id.weights_bytes, id.weights_fnv1a), (bytes, hash.hex()));
    }

    #[test]
    fn autoencoder_id_notices_changed_weights() {
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default");
        let dir = tempfile::tempdir().unwrap();
        for f in ["config.json", WEIGHTS_FILE] {
            std::fs::copy(src.join(f), dir.path().join(f)).unwrap();
        }
        let a = AutoencoderId::of(dir.path()).unwrap();
        assert_eq!(a, AutoencoderId::of(&src).unwrap());
        let mut bytes = std::fs::read(dir.path().join(WEIGHTS_FILE)).unwrap();
        let last = bytes.len() - 1;
        bytes[last] ^= 1;
        std::fs::write(dir.path().join(WEIGHTS_FILE), bytes).unwrap();
        assert_ne!(a, AutoencoderId::of(dir.path()).unwrap());
    }
}
