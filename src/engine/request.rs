//! What a client asks for, prepared for the scheduler: the conditioning (the request's kind)
//! and the decoding options.

use std::sync::Arc;
use std::time::Instant;

use crate::diffusion::PreparedImage;
use crate::mesh::{Mesh, Normalization, UpAxis, farthest_point_sampling, input_clouds};
use crate::model::{FaceConfig, SamplingParams};

use super::EngineError;

/// One draw of a request's input points for the encoder, in the normalized frame.
#[derive(Debug, Clone, PartialEq)]
pub struct EncoderPoints {
    pub points: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    /// Farthest-point-sampled indices into `points`: the encoder's queries.
    pub queries: Vec<u32>,
}

/// A points request's input: what its encoder reads, the denser reference its candidates are
/// judged and fitted against, and the normalization that takes the result back to the
/// caller's coordinates.
#[derive(Debug, Clone)]
pub struct PreparedPoints {
    /// What this request's encoder reads (the input's first draw).
    pub encoder: EncoderPoints,
    /// The input's further draws, one for each further candidate of a best-of-N request
    /// (candidate `i` reads draw `i`, see [`crate::candidates`]); empty otherwise.
    pub more_draws: Vec<EncoderPoints>,
    /// Up to [`crate::mesh::REFERENCE_POINTS`] points with normals by default (see [`input_clouds`]);
    /// shared, as every candidate of a request carries it.
    pub reference: Arc<Mesh>,
    pub normalization: Normalization,
}

impl PreparedPoints {
    /// From a point cloud (normals kept, or estimated when absent) or a mesh (its surface is
    /// sampled), in the caller's own coordinates, with up to `reference` points to judge and
    /// fit candidates against ([`crate::mesh::REFERENCE_POINTS`] unless a server is told
    /// otherwise), and `draws` draws for the encoder (a request's candidate count); `up` is the
    /// caller's up axis, turned onto the models' +y. CPU work: run it off the async runtime.
    pub fn from_mesh(
        input: &Mesh,
        cfg: &FaceConfig,
        reference: usize,
        seed: u64,
        draws: usize,
        up: UpAxis,
    ) -> Result<Self, EngineError> {
        if input.vertices.is_empty() {
            return Err(EngineError::InvalidInput("the input has no points".into()));
        }
        input.validate()?;
        let normalization = Normalization::fit(&input.vertices)?.with_up(up);
        let clouds = input_clouds(
            &normalization.apply_mesh(input),
            cfg.num_points,
            cfg.point_oversampling,
            reference,
            seed,
            draws,
        )?;
        let mut encoder = clouds.encoder.into_iter().map(|cloud| EncoderPoints::new(cloud, cfg));
        Ok(Self {
            encoder: encoder
                .next()
                .ok_or_else(|| EngineError::Model("no points drawn".into()))??,
            more_draws: encoder.collect::<Result<_, _>>()?,
            reference: Arc::new(clouds.reference),
            normalization,
        })
    }

    /// What candidate `i` of this request reads: draw `i` (the draws taken in turn when there
    /// are fewer), with the request's reference and normalization.
    pub fn for_candidate(&self, i: usize) -> Self {
        let draws = 1 + self.more_draws.len();
        let encoder = match i % draws {
            0 => &self.encoder,
            d => &self.more_draws[d - 1],
        };
        Self {
            encoder: encoder.clone(),
            more_draws: Vec::new(),
            reference: Arc::clone(&self.reference),
            normalization: self.normalization,
        }
    }
}

impl EncoderPoints {
    fn new(cloud: Mesh, cfg: &FaceConfig) -> Result<Self, EngineError> {
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
        Ok(Self { points: cloud.vertices, normals, queries })
    }

    /// Whether it has the model's point and query counts, every query a point.
    pub(super) fn fits(&self, cfg: &FaceConfig) -> bool {
        self.points.len() == cfg.num_points
            && self.normals.len() == cfg.num_points
            && self.queries.len() == cfg.num_latents
            && self.queries.iter().all(|&i| (i as usize) < self.points.len())
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
    /// Decode this many meshes, each from its own draw of the input points (see
    /// [`crate::candidates::candidate_sampling`]), and keep the one that ends closest to the
    /// input points; points requests only. `None`: 1.
    pub candidates: Option<usize>,
    /// Rounds of fitting each finished candidate's corners to the input points (`mesh::fit`),
    /// after which the winner drops its folded faces and the parts and sheets the points do not
    /// need ([`crate::mesh::without_folded_faces`], [`crate::mesh::without_stray_parts`],
    /// [`crate::mesh::without_stray_sheets`]); points requests only. Its faces then arrive
    /// together at the end, as with candidates. `None` or 0: the corners as decoded, faces as
    /// they come.
    pub fit_rounds: Option<usize>,
    /// Merge each finished candidate's corners within this many grid cells of each other, and
    /// split its faces at corners this close to their open edges
    /// ([`crate::tokenize::weld_near_corners`]); points requests only, faces arriving at the
    /// end as with candidates. `None` or 0: faces as they come.
    pub weld_radius: Option<u16>,
    /// A fitted answer's loops of at most this many open edges are closed where the input
    /// points cover them ([`crate::mesh::with_small_holes_filled`]); points requests only.
    /// `None`: [`crate::mesh::DEFAULT_MAX_HOLE_EDGES`]; below 3: none.
    pub max_hole_edges: Option<usize>,
    /// A fitted answer may be the convex hull of the input points with at most this many
    /// faces ([`crate::candidates::hull_candidate`]), within the face budget; 0: never.
    /// `None`: the engine's setting (`EngineConfig::hull_faces`). Points requests only,
    /// fitted ones: others are the model's faces.
    pub hull_faces: Option<usize>,
    /// While an answer whose faces come at the end (several candidates, welded or fitted) is
    /// made, stream the first candidate's faces as they are decoded, as [`super::Event::Draft`]s:
    /// a client watching sees the decoding, then the answer. Ignored where the faces come as
    /// they are decoded anyway.
    pub drafts: bool,
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
        let prepared =
            PreparedPoints::from_mesh(&boxy, &cfg, REFERENCE_POINTS, 0, 1, UpAxis::Y).unwrap();
        assert_eq!(prepared.encoder.points.len(), cfg.num_points);
        assert!(prepared.more_draws.is_empty());
        assert_eq!(prepared.reference.vertices.len(), REFERENCE_POINTS);
        // In the normalized frame, as the encoder's points are.
        let (lo, hi) = prepared.reference.bounds().unwrap();
        assert!(lo.iter().chain(&hi).all(|c| c.abs() <= 1.0 + 1e-5), "{lo:?} {hi:?}");

        let cloud = Mesh { faces: Vec::new(), ..sample_surface(&boxy, 3000, 1).unwrap() };
        let prepared =
            PreparedPoints::from_mesh(&cloud, &cfg, REFERENCE_POINTS, 0, 1, UpAxis::Y).unwrap();
        assert_eq!(prepared.reference.vertices, prepared.normalization.apply_mesh(&cloud).vertices);
        // A server told to judge against fewer takes a subset.
        let prepared = PreparedPoints::from_mesh(&cloud, &cfg, 2000, 0, 1, UpAxis::Y).unwrap();
        assert_eq!(prepared.reference.vertices.len(), 2000);
    }

    #[test]
    fn a_z_up_input_is_prepared_as_the_same_input_standing_on_y() {
        let cfg = FaceConfig::tiny();
        let standing = cuboid([2.0, 3.0, 0.5]).translated([5.0, 1.0, 0.0]);
        let lying = Normalization { center: [0.0; 3], half_extent: 1.0, up: UpAxis::Z }
            .invert_mesh(&standing);
        let expected = PreparedPoints::from_mesh(&standing, &cfg, 4096, 7, 1, UpAxis::Y).unwrap();
        let prepared = PreparedPoints::from_mesh(&lying, &cfg, 4096, 7, 1, UpAxis::Z).unwrap();
        assert_eq!(prepared.encoder, expected.encoder);
        assert_eq!(prepared.reference, expected.reference);
        // And the result goes back lying, as the caller sent it.
        let corner = expected.normalization.apply([7.0, 2.5, 0.25]);
        let back = prepared.normalization.invert(corner);
        assert_eq!(
            back,
            Normalization { up: UpAxis::Z, ..Normalization::identity() }.invert([7.0, 2.5, 0.25])
        );
    }

    #[test]
    fn each_candidate_reads_its_own_draw_of_the_points_and_shares_the_reference() {
        let cfg = FaceConfig::tiny();
        let boxy = cuboid([2.0, 1.0, 0.5]);
        let prepared = PreparedPoints::from_mesh(&boxy, &cfg, 4096, 3, 3, UpAxis::Y).unwrap();
        assert_eq!(prepared.more_draws.len(), 2);
        let alone = PreparedPoints::from_mesh(&boxy, &cfg, 4096, 3, 1, UpAxis::Y).unwrap();
        assert_eq!(prepared.encoder, alone.encoder);
        let candidates: Vec<PreparedPoints> = (0..4).map(|i| prepared.for_candidate(i)).collect();
        assert_eq!(candidates[0].encoder, prepared.encoder);
        assert_eq!(candidates[1].encoder, prepared.more_draws[0]);
        assert_eq!(candidates[2].encoder, prepared.more_draws[1]);
        assert_eq!(candidates[3].encoder, prepared.encoder, "the draws are taken in turn");
        assert_ne!(candidates[1].encoder, candidates[0].encoder);
        for c in &candidates {
            assert!(c.more_draws.is_empty() && c.encoder.fits(&cfg));
            assert!(Arc::ptr_eq(&c.reference, &prepared.reference));
        }
    }
}
