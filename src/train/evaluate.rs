//! Evaluation on held-aside meshes: the teacher-forced loss, and greedy reconstruction from
//! points scored with Chamfer and Hausdorff distance (DESIGN.md's definition), the failure
//! count and the face-count error.

use candle_core::Device;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::mesh::Mesh;
use crate::metrics::{EvalRecord, MetricOptions, mesh_distances, summarize};
use crate::model::{
    FaceModel, GenerateOptions, Generation, TrainBatch, TrainExample, step_generations,
};
use crate::tokenize::{Quantizer, detokenize};

use super::augment::AugmentConfig;
use super::batch::{SampleConfig, TrainingSample, prepare_sample};
use super::dataset::FolderData;
use super::procedural::ProceduralShapes;

/// A fixed set of meshes with their (unaugmented) samples.
pub struct EvalSet {
    pub items: Vec<(Mesh, TrainingSample)>,
}

/// Seed of the held-aside procedural shapes: far from any training seed a user would pick.
pub const HELD_OUT_PROCEDURAL_SEED: u64 = 0x005E_ED0F_E7A1;

impl EvalSet {
    /// The first `from_folder` meshes of `folder` (in name order) and `procedural` held-aside
    /// procedural shapes, each with at most `max_faces` faces after quantization.
    pub fn build(
        folder: Option<&FolderData>,
        from_folder: usize,
        procedural: usize,
        cfg: &SampleConfig,
        max_faces: usize,
    ) -> Result<Self, super::TrainError> {
        let cfg = SampleConfig { augment: AugmentConfig::OFF, ..*cfg };
        let mut rng = ChaCha8Rng::seed_from_u64(HELD_OUT_PROCEDURAL_SEED);
        let mut items = Vec::new();
        let mut records: Vec<_> = folder.map_or(Vec::new(), |f| f.meshes.iter().collect());
        records.sort_by(|a, b| a.name.cmp(&b.name));
        for record in records.into_iter().filter(|r| r.faces <= max_faces).take(from_folder) {
            if let Some(sample) =
                prepare_sample(&record.name, &record.mesh, &cfg, max_faces, &mut rng)?
            {
                items.push((record.mesh.clone(), sample));
            }
        }
        let shapes = ProceduralShapes::new(HELD_OUT_PROCEDURAL_SEED, max_faces);
        for (i, (kind, mesh)) in shapes.take(procedural).enumerate() {
            let name = format!("procedural-{i:03}-{kind:?}");
            if let Some(sample) = prepare_sample(&name, &mesh, &cfg, max_faces, &mut rng)? {
                let (normalized, _) = mesh.normalized()?;
                items.push((normalized, sample));
            }
        }
        Ok(Self { items })
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct EvalReport {
    pub meshes: usize,
    /// Teacher-forced loss (nats per face, EOS included), as in training.
    pub loss: f64,
    /// The same loss with each mesh decoded from the next mesh's points. Its excess over
    /// `loss` is how much the decoder reads the shape from its latents; a decoder that only
    /// learned the prior of face sequences scores the same with any points. (None in logs
    /// written before it was measured, or for a set of one mesh.)
    #[serde(default)]
    pub loss_other_points: Option<f64>,
    pub chamfer_mean: Option<f64>,
    pub hausdorff_mean: Option<f64>,
    /// Reconstructions with no faces (or that failed): counted, never dropped.
    pub failures: usize,
    /// Mean of |predicted faces - true faces| / true faces.
    pub face_count_error: f64,
    /// Reconstructions whose faces equal the ground truth's tokens exactly.
    pub exact: usize,
}

/// Scores `model` on `set`: the loss in batches of `batch` meshes, then greedy decoding of
/// all meshes together (one batched step per face).
pub fn evaluate(
    model: &FaceModel,
    set: &EvalSet,
    batch: usize,
    metric: &MetricOptions,
) -> Result<EvalReport, crate::model::ModelError> {
    let device = model.device().clone();
    let n = set.items.len();
    let own = teacher_forced_loss(model, set, batch, |i| i)?;
    let other =
        if n > 1 { Some(teacher_forced_loss(model, set, batch, |i| (i + 1) % n)?) } else { None };
    let predictions = reconstruct(model, set, batch, &device)?;
    let q = Quantizer::new(model.config().quant_levels as u16)
        .map_err(|e| crate::model::ModelError::bad_input(e.to_string()))?;
    let mut records = Vec::new();
    let (mut count_error, mut exact) = (0.0, 0);
    for ((gt, sample), faces) in set.items.iter().zip(&predictions) {
        count_error +=
            (faces.len() as f64 - sample.faces.len() as f64).abs() / sample.faces.len() as f64;
        exact += usize::from(*faces == sample.faces);
        let pred = detokenize(faces, q);
        let result = mesh_distances(&pred, gt, metric).map_err(|e| e.to_string());
        records.push(EvalRecord { name: sample.name.clone(), result });
    }
    let summary = summarize(&records);
    let meshes = set.items.len();
    Ok(EvalReport {
        meshes,
        loss: own,
        loss_other_points: other,
        chamfer_mean: summary.chamfer_mean,
        hausdorff_mean: summary.hausdorff_mean,
        failures: summary.failures,
        face_count_error: if meshes > 0 { count_error / meshes as f64 } else { 0.0 },
        exact,
    })
}

/// Teacher-forced loss (nats per face position) of every mesh of the set, mesh `i` decoded
/// from the points of mesh `points_of(i)`, in batches of `batch` meshes.
fn teacher_forced_loss(
    model: &FaceModel,
    set: &EvalSet,
    batch: usize,
    points_of: impl Fn(usize) -> usize,
) -> Result<f64, crate::model::ModelError> {
    let indices: Vec<usize> = (0..set.items.len()).collect();
    let (mut loss_sum, mut positions) = (0.0, 0usize);
    for chunk in indices.chunks(batch.max(1)) {
        let examples: Vec<TrainExample> = chunk
            .iter()
            .map(|&i| TrainExample {
                faces: &set.items[i].1.faces,
                ..example(&set.items[points_of(i)].1)
            })
            .collect();
        let b = TrainBatch::new(&examples, model.device())?;
        let n: usize = chunk.iter().map(|&i| set.items[i].1.faces.len() + 1).sum();
        loss_sum += f64::from(model.loss(&b)?.coords.to_scalar::<f32>()?) * n as f64;
        positions += n;
    }
    Ok(if positions > 0 { loss_sum / positions as f64 } else { 0.0 })
}

/// Greedy reconstructions of every mesh of the set, `batch` sequences decoded together.
pub fn reconstruct(
    model: &FaceModel,
    set: &EvalSet,
    batch: usize,
    device: &Device,
) -> Result<Vec<Vec<crate::tokenize::FaceToken>>, crate::model::ModelError> {
    let mut out = Vec::with_capacity(set.items.len());
    for chunk in set.items.chunks(batch.max(1)) {
        let examples: Vec<TrainExample> = chunk.iter().map(|(_, s)| example(s)).collect();
        let b = TrainBatch::new(&examples, device)?;
        let latents = model.encode(&b.points, &b.normals, &b.query_indices)?;
        out.extend(greedy_decode(model, &latents, GenerateOptions::default())?);
    }
    Ok(out)
}

/// Greedy decoding of every row of `latents` (B, K, d) together, one batched step per face.
pub fn greedy_decode(
    model: &FaceModel,
    latents: &candle_core::Tensor,
    options: GenerateOptions,
) -> Result<Vec<Vec<crate::tokenize::FaceToken>>, crate::model::ModelError> {
    let mut gens = (0..latents.dim(0)?)
        .map(|r| Generation::new(model, &latents.get(r)?, options.clone()))
        .collect::<Result<Vec<_>, _>>()?;
    while gens.iter().any(|g| !g.is_finished()) {
        let mut refs: Vec<&mut Generation> = gens.iter_mut().collect();
        step_generations(model, &mut refs)?;
    }
    Ok(gens.iter().map(|g| g.faces().to_vec()).collect())
}

pub fn example(s: &TrainingSample) -> TrainExample<'_> {
    TrainExample {
        points: &s.points,
        normals: &s.normals,
        query_indices: &s.queries,
        faces: &s.faces,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::FaceConfig;
    use crate::model::testing::random_model;

    fn sample_config(cfg: &FaceConfig) -> SampleConfig {
        SampleConfig {
            levels: cfg.quant_levels as u16,
            num_points: cfg.num_points,
            num_queries: cfg.num_latents,
            augment: AugmentConfig::OFF,
        }
    }

    #[test]
    fn other_points_loss_pairs_each_mesh_with_the_next_meshs_points() {
        // The training data is quantized to the usual 128 levels.
        let cfg = FaceConfig { quant_levels: 128, ..FaceConfig::micro() };
        let (_, model) = random_model(&cfg);
        let set = EvalSet::build(None, 0, 3, &sample_config(&cfg), cfg.max_faces).unwrap();
        assert_eq!(set.items.len(), 3);
        let own = teacher_forced_loss(&model, &set, 2, |i| i).unwrap();
        let other = teacher_forced_loss(&model, &set, 2, |i| (i + 1) % 3).unwrap();
        assert!(own.is_finite() && other.is_finite());
        // Other shapes' latents change the predictions even with random weights.
        assert!((own - other).abs() > 1e-4, "own {own}, other {other}");

        // A set of copies of one mesh: another mesh's points are its own points.
        let copies = EvalSet { items: vec![set.items[0].clone(); 3] };
        let same = teacher_forced_loss(&model, &copies, 2, |i| i).unwrap();
        let swapped = teacher_forced_loss(&model, &copies, 2, |i| (i + 1) % 3).unwrap();
        assert!((same - swapped).abs() < 1e-5, "{same} vs {swapped}");

        let report = evaluate(&model, &set, 2, &MetricOptions::default()).unwrap();
        assert_eq!((report.loss, report.loss_other_points), (own, Some(other)));
        let one = EvalSet { items: set.items[..1].to_vec() };
        assert_eq!(
            evaluate(&model, &one, 2, &MetricOptions::default()).unwrap().loss_other_points,
            None
        );
    }
}
