//! Uniform surface sampling: the point clouds the encoder reads and the metrics compare.

use rand::SeedableRng;
use rand::distr::Distribution;
use rand::distr::weighted::WeightedIndex;
use rand::{Rng, RngCore};
use rand_chacha::ChaCha8Rng;

use super::{Mesh, MeshError, triangle_area};

/// `n` points uniformly distributed by area on the surface, each with its face's unit normal;
/// the same seed gives the same points.
///
/// Returns a point cloud (no faces, `normals` set). Errors (`MeshError::Invalid`) for an
/// invalid mesh, a mesh without faces, or one whose total area is zero.
pub fn sample_surface(mesh: &Mesh, n: usize, seed: u64) -> Result<Mesh, MeshError> {
    let samples = surface_samples(mesh, n, seed)?;
    let normals = mesh.face_normals();
    let (points, point_normals) =
        samples.into_iter().map(|sample| (sample.position(mesh), normals[sample.face])).unzip();
    Ok(Mesh { vertices: points, faces: Vec::new(), normals: Some(point_normals) })
}

/// A point on a mesh's surface, kept as where it lies rather than as a position, so that it
/// can follow the corners when they move.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct SurfaceSample {
    pub face: usize,
    /// Barycentric weights of the face's three corners (they sum to 1).
    pub weights: [f64; 3],
}

impl SurfaceSample {
    pub fn position(&self, mesh: &Mesh) -> [f32; 3] {
        let corners = mesh.triangle(&mesh.faces[self.face]);
        std::array::from_fn(|k| {
            (0..3).map(|c| self.weights[c] * f64::from(corners[c][k])).sum::<f64>() as f32
        })
    }
}

/// The samples behind [`sample_surface`]: `n` uniform by area; same errors.
pub(crate) fn surface_samples(
    mesh: &Mesh,
    n: usize,
    seed: u64,
) -> Result<Vec<SurfaceSample>, MeshError> {
    mesh.validate()?;
    if mesh.faces.is_empty() {
        return Err(MeshError::invalid("no faces to sample"));
    }
    let areas: Vec<f64> = mesh.faces.iter().map(|f| triangle_area(mesh.triangle(f))).collect();
    // Zero-area faces are simply never chosen. (Areas are f64, so even faces spanning the
    // whole f32 range have a finite area.)
    if areas.iter().all(|&a| a == 0.0) {
        return Err(MeshError::invalid("no surface to sample: every face has no area"));
    }
    let choose = WeightedIndex::new(&areas)
        .map_err(|e| MeshError::invalid(format!("cannot sample the surface by area: {e}")))?;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    Ok((0..n)
        .map(|_| {
            let face = choose.sample(&mut rng);
            SurfaceSample { face, weights: uniform_in_triangle(&mut rng) }
        })
        .collect())
}

/// The barycentric weights of a uniform point in a triangle: with r1, r2 uniform in [0, 1)
/// and s = sqrt(r1), (1 - s, s (1 - r2), s r2) are uniform over the triangle (the square
/// root undoes the density growing linearly away from the first corner).
fn uniform_in_triangle(rng: &mut impl RngCore) -> [f64; 3] {
    let s = rng.random::<f64>().sqrt();
    let r2 = rng.random::<f64>();
    [1.0 - s, s * (1.0 - r2), s * r2]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::cuboid;

    #[test]
    fn same_seed_same_points_other_seed_other_points() {
        let m = cuboid([2.0; 3]);
        let a = sample_surface(&m, 500, 7).unwrap();
        assert_eq!(a, sample_surface(&m, 500, 7).unwrap());
        assert_ne!(a.vertices, sample_surface(&m, 500, 8).unwrap().vertices);
        assert_eq!(a.vertices.len(), 500);
        assert!(a.is_point_cloud());
    }

    #[test]
    fn points_lie_on_the_cube_with_their_faces_normals() {
        let m = cuboid([2.0; 3]);
        let s = sample_surface(&m, 5000, 1).unwrap();
        let normals = s.normals.as_ref().unwrap();
        for (p, n) in s.vertices.iter().zip(normals) {
            assert!(p.iter().all(|c| c.abs() <= 1.0 + 1e-6), "{p:?} outside the cube");
            // The normal is the outward axis of a face the point lies on.
            let axis = (0..3).find(|&k| n[k] != 0.0).unwrap();
            assert_eq!(n[axis].abs(), 1.0);
            assert!((p[axis] - n[axis]).abs() < 1e-6, "{p:?} not on the face with normal {n:?}");
        }
    }

    #[test]
    fn points_lie_in_their_triangle() {
        // One slanted triangle: every point is a convex combination of the corners, so it lies
        // in the plane x + y + z = 1 and inside the positive octant.
        let m = Mesh::new(vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], vec![[0, 1, 2]]);
        let s = sample_surface(&m, 2000, 3).unwrap();
        let n = 1.0 / 3f32.sqrt();
        for (p, normal) in s.vertices.iter().zip(s.normals.unwrap()) {
            assert!((p[0] + p[1] + p[2] - 1.0).abs() < 1e-6);
            assert!(p.iter().all(|&c| c >= 0.0));
            assert!(normal.iter().all(|&c| (c - n).abs() < 1e-6));
        }
    }

    #[test]
    fn sample_counts_are_proportional_to_area() {
        // Four triangles in separate planes z = 0, 1, 2, 3 (so each point tells its face) with
        // areas 0.5, 1.5, 3 and 0 (degenerate): expected shares 0.1, 0.3, 0.6, 0.
        let tri = |z: f32, w: f32| [[0.0, 0.0, z], [w, 0.0, z], [0.0, 1.0, z]];
        let corners = [tri(0.0, 1.0), tri(1.0, 3.0), tri(2.0, 6.0), tri(3.0, 0.0)];
        let vertices = corners.concat();
        let faces = (0..4).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
        let n = 20_000;
        let s = sample_surface(&Mesh::new(vertices, faces), n, 11).unwrap();
        let mut counts = [0usize; 4];
        for p in &s.vertices {
            counts[p[2].round() as usize] += 1;
        }
        assert_eq!(counts[3], 0, "a zero-area face was sampled");
        for (count, share) in counts.iter().zip([0.1, 0.3, 0.6]) {
            // Binomial standard deviation sqrt(n p (1 - p)); 5 sigma keeps the test stable.
            let expected = n as f64 * share;
            let sigma = (expected * (1.0 - share)).sqrt();
            assert!((*count as f64 - expected).abs() < 5.0 * sigma, "{counts:?}");
        }
    }

    #[test]
    fn uniform_within_a_triangle() {
        // The right triangle (0,0)-(1,0)-(0,1): the part with x + y < 1/2 holds a quarter of its
        // area, so a quarter of the points.
        let m = Mesh::new(vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], vec![[0, 1, 2]]);
        let n = 20_000;
        let s = sample_surface(&m, n, 5).unwrap();
        let inner = s.vertices.iter().filter(|p| p[0] + p[1] < 0.5).count() as f64;
        let sigma = (n as f64 * 0.25 * 0.75).sqrt();
        assert!((inner - n as f64 * 0.25).abs() < 5.0 * sigma, "{inner}");
    }

    #[test]
    fn meshes_without_area_are_errors() {
        let cloud = Mesh::new(vec![[0.0; 3], [1.0, 0.0, 0.0]], vec![]);
        assert!(matches!(sample_surface(&cloud, 10, 0), Err(MeshError::Invalid(_))));
        let flat = Mesh::new(vec![[0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]], vec![[0, 1, 2]]);
        let error = sample_surface(&flat, 10, 0).unwrap_err().to_string();
        assert!(error.contains("every face has no area"), "{error}");
        let bad_index = Mesh::new(vec![[0.0; 3]], vec![[0, 1, 2]]);
        assert!(sample_surface(&bad_index, 10, 0).is_err());
        assert_eq!(
            sample_surface(&crate::mesh::primitives::cuboid([1.0; 3]), 0, 0)
                .unwrap()
                .vertices
                .len(),
            0
        );
    }
}
