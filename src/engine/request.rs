//! What a client asks for, prepared for the scheduler: the conditioning (the request's kind)
//! and the decoding options.

use std::time::Instant;

use crate::mesh::{Mesh, Normalization, encoder_points, farthest_point_sampling};
use crate::model::{FaceConfig, SamplingParams};

use super::EngineError;

/// The encoder's input for one request, in the normalized frame, and the normalization that
/// takes the result back to the caller's coordinates.
#[derive(Debug, Clone)]
pub struct PreparedPoints {
    pub points: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    /// Farthest-point-sampled indices into `points`: the encoder's queries.
    pub queries: Vec<u32>,
    pub normalization: Normalization,
}

impl PreparedPoints {
    /// From a point cloud (normals kept, or estimated when absent) or a mesh (its surface is
    /// sampled), in the caller's own coordinates. CPU work: run it off the async runtime.
    pub fn from_mesh(input: &Mesh, cfg: &FaceConfig, seed: u64) -> Result<Self, EngineError> {
        if input.vertices.is_empty() {
            return Err(EngineError::InvalidInput("the input has no points".into()));
        }
        input.validate()?;
        let normalization = Normalization::fit(&input.vertices)?;
        let cloud = encoder_points(&normalization.apply_mesh(input), cfg.num_points, seed)?;
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
        Ok(Self { points: cloud.vertices, normals, queries, normalization })
    }
}

/// What the decoder is conditioned on. Each kind has its own stage before decoding (for
/// points, the encoder); image conditioning joins here as a kind with a diffusion stage.
#[derive(Debug, Clone)]
pub enum Conditioning {
    Points(PreparedPoints),
}

impl Conditioning {
    pub fn normalization(&self) -> Normalization {
        match self {
            Self::Points(p) => p.normalization,
        }
    }
}

#[derive(Debug, Clone, Default)]
pub struct DecodeOptions {
    /// Face budget; `None`: the engine's and the model's limit.
    pub max_faces: Option<usize>,
    pub sampling: SamplingParams,
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
