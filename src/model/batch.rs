//! Padded training batches and the masked cross-entropy of the CausalMLP head.

use candle_core::{D, DType, Device, Tensor};

use super::config::COORDS_PER_FACE;
use super::{FaceToken, ModelError, Result};

/// One training example: a point cloud with normals, its FPS query indices, and the canonical
/// face sequence of its mesh.
#[derive(Debug, Clone)]
pub struct TrainExample<'a> {
    pub points: &'a [[f32; 3]],
    pub normals: &'a [[f32; 3]],
    pub query_indices: &'a [u32],
    pub faces: &'a [FaceToken],
}

/// A batch padded to its longest face sequence. All examples must share the point and query
/// counts.
#[derive(Debug, Clone)]
pub struct TrainBatch {
    pub points: Tensor,
    pub normals: Tensor,
    pub query_indices: Tensor,
    /// (B, N_max, 9) u32, zero past each row's length.
    pub faces: Tensor,
    pub lengths: Vec<usize>,
    /// The largest coordinate in `faces` and the largest query index, known on the host:
    /// checking them there spares the device two copies back (stalls) in every forward pass.
    pub max_coordinate: u32,
    pub max_query_index: u32,
    /// Each face's first coordinate, (B, N) on the host: the first sub-head's targets, made
    /// without copying `faces` back from the device.
    first_coordinates: Vec<u32>,
}

impl TrainBatch {
    pub fn new(examples: &[TrainExample], device: &Device) -> Result<Self> {
        let first = examples.first().ok_or_else(|| ModelError::bad_input("empty batch"))?;
        let (m, k) = (first.points.len(), first.query_indices.len());
        if let Some(e) = examples
            .iter()
            .find(|e| e.points.len() != m || e.normals.len() != m || e.query_indices.len() != k)
        {
            return Err(ModelError::bad_input(format!(
                "examples differ in size: {} points / {} normals / {} queries, expected {m} / {m} / {k}",
                e.points.len(),
                e.normals.len(),
                e.query_indices.len()
            )));
        }
        let b = examples.len();
        let n = examples.iter().map(|e| e.faces.len()).max().unwrap_or(0);
        let flat3 = |pick: &dyn Fn(&TrainExample<'_>) -> Vec<f32>| -> Vec<f32> {
            examples.iter().flat_map(pick).collect()
        };
        let mut faces = vec![0u32; b * n * COORDS_PER_FACE];
        for (r, e) in examples.iter().enumerate() {
            for (i, face) in e.faces.iter().enumerate() {
                let at = (r * n + i) * COORDS_PER_FACE;
                for (slot, &c) in face.iter().enumerate() {
                    faces[at + slot] = u32::from(c);
                }
            }
        }
        let queries: Vec<u32> =
            examples.iter().flat_map(|e| e.query_indices.iter().copied()).collect();
        let first_coordinates = faces.iter().step_by(COORDS_PER_FACE).copied().collect();
        // Padding is zeros, so it never raises a maximum.
        let max_coordinate = faces.iter().copied().max().unwrap_or(0);
        let max_query_index = queries.iter().copied().max().unwrap_or(0);
        Ok(Self {
            points: Tensor::from_vec(
                flat3(&|e| e.points.iter().flatten().copied().collect()),
                (b, m, 3),
                device,
            )?,
            normals: Tensor::from_vec(
                flat3(&|e| e.normals.iter().flatten().copied().collect()),
                (b, m, 3),
                device,
            )?,
            query_indices: Tensor::from_vec(queries, (b, k), device)?,
            faces: Tensor::from_vec(faces, (b, n, COORDS_PER_FACE), device)?,
            lengths: examples.iter().map(|e| e.faces.len()).collect(),
            max_coordinate,
            max_query_index,
            first_coordinates,
        })
    }

    /// Summed cross-entropy over the 9 coordinates, averaged over the face positions of the
    /// batch (each row's N faces plus its end-of-mesh step). `logits` as returned by
    /// `FaceModel::teacher_forced_logits`.
    pub fn cross_entropy(&self, logits: &[Tensor], quant_levels: usize) -> Result<Tensor> {
        let positions: usize = self.lengths.iter().map(|l| l + 1).sum();
        let sums = self
            .nll(logits, quant_levels)?
            .into_iter()
            .map(|(picked, weights)| (picked * weights)?.sum_all())
            .collect::<candle_core::Result<Vec<_>>>()?;
        Ok((Tensor::stack(&sums, 0)?.sum_all()? / positions as f64)?)
    }

    /// The teacher-forced loss of each row split by coordinate: which of a face's 9 values the
    /// model does not know (the mean over the row's faces), and how surely it ends the mesh.
    pub fn coordinate_nll(
        &self,
        logits: &[Tensor],
        quant_levels: usize,
    ) -> Result<Vec<CoordinateNll>> {
        let nll = self.nll(logits, quant_levels)?;
        let tables: Vec<Vec<Vec<f32>>> =
            nll.iter().map(|(picked, _)| picked.to_vec2::<f32>()).collect::<Result<_, _>>()?;
        Ok(self
            .lengths
            .iter()
            .enumerate()
            .map(|(r, &len)| {
                let mean = |row: &[f32]| row[..len].iter().sum::<f32>() / len.max(1) as f32;
                CoordinateNll {
                    coordinates: std::array::from_fn(|j| mean(&tables[j][r])),
                    end: tables[0][r][len],
                }
            })
            .collect())
    }

    /// Per sub-head j: -log p(target) at every position, (B, N + 1) for sub-head 0 (the face's
    /// first coordinate, then the end of mesh at each row's length) and (B, N) for the others,
    /// with the weights (1, or 0 on padding) that mask them.
    fn nll(&self, logits: &[Tensor], quant_levels: usize) -> Result<Vec<(Tensor, Tensor)>> {
        if logits.len() != COORDS_PER_FACE {
            return Err(ModelError::bad_input(format!(
                "{} logit tensors, expected 9",
                logits.len()
            )));
        }
        let dev = self.faces.device();
        let (b, n, _) = self.faces.dims3()?;
        let mut targets0 = vec![0u32; b * (n + 1)];
        let mut weights0 = vec![0f32; b * (n + 1)];
        for (r, &len) in self.lengths.iter().enumerate() {
            for i in 0..=len {
                targets0[r * (n + 1) + i] =
                    if i < len { self.first_coordinates[r * n + i] } else { quant_levels as u32 };
                weights0[r * (n + 1) + i] = 1.0;
            }
        }
        let targets0 = Tensor::from_vec(targets0, (b, n + 1), dev)?;
        let mut out = vec![(
            picked_nll(&logits[0], &targets0)?,
            Tensor::from_vec(weights0, (b, n + 1), dev)?,
        )];
        let weights: Vec<f32> = self
            .lengths
            .iter()
            .flat_map(|&len| (0..n).map(move |i| if i < len { 1.0 } else { 0.0 }))
            .collect();
        let weights = Tensor::from_vec(weights, (b, n), dev)?;
        for (j, l) in logits.iter().enumerate().skip(1) {
            let targets = self.faces.narrow(2, j, 1)?.squeeze(2)?.contiguous()?;
            out.push((picked_nll(l, &targets)?, weights.clone()));
        }
        Ok(out)
    }
}

/// One mesh's teacher-forced loss by coordinate, in nats (see [`TrainBatch::coordinate_nll`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct CoordinateNll {
    /// Mean over the faces of each of the 9 values, in token order (z, y, x of each corner).
    pub coordinates: [f32; COORDS_PER_FACE],
    /// The end of mesh at the position after the last face.
    pub end: f32,
}

impl CoordinateNll {
    /// The mesh's loss as training counts it, nats per position, for a mesh of `faces` faces:
    /// the coordinates' means summed over its faces, plus the end of mesh.
    pub fn per_position(&self, faces: usize) -> f32 {
        (self.coordinates.iter().sum::<f32>() * faces as f32 + self.end) / (faces + 1) as f32
    }
}

/// -log p(target) at every position. logits (B, T, C), targets (B, T) u32.
fn picked_nll(logits: &Tensor, targets: &Tensor) -> Result<Tensor> {
    if targets.elem_count() == 0 {
        // A batch of meshes without faces (a greedy decode that ended at once) has no
        // coordinates to score, and candle cannot take the softmax of nothing.
        return Ok(Tensor::zeros(targets.dims(), logits.dtype(), logits.device())?);
    }
    let logp = candle_nn::ops::log_softmax(logits, D::Minus1)?;
    let targets = targets.to_dtype(DType::U32)?.unsqueeze(D::Minus1)?.contiguous()?;
    let picked = logp.contiguous()?.gather(&targets, D::Minus1)?;
    Ok(picked.squeeze(D::Minus1)?.neg()?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::testing::{random_faces, random_model};
    use crate::model::{EncoderTraining, FaceConfig};

    #[test]
    fn padded_loss_is_the_position_weighted_mean_of_row_losses() {
        let cfg = FaceConfig::micro();
        let (_, model) = random_model(&cfg);
        let pts: Vec<[f32; 3]> =
            (0..cfg.num_points).map(|i| [(i as f32).sin(), (i as f32).cos(), 0.5]).collect();
        let queries: Vec<u32> = (0..cfg.num_latents as u32).collect();
        let faces = [random_faces(&cfg, 5, 1), random_faces(&cfg, 2, 2)];
        let example =
            |f| TrainExample { points: &pts, normals: &pts, query_indices: &queries, faces: f };
        let dev = Device::Cpu;
        let loss = |ex: &[TrainExample<'_>]| {
            let batch = TrainBatch::new(ex, &dev).unwrap();
            model.loss(&batch, EncoderTraining::Trained).unwrap().total.to_scalar::<f32>().unwrap()
        };
        let a = loss(&[example(&faces[0])]);
        let b = loss(&[example(&faces[1])]);
        let both = loss(&[example(&faces[0]), example(&faces[1])]);
        let expect = (a * 6.0 + b * 3.0) / 9.0;
        assert!((both - expect).abs() < 1e-4, "{both} vs {expect}");
        // Roughly uniform predictions at initialization: about ln(Q) per coordinate.
        assert!(a > 0.0 && a < 9.0 * (cfg.quant_levels as f32 + 1.0).ln() * 2.0, "{a}");
    }

    #[test]
    fn the_loss_by_coordinate_adds_up_to_the_loss() {
        let cfg = FaceConfig::micro();
        let (_, model) = random_model(&cfg);
        let pts: Vec<[f32; 3]> =
            (0..cfg.num_points).map(|i| [(i as f32).cos(), 0.3, (i as f32).sin()]).collect();
        let queries: Vec<u32> = (0..cfg.num_latents as u32).collect();
        let faces = [random_faces(&cfg, 4, 7), random_faces(&cfg, 1, 8)];
        let examples: Vec<TrainExample> = faces
            .iter()
            .map(|f| TrainExample {
                points: &pts,
                normals: &pts,
                query_indices: &queries,
                faces: f,
            })
            .collect();
        let batch = TrainBatch::new(&examples, &Device::Cpu).unwrap();
        let loss = model.loss(&batch, EncoderTraining::Frozen).unwrap();
        let by_coordinate = model.coordinate_nll(&batch).unwrap();
        assert_eq!(by_coordinate.len(), 2);
        // Each row: its faces' summed means times its face count, plus its end of mesh.
        let summed: f32 = by_coordinate
            .iter()
            .zip(&faces)
            .map(|(c, f)| c.coordinates.iter().sum::<f32>() * f.len() as f32 + c.end)
            .sum();
        let expect = loss.coords.to_scalar::<f32>().unwrap() * (5 + 2) as f32;
        assert!((summed - expect).abs() < 1e-3 * expect, "{summed} vs {expect}");
        assert!(
            by_coordinate.iter().all(|c| c.end > 0.0 && c.coordinates.iter().all(|&v| v > 0.0))
        );

        // A mesh without faces has only its end of mesh to score.
        let empty = TrainExample { faces: &[], ..examples[0] };
        let batch = TrainBatch::new(&[empty], &Device::Cpu).unwrap();
        let nothing = model.coordinate_nll(&batch).unwrap();
        assert_eq!(nothing[0].coordinates, [0.0; 9]);
        assert!(nothing[0].end > 0.0 && nothing[0].per_position(0) == nothing[0].end);
    }

    #[test]
    fn mismatched_examples_are_rejected() {
        let pts = vec![[0.0f32; 3]; 4];
        let q = vec![0u32; 2];
        let a = TrainExample { points: &pts, normals: &pts, query_indices: &q, faces: &[] };
        let b =
            TrainExample { points: &pts[..3], normals: &pts[..3], query_indices: &q, faces: &[] };
        assert!(TrainBatch::new(&[a.clone(), b], &Device::Cpu).is_err());
        assert!(TrainBatch::new(&[], &Device::Cpu).is_err());
    }
}
