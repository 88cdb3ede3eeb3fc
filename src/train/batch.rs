//! Training samples and batches. A batch is a pure function of (seed, batch index), so a
//! resumed run sees exactly the data it would have seen, and batches can be made ahead on a
//! thread of their own while the model trains.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::mesh::{Mesh, farthest_point_sampling, sample_surface, spread_points};
use crate::model::FaceConfig;
use crate::tokenize::{FaceToken, Quantizer, tokenize};

use super::TrainError;
use super::augment::{AugmentConfig, augment, maybe_scanned};
use super::dataset::FolderData;
use super::procedural::{ProceduralShapes, ShapeKind};

/// One mesh ready for the model: its face tokens and the encoder's input.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainingSample {
    pub name: String,
    pub faces: Vec<FaceToken>,
    /// Surface points in the normalized frame, with unit normals.
    pub points: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    /// Farthest-point-sampled indices into `points`: the encoder's queries.
    pub queries: Vec<u32>,
}

/// How one mesh becomes a sample.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct SampleConfig {
    pub levels: u16,
    pub num_points: usize,
    /// The model's [`FaceConfig::point_oversampling`] (1 in runs made before it).
    #[serde(default = "FaceConfig::independent_points")]
    pub point_oversampling: usize,
    pub num_queries: usize,
    pub augment: AugmentConfig,
}

impl SampleConfig {
    /// How `model` reads a mesh, with `augment` applied first.
    pub fn for_model(model: &FaceConfig, augment: AugmentConfig) -> Result<Self, TrainError> {
        Ok(Self {
            levels: u16::try_from(model.quant_levels)
                .map_err(|_| TrainError::Config("quant_levels too large".into()))?,
            num_points: model.num_points,
            point_oversampling: model.point_oversampling,
            num_queries: model.num_latents,
            augment,
        })
    }
}

/// Augments, normalizes and tokenizes `mesh`, and samples the encoder's points from the
/// augmented surface. `None` when the result has no faces or more than `max_faces`.
pub fn prepare_sample(
    name: &str,
    mesh: &Mesh,
    cfg: &SampleConfig,
    max_faces: usize,
    rng: &mut ChaCha8Rng,
) -> Result<Option<TrainingSample>, TrainError> {
    let q = Quantizer::new(cfg.levels)?;
    let (normalized, _) = augment(mesh, &cfg.augment, rng).normalized()?;
    let faces = tokenize(&normalized, q).faces;
    if faces.is_empty() || faces.len() > max_faces {
        return Ok(None);
    }
    let drawn = cfg.num_points.saturating_mul(cfg.point_oversampling.max(1));
    let pool = sample_surface(&normalized, drawn, rng.random())?;
    let cloud = spread_points(maybe_scanned(pool, &cfg.augment, rng), cfg.num_points);
    let start = rng.random_range(0..cloud.vertices.len().max(1));
    let queries = farthest_point_sampling(&cloud.vertices, cfg.num_queries, start)
        .into_iter()
        .map(|i| i as u32)
        .collect();
    Ok(Some(TrainingSample {
        name: name.to_string(),
        faces,
        normals: cloud.normals.unwrap_or_default(),
        points: cloud.vertices,
        queries,
    }))
}

/// The largest mesh (in faces) allowed from a step on: small meshes first, so that shape
/// conditioning and the end of a mesh are learned before long sequences.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct CurriculumStage {
    pub from_step: u64,
    pub max_faces: usize,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct BatchConfig {
    pub sample: SampleConfig,
    /// Faces per batch (start/end positions included): batches are filled up to this.
    pub faces_per_batch: usize,
    /// Fraction of samples drawn from the procedural generator rather than the folder.
    pub procedural_ratio: f32,
    /// How often each procedural kind is drawn relative to the others (1 if not listed).
    #[serde(default)]
    pub procedural_weights: BTreeMap<ShapeKind, u32>,
    /// Sorted by `from_step`; the first stage applies before its step too.
    pub curriculum: Vec<CurriculumStage>,
    /// The model's face limit: the last stage never exceeds it.
    pub max_faces: usize,
    /// Seed of the batches, and of the run's initial weights.
    pub seed: u64,
    /// Padding allowed inside one forward pass, as a fraction of its real positions: a batch
    /// is run as groups of similar lengths so short meshes do not pay for the longest one.
    #[serde(default = "default_max_padding")]
    pub max_padding: f64,
}

fn default_max_padding() -> f64 {
    0.25
}

impl BatchConfig {
    pub fn max_faces_at(&self, step: u64) -> usize {
        let stage = self.curriculum.iter().rev().find(|s| s.from_step <= step);
        stage
            .or(self.curriculum.first())
            .map_or(self.max_faces, |s| s.max_faces.min(self.max_faces))
    }
}

#[derive(Debug, Clone)]
pub struct Batch {
    pub index: u64,
    pub samples: Vec<TrainingSample>,
}

impl Batch {
    /// Face positions the decoder processes: each sample's faces plus its end-of-mesh step.
    pub fn positions(&self) -> usize {
        self.samples.iter().map(|s| s.faces.len() + 1).sum()
    }

    /// The samples split into groups of similar length, each padded by at most `max_padding`
    /// of its real positions (a single sample is always a group of its own).
    pub fn length_groups(&self, max_padding: f64) -> Vec<Vec<&TrainingSample>> {
        let mut order: Vec<&TrainingSample> = self.samples.iter().collect();
        order.sort_by_key(|s| std::cmp::Reverse(s.faces.len()));
        let mut groups: Vec<Vec<&TrainingSample>> = Vec::new();
        let mut real = 0;
        for sample in order {
            let len = sample.faces.len() + 1;
            if let Some(group) = groups.last_mut() {
                // Sorted longest first, so the group's first sample sets its padded length.
                let padded = (group.len() + 1) * (group[0].faces.len() + 1);
                if padded as f64 <= (1.0 + max_padding) * (real + len) as f64 {
                    group.push(sample);
                    real += len;
                    continue;
                }
            }
            groups.push(vec![sample]);
            real = len;
        }
        groups
    }
}

/// Meshes of the folder sorted by face count, so each curriculum stage picks among a prefix.
pub struct BatchSource {
    folder: Option<Arc<FolderData>>,
    by_faces: Vec<usize>,
    cfg: BatchConfig,
}

impl BatchSource {
    pub fn new(folder: Option<Arc<FolderData>>, cfg: BatchConfig) -> Self {
        let mut by_faces: Vec<usize> = (0..folder.as_ref().map_or(0, |f| f.meshes.len())).collect();
        if let Some(f) = &folder {
            by_faces.sort_by_key(|&i| f.meshes[i].faces);
        }
        Self { folder, by_faces, cfg }
    }

    /// Batch number `index` (a pure function of the seed and the index).
    pub fn batch(&self, index: u64) -> Result<Batch, TrainError> {
        let mut rng = ChaCha8Rng::seed_from_u64(self.cfg.seed);
        rng.set_stream(index);
        let max_faces = self.cfg.max_faces_at(index);
        let eligible = self
            .folder
            .as_ref()
            .map_or(0, |f| self.by_faces.partition_point(|&i| f.meshes[i].faces <= max_faces));
        let mut procedural =
            ProceduralShapes::weighted(rng.random(), max_faces, &self.cfg.procedural_weights)
                .map_err(|e| TrainError::Config(e.to_string()))?
                .on_grid(Quantizer::new(self.cfg.sample.levels)?);
        let mut samples = Vec::new();
        let mut positions = 0;
        // Bounded attempts: augmentation can push a mesh over the limit, so some draws fail.
        for _ in 0..self.cfg.faces_per_batch.max(16) {
            let from_folder = eligible > 0 && rng.random::<f32>() >= self.cfg.procedural_ratio;
            let (name, mesh) = match (&self.folder, from_folder) {
                (Some(f), true) => {
                    let record = &f.meshes[self.by_faces[rng.random_range(0..eligible)]];
                    (record.name.clone(), record.mesh.clone())
                }
                _ => match procedural.next() {
                    Some((kind, mesh)) => (format!("{kind:?}"), mesh),
                    None => continue,
                },
            };
            let Some(sample) = prepare_sample(&name, &mesh, &self.cfg.sample, max_faces, &mut rng)?
            else {
                continue;
            };
            let len = sample.faces.len() + 1;
            if !samples.is_empty() && positions + len > self.cfg.faces_per_batch {
                break;
            }
            positions += len;
            samples.push(sample);
        }
        Ok(Batch { index, samples })
    }
}

/// Makes batches `start, start + 1, ...` ahead of the trainer on threads of their own: worker
/// `w` of `n` makes every `n`th batch from `start + w`, and they are read back in index order,
/// so the stream is the same whatever the number of workers. Dropping it stops the threads at
/// their next send.
pub struct Prefetcher {
    workers: Vec<(BatchReceiver, JoinHandle<()>)>,
    next: usize,
}

type BatchReceiver = Receiver<Result<Batch, TrainError>>;

impl Prefetcher {
    /// `depth` batches are made ahead per worker.
    pub fn spawn(source: BatchSource, start: u64, depth: usize, workers: usize) -> Self {
        let source = Arc::new(source);
        let count = workers.max(1) as u64;
        let workers = (0..count)
            .filter_map(|w| {
                let (tx, rx): (SyncSender<_>, _) = sync_channel(depth.max(1));
                let source = source.clone();
                let handle = std::thread::Builder::new()
                    .name(format!("batch-prefetch-{w}"))
                    .spawn(move || {
                        for index in (start + w..).step_by(count as usize) {
                            if tx.send(source.batch(index)).is_err() {
                                return;
                            }
                        }
                    })
                    .ok()?;
                Some((rx, handle))
            })
            .collect::<Vec<_>>();
        // A worker that could not start would leave a gap in the order: use none then.
        let workers = if workers.len() as u64 == count { workers } else { Vec::new() };
        Self { workers, next: 0 }
    }

    /// The next batch, in index order; `None` if the threads could not start or stopped.
    pub fn next_batch(&mut self) -> Option<Result<Batch, TrainError>> {
        let (rx, _) = self.workers.get(self.next % self.workers.len().max(1))?;
        self.next += 1;
        rx.recv().ok()
    }
}

impl Drop for Prefetcher {
    fn drop(&mut self) {
        // Closing every receiver first makes each thread's next send fail, which ends it.
        let (receivers, handles): (Vec<_>, Vec<_>) = self.workers.drain(..).unzip();
        drop(receivers);
        for h in handles {
            let _ = h.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(faces_per_batch: usize) -> BatchConfig {
        BatchConfig {
            sample: SampleConfig {
                levels: 128,
                num_points: 256,
                point_oversampling: 1,
                num_queries: 32,
                augment: AugmentConfig::default(),
            },
            faces_per_batch,
            procedural_ratio: 1.0,
            procedural_weights: BTreeMap::new(),
            curriculum: vec![
                CurriculumStage { from_step: 0, max_faces: 40 },
                CurriculumStage { from_step: 10, max_faces: 400 },
            ],
            max_faces: 200,
            seed: 5,
            max_padding: 0.25,
        }
    }

    #[test]
    fn oversampled_points_are_spread_apart() {
        let sphere = crate::mesh::primitives::uv_sphere(1.0, 16, 8);
        let closest_pair = |oversampling: usize| {
            let cfg = SampleConfig { point_oversampling: oversampling, ..config(300).sample };
            let mut rng = ChaCha8Rng::seed_from_u64(3);
            let s = prepare_sample("sphere", &sphere, &cfg, 400, &mut rng).unwrap().unwrap();
            assert_eq!((s.points.len(), s.normals.len(), s.queries.len()), (256, 256, 32));
            let mut closest = f32::INFINITY;
            for (i, a) in s.points.iter().enumerate() {
                for b in &s.points[..i] {
                    closest = closest.min((0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f32>());
                }
            }
            closest.sqrt()
        };
        // Independent draws put some pairs almost on top of each other; farthest point
        // sampling keeps every pair at least about the spacing of an even cover apart.
        let (drawn, spread) = (closest_pair(1), closest_pair(4));
        assert!(spread > 5.0 * drawn, "{spread} against {drawn}");
    }

    #[test]
    fn scanned_samples_keep_their_faces_and_take_noisy_points() {
        let sphere = crate::mesh::primitives::uv_sphere(1.0, 16, 8);
        let sample = |scanned_share: f32| {
            let mut cfg = config(300).sample;
            cfg.augment = AugmentConfig { scanned_share, scan_noise: 0.02, ..AugmentConfig::OFF };
            let mut rng = ChaCha8Rng::seed_from_u64(3);
            prepare_sample("sphere", &sphere, &cfg, 400, &mut rng).unwrap().unwrap()
        };
        let (surface, scanned) = (sample(0.0), sample(1.0));
        assert_eq!(scanned.faces, surface.faces, "the targets are the mesh's own");
        assert_eq!(scanned.points.len(), surface.points.len());
        // Points off the unit sphere by the noise, where the surface's lie on it (up to its
        // flat faces' sag).
        let off = |s: &TrainingSample| {
            s.points
                .iter()
                .map(|p| (p.iter().map(|c| c * c).sum::<f32>().sqrt() - 1.0).abs())
                .fold(0.0f32, f32::max)
        };
        assert!(off(&scanned) > off(&surface), "{} against {}", off(&scanned), off(&surface));
        assert_ne!(scanned.normals, surface.normals);
    }

    #[test]
    fn batches_are_a_function_of_their_index() {
        let source = BatchSource::new(None, config(300));
        let a = source.batch(3).unwrap();
        let b = source.batch(3).unwrap();
        assert_eq!(a.samples, b.samples);
        assert_ne!(source.batch(4).unwrap().samples, a.samples);
    }

    #[test]
    fn budget_curriculum_and_samples_are_respected() {
        let cfg = config(300);
        assert_eq!(cfg.max_faces_at(0), 40);
        assert_eq!(cfg.max_faces_at(50), 200, "capped by the model's limit");
        let source = BatchSource::new(None, cfg);
        for index in [0, 1, 2, 20] {
            let batch = source.batch(index).unwrap();
            assert!(!batch.samples.is_empty());
            assert!(batch.positions() <= 300 || batch.samples.len() == 1);
            let limit = if index < 10 { 40 } else { 200 };
            for s in &batch.samples {
                assert!(!s.faces.is_empty() && s.faces.len() <= limit, "{} faces", s.faces.len());
                assert!(crate::tokenize::is_canonical_sequence(&s.faces));
                assert_eq!(s.points.len(), 256);
                assert_eq!(s.normals.len(), 256);
                assert_eq!(s.queries.len(), 32);
                assert!(s.points.iter().flatten().all(|c| c.abs() <= 1.0 + 1e-5));
            }
        }
    }

    #[test]
    fn procedural_weights_reach_the_batches() {
        let only_wedges = ShapeKind::ALL.iter().map(|&k| (k, u32::from(k == ShapeKind::Wedge)));
        let cfg = BatchConfig { procedural_weights: only_wedges.collect(), ..config(300) };
        let batch = BatchSource::new(None, cfg).batch(2).unwrap();
        assert!(!batch.samples.is_empty());
        assert!(batch.samples.iter().all(|s| s.name == "Wedge"));
    }

    #[test]
    fn length_groups_bound_padding_and_keep_every_sample() {
        let source = BatchSource::new(None, config(2000));
        let batch = source.batch(20).unwrap();
        assert!(batch.samples.len() > 4, "{} samples", batch.samples.len());
        let groups = batch.length_groups(0.25);
        let mut names: Vec<_> = groups.iter().flatten().map(|s| &s.name).collect();
        let mut expected: Vec<_> = batch.samples.iter().map(|s| &s.name).collect();
        names.sort();
        expected.sort();
        assert_eq!(names, expected);
        for group in &groups {
            let longest = group.iter().map(|s| s.faces.len() + 1).max().unwrap();
            let real: usize = group.iter().map(|s| s.faces.len() + 1).sum();
            assert!((group.len() * longest) as f64 <= 1.25 * real as f64 + 1e-9);
        }
        assert_eq!(batch.length_groups(f64::INFINITY).len(), 1);
    }

    #[test]
    fn prefetcher_delivers_in_order_and_stops_when_dropped() {
        let mut prefetch = Prefetcher::spawn(BatchSource::new(None, config(200)), 7, 2, 1);
        for expected in 7..10 {
            assert_eq!(prefetch.next_batch().unwrap().unwrap().index, expected);
        }
        drop(prefetch);
    }

    #[test]
    fn several_workers_make_the_same_stream_as_one() {
        let names = |workers| {
            let mut prefetch =
                Prefetcher::spawn(BatchSource::new(None, config(200)), 3, 1, workers);
            (0..7)
                .map(|_| {
                    let batch = prefetch.next_batch().unwrap().unwrap();
                    (batch.index, batch.samples.iter().map(|s| s.faces.clone()).collect::<Vec<_>>())
                })
                .collect::<Vec<_>>()
        };
        let one = names(1);
        assert_eq!(one.iter().map(|(i, _)| *i).collect::<Vec<_>>(), (3..10).collect::<Vec<_>>());
        assert_eq!(names(3), one);
    }
}
