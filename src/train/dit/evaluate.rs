//! Evaluation of the DiT on held-aside meshes, end to end: one fixed view of each normalized
//! ground truth -> latents sampled by the DiT (Euler steps, classifier-free guidance, fixed
//! seed) -> greedy decoding by the frozen autoencoder -> Chamfer and Hausdorff distance to the
//! ground truth. Also the flow-matching loss on the ground truth's own latents.

use std::time::Instant;

use candle_core::Tensor;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::diffusion::DiffusionModel;
use crate::mesh::Mesh;
use crate::metrics::{
    EvalRecord, MetricOptions, Topology, TopologySummary, mesh_distances, summarize,
    summarize_topology, topology,
};
use crate::model::{FaceModel, GenerateOptions, TrainBatch};
use crate::tokenize::{Quantizer, detokenize};

use super::super::TrainError;
use super::super::batch::SampleConfig;
use super::super::dataset::FolderData;
use super::super::evaluate::{EvalSet, example, greedy_decode};
use super::views::{ViewConfig, images_tensor, render_rgb};

/// The held-aside meshes with their fixed view and their autoencoder latents.
pub struct DitEvalSet {
    pub names: Vec<String>,
    /// Normalized ground truths.
    pub meshes: Vec<Mesh>,
    /// (N, 3, S, S) in [0, 1].
    images: Option<Tensor>,
    /// (N, K, d).
    latents: Option<Tensor>,
}

impl DitEvalSet {
    /// The first `from_folder` meshes of `folder` and `procedural` held-aside procedural
    /// shapes (the autoencoder trainer's evaluation meshes), rendered from `view`'s fixed
    /// view and encoded by `autoencoder`.
    pub fn build(
        folder: Option<&FolderData>,
        from_folder: usize,
        procedural: usize,
        view: &ViewConfig,
        autoencoder: &FaceModel,
    ) -> Result<Self, TrainError> {
        let ae = autoencoder.config();
        let sample = SampleConfig::for_model(ae, super::super::augment::AugmentConfig::OFF)?;
        let set = EvalSet::build(folder, from_folder, procedural, &sample, ae.max_faces)?;
        let size = view.size as usize;
        let mut pixels = Vec::with_capacity(set.items.len());
        for (mesh, s) in &set.items {
            let img = render_rgb(mesh, &view.fixed()).map_err(|e| {
                TrainError::Config(format!("rendering evaluation mesh {}: {e}", s.name))
            })?;
            pixels.push(img);
        }
        let device = autoencoder.device();
        let (images, latents) = if set.items.is_empty() {
            (None, None)
        } else {
            let refs: Vec<&[u8]> = pixels.iter().map(Vec::as_slice).collect();
            let examples: Vec<_> = set.items.iter().map(|(_, s)| example(s)).collect();
            let b = TrainBatch::new(&examples, device)?;
            (
                Some(images_tensor(&refs, size, device)?),
                Some(autoencoder.encode(&b.points, &b.normals, &b.query_indices)?),
            )
        };
        Ok(Self {
            names: set.items.iter().map(|(_, s)| s.name.clone()).collect(),
            meshes: set.items.into_iter().map(|(m, _)| m).collect(),
            images,
            latents,
        })
    }

    pub fn len(&self) -> usize {
        self.meshes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.meshes.is_empty()
    }
}

/// How an evaluation samples and scores.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DitEvalOptions {
    /// Euler steps of the sampler.
    pub steps: usize,
    /// Classifier-free guidance scale.
    pub guidance: f32,
    /// Seed of the sampler's noise and of the loss's noise: fixed, so evaluations compare.
    pub seed: u64,
    /// Face budget of the greedy decoding (capped by the autoencoder's own limit).
    pub max_faces: usize,
    /// Points per surface for Chamfer and Hausdorff distance.
    pub metric_samples: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DitEvalReport {
    pub meshes: usize,
    /// Flow-matching loss on the ground truths' latents and views.
    pub loss: f64,
    pub chamfer_mean: Option<f64>,
    pub hausdorff_mean: Option<f64>,
    /// Decoded meshes with no faces (or that could not be scored): counted, never dropped.
    pub failures: usize,
    /// Mean faces of the decoded meshes.
    pub mean_faces: f64,
    /// How the decoded meshes with faces are put together (open and non-manifold edges,
    /// parts). (None in logs written before it was measured.)
    #[serde(default)]
    pub topology: Option<TopologySummary>,
    pub seconds: f64,
}

/// Scores `model` on `set` end to end (see the module documentation).
pub fn evaluate(
    model: &DiffusionModel,
    autoencoder: &FaceModel,
    set: &DitEvalSet,
    opts: &DitEvalOptions,
) -> Result<DitEvalReport, TrainError> {
    let start = Instant::now();
    let (Some(images), Some(gt_latents)) = (&set.images, &set.latents) else {
        return Err(TrainError::Config("the evaluation set is empty".into()));
    };
    let n = set.len();
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    let loss = f64::from(model.training_loss(gt_latents, images, &mut rng)?.to_scalar::<f32>()?);
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    let latents = model.generate(images, vec![opts.guidance; n], opts.steps.max(1), &mut rng)?;
    let decode = GenerateOptions { max_faces: opts.max_faces, ..GenerateOptions::default() };
    let faces = greedy_decode(autoencoder, &latents, decode)?;
    let q = Quantizer::new(u16::try_from(autoencoder.config().quant_levels).unwrap_or(u16::MAX))?;
    let metric = MetricOptions { samples: opts.metric_samples, ..MetricOptions::default() };
    let decoded: Vec<Mesh> = faces.iter().map(|f| detokenize(f, q)).collect();
    let records: Vec<EvalRecord> = decoded
        .iter()
        .zip(&set.meshes)
        .zip(&set.names)
        .map(|((pred, gt), name)| EvalRecord {
            name: name.clone(),
            result: mesh_distances(pred, gt, &metric).map_err(|e| e.to_string()),
        })
        .collect();
    let summary = summarize(&records);
    let with_faces: Vec<Topology> =
        decoded.iter().filter(|m| !m.faces.is_empty()).map(topology).collect();
    Ok(DitEvalReport {
        meshes: n,
        loss,
        chamfer_mean: summary.chamfer_mean,
        hausdorff_mean: summary.hausdorff_mean,
        failures: summary.failures,
        mean_faces: faces.iter().map(Vec::len).sum::<usize>() as f64 / n as f64,
        topology: Some(summarize_topology(&with_faces)),
        seconds: start.elapsed().as_secs_f64(),
    })
}

pub fn eval_line(step: u64, r: &DitEvalReport) -> String {
    let opt = |v: Option<f64>| v.map_or_else(|| "-".into(), |v| format!("{v:.4}"));
    format!(
        "eval @ {step}: loss {:.4}, CD {}, HD {}, failures {}/{}, mean faces {:.1}{} ({:.0} s)",
        r.loss,
        opt(r.chamfer_mean),
        opt(r.hausdorff_mean),
        r.failures,
        r.meshes,
        r.mean_faces,
        r.topology.map_or_else(String::new, |t| format!("; {t}")),
        r.seconds
    )
}
