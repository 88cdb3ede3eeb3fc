//! Evaluation on held-aside meshes: the teacher-forced loss, and greedy reconstruction from
//! points scored with Chamfer and Hausdorff distance (DESIGN.md's definition), the failure
//! count and the face-count error.

use candle_core::Device;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::mesh::Mesh;
use crate::metrics::{
    DEFAULT_FACE_TOLERANCE, EvalRecord, FaceMatch, MetricOptions, Topology, TopologySummary,
    face_match, mesh_distances, summarize, summarize_faces, summarize_topology, topology,
};
use crate::model::{
    CoordinateNll, EncoderTraining, FaceModel, GenerateOptions, Generation, TrainBatch,
    TrainExample, step_generations,
};
use crate::tokenize::{FaceToken, Quantizer, detokenize};

use super::augment::AugmentConfig;
use super::batch::{SampleConfig, TrainingSample, prepare_sample};
use super::dataset::FolderData;
use super::procedural::ProceduralShapes;

/// A fixed set of meshes with their (unaugmented) samples: the folder's first, then the
/// procedural shapes.
pub struct EvalSet {
    pub items: Vec<(Mesh, TrainingSample)>,
    /// How many of `items` (the first) come from the folder.
    pub from_folder: usize,
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
        let from_folder = items.len();
        let shapes = ProceduralShapes::new(HELD_OUT_PROCEDURAL_SEED, max_faces)
            .on_grid(Quantizer::new(cfg.levels)?);
        for (i, (kind, mesh)) in shapes.take(procedural).enumerate() {
            let name = format!("procedural-{i:03}-{kind:?}");
            if let Some(sample) = prepare_sample(&name, &mesh, &cfg, max_faces, &mut rng)? {
                let (normalized, _) = mesh.normalized()?;
                items.push((normalized, sample));
            }
        }
        Ok(Self { items, from_folder })
    }

    /// Meshes given by the caller, as they are (no augmentation), their points sampled with
    /// `seed`. A mesh that cannot be prepared (no extent, no faces, or more than `max_faces`
    /// after quantization) is left out, and comes back with the set as its name and why.
    pub fn of_meshes(
        meshes: &[(String, Mesh)],
        cfg: &SampleConfig,
        max_faces: usize,
        seed: u64,
    ) -> (Self, Vec<(String, String)>) {
        let cfg = SampleConfig { augment: AugmentConfig::OFF, ..*cfg };
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (mut items, mut left_out) = (Vec::new(), Vec::new());
        for (name, mesh) in meshes {
            let prepared = prepare_sample(name, mesh, &cfg, max_faces, &mut rng)
                .and_then(|s| s.map(|sample| Ok((mesh.normalized()?.0, sample))).transpose());
            match prepared {
                Ok(Some(item)) => items.push(item),
                Ok(None) => left_out.push((
                    name.clone(),
                    format!("no faces, or more than {max_faces} after quantization"),
                )),
                Err(e) => left_out.push((name.clone(), e.to_string())),
            }
        }
        (Self { from_folder: items.len(), items }, left_out)
    }

    /// The items' indices by source: (folder, procedural).
    fn sources(&self) -> [std::ops::Range<usize>; 2] {
        let split = self.from_folder.min(self.items.len());
        [0..split, split..self.items.len()]
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
    /// Mean share of the ground truth's faces that the reconstruction has, corner for corner
    /// (`meshstream eval`'s "faces right" at its default tolerance): progress toward `exact`
    /// long before a whole mesh is right. (None in logs written before it was measured.)
    #[serde(default)]
    pub faces_right: Option<f64>,
    /// How the reconstructions with faces are put together (`meshstream eval`'s topology:
    /// shares of open and non-manifold edges, connected parts), which the Chamfer distance
    /// does not see. (None in logs written before it was measured.)
    #[serde(default)]
    pub topology: Option<TopologySummary>,
    /// `loss` and `chamfer_mean` over the folder's meshes and over the procedural shapes
    /// alone: the two can move in opposite directions. (None where a source has no meshes,
    /// and in logs written before they were measured.)
    #[serde(default)]
    pub by_source: Option<SourceFigures>,
}

/// Figures of an evaluation per source of meshes.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct SourceFigures {
    pub loss_folder: Option<f64>,
    pub loss_procedural: Option<f64>,
    pub chamfer_folder: Option<f64>,
    pub chamfer_procedural: Option<f64>,
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
    let [folder, procedural] = set.sources();
    let own_folder = teacher_forced_loss(model, set, folder.clone(), batch, |i| i)?;
    let own_procedural = teacher_forced_loss(model, set, procedural.clone(), batch, |i| i)?;
    let own = own_folder.combined(&own_procedural).mean();
    let other = if n > 1 {
        teacher_forced_loss(model, set, 0..n, batch, |i| (i + 1) % n)?.mean()
    } else {
        None
    };
    let predictions = reconstruct(model, set, batch, &device)?;
    let q = Quantizer::new(model.config().quant_levels as u16)
        .map_err(|e| crate::model::ModelError::bad_input(e.to_string()))?;
    let scores = score(set, &predictions, q, metric);
    let summary = summarize(&scores.records);
    let by_source = SourceFigures {
        loss_folder: own_folder.mean(),
        loss_procedural: own_procedural.mean(),
        chamfer_folder: summarize(&scores.records[folder]).chamfer_mean,
        chamfer_procedural: summarize(&scores.records[procedural]).chamfer_mean,
    };
    Ok(EvalReport {
        meshes: n,
        loss: own.unwrap_or(0.0),
        loss_other_points: other,
        chamfer_mean: summary.chamfer_mean,
        hausdorff_mean: summary.hausdorff_mean,
        failures: summary.failures,
        face_count_error: scores.face_count_error,
        exact: scores.exact,
        faces_right: summarize_faces(&scores.face_matches).recall_mean,
        topology: Some(summarize_topology(&scores.topologies)),
        by_source: Some(by_source),
    })
}

/// What the reconstructions of a set score against its meshes.
struct Scores {
    /// Distances per mesh, in the set's order.
    records: Vec<EvalRecord>,
    /// For every reconstruction; one without faces has none right, counted rather than dropped.
    face_matches: Vec<FaceMatch>,
    /// For every reconstruction with faces.
    topologies: Vec<Topology>,
    /// Mean of |predicted faces - true faces| / true faces.
    face_count_error: f64,
    exact: usize,
}

fn score(
    set: &EvalSet,
    predictions: &[Vec<FaceToken>],
    q: Quantizer,
    metric: &MetricOptions,
) -> Scores {
    let mut scores = Scores {
        records: Vec::new(),
        face_matches: Vec::new(),
        topologies: Vec::new(),
        face_count_error: 0.0,
        exact: 0,
    };
    for ((gt, sample), faces) in set.items.iter().zip(predictions) {
        scores.face_count_error +=
            (faces.len() as f64 - sample.faces.len() as f64).abs() / sample.faces.len() as f64;
        scores.exact += usize::from(*faces == sample.faces);
        let pred = detokenize(faces, q);
        if !pred.faces.is_empty() {
            scores.topologies.push(topology(&pred));
        }
        let result = mesh_distances(&pred, gt, metric).map_err(|e| e.to_string());
        let nothing_right = FaceMatch { matched: 0, predicted: faces.len(), truth: gt.faces.len() };
        scores
            .face_matches
            .push(face_match(&pred, gt, DEFAULT_FACE_TOLERANCE).unwrap_or(nothing_right));
        scores.records.push(EvalRecord { name: sample.name.clone(), result });
    }
    if !set.items.is_empty() {
        scores.face_count_error /= set.items.len() as f64;
    }
    scores
}

/// A loss summed over face positions, and their count.
#[derive(Debug, Clone, Copy, Default)]
struct LossSum {
    sum: f64,
    positions: usize,
}

impl LossSum {
    /// Nats per face position; `None` over no positions.
    fn mean(&self) -> Option<f64> {
        (self.positions > 0).then(|| self.sum / self.positions as f64)
    }

    fn combined(&self, other: &Self) -> Self {
        Self { sum: self.sum + other.sum, positions: self.positions + other.positions }
    }
}

/// Teacher-forced loss of the set's meshes `indices`, mesh `i` decoded from the points of
/// mesh `points_of(i)`, in batches of `batch` meshes.
fn teacher_forced_loss(
    model: &FaceModel,
    set: &EvalSet,
    indices: std::ops::Range<usize>,
    batch: usize,
    points_of: impl Fn(usize) -> usize,
) -> Result<LossSum, crate::model::ModelError> {
    let indices: Vec<usize> = indices.collect();
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
        // Nothing learns here: the latents need no gradient.
        let loss = model.loss(&b, EncoderTraining::Frozen)?;
        loss_sum += f64::from(loss.coords.to_scalar::<f32>()?) * n as f64;
        positions += n;
    }
    Ok(LossSum { sum: loss_sum, positions })
}

/// The teacher-forced loss of each mesh of the set from its own points, in the set's order:
/// nats per face position (its faces and its end of mesh), as in training.
pub fn loss_per_mesh(
    model: &FaceModel,
    set: &EvalSet,
) -> Result<Vec<f64>, crate::model::ModelError> {
    (0..set.items.len())
        .map(|i| {
            let loss = teacher_forced_loss(model, set, i..i + 1, 1, |i| i)?;
            Ok(loss.sum / loss.positions as f64)
        })
        .collect()
}

/// Each mesh's teacher-forced loss by coordinate, from its own points, in the set's order:
/// which of a face's 9 values the model does not know.
pub fn coordinate_nll_per_mesh(
    model: &FaceModel,
    set: &EvalSet,
) -> Result<Vec<CoordinateNll>, crate::model::ModelError> {
    let mut out = Vec::with_capacity(set.items.len());
    for (_, sample) in &set.items {
        let batch = TrainBatch::new(&[example(sample)], model.device())?;
        out.extend(model.coordinate_nll(&batch)?);
    }
    Ok(out)
}

/// What greedy decoding makes of a mesh from its own points, scored by the model that made it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct GreedyScore {
    pub faces: usize,
    /// The decode's teacher-forced loss from the same points, nats per face position (as
    /// [`loss_per_mesh`] counts the truth's).
    pub loss: f64,
    /// Whether the decode is the truth's sequence, token for token.
    pub same: bool,
}

impl GreedyScore {
    /// -log p of the whole decode, end of mesh included.
    pub fn nll(&self) -> f64 {
        self.loss * (self.faces + 1) as f64
    }
}

/// Greedy decoding of each mesh of the set from its own points, and what the model thinks of
/// the result. Where a wrong decode costs fewer nats in all than the truth, the model prefers
/// it and a wider search would not find the truth; where it costs more, decoding missed it.
pub fn greedy_scores(
    model: &FaceModel,
    set: &EvalSet,
) -> Result<Vec<GreedyScore>, crate::model::ModelError> {
    let mut out = Vec::with_capacity(set.items.len());
    for (_, sample) in &set.items {
        let batch = TrainBatch::new(&[example(sample)], model.device())?;
        let latents = model.encode(&batch.points, &batch.normals, &batch.query_indices)?;
        let faces =
            greedy_decode(model, &latents, GenerateOptions::default())?.pop().unwrap_or_default();
        let decoded = TrainExample { faces: &faces, ..example(sample) };
        let split = model.coordinate_nll(&TrainBatch::new(&[decoded], model.device())?)?;
        let loss = split.first().map_or(f64::NAN, |c| f64::from(c.per_position(faces.len())));
        out.push(GreedyScore { faces: faces.len(), loss, same: faces == sample.faces });
    }
    Ok(out)
}

/// Greedy reconstructions of every mesh of the set: encoded `batch` meshes at a time, then
/// decoded all together, one batched step per face.
///
/// Why all together: on a GPU a step costs about the same for few rows as for many (on an
/// H200, `meshstream-train check-device` decoded its 8 meshes in 885 ms, the machine's CPU in
/// 805), so an evaluation waits on its steps, and 16 meshes at a time took as many steps as
/// the longest of every 16.
pub fn reconstruct(
    model: &FaceModel,
    set: &EvalSet,
    batch: usize,
    device: &Device,
) -> Result<Vec<Vec<FaceToken>>, crate::model::ModelError> {
    let latents = set
        .items
        .chunks(batch.max(1))
        .map(|chunk| {
            let examples: Vec<TrainExample> = chunk.iter().map(|(_, s)| example(s)).collect();
            let b = TrainBatch::new(&examples, device)?;
            model.encode(&b.points, &b.normals, &b.query_indices)
        })
        .collect::<Result<Vec<_>, _>>()?;
    if latents.is_empty() {
        return Ok(Vec::new());
    }
    greedy_decode(model, &candle_core::Tensor::cat(&latents, 0)?, GenerateOptions::default())
}

/// Greedy decoding of every row of `latents` (B, K, d) together, one batched step per face.
pub fn greedy_decode(
    model: &FaceModel,
    latents: &candle_core::Tensor,
    options: GenerateOptions,
) -> Result<Vec<Vec<FaceToken>>, crate::model::ModelError> {
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
        SampleConfig::for_model(cfg, AugmentConfig::OFF).unwrap()
    }

    #[test]
    fn other_points_loss_pairs_each_mesh_with_the_next_meshs_points() {
        // The training data is quantized to the usual 128 levels.
        let cfg = FaceConfig { quant_levels: 128, ..FaceConfig::micro() };
        let (_, model) = random_model(&cfg);
        let set = EvalSet::build(None, 0, 3, &sample_config(&cfg), cfg.max_faces).unwrap();
        assert_eq!(set.items.len(), 3);
        let loss = |set: &EvalSet, points_of: fn(usize) -> usize| {
            teacher_forced_loss(&model, set, 0..3, 2, points_of).unwrap().mean().unwrap()
        };
        let own = loss(&set, |i| i);
        let other = loss(&set, |i| (i + 1) % 3);
        assert!(own.is_finite() && other.is_finite());
        // Other shapes' latents change the predictions even with random weights.
        assert!((own - other).abs() > 1e-4, "own {own}, other {other}");

        // A set of copies of one mesh: another mesh's points are its own points.
        let copies = EvalSet { items: vec![set.items[0].clone(); 3], from_folder: 0 };
        let (same, swapped) = (loss(&copies, |i| i), loss(&copies, |i| (i + 1) % 3));
        assert!((same - swapped).abs() < 1e-5, "{same} vs {swapped}");

        let report = evaluate(&model, &set, 2, &MetricOptions::default()).unwrap();
        assert!((report.loss - own).abs() < 1e-5, "{} vs {own}", report.loss);
        assert_eq!(report.loss_other_points, Some(other));
        let one = EvalSet { items: set.items[..1].to_vec(), from_folder: 0 };
        assert_eq!(
            evaluate(&model, &one, 2, &MetricOptions::default()).unwrap().loss_other_points,
            None
        );
    }

    #[test]
    fn losses_per_mesh_add_up_to_the_sets_and_oversized_meshes_are_left_out() {
        let cfg = FaceConfig { quant_levels: 128, ..FaceConfig::micro() };
        let (_, model) = random_model(&cfg);
        let shapes = ProceduralShapes::new(4, cfg.max_faces).take(3);
        let mut meshes: Vec<(String, Mesh)> =
            shapes.enumerate().map(|(i, (_, mesh))| (format!("shape-{i}"), mesh)).collect();
        let big = crate::mesh::primitives::uv_sphere(0.5, 32, 16);
        assert!(big.faces.len() > cfg.max_faces);
        meshes.insert(1, ("big".into(), big));
        let points = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        meshes.push(("points".into(), Mesh { vertices: points, ..Mesh::default() }));

        let flat = Mesh::new(vec![[1.0; 3]; 3], vec![[0, 1, 2]]);
        meshes.push(("no extent".into(), flat));

        let (set, left_out) = EvalSet::of_meshes(&meshes, &sample_config(&cfg), cfg.max_faces, 0);
        let names: Vec<&str> = left_out.iter().map(|(name, _)| name.as_str()).collect();
        assert_eq!(names, ["big", "points", "no extent"]);
        assert!(left_out[2].1.contains("extent"), "{left_out:?}");
        let names: Vec<&str> = set.items.iter().map(|(_, s)| s.name.as_str()).collect();
        assert_eq!(names, ["shape-0", "shape-1", "shape-2"]);

        let losses = loss_per_mesh(&model, &set).unwrap();
        let positions: Vec<f64> =
            set.items.iter().map(|(_, s)| (s.faces.len() + 1) as f64).collect();
        let weighted: f64 = losses.iter().zip(&positions).map(|(l, p)| l * p).sum::<f64>()
            / positions.iter().sum::<f64>();
        let whole = teacher_forced_loss(&model, &set, 0..3, 3, |i| i).unwrap().mean().unwrap();
        assert!((weighted - whole).abs() < 1e-4, "{weighted} vs {whole}");
    }

    #[test]
    fn greedy_scores_find_the_decode_of_a_mesh_that_is_its_own_decode() {
        let cfg = FaceConfig { quant_levels: 128, ..FaceConfig::micro() };
        let (_, model) = random_model(&cfg);
        let set = EvalSet::build(None, 0, 2, &sample_config(&cfg), cfg.max_faces).unwrap();
        let scores = greedy_scores(&model, &set).unwrap();
        assert_eq!(scores.len(), 2);
        assert!(scores.iter().all(|s| s.loss.is_finite() && s.loss > 0.0), "{scores:?}");

        // Give each mesh the faces greedy decoding makes from its points: the decode is then
        // the truth, and its loss is the truth's loss.
        let decodes = reconstruct(&model, &set, 2, &Device::Cpu).unwrap();
        let mut own = EvalSet { items: set.items.clone(), from_folder: 0 };
        for ((_, sample), faces) in own.items.iter_mut().zip(decodes) {
            sample.faces = faces;
        }
        let scores = greedy_scores(&model, &own).unwrap();
        let losses = loss_per_mesh(&model, &own).unwrap();
        for ((score, loss), (_, sample)) in scores.iter().zip(&losses).zip(&own.items) {
            assert!(score.same, "{score:?}");
            assert_eq!(score.faces, sample.faces.len());
            assert!((score.loss - loss).abs() < 1e-4 * loss, "{score:?} against {loss}");
            assert!((score.nll() - loss * (score.faces + 1) as f64).abs() < 1e-3);
        }
    }

    #[test]
    fn scores_of_the_ground_truths_own_faces_of_them_one_short_and_of_none() {
        let cfg = FaceConfig { quant_levels: 128, ..FaceConfig::micro() };
        let set = EvalSet::build(None, 0, 4, &sample_config(&cfg), cfg.max_faces).unwrap();
        let q = Quantizer::new(128).unwrap();
        let metric = MetricOptions { samples: 2000, ..MetricOptions::default() };
        let truth: Vec<Vec<FaceToken>> = set.items.iter().map(|(_, s)| s.faces.clone()).collect();
        let scores = score(&set, &truth, q, &metric);
        assert_eq!((scores.exact, scores.face_count_error), (4, 0.0));
        assert_eq!(summarize_faces(&scores.face_matches).recall_mean, Some(1.0));
        // The shapes are closed solids in one piece, and so are their own faces.
        let closed = TopologySummary {
            meshes: 4,
            boundary_share_mean: Some(0.0),
            non_manifold_share_mean: Some(0.0),
            misoriented_share_mean: Some(0.0),
            parts_mean: Some(1.0),
        };
        assert_eq!(summarize_topology(&scores.topologies), closed);

        // Dropping each mesh's last face: not exact, one face short of every mesh.
        let short: Vec<Vec<FaceToken>> = truth.iter().map(|f| f[..f.len() - 1].to_vec()).collect();
        let scores = score(&set, &short, q, &metric);
        assert_eq!(scores.exact, 0);
        // A face short, each has the three open edges of the hole it leaves.
        for (t, (_, s)) in scores.topologies.iter().zip(&set.items) {
            assert_eq!((t.faces, t.boundary_edges), (s.faces.len() - 1, 3));
        }
        for (m, (_, s)) in scores.face_matches.iter().zip(&set.items) {
            assert_eq!((m.matched, m.predicted), (s.faces.len() - 1, s.faces.len() - 1));
        }

        // Empty reconstructions are failures, and count as nothing right.
        let scores = score(&set, &vec![Vec::new(); 4], q, &metric);
        assert_eq!(summarize(&scores.records).failures, 4);
        assert_eq!(summarize_faces(&scores.face_matches).recall_mean, Some(0.0));
        assert!(scores.topologies.is_empty());
    }

    #[test]
    fn figures_are_also_given_per_source() {
        let cfg = FaceConfig { quant_levels: 128, ..FaceConfig::micro() };
        let (_, model) = random_model(&cfg);
        let mut set = EvalSet::build(None, 0, 3, &sample_config(&cfg), cfg.max_faces).unwrap();
        assert_eq!(set.from_folder, 0);
        // Count the first shape as the folder's.
        set.from_folder = 1;
        let metric = MetricOptions { samples: 2000, ..MetricOptions::default() };
        let report = evaluate(&model, &set, 2, &metric).unwrap();
        let by = report.by_source.clone().unwrap();
        let alone = |range: std::ops::Range<usize>| {
            let items = set.items[range].to_vec();
            evaluate(&model, &EvalSet { items, from_folder: 0 }, 2, &metric).unwrap()
        };
        let (first, rest) = (alone(0..1), alone(1..3));
        let close = |a: Option<f64>, b: f64| (a.unwrap() - b).abs() < 1e-5;
        assert!(close(by.loss_folder, first.loss), "{by:?} {first:?}");
        assert!(close(by.loss_procedural, rest.loss), "{by:?} {rest:?}");
        assert_eq!(by.chamfer_folder, first.chamfer_mean);
        assert_eq!(by.chamfer_procedural, rest.chamfer_mean);
        // The whole set's loss lies between its parts' (a mean over face positions).
        let (lo, hi) = (first.loss.min(rest.loss), first.loss.max(rest.loss));
        assert!(report.loss >= lo - 1e-5 && report.loss <= hi + 1e-5, "{report:?}");
    }
}
