//! What a client asks for, prepared for the scheduler: the conditioning (the request's kind)
//! and the decoding options.

use std::sync::Arc;
use std::time::Instant;

use crate::diffusion::PreparedImage;
use crate::mesh::{Mesh, Normalization, farthest_point_sampling, input_clouds};
use crate::model::{FaceConfig, SamplingParams};

use super::EngineError;

/// The encoder's input for one request, in the normalized frame, the denser reference its
/// candidates are judged and fitted against, and the normalization that takes the result
/// back to the caller's coordinates.
#[derive(Debug, Clone)]
pub struct PreparedPoints {
    pub points: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    /// Farthest-point-sampled indices into `points`: the encoder's queries.
    pub queries: Vec<u32>,
    /// Up to [`crate::mesh::REFERENCE_POINTS`] points with normals by default (see [`input_clouds`]);
    /// shared, as every candidate of a request carries it.
    pub reference: Arc<Mesh>,
    pub normalization: Normalization,
}

impl PreparedPoints {
    /// From a point cloud (normals kept, or estimated when absent) or a mesh (its surface is
    /// sampled), in the caller's own coordinates, with up to `reference` points to judge and
    /// fit candidates against ([`crate::mesh::REFERENCE_POINTS`] unless a server is told otherwise). CPU
    /// work: run it off the async runtime.
    pub fn from_mesh(
        input: &Mesh,
        cfg: &FaceConfig,
        reference: usize,
        seed: u64,
    ) -> Result<Self, EngineError> {
        if input.vertices.is_empty() {
            return Err(EngineError::InvalidInput("the input has no points".into()));
        }
        input.validate()?;
        let normalization = Normalization::fit(&input.vertices)?;
        let clouds = input_clouds(
            &normalization.apply_mesh(input),
            cfg.num_points,
            cfg.point_oversampling,
            reference,
            seed,
        )?;
        let cloud = clouds.encoder;
        let normals = cloud.normals.unwrap_or_default();
        if normals.len() != cloud.vertices.len()
            || normals.iter().chain(&cloud.vertices).flatten().any(|c| !c.is_finite())
        {
            return Err(EngineError::InvalidInput(
                "the input's normals must be finite and non-zero".into(),
            ));
        }
        let queries = farthest_point_sampling(&cloud.vertices, cfg.num_latents, 0)
            .into_iter()
            .map(|i| i as u32)
            .collect();
        Ok(Self {
            points: cloud.vertices,
            normals,
            queries,
            reference: Arc::new(clouds.reference),
            normalization,
        })
    }
}

/// An image request's input and its sampler's settings.
#[derive(Debug, Clone)]
pub struct ImagePrompt {
    /// Decoded, square, at the image model's input size.
    pub image: PreparedImage,
    /// Euler steps of the diffusion sampler.
    pub steps: usize,
    /// Classifier-free guidance: 0 ignores the image, 1 is plain conditional sampling, more
    /// follows the image more closely.
    pub guidance: f32,
    /// Seed of the sampler's starting noise.
    pub seed: u64,
}

/// What the decoder is conditioned on. Each kind has its own stage before decoding: the
/// point encoder, or diffusion from the image.
#[derive(Debug, Clone)]
pub enum Conditioning {
    Points(PreparedPoints),
    Image(ImagePrompt),
}

impl Conditioning {
    /// From the model's frame to the caller's. A mesh generated from an image has no
    /// caller's frame: it stays in the model's, centred in [-1, 1]^3.
    pub fn normalization(&self) -> Normalization {
        match self {
            Self::Points(p) => p.normalization,
            Self::Image(_) => Normalization::identity(),
        }
    }
}

#[derive(Debug, Clone, Default)]
pub struct DecodeOptions {
    /// Face budget; `None`: the engine's and the model's limit.
    pub max_faces: Option<usize>,
    pub sampling: SamplingParams,
    /// Partial faces kept by greedy decoding (`GenerateOptions::face_beam`); `None`: the
    /// model's default.
    pub face_beam: Option<usize>,
    /// Decode this many meshes (the first as asked, the others sampled) and keep the one
    /// closest to the input points; points requests only. `None`: 1.
    pub candidates: Option<usize>,
    /// Rounds of fitting the finished mesh's corners to the input points (`mesh::fit`);
    /// points requests only. Its faces then arrive together at the end, as with candidates.
    /// `None` or 0: the corners as decoded, faces as they come.
    pub fit_rounds: Option<usize>,
}

#[derive(Debug, Clone)]
pub struct Request {
    /// Echoed in logs and responses.
    pub id: String,
    pub conditioning: Conditioning,
    pub options: DecodeOptions,
    /// The request fails with `DeadlineExceeded` if it is not finished by then.
    pub deadline: Option<Instant>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::REFERENCE_POINTS;
    use crate::mesh::primitives::cuboid;
    use crate::mesh::sample_surface;

    #[test]
    fn a_mesh_is_sampled_for_the_reference_and_a_small_cloud_is_its_own() {
        let cfg = FaceConfig::tiny();
        let boxy = cuboid([2.0, 1.0, 0.5]).translated([10.0, 0.0, 0.0]);
        let prepared = PreparedPoints::from_mesh(&boxy, &cfg, REFERENCE_POINTS, 0).unwrap();
        assert_eq!(prepared.points.len(), cfg.num_points);
        assert_eq!(prepared.reference.vertices.len(), REFERENCE_POINTS);
        // In the normalized frame, as the encoder's points are.
        let (lo, hi) = prepared.reference.bounds().unwrap();
        assert!(lo.iter().chain(&hi).all(|c| c.abs() <= 1.0 + 1e-5), "{lo:?} {hi:?}");

        let cloud = Mesh { faces: Vec::new(), ..sample_surface(&boxy, 3000, 1).unwrap() };
        let prepared = PreparedPoints::from_mesh(&cloud, &cfg, REFERENCE_POINTS, 0).unwrap();
        assert_eq!(prepared.reference.vertices, prepared.normalization.apply_mesh(&cloud).vertices);
        // A server told to judge against fewer takes a subset.
        let prepared = PreparedPoints::from_mesh(&cloud, &cfg, 2000, 0).unwrap();
        assert_eq!(prepared.reference.vertices.len(), 2000);
    }
}
