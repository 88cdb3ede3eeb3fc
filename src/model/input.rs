//! Turning a point cloud into the encoder's input tensors (with farthest point sampling for
//! the queries).

use candle_core::{Device, Tensor};

use super::{ModelError, Result};
use crate::mesh::{Mesh, farthest_point_sampling};

/// Encoder input for one point cloud: points and normals (1, M, 3), query indices (1, K).
#[derive(Debug, Clone)]
pub struct PointCloudInput {
    pub points: Tensor,
    pub normals: Tensor,
    pub query_indices: Tensor,
}

impl PointCloudInput {
    /// `cloud`: points with normals, already in the normalized frame. The `num_latents`
    /// queries are picked by farthest point sampling from the first point.
    pub fn new(cloud: &Mesh, num_latents: usize, device: &Device) -> Result<Self> {
        let m = cloud.vertices.len();
        let normals =
            cloud.normals.as_ref().filter(|n| n.len() == m).ok_or_else(|| {
                ModelError::bad_input("the point cloud needs one normal per point")
            })?;
        if m < num_latents || num_latents == 0 {
            return Err(ModelError::bad_input(format!(
                "{m} points cannot provide {num_latents} latent queries"
            )));
        }
        if cloud.vertices.iter().chain(normals).flatten().any(|c| !c.is_finite()) {
            return Err(ModelError::bad_input("non-finite point or normal"));
        }
        let queries: Vec<u32> = farthest_point_sampling(&cloud.vertices, num_latents, 0)
            .iter()
            .map(|&i| i as u32)
            .collect();
        let flat = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<f32>>();
        Ok(Self {
            points: Tensor::from_vec(flat(&cloud.vertices), (1, m, 3), device)?,
            normals: Tensor::from_vec(flat(normals), (1, m, 3), device)?,
            query_indices: Tensor::from_vec(queries, (1, num_latents), device)?,
        })
    }
}
