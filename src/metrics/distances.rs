//! Chamfer and Hausdorff distances, as DESIGN.md's "Evaluation metrics" define them.

use kiddo::{ImmutableKdTree, SquaredEuclidean};

use crate::mesh::{Mesh, MeshError, Normalization, sample_surface};

use super::MetricsError;

/// How surfaces are sampled for [`mesh_distances`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct MetricOptions {
    /// Points sampled on each surface (DESIGN.md: 50,000).
    pub samples: usize,
    /// Seed of the ground truth's samples; the prediction's use `seed + 1` (see
    /// [`mesh_distances`]).
    pub seed: u64,
}

impl Default for MetricOptions {
    fn default() -> Self {
        Self { samples: 50_000, seed: 0 }
    }
}

/// Chamfer distance (sum of both mean nearest-neighbour distances) and Hausdorff distance
/// (larger of both maxima), plain Euclidean, in the ground truth's normalized frame; and the
/// Chamfer distance's two halves, which tell wrong surface from missing surface.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Distances {
    pub chamfer: f64,
    pub hausdorff: f64,
    /// Mean distance from the prediction to the ground truth: high when the prediction has
    /// surface where the ground truth has none.
    pub accuracy: f64,
    /// Mean distance from the ground truth to the prediction: high when the prediction misses
    /// part of the ground truth (an early end of mesh, say).
    pub completeness: f64,
}

impl Distances {
    /// The result when there is nothing to match: no point is near an empty set.
    const INFINITE: Self = Self {
        chamfer: f64::INFINITY,
        hausdorff: f64::INFINITY,
        accuracy: f64::INFINITY,
        completeness: f64::INFINITY,
    };
}

/// CD = mean_a d(a, B) + mean_b d(b, A), HD = max(max_a d(a, B), max_b d(b, A)), with d the
/// Euclidean distance to the nearest point of the other set; `a` is the prediction's samples
/// and `b` the ground truth's (accuracy is mean_a d(a, B), completeness mean_b d(b, A)).
///
/// When either set is empty or holds a non-finite coordinate, both distances are infinite:
/// there is no meaningful nearest point, and an infinite figure cannot pass for a good one.
pub fn point_set_distances(a: &[[f32; 3]], b: &[[f32; 3]]) -> Distances {
    let finite = |s: &[[f32; 3]]| s.iter().flatten().all(|c| c.is_finite());
    if a.is_empty() || b.is_empty() || !finite(a) || !finite(b) {
        return Distances::INFINITE;
    }
    match (directed(a, b), directed(b, a)) {
        (Some((mean_ab, max_ab)), Some((mean_ba, max_ba))) => Distances {
            chamfer: mean_ab + mean_ba,
            hausdorff: max_ab.max(max_ba),
            accuracy: mean_ab,
            completeness: mean_ba,
        },
        // Only a set past the tree's u32 item indices (2^32 points) fails to build.
        _ => Distances::INFINITE,
    }
}

/// Mean and maximum over `from` of the distance to the nearest point of `to` (both non-empty,
/// finite); `None` if `to` is too large for a k-d tree.
fn directed(from: &[[f32; 3]], to: &[[f32; 3]]) -> Option<(f64, f64)> {
    let tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(to).ok()?;
    let nearest = tree.query_batch(from).nearest_one::<SquaredEuclidean<f32>>().execute();
    let (sum, max) = nearest.iter().fold((0.0f64, 0.0f64), |(sum, max), n| {
        let d = f64::from(n.distance).sqrt();
        (sum + d, max.max(d))
    });
    Some((sum / from.len() as f64, max))
}

/// Chamfer and Hausdorff distances between a predicted and a ground-truth mesh, both in the
/// GROUND TRUTH's normalized frame (its normalization applied to both).
///
/// `opts.samples` points are sampled uniformly by area on each surface. The two samplings use
/// different streams (`seed` for the ground truth, `seed + 1` for the prediction): identical
/// meshes then score the sampling floor DESIGN.md quotes (CD about 0.022 for the cube at
/// 50,000 points), as two independent scans would, not an exact zero. A ground truth without
/// faces (a point cloud) is used as its points. A prediction without faces is
/// [`MetricsError::EmptyPrediction`].
pub fn mesh_distances(
    pred: &Mesh,
    gt: &Mesh,
    opts: &MetricOptions,
) -> Result<Distances, MetricsError> {
    if opts.samples == 0 {
        return Err(MetricsError::NoSamples);
    }
    gt.validate().map_err(MetricsError::InvalidGroundTruth)?;
    pred.validate().map_err(MetricsError::InvalidPrediction)?;
    if pred.faces.is_empty() {
        return Err(MetricsError::EmptyPrediction);
    }
    let frame = Normalization::fit(&gt.vertices).map_err(MetricsError::InvalidGroundTruth)?;

    let gt_points = if gt.is_point_cloud() {
        frame.apply_mesh(gt).vertices
    } else {
        sample_surface(&frame.apply_mesh(gt), opts.samples, opts.seed)
            .map_err(MetricsError::InvalidGroundTruth)?
            .vertices
    };
    let pred = frame.apply_mesh(pred);
    // A prediction far outside the ground truth's box can overflow f32 in its frame.
    pred.validate().map_err(|e| {
        MetricsError::InvalidPrediction(MeshError::invalid(format!(
            "in the ground truth's frame: {e}"
        )))
    })?;
    let pred_points = sample_surface(&pred, opts.samples, opts.seed.wrapping_add(1))
        .map_err(MetricsError::InvalidPrediction)?
        .vertices;
    Ok(point_set_distances(&pred_points, &gt_points))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::{cuboid, uv_sphere};

    const N: usize = 50_000;

    fn opts() -> MetricOptions {
        MetricOptions { samples: N, seed: 42 }
    }

    /// Expected mean nearest-neighbour distance from a point of a surface to N uniform samples
    /// of the same flat surface of area `area`: the nearest of a 2-D Poisson process of density
    /// rho is 1 / (2 sqrt(rho)) away on average. Two directions make the Chamfer floor.
    fn chamfer_floor(area: f64) -> f64 {
        2.0 / (2.0 * (N as f64 / area).sqrt())
    }

    fn moved(m: &Mesh, by: [f32; 3]) -> Mesh {
        let vertices = m.vertices.iter().map(|v| [0, 1, 2].map(|k| v[k] + by[k])).collect();
        Mesh::new(vertices, m.faces.clone())
    }

    fn scaled(m: &Mesh, s: f32) -> Mesh {
        Mesh::new(m.vertices.iter().map(|v| v.map(|c| c * s)).collect(), m.faces.clone())
    }

    #[test]
    fn tiny_point_sets_have_exact_answers() {
        let a = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]];
        let b = [[0.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, 4.0]];
        // a -> B: 0 and 1 (mean 1/2, max 1). b -> A: 0, 3 (not sqrt 10), 4 (not sqrt 17):
        // mean 7/3, max 4.
        let d = point_set_distances(&a, &b);
        assert!((d.chamfer - (0.5 + 7.0 / 3.0)).abs() < 1e-12, "{d:?}");
        assert_eq!(d.hausdorff, 4.0);
        assert_eq!(d.accuracy, 0.5);
        assert!((d.completeness - 7.0 / 3.0).abs() < 1e-12, "{d:?}");
        // Swapping the sets swaps the halves and nothing else.
        let swapped = point_set_distances(&b, &a);
        assert_eq!((swapped.chamfer, swapped.hausdorff), (d.chamfer, d.hausdorff));
        assert_eq!((swapped.accuracy, swapped.completeness), (d.completeness, d.accuracy));
        // A 3-4-5 triangle: one pair at distance 5 each way.
        let d = point_set_distances(&[[3.0, 4.0, 0.0]], &[[0.0; 3]]);
        assert_eq!((d.chamfer, d.hausdorff), (10.0, 5.0));
        // Many copies of one point (more than a k-d tree bucket) against that point.
        let d = point_set_distances(&[[1.0, 2.0, 3.0]; 100], &[[1.0, 2.0, 3.0]; 70]);
        assert_eq!((d.chamfer, d.hausdorff), (0.0, 0.0));
    }

    #[test]
    fn empty_or_non_finite_sets_are_infinitely_far() {
        let p = [[0.0f32; 3]];
        for (a, b) in [(&[][..], &p[..]), (&p[..], &[][..]), (&[[f32::NAN, 0.0, 0.0]][..], &p[..])]
        {
            let d = point_set_distances(a, b);
            assert_eq!((d.chamfer, d.hausdorff), (f64::INFINITY, f64::INFINITY));
        }
    }

    #[test]
    fn cube_against_the_cube_shifted_along_x() {
        // GT: the unit cube [0, 1]^3; its frame maps it to [-1, 1]^3 (scale 2), so the shift of
        // 0.1 becomes s = 0.2: the prediction is [-1 + s, 1 + s] x [-1, 1]^2. Area 24.
        //
        // Mean distance from the GT surface A to the prediction B, face by face (integrals):
        // - x = -1 (area 4): outside B, s from B's face x = -1 + s: 4 s.
        // - x = +1 (area 4): inside B; distance min(s, 1 - |y|, 1 - |z|) to B's walls. With
        //   u = 1 - |y|, w = 1 - |z| uniform on [0, 1]^2 (4 copies), m = min(u, w) has density
        //   2 (1 - m): 4 [ int_0^s 2m(1 - m) dm + s (1 - s)^2 ] = 4 (s^2 - 2 s^3 / 3 + s (1 - s)^2).
        // - y = +-1, z = +-1 (4 faces): on B where x >= -1 + s, else (-1 + s) - x away from B's
        //   edge: each 2 x int_0^s t dt = s^2, together 4 s^2.
        // By the mirror x -> -x the mean from B to A is the same, so CD = 2 x (sum) / 24.
        // HD: the x = -1 face is s from B everywhere and nothing is farther: HD = s.
        let gt = cuboid([1.0; 3]).translated([0.5; 3]);
        let pred = moved(&gt, [0.1, 0.0, 0.0]);
        let s = 0.1 / Normalization::fit(&gt.vertices).unwrap().half_extent;
        let integral =
            4.0 * s + 4.0 * (s * s - 2.0 * s.powi(3) / 3.0 + s * (1.0 - s).powi(2)) + 4.0 * s * s;
        let exact_cd = 2.0 * integral / 24.0; // 0.1342 for s = 0.2
        let d = mesh_distances(&pred, &gt, &opts()).unwrap();
        // Nearest samples are never closer than the surface itself, so the estimate exceeds the
        // exact value by at most the sampling floor (where the surfaces touch) and falls below
        // it only by the Monte Carlo error of the mean (about 0.1 / sqrt(N)).
        let floor = chamfer_floor(24.0);
        assert!(
            d.chamfer > exact_cd - 0.002 && d.chamfer < exact_cd + floor,
            "{d:?} vs {exact_cd}"
        );
        // Points of the x = -1 face are exactly s away; a gap between samples of up to 0.05
        // (DESIGN.md's Hausdorff floor) adds at most sqrt(s^2 + 0.05^2) - s.
        assert!(d.hausdorff > s - 1e-4, "{d:?}");
        assert!(d.hausdorff < (s * s + 0.05f64.powi(2)).sqrt(), "{d:?}");
    }

    #[test]
    fn concentric_spheres() {
        // Between concentric spheres every point is R2 - R1 from the other surface, both ways:
        // CD = 2 (R2 - R1), HD = R2 - R1, scaled by the GT frame (1 / its half extent). The fine
        // tessellation changes the gap by (R2 - R1)(1 - cos(pi / 128)), below 1e-4.
        let (r1, r2) = (1.0f32, 1.25f32);
        let gt = uv_sphere(r1, 128, 64);
        let pred = scaled(&gt, r2 / r1);
        let frame = Normalization::fit(&gt.vertices).unwrap();
        let gap = f64::from(r2 - r1) / frame.half_extent;
        let d = mesh_distances(&pred, &gt, &opts()).unwrap();
        // At distance `gap`, a nearest sample r off the foot point is sqrt(gap^2 + r^2) away:
        // r of 0.01 (mean spacing) or 0.05 (largest gap) adds r^2 / (2 gap).
        let mean_bias = 2.0 * 0.01f64.powi(2) / (2.0 * gap);
        assert!((d.chamfer - 2.0 * gap).abs() < 0.001 + mean_bias, "{d:?} vs {}", 2.0 * gap);
        assert!(d.hausdorff > gap - 0.001, "{d:?}");
        assert!(d.hausdorff < gap + 0.05f64.powi(2) / (2.0 * gap), "{d:?}");
        // The prediction may be the smaller one: the same by symmetry.
        let d_inner = mesh_distances(&scaled(&gt, 0.8), &gt, &opts()).unwrap();
        let inner_gap = 0.2 / frame.half_extent;
        assert!((d_inner.chamfer - 2.0 * inner_gap).abs() < 0.001 + mean_bias, "{d_inner:?}");
    }

    #[test]
    fn identical_meshes_score_the_sampling_floor() {
        // DESIGN.md: CD 0.022, HD 0.046 for the cube [-1, 1]^3 at N = 50,000.
        let gt = cuboid([2.0; 3]);
        let floor = chamfer_floor(24.0); // 0.0219
        let d = mesh_distances(&gt, &gt, &opts()).unwrap();
        assert!(d.chamfer > 0.8 * floor && d.chamfer < 1.25 * floor, "{d:?} vs {floor}");
        assert!(d.hausdorff > 0.0 && d.hausdorff < 0.08, "{d:?}");
        // The frame is the ground truth's: a GT of another size scales both figures alike.
        let big = scaled(&gt, 10.0);
        let d_big = mesh_distances(&big, &big, &opts()).unwrap();
        assert!((d_big.chamfer - d.chamfer).abs() < 0.1 * floor, "{d_big:?} vs {d:?}");
    }

    #[test]
    fn a_point_cloud_ground_truth_is_used_as_it_is() {
        let gt = cuboid([2.0; 3]);
        let cloud = sample_surface(&gt, N, 9).unwrap();
        let d = mesh_distances(&gt, &cloud, &opts()).unwrap();
        assert!(d.chamfer < 1.25 * chamfer_floor(24.0), "{d:?}");
    }

    #[test]
    fn unusable_inputs_are_typed_errors() {
        let gt = cuboid([2.0; 3]);
        let points_only = Mesh::new(gt.vertices.clone(), vec![]);
        let err = |pred: &Mesh, gt: &Mesh, o: MetricOptions| mesh_distances(pred, gt, &o).err();
        assert!(matches!(err(&points_only, &gt, opts()), Some(MetricsError::EmptyPrediction)));
        assert!(matches!(err(&Mesh::default(), &gt, opts()), Some(MetricsError::EmptyPrediction)));
        let flat = Mesh::new(vec![[0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]], vec![[0, 1, 2]]);
        assert!(matches!(err(&flat, &gt, opts()), Some(MetricsError::InvalidPrediction(_))));
        let bad = Mesh::new(vec![[0.0; 3]], vec![[0, 0, 5]]);
        assert!(matches!(err(&bad, &gt, opts()), Some(MetricsError::InvalidPrediction(_))));
        assert!(matches!(
            err(&gt, &Mesh::default(), opts()),
            Some(MetricsError::InvalidGroundTruth(_))
        ));
        let one_point = Mesh::new(vec![[1.0; 3]; 3], vec![]);
        assert!(matches!(err(&gt, &one_point, opts()), Some(MetricsError::InvalidGroundTruth(_))));
        let no_samples = MetricOptions { samples: 0, seed: 0 };
        assert!(matches!(err(&gt, &gt, no_samples), Some(MetricsError::NoSamples)));
        // A tiny GT makes a far prediction overflow f32 in the GT's frame.
        let tiny = scaled(&gt, 1e-20);
        let far = moved(&gt, [1e20, 0.0, 0.0]);
        assert!(matches!(err(&far, &tiny, opts()), Some(MetricsError::InvalidPrediction(_))));
    }

    /// Timing at the size DESIGN.md fixes, and the sampling floor of the cube:
    /// `cargo test --release --lib -- --ignored --nocapture metrics::`.
    #[test]
    #[ignore = "timing, run in release"]
    fn time_mesh_distances_at_50k() {
        let gt = uv_sphere(1.0, 128, 64);
        let pred = scaled(&gt, 1.1);
        let start = std::time::Instant::now();
        let d = mesh_distances(&pred, &gt, &MetricOptions::default()).unwrap();
        let elapsed = start.elapsed();
        println!("mesh_distances, {} faces each, N = 50,000: {elapsed:?} ({d:?})", gt.faces.len());
        let cube = cuboid([2.0; 3]);
        let d = mesh_distances(&cube, &cube, &MetricOptions::default()).unwrap();
        println!("cube [-1, 1]^3 against itself, N = 50,000: {d:?}");
    }
}
