//! What the load generators (`bench serve`, `bench soak`) send: a fixed test shape as points
//! (or a given file's, for `bench serve --input`), and how they summarize the times they
//! measure.

use std::path::Path;
use std::time::Duration;

use anyhow::Context;
use meshstream::mesh::{
    Mesh, ReadLimits, primitives, read_mesh_file, reference_points, sample_surface,
};
use meshstream::server::proto::{Options, PointCloud, ReconstructRequest, reconstruct_request};

/// A fixed test shape (a box with a sphere on top), sampled to `points` points with normals.
pub fn test_cloud(points: usize) -> Mesh {
    let mut shape = primitives::cuboid([1.0, 0.6, 0.8]);
    shape.append(&primitives::uv_sphere(0.4, 8, 5).translated([0.0, 0.6, 0.0]));
    sample_surface(&shape, points, 0).unwrap_or_default()
}

/// The points of the mesh or point cloud file `input` (any format `reconstruct` reads): at
/// most `points` of them, a mesh's sampled on its surface, a cloud's its own; with normals.
pub fn file_cloud(input: &Path, points: usize) -> anyhow::Result<Mesh> {
    let mesh = read_mesh_file(input, &ReadLimits::default())
        .with_context(|| format!("reading {}", input.display()))?;
    reference_points(&mesh, points, 0).with_context(|| format!("points of {}", input.display()))
}

/// `cloud` as the gRPC API's points.
pub fn point_cloud(cloud: &Mesh) -> PointCloud {
    PointCloud {
        positions: cloud.vertices.iter().flatten().copied().collect(),
        normals: cloud.normals.iter().flatten().flatten().copied().collect(),
    }
}

/// The gRPC request for `cloud` with `options`.
pub fn points_request(cloud: &Mesh, options: Options) -> ReconstructRequest {
    ReconstructRequest {
        input: Some(reconstruct_request::Input::Points(point_cloud(cloud))),
        options: Some(options),
    }
}

/// The `p` quantile (0 to 1) of `sorted`.
pub fn percentile(sorted: &[Duration], p: f64) -> Option<Duration> {
    sorted.get(((sorted.len() as f64 - 1.0) * p).round() as usize).copied()
}

/// [`percentile`] as milliseconds, or "-" when there is none.
pub fn percentile_ms(sorted: &[Duration], p: f64) -> String {
    percentile(sorted, p).map_or("-".to_string(), |d| format!("{:.1} ms", d.as_secs_f64() * 1e3))
}
