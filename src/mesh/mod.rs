//! The triangle mesh (or point cloud) type, its file formats, normalization and sampling.

mod assemble;
mod disjoint_sets;
mod error;
mod facing;
mod files;
mod fit;
mod folded_faces;
mod format;
mod fps;
mod gltf_read;
mod gltf_write;
mod holes;
mod limits;
mod normalize;
mod obj;
mod ply;
mod points;
pub mod primitives;
mod sample;
mod stl;
mod stray_parts;
mod surfaces;
mod text;
pub mod transform;

pub(crate) use disjoint_sets::DisjointSets;
pub use error::MeshError;
pub use facing::with_faces_facing_out;
pub(crate) use facing::{RayTarget, axes_across};
pub use files::{expand_mesh_paths, mesh_files_in};
pub use fit::{FitOptions, FitTarget, MAX_FIT_ROUNDS, fit_to_points, fit_to_target};
pub use folded_faces::without_folded_faces;
pub use format::{Format, read_mesh, read_mesh_file, write_mesh, write_mesh_file};
pub use fps::farthest_point_sampling;
pub use holes::{DEFAULT_MAX_HOLE_EDGES, MAX_HOLE_EDGES, with_small_holes_filled};
pub use limits::ReadLimits;
pub use normalize::{Normalization, UpAxis};
pub use points::{
    InputClouds, NORMAL_NEIGHBOURS, REFERENCE_POINTS, estimate_normals, input_clouds,
    reference_points, spread_points,
};
pub use sample::sample_surface;
pub use stray_parts::{STRAY_TOLERANCE, without_stray_parts, without_stray_sheets};

/// What welds two corners: their exact position. Adding 0.0 turns -0.0 into 0.0, so that
/// the two zeros weld.
pub(crate) fn position_key(p: [f32; 3]) -> [u32; 3] {
    p.map(|c| (c + 0.0).to_bits())
}

/// The edge between corners `p` and `q` either way round, as [`edge_uses`] keys it.
pub(crate) fn undirected(p: u32, q: u32) -> (u32, u32) {
    (p.min(q), p.max(q))
}

/// How many of `faces` use each edge: 1 on an open border, 3 or more where it is not manifold.
pub(crate) fn edge_uses(faces: &[[u32; 3]]) -> std::collections::HashMap<(u32, u32), usize> {
    let mut uses = std::collections::HashMap::new();
    for &[a, b, c] in faces {
        for (p, q) in [(a, b), (b, c), (c, a)] {
            *uses.entry(undirected(p, q)).or_default() += 1;
        }
    }
    uses
}

/// A triangle mesh, or a point cloud when `faces` is empty.
///
/// Coordinates are `f32` (the precision every format we read stores); indices are `u32`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<[f32; 3]>,
    pub faces: Vec<[u32; 3]>,
    /// Per-vertex normals, when the source had them (point clouds with normals above all).
    /// When present it has exactly one entry per vertex.
    pub normals: Option<Vec<[f32; 3]>>,
}

impl Mesh {
    pub fn new(vertices: Vec<[f32; 3]>, faces: Vec<[u32; 3]>) -> Self {
        Self { vertices, faces, normals: None }
    }

    /// A mesh without faces: the points of a point cloud.
    pub fn is_point_cloud(&self) -> bool {
        self.faces.is_empty()
    }

    /// Checks the invariants every reader guarantees: indices in range, finite coordinates,
    /// normals (if any) one per vertex.
    pub fn validate(&self) -> Result<(), MeshError> {
        let n = self.vertices.len();
        if let Some(normals) = &self.normals
            && normals.len() != n
        {
            return Err(MeshError::invalid(format!(
                "{} normals for {} vertices",
                normals.len(),
                n
            )));
        }
        if let Some(i) = self.vertices.iter().position(|v| v.iter().any(|c| !c.is_finite())) {
            return Err(MeshError::invalid(format!("vertex {i} has a non-finite coordinate")));
        }
        for (f, face) in self.faces.iter().enumerate() {
            if let Some(&i) = face.iter().find(|&&i| i as usize >= n) {
                return Err(MeshError::invalid(format!(
                    "face {f} refers to vertex {i}, but there are {n} vertices"
                )));
            }
        }
        Ok(())
    }

    /// Axis-aligned bounding box `(min, max)`, or `None` for an empty mesh.
    pub fn bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        bounds(&self.vertices)
    }

    /// One unit normal per face (zero for a degenerate face), by the right-hand rule.
    pub fn face_normals(&self) -> Vec<[f32; 3]> {
        self.faces.iter().map(|f| triangle_normal(self.triangle(f))).collect()
    }

    /// Area-weighted per-vertex normals, for writers that want them (GLB) and for point clouds
    /// sampled from meshes.
    pub fn vertex_normals(&self) -> Vec<[f32; 3]> {
        let mut acc = vec![[0.0f32; 3]; self.vertices.len()];
        for f in &self.faces {
            // The unnormalized cross product weights each face by twice its area.
            let c = cross_of(self.triangle(f));
            for &i in f {
                for k in 0..3 {
                    acc[i as usize][k] += c[k];
                }
            }
        }
        acc.into_iter().map(normalized).collect()
    }

    /// A mesh of `triangles` whose corners at exactly the same position share one vertex,
    /// numbered in order of first appearance.
    pub fn from_triangles(triangles: impl IntoIterator<Item = [[f32; 3]; 3]>) -> Mesh {
        let mut index_of = std::collections::HashMap::new();
        let mut mesh = Mesh::default();
        for corners in triangles {
            let face = corners.map(|p| {
                *index_of.entry(position_key(p)).or_insert_with(|| {
                    mesh.vertices.push(p);
                    // Saturating only past 2^32 distinct corners, far beyond any face limit.
                    u32::try_from(mesh.vertices.len() - 1).unwrap_or(u32::MAX)
                })
            });
            mesh.faces.push(face);
        }
        mesh
    }

    /// The three corner positions of a face.
    pub fn triangle(&self, f: &[u32; 3]) -> [[f32; 3]; 3] {
        [self.vertices[f[0] as usize], self.vertices[f[1] as usize], self.vertices[f[2] as usize]]
    }

    /// Total surface area.
    pub fn area(&self) -> f64 {
        self.faces.iter().map(|f| triangle_area(self.triangle(f))).sum()
    }

    /// For each vertex, the first vertex at exactly its position: files split vertices along
    /// seams (normals, UVs), which is not a hole in the surface.
    pub fn first_vertex_at_each_position(&self) -> Vec<u32> {
        let mut first_at: std::collections::HashMap<[u32; 3], u32> = Default::default();
        (0..)
            .zip(&self.vertices)
            .map(|(i, &p)| *first_at.entry(position_key(p)).or_insert(i))
            .collect()
    }

    /// Each valid face with its corners replaced by the first vertex at the same position,
    /// without the faces that collapse to an edge or a point: the faces as a user sees them
    /// joined, since files split vertices along seams (normals, UVs).
    pub fn welded_faces(&self) -> Vec<[u32; 3]> {
        let canonical = self.first_vertex_at_each_position();
        self.faces
            .iter()
            .filter_map(|f| {
                let [a, b, c] = f.map(|i| canonical.get(i as usize).copied());
                let face = [a?, b?, c?];
                (face[0] != face[1] && face[1] != face[2] && face[2] != face[0]).then_some(face)
            })
            .collect()
    }

    /// The same faces over only the vertices they use, which keep their order (and normals);
    /// indices must be valid ([`Self::validate`]). A point cloud comes back as it is.
    pub fn without_unused_vertices(&self) -> Mesh {
        if self.is_point_cloud() {
            return self.clone();
        }
        let mut index: Vec<Option<u32>> = vec![None; self.vertices.len()];
        for &c in self.faces.iter().flatten() {
            index[c as usize] = Some(0);
        }
        for (next, slot) in (0..).zip(index.iter_mut().flatten()) {
            *slot = next;
        }
        let used = |values: &[[f32; 3]]| -> Vec<[f32; 3]> {
            values.iter().zip(&index).filter(|(_, i)| i.is_some()).map(|(v, _)| *v).collect()
        };
        Mesh {
            vertices: used(&self.vertices),
            faces: self.faces.iter().map(|f| f.map(|c| index[c as usize].unwrap_or(0))).collect(),
            normals: self.normals.as_deref().map(used),
        }
    }
}

/// Axis-aligned bounding box of a point set, or `None` when it is empty.
pub fn bounds(points: &[[f32; 3]]) -> Option<([f32; 3], [f32; 3])> {
    let first = *points.first()?;
    Some(points.iter().fold((first, first), |(mut lo, mut hi), p| {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
        (lo, hi)
    }))
}

fn cross_of([a, b, c]: [[f32; 3]; 3]) -> [f32; 3] {
    let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]
}

/// `v` scaled to unit length, or zero when it has no direction (zero or non-finite length).
pub fn normalized(v: [f32; 3]) -> [f32; 3] {
    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if len > 0.0 && len.is_finite() { [v[0] / len, v[1] / len, v[2] / len] } else { [0.0; 3] }
}

/// Unit normal of a triangle (zero when it is degenerate).
pub fn triangle_normal(t: [[f32; 3]; 3]) -> [f32; 3] {
    normalized(cross_of(t))
}

/// Area of a triangle, computed in f64 so that large, thin faces keep their weight.
pub fn triangle_area([a, b, c]: [[f32; 3]; 3]) -> f64 {
    let u = [(b[0] - a[0]) as f64, (b[1] - a[1]) as f64, (b[2] - a[2]) as f64];
    let v = [(c[0] - a[0]) as f64, (c[1] - a[1]) as f64, (c[2] - a[2]) as f64];
    let x = u[1] * v[2] - u[2] * v[1];
    let y = u[2] * v[0] - u[0] * v[2];
    let z = u[0] * v[1] - u[1] * v[0];
    0.5 * (x * x + y * y + z * z).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_square() -> Mesh {
        Mesh::new(
            vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]],
            vec![[0, 1, 2], [0, 2, 3]],
        )
    }

    #[test]
    fn area_and_normals_of_a_square() {
        let m = unit_square();
        assert!((m.area() - 1.0).abs() < 1e-12);
        for n in m.face_normals().into_iter().chain(m.vertex_normals()) {
            assert_eq!(n, [0.0, 0.0, 1.0]);
        }
    }

    #[test]
    fn unused_vertices_go_and_the_rest_keep_their_order_and_normals() {
        let mut m = unit_square();
        m.normals = Some(vec![[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]]);
        m.faces = vec![[3, 2, 0]];
        let used = m.without_unused_vertices();
        assert_eq!(used.vertices, [[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]);
        assert_eq!(used.faces, [[2, 1, 0]]);
        assert_eq!(used.normals, Some(vec![[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]]));
        assert_eq!(unit_square().without_unused_vertices(), unit_square());
        let cloud = Mesh::new(m.vertices.clone(), Vec::new());
        assert_eq!(cloud.without_unused_vertices(), cloud);
    }

    #[test]
    fn validate_rejects_bad_indices_and_nan() {
        let mut m = unit_square();
        assert!(m.validate().is_ok());
        m.faces.push([0, 1, 9]);
        assert!(m.validate().is_err());
        let mut m = unit_square();
        m.vertices[1][2] = f32::NAN;
        assert!(m.validate().is_err());
    }

    #[test]
    fn bounds_of_empty_is_none() {
        assert_eq!(Mesh::default().bounds(), None);
        assert_eq!(unit_square().bounds(), Some(([0.0; 3], [1.0, 1.0, 0.0])));
    }
}
