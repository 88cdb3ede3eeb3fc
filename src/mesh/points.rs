//! The encoder's input from whatever a user sends: points with normals, sampled from a
//! mesh's surface, taken from a point cloud, or with normals estimated when a cloud has none.

use std::num::NonZeroUsize;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rand::SeedableRng;
use rand::seq::index::sample;
use rand_chacha::ChaCha8Rng;

use super::{Mesh, MeshError, sample_surface};

/// Neighbours used to fit each estimated normal's plane.
pub const NORMAL_NEIGHBOURS: usize = 16;

/// Exactly `n` points with unit normals: sampled by area from a mesh's faces, or drawn from a
/// point cloud (a seeded subset if it has more than `n` points, repeats if fewer), its normals
/// kept when it has them and estimated otherwise.
pub fn encoder_points(mesh: &Mesh, n: usize, seed: u64) -> Result<Mesh, MeshError> {
    if !mesh.faces.is_empty() {
        return sample_surface(mesh, n, seed);
    }
    mesh.validate()?;
    let m = mesh.vertices.len();
    if m < 3 {
        return Err(MeshError::invalid(format!("a point cloud needs at least 3 points, got {m}")));
    }
    let normals = match &mesh.normals {
        Some(normals)
            if normals.iter().all(|v| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) > 0.0) =>
        {
            normals.iter().map(|&v| unit(v)).collect()
        }
        _ => estimate_normals(&mesh.vertices, NORMAL_NEIGHBOURS),
    };
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let picks: Vec<usize> = if m >= n {
        sample(&mut rng, m, n).into_vec()
    } else {
        // Every point once, then seeded repeats up to n.
        (0..m).chain(sample(&mut rng, m, m).into_iter().cycle().take(n - m)).collect()
    };
    Ok(Mesh {
        vertices: picks.iter().map(|&i| mesh.vertices[i]).collect(),
        faces: Vec::new(),
        normals: Some(picks.iter().map(|&i| normals[i]).collect()),
    })
}

fn unit(v: [f32; 3]) -> [f32; 3] {
    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    v.map(|c| c / len)
}

/// Normals of a point cloud: the direction of least variance of each point's `k` nearest
/// neighbours (principal component analysis), turned to point away from the cloud's centroid.
/// That orientation is right for shapes that are star-shaped around their centroid; a cloud
/// whose normals matter beyond that should carry its own.
pub fn estimate_normals(points: &[[f32; 3]], k: usize) -> Vec<[f32; 3]> {
    let Ok(tree) = ImmutableKdTree::<f32, 3>::new_from_slice(points) else {
        return vec![[0.0, 0.0, 1.0]; points.len()];
    };
    let k = NonZeroUsize::new(k.clamp(3, points.len().max(3))).unwrap_or(NonZeroUsize::MIN);
    let neighbours = tree.query_batch(points).nearest_n::<SquaredEuclidean<f32>>(k).execute();
    let centroid = mean(points.iter());
    points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let group = neighbours.get(i).unwrap_or_default();
            let local: Vec<[f32; 3]> = group.iter().map(|n| points[n.item as usize]).collect();
            let mut n = least_variance_direction(&local);
            let outward: f32 = (0..3).map(|a| (p[a] - centroid[a]) * n[a]).sum();
            if outward < 0.0 {
                n = n.map(|c| -c);
            }
            n
        })
        .collect()
}

fn mean<'a>(points: impl ExactSizeIterator<Item = &'a [f32; 3]>) -> [f32; 3] {
    let n = points.len().max(1) as f64;
    let sum = points.fold([0.0f64; 3], |acc, p| std::array::from_fn(|a| acc[a] + p[a] as f64));
    sum.map(|s| (s / n) as f32)
}

/// The unit eigenvector of the smallest eigenvalue of the points' covariance (the normal of
/// their best-fitting plane); (0, 0, 1) when the points do not define one.
fn least_variance_direction(points: &[[f32; 3]]) -> [f32; 3] {
    let c = mean(points.iter());
    let mut cov = [[0.0f64; 3]; 3];
    for p in points {
        let d: [f64; 3] = std::array::from_fn(|a| (p[a] - c[a]) as f64);
        for r in 0..3 {
            for s in 0..3 {
                cov[r][s] += d[r] * d[s];
            }
        }
    }
    let lambda = smallest_eigenvalue(&cov);
    // The eigenvector is orthogonal to the rows of (C - lambda I): take the longest cross
    // product of two rows, which is the most stable choice.
    let m: [[f64; 3]; 3] = std::array::from_fn(|r| {
        std::array::from_fn(|s| cov[r][s] - if r == s { lambda } else { 0.0 })
    });
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    };
    let candidates = [cross(m[0], m[1]), cross(m[0], m[2]), cross(m[1], m[2])];
    let norm2 = |v: &[f64; 3]| v.iter().map(|x| x * x).sum::<f64>();
    let best = candidates.iter().copied().max_by(|a, b| norm2(a).total_cmp(&norm2(b)));
    match best {
        Some(v) if norm2(&v) > 1e-30 => {
            let len = norm2(&v).sqrt();
            v.map(|x| (x / len) as f32)
        }
        _ => [0.0, 0.0, 1.0],
    }
}

/// Smallest eigenvalue of a symmetric 3 x 3 matrix, in closed form (the trigonometric
/// solution of the characteristic cubic).
fn smallest_eigenvalue(a: &[[f64; 3]; 3]) -> f64 {
    let p1 = a[0][1].powi(2) + a[0][2].powi(2) + a[1][2].powi(2);
    let q = (a[0][0] + a[1][1] + a[2][2]) / 3.0;
    if p1 <= f64::EPSILON * (q * q).max(f64::MIN_POSITIVE) {
        return a[0][0].min(a[1][1]).min(a[2][2]);
    }
    let p2 = (a[0][0] - q).powi(2) + (a[1][1] - q).powi(2) + (a[2][2] - q).powi(2) + 2.0 * p1;
    let p = (p2 / 6.0).sqrt();
    let b: [[f64; 3]; 3] = std::array::from_fn(|r| {
        std::array::from_fn(|s| (a[r][s] - if r == s { q } else { 0.0 }) / p)
    });
    let det = b[0][0] * (b[1][1] * b[2][2] - b[1][2] * b[2][1])
        - b[0][1] * (b[1][0] * b[2][2] - b[1][2] * b[2][0])
        + b[0][2] * (b[1][0] * b[2][1] - b[1][1] * b[2][0]);
    let phi = (det / 2.0).clamp(-1.0, 1.0).acos() / 3.0;
    // The three roots are q + 2p cos(phi + 2 pi j / 3); j = 1 gives the smallest.
    q + 2.0 * p * (phi + 2.0 * std::f64::consts::PI / 3.0).cos()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::uv_sphere;

    #[test]
    fn meshes_are_sampled_and_clouds_subsampled_or_repeated() {
        let sphere = uv_sphere(1.0, 32, 16);
        let cloud = encoder_points(&sphere, 300, 1).unwrap();
        assert_eq!(cloud.vertices.len(), 300);
        let mut points = sphere.clone();
        points.faces.clear();
        for n in [100, sphere.vertices.len() + 50] {
            let c = encoder_points(&points, n, 2).unwrap();
            assert_eq!(c.vertices.len(), n);
            assert_eq!(c.normals.as_ref().unwrap().len(), n);
        }
        assert!(encoder_points(&Mesh::new(vec![[0.0; 3]; 2], vec![]), 10, 0).is_err());
    }

    #[test]
    fn estimated_normals_of_a_sphere_point_outwards() {
        let sphere = sample_surface(&uv_sphere(2.0, 64, 32), 2000, 3).unwrap();
        let normals = estimate_normals(&sphere.vertices, NORMAL_NEIGHBOURS);
        for (p, n) in sphere.vertices.iter().zip(&normals) {
            let radial = unit(*p);
            let cos: f32 = (0..3).map(|a| radial[a] * n[a]).sum();
            assert!(cos > 0.95, "normal {n:?} at {p:?}");
        }
    }

    #[test]
    fn smallest_eigenvalue_of_known_matrices() {
        let diag = [[3.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2.0]];
        assert_eq!(smallest_eigenvalue(&diag), 1.0);
        // Eigenvalues 1, 2 and 4 after a rotation about z by 45 degrees.
        let a = [[3.0, 1.0, 0.0], [1.0, 3.0, 0.0], [0.0, 0.0, 1.0]];
        assert!((smallest_eigenvalue(&a) - 1.0).abs() < 1e-12);
        let a = [[2.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 5.0]];
        assert!((smallest_eigenvalue(&a) - 1.0).abs() < 1e-12);
        assert_eq!(
            least_variance_direction(&[
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [1.0, 1.0, 0.0]
            ])
            .map(f32::abs),
            [0.0, 0.0, 1.0]
        );
    }
}
