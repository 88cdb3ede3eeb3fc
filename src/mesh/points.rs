//! What a reconstruction takes from whatever a user sends: points with normals, sampled from
//! a mesh's surface, taken from a point cloud, or with normals estimated when a cloud has none.

use std::num::NonZeroUsize;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rand::SeedableRng;
use rand::seq::index::sample;
use rand_chacha::ChaCha8Rng;

use super::{Mesh, MeshError, farthest_point_sampling, sample_surface};

/// Neighbours used to fit each estimated normal's plane.
pub const NORMAL_NEIGHBOURS: usize = 16;

/// The most points of its input a reconstruction is judged and fitted against
/// ([`InputClouds::reference`]). The encoder takes far fewer (the model's `num_points`), but
/// picking a candidate and fitting corners use the points directly, and 1,024 points leave a
/// shape's sharp tips unsampled, so a fitted corner stops short of them. 16,384 took 0.004 off
/// the dev split's Chamfer distance with the defaults, for a fit of a 400-face mesh four times
/// as long (0.2 s against 0.05 s; `docs/decisions.md`, "Fitting").
pub const REFERENCE_POINTS: usize = 16_384;

/// What a reconstruction takes of its input: the encoder's points, one draw per candidate,
/// and the denser reference it picks and fits its result against. All have unit normals.
#[derive(Debug, Clone, PartialEq)]
pub struct InputClouds {
    /// `draws` of them, the `i`-th drawn with seed `seed + i` (candidate `i`'s, see
    /// [`crate::candidates`]); the first is what a single decode reads.
    pub encoder: Vec<Mesh>,
    pub reference: Mesh,
}

/// `n` points for the encoder, `draws` times, and up to `reference` for the reference (as
/// [`reference_points`]), in `mesh`'s frame: sampled by area from a mesh's faces; from a
/// point cloud, a seeded subset of its points (the encoder's repeated up to `n` when the
/// cloud has fewer), its normals kept when it has them and estimated otherwise (once for all
/// draws). With an `oversampling` above 1 the encoder's are [`spread_points`] of that many
/// times as many (the model's [`crate::model::FaceConfig::point_oversampling`]).
pub fn input_clouds(
    mesh: &Mesh,
    n: usize,
    oversampling: usize,
    reference: usize,
    seed: u64,
    draws: usize,
) -> Result<InputClouds, MeshError> {
    let source = Source::of(mesh)?;
    Ok(InputClouds {
        encoder: (0..draws.max(1) as u64)
            .map(|i| source.spread(n, oversampling, seed.wrapping_add(i)))
            .collect::<Result<_, _>>()?,
        reference: source.at_most(reference, seed)?,
    })
}

/// The `n` points of `pool` farthest apart, in turn (farthest point sampling from its first
/// point: a pool drawn at random starts anywhere), with their normals; `pool` itself when it
/// has no more. Why: points drawn independently clump in places and leave gaps in others,
/// and what the model decodes depends on where they fall (`docs/decisions.md`, "Even encoder
/// points").
pub fn spread_points(pool: Mesh, n: usize) -> Mesh {
    if pool.vertices.len() <= n {
        return pool;
    }
    let picks = farthest_point_sampling(&pool.vertices, n, 0);
    let pick = |values: &[[f32; 3]]| picks.iter().map(|&i| values[i]).collect();
    Mesh {
        vertices: pick(&pool.vertices),
        faces: Vec::new(),
        normals: pool.normals.as_deref().map(pick),
    }
}

/// The reference points of [`input_clouds`] alone: up to `max` points of `mesh`, never a point
/// of a cloud twice. The baselines take these, so that they see what a reconstruction fits to.
pub fn reference_points(mesh: &Mesh, max: usize, seed: u64) -> Result<Mesh, MeshError> {
    Source::of(mesh)?.at_most(max, seed)
}

/// Where points are drawn from: a mesh's surface, or a cloud's points with unit normals.
enum Source<'a> {
    Surface(&'a Mesh),
    Cloud { points: &'a [[f32; 3]], normals: Vec<[f32; 3]> },
}

impl<'a> Source<'a> {
    fn of(mesh: &'a Mesh) -> Result<Self, MeshError> {
        if !mesh.faces.is_empty() {
            return Ok(Self::Surface(mesh));
        }
        mesh.validate()?;
        let m = mesh.vertices.len();
        if m < 3 {
            return Err(MeshError::invalid(format!(
                "a point cloud needs at least 3 points, got {m}"
            )));
        }
        let normals = match &mesh.normals {
            Some(normals)
                if normals.iter().all(|v| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) > 0.0) =>
            {
                normals.iter().map(|&v| unit(v)).collect()
            }
            _ => estimate_normals(&mesh.vertices, NORMAL_NEIGHBOURS),
        };
        Ok(Self::Cloud { points: &mesh.vertices, normals })
    }

    /// Exactly `n` points: a cloud's every point once, then seeded repeats, when it has fewer.
    fn exactly(&self, n: usize, seed: u64) -> Result<Mesh, MeshError> {
        match self {
            Self::Surface(mesh) => sample_surface(mesh, n, seed),
            Self::Cloud { points, normals } => {
                let m = points.len();
                let mut rng = ChaCha8Rng::seed_from_u64(seed);
                let picks: Vec<usize> = if m >= n {
                    sample(&mut rng, m, n).into_vec()
                } else {
                    (0..m).chain(sample(&mut rng, m, m).into_iter().cycle().take(n - m)).collect()
                };
                Ok(picked(points, normals, &picks))
            }
        }
    }

    /// Exactly `n` points, spread over `oversampling` times as many when that is above 1 and
    /// there are more than `n` to spread. The pool comes in a seeded order, so that the
    /// spreading starts elsewhere for another seed even when the pool is a whole cloud.
    fn spread(&self, n: usize, oversampling: usize, seed: u64) -> Result<Mesh, MeshError> {
        if oversampling <= 1 {
            return self.exactly(n, seed);
        }
        let mut pool_size = n.saturating_mul(oversampling);
        if let Self::Cloud { points, .. } = self {
            pool_size = pool_size.min(points.len());
        }
        let pool = self.exactly(pool_size, seed)?;
        if pool.vertices.len() <= n {
            return self.exactly(n, seed);
        }
        Ok(spread_points(pool, n))
    }

    /// At most `max` points: all of a cloud's when it has no more.
    fn at_most(&self, max: usize, seed: u64) -> Result<Mesh, MeshError> {
        match self {
            Self::Cloud { points, normals } if points.len() <= max => Ok(Mesh {
                vertices: points.to_vec(),
                faces: Vec::new(),
                normals: Some(normals.clone()),
            }),
            _ => self.exactly(max, seed),
        }
    }
}

/// The points `picks` of a cloud, with their normals.
fn picked(points: &[[f32; 3]], normals: &[[f32; 3]], picks: &[usize]) -> Mesh {
    Mesh {
        vertices: picks.iter().map(|&i| points[i]).collect(),
        faces: Vec::new(),
        normals: Some(picks.iter().map(|&i| normals[i]).collect()),
    }
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
    use crate::metrics::point_set_distances;

    #[test]
    fn meshes_are_sampled_and_clouds_subsampled_or_repeated() {
        let sphere = uv_sphere(1.0, 32, 16);
        let clouds = input_clouds(&sphere, 300, 1, 5000, 1, 1).unwrap();
        assert_eq!(clouds.encoder[0].vertices.len(), 300);
        assert_eq!(clouds.reference.vertices.len(), 5000);
        let points = Mesh { faces: Vec::new(), ..sample_surface(&sphere, 2000, 3).unwrap() };
        let m = points.vertices.len();
        for (n, reference) in [(100, 200), (m + 50, m + 50), (m + 50, m / 2)] {
            let c = input_clouds(&points, n, 1, reference, 2, 1).unwrap();
            assert_eq!(c.encoder[0].vertices.len(), n);
            assert_eq!(c.encoder[0].normals.as_ref().unwrap().len(), n);
            // The reference never repeats a point, so it has at most the cloud's.
            let expected = reference.min(m);
            assert_eq!(c.reference.normals.as_ref().unwrap().len(), expected);
            let mut distinct = c.reference.vertices.clone();
            distinct.sort_by(|a, b| a.partial_cmp(b).unwrap());
            distinct.dedup();
            assert_eq!(distinct.len(), expected);
        }
        assert!(input_clouds(&Mesh::new(vec![[0.0; 3]; 2], vec![]), 10, 1, 10, 0, 1).is_err());
    }

    #[test]
    fn spread_points_leave_smaller_gaps_than_independent_draws() {
        let sphere = uv_sphere(1.0, 32, 16);
        let dense = sample_surface(&sphere, 20_000, 9).unwrap().vertices;
        let cloud = Mesh { faces: Vec::new(), ..sample_surface(&sphere, 30_000, 8).unwrap() };
        for input in [&sphere, &cloud] {
            let spread = input_clouds(input, 256, 4, 1000, 5, 1).unwrap().encoder.remove(0);
            let drawn = input_clouds(input, 256, 1, 1000, 5, 1).unwrap().encoder.remove(0);
            assert_eq!(spread.normals.as_ref().map(Vec::len), Some(256));
            // How far the surface is from the nearest encoder point: on average, and at worst.
            let gaps = |points: &[[f32; 3]]| {
                let d = point_set_distances(points, &dense);
                (d.completeness, d.hausdorff)
            };
            let (spread_mean, spread_max) = gaps(&spread.vertices);
            let (drawn_mean, drawn_max) = gaps(&drawn.vertices);
            // Measured: 0.79-0.82 and 0.62-0.69 of the independent draws' gaps.
            assert!(spread_mean < 0.9 * drawn_mean, "{spread_mean} against {drawn_mean}");
            assert!(spread_max < 0.8 * drawn_max, "{spread_max} against {drawn_max}");
        }
        // A cloud's encoder points are its own, each once; a cloud too small to spread gives
        // the independent draw.
        let spread = input_clouds(&cloud, 256, 4, 1000, 5, 1).unwrap().encoder.remove(0).vertices;
        assert!(spread.iter().all(|p| cloud.vertices.contains(p)));
        let mut distinct = spread.clone();
        distinct.sort_by(|a, b| a.partial_cmp(b).unwrap());
        distinct.dedup();
        assert_eq!(distinct.len(), 256);
        let small = Mesh { faces: Vec::new(), ..sample_surface(&sphere, 200, 8).unwrap() };
        assert_eq!(
            input_clouds(&small, 256, 4, 1000, 5, 1).unwrap(),
            input_clouds(&small, 256, 1, 1000, 5, 1).unwrap()
        );
    }

    #[test]
    fn each_draw_of_the_encoder_points_is_its_seed_s_own() {
        let sphere = uv_sphere(1.0, 32, 16);
        // A cloud the spreading takes whole (600 points for 256 from 4 times as many).
        let cloud = Mesh { faces: Vec::new(), ..sample_surface(&sphere, 600, 8).unwrap() };
        for input in [&sphere, &cloud] {
            let clouds = input_clouds(input, 256, 4, 1000, 5, 3).unwrap();
            assert_eq!(clouds.encoder.len(), 3);
            for (i, draw) in clouds.encoder.iter().enumerate() {
                let alone = input_clouds(input, 256, 4, 1000, 5 + i as u64, 1).unwrap();
                assert_eq!(&alone.encoder[0], draw, "draw {i}");
            }
            assert_ne!(clouds.encoder[0], clouds.encoder[1]);
            assert_ne!(clouds.encoder[1], clouds.encoder[2]);
            // The reference is the request's, whatever the draws.
            assert_eq!(
                clouds.reference,
                input_clouds(input, 256, 4, 1000, 5, 1).unwrap().reference
            );
        }
    }

    #[test]
    fn the_baselines_get_the_reconstruction_s_reference() {
        let sphere = uv_sphere(1.0, 16, 8);
        let points = Mesh { faces: Vec::new(), ..sample_surface(&sphere, 3000, 4).unwrap() };
        for (input, max) in [(&sphere, 500), (&points, 2500), (&points, 5000)] {
            let clouds = input_clouds(input, 1024, 4, max, 7, 1).unwrap();
            assert_eq!(reference_points(input, max, 7).unwrap(), clouds.reference);
        }
        // Given normals are kept (made unit), not estimated.
        let reference = reference_points(&points, 5000, 7).unwrap();
        assert_eq!(reference.vertices, points.vertices);
        let given = points.normals.as_ref().unwrap().iter().map(|&n| unit(n));
        assert!(given.eq(reference.normals.unwrap()));
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
