//! Augmentation as in the paper: random rotation, random flips, independent scaling per axis;
//! and, beyond it, encoder points taken as a scan gives them (noisy, normals estimated).

use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::mesh::transform::{Mat3, mat_mul, rotation, rotation_from_quaternion, scaling};
use crate::mesh::{Mesh, NORMAL_NEIGHBOURS, estimate_normals};

/// The vertical axis: y, as in glTF; procedural shapes are built the same way. The low-poly
/// data set is mixed: 1,264 of its meshes stand on y = 0, but 1,084 (nearly every Kenney
/// family) on z = 0, and these are trained lying (`docs/decisions.md`, "The caller says which
/// axis is up").
pub const UP: usize = 1;

/// Which rotations augmentation draws from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Rotation {
    /// No rotation.
    None,
    /// About the vertical axis ([`UP`]) only, by any angle or by a quarter turn (see
    /// [`AugmentConfig::any_angle_share`]), and flips of the horizontal axes only: artist
    /// meshes mostly stand upright, and stay so.
    Upright,
    /// One of the 24 rotations of the cube: keeps axis-aligned faces axis-aligned.
    RightAngles,
    /// Uniformly random in 3-D.
    Full,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AugmentConfig {
    pub rotation: Rotation,
    /// Probability of mirroring along each axis, drawn independently per axis (not the
    /// vertical one with [`Rotation::Upright`]).
    pub flip_probability: f32,
    /// Each axis is scaled by a factor drawn uniformly from `[1 - s, 1 + s]`.
    pub scale_jitter: f32,
    /// With [`Rotation::Upright`]: the share of samples turned by any angle; the others turn
    /// by a multiple of 90 degrees, which keeps axis-aligned faces axis-aligned. Artist meshes
    /// are mostly built on the axes (38% of the low-poly dev split's surface is on vertical
    /// faces within 1 degree of x or z), and under any-angle turns the decoder practically
    /// never sees such a wall. Runs from before this field existed turned every sample by any
    /// angle.
    #[serde(default = "every_sample")]
    pub any_angle_share: f32,
    /// The share of samples whose encoder points come as a scan's do ([`as_scanned`]): users'
    /// point clouds often have no normals, and the model trained on the surface's alone
    /// answers estimated ones and noise with heavier, less manifold meshes
    /// (`docs/decisions.md`, "Inputs as users send them"). Runs from before it had none.
    #[serde(default)]
    pub scanned_share: f32,
    /// The largest standard deviation of a scanned sample's noise, as a share of its longest
    /// side: each draws its own uniformly from 0 to this.
    #[serde(default)]
    pub scan_noise: f32,
}

fn every_sample() -> f32 {
    1.0
}

impl AugmentConfig {
    /// No augmentation, for evaluation.
    pub const OFF: AugmentConfig = AugmentConfig {
        rotation: Rotation::None,
        flip_probability: 0.0,
        scale_jitter: 0.0,
        any_angle_share: 0.0,
        scanned_share: 0.0,
        scan_noise: 0.0,
    };
}

impl Default for AugmentConfig {
    fn default() -> Self {
        Self {
            rotation: Rotation::Upright,
            flip_probability: 0.5,
            scale_jitter: 0.25,
            any_angle_share: 0.25,
            scanned_share: 0.0,
            scan_noise: 0.0,
        }
    }
}

/// A random linear map drawn from the configuration.
pub fn random_transform(cfg: &AugmentConfig, rng: &mut impl Rng) -> Mat3 {
    let rot = match cfg.rotation {
        Rotation::None => crate::mesh::transform::IDENTITY,
        Rotation::Upright => upright_rotation(cfg.any_angle_share, rng),
        Rotation::RightAngles => right_angle_rotation(rng.random_range(0..24)),
        Rotation::Full => {
            rotation_from_quaternion(std::array::from_fn(|_| StandardNormal.sample(rng)))
        }
    };
    let s = cfg.scale_jitter.clamp(0.0, 0.9);
    let keep_up = cfg.rotation == Rotation::Upright;
    let factors: [f32; 3] = std::array::from_fn(|axis| {
        let flipped = rng.random::<f32>() < cfg.flip_probability && !(keep_up && axis == UP);
        let flip = if flipped { -1.0 } else { 1.0 };
        let scale = if s > 0.0 { rng.random_range(1.0 - s..=1.0 + s) } else { 1.0 };
        flip * scale
    });
    mat_mul(&scaling(factors), &rot)
}

/// A turn about [`UP`]: by any angle with probability `any_angle_share`, else by a quarter turn.
fn upright_rotation(any_angle_share: f32, rng: &mut impl Rng) -> Mat3 {
    let mut axis = [0.0; 3];
    axis[UP] = 1.0;
    // A share of 1 draws no coin, so runs from before the share existed draw the same numbers
    // and resume exactly.
    if any_angle_share >= 1.0 || rng.random::<f32>() < any_angle_share {
        return rotation(axis, rng.random_range(0.0..std::f32::consts::TAU));
    }
    let quarters = rng.random_range(0..4u8);
    // Round away the float noise so axis-aligned stays exactly axis-aligned.
    rotation(axis, std::f32::consts::FRAC_PI_2 * f32::from(quarters)).map(|row| row.map(f32::round))
}

/// The `i`-th of the 24 proper rotations of the cube (i in 0..24): one of 6 directions for the
/// x axis, then one of 4 quarter turns about it.
fn right_angle_rotation(i: usize) -> Mat3 {
    use std::f32::consts::{FRAC_PI_2, PI};
    let to_face: [Mat3; 6] = [
        crate::mesh::transform::IDENTITY,
        rotation([0.0, 0.0, 1.0], PI),
        rotation([0.0, 0.0, 1.0], FRAC_PI_2),
        rotation([0.0, 0.0, 1.0], -FRAC_PI_2),
        rotation([0.0, 1.0, 0.0], FRAC_PI_2),
        rotation([0.0, 1.0, 0.0], -FRAC_PI_2),
    ];
    let spin = rotation([1.0, 0.0, 0.0], FRAC_PI_2 * (i % 4) as f32);
    // Round away the float noise so axis-aligned stays exactly axis-aligned.
    mat_mul(&to_face[(i / 4) % 6], &spin).map(|row| row.map(f32::round))
}

/// The mesh under a random augmentation (winding kept outward, see `Mesh::transformed`).
pub fn augment(mesh: &Mesh, cfg: &AugmentConfig, rng: &mut impl Rng) -> Mesh {
    mesh.transformed(&random_transform(cfg, rng), [0.0; 3])
}

/// `points` as a scan gives them, with [`AugmentConfig::scanned_share`]'s probability: each
/// point moved by Gaussian noise (a standard deviation drawn from 0 to
/// [`AugmentConfig::scan_noise`] of the longest side), and the normals estimated from the moved
/// points as a request without normals has them. With a share of 0 no number is drawn, so
/// runs from before the share existed draw the same batches.
pub fn maybe_scanned(points: Mesh, cfg: &AugmentConfig, rng: &mut impl Rng) -> Mesh {
    if cfg.scanned_share <= 0.0 || rng.random::<f32>() >= cfg.scanned_share {
        return points;
    }
    as_scanned(points, cfg.scan_noise, rng)
}

fn as_scanned(mut points: Mesh, max_noise: f32, rng: &mut impl Rng) -> Mesh {
    let longest = points
        .bounds()
        .map_or(0.0, |(lo, hi)| (0..3).map(|a| hi[a] - lo[a]).fold(0.0f32, f32::max));
    let sigma = rng.random::<f32>() * max_noise * longest;
    if sigma > 0.0 {
        for v in &mut points.vertices {
            for c in v.iter_mut() {
                let offset: f32 = StandardNormal.sample(rng);
                *c += sigma * offset;
            }
        }
    }
    points.normals = Some(estimate_normals(&points.vertices, NORMAL_NEIGHBOURS));
    points
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::transform::determinant;
    use rand::SeedableRng;

    #[test]
    fn right_angle_rotations_are_24_distinct_proper_rotations() {
        let all: Vec<Mat3> = (0..24).map(right_angle_rotation).collect();
        for (i, m) in all.iter().enumerate() {
            assert_eq!(determinant(m), 1.0);
            assert!(m.iter().flatten().all(|v| [-1.0, 0.0, 1.0].contains(v)));
            assert!(all[..i].iter().all(|other| other != m), "rotation {i} repeats");
        }
    }

    #[test]
    fn off_is_the_identity_and_default_varies() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        assert_eq!(
            random_transform(&AugmentConfig::OFF, &mut rng),
            crate::mesh::transform::IDENTITY
        );
        let a = random_transform(&AugmentConfig::default(), &mut rng);
        let b = random_transform(&AugmentConfig::default(), &mut rng);
        assert_ne!(a, b);
    }

    /// Whether `v` lies on one of the axes (exactly: no float noise).
    fn on_an_axis(v: [f32; 3]) -> bool {
        v.iter().filter(|c| **c != 0.0).count() == 1
    }

    #[test]
    fn quarter_turns_keep_axis_aligned_faces_axis_aligned() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let cfg = AugmentConfig { any_angle_share: 0.0, scale_jitter: 0.0, ..Default::default() };
        let mut turned = std::collections::HashSet::new();
        for _ in 0..200 {
            let m = random_transform(&cfg, &mut rng);
            let x = crate::mesh::transform::mat_vec(&m, [1.0, 0.0, 0.0]);
            assert!(on_an_axis(x), "{x:?}");
            assert!(on_an_axis(crate::mesh::transform::mat_vec(&m, [0.0, 0.0, 1.0])));
            turned.insert(x.map(|c| c as i8));
        }
        // x goes to each of +-x and +-z: all four quarter turns (with flips) are drawn.
        assert_eq!(turned.len(), 4, "{turned:?}");
    }

    #[test]
    fn any_angle_share_is_the_share_of_oblique_turns() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let share = |any_angle_share: f32, rng: &mut rand_chacha::ChaCha8Rng| {
            let cfg = AugmentConfig { any_angle_share, ..Default::default() };
            let n = 4000;
            let oblique = (0..n)
                .filter(|_| {
                    let m = random_transform(&cfg, rng);
                    !on_an_axis(crate::mesh::transform::mat_vec(&m, [1.0, 0.0, 0.0]))
                })
                .count();
            oblique as f64 / n as f64
        };
        assert_eq!(share(0.0, &mut rng), 0.0);
        assert_eq!(share(1.0, &mut rng), 1.0);
        let quarter = share(0.25, &mut rng);
        assert!((quarter - 0.25).abs() < 0.03, "{quarter}");
    }

    #[test]
    fn configs_from_before_the_share_turn_every_sample_by_any_angle() {
        let old = r#"{"rotation":"upright","flip_probability":0.5,"scale_jitter":0.25}"#;
        let cfg: AugmentConfig = serde_json::from_str(old).unwrap();
        assert_eq!(cfg.any_angle_share, 1.0);
        assert_eq!((cfg.scanned_share, cfg.scan_noise), (0.0, 0.0), "and nothing scanned");
    }

    /// 4,096 points on a 2 x 1 x 1 box's surface, with its faces' normals.
    fn box_points() -> Mesh {
        let surface = crate::mesh::primitives::cuboid([2.0, 1.0, 1.0]);
        crate::mesh::sample_surface(&surface, 4096, 0).unwrap()
    }

    /// Root mean square distance between paired points.
    fn rms_moved(a: &Mesh, b: &Mesh) -> f32 {
        let sum: f32 = a
            .vertices
            .iter()
            .zip(&b.vertices)
            .map(|(p, q)| (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f32>())
            .sum();
        (sum / a.vertices.len() as f32).sqrt()
    }

    #[test]
    fn scanned_points_move_by_their_noise_and_have_estimated_normals() {
        let points = box_points();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        // Without noise the points stay; their normals are estimated, so away from the box's
        // edges they are the faces' (up to sign), and at the edges they are not.
        let still = as_scanned(points.clone(), 0.0, &mut rng);
        assert_eq!(still.vertices, points.vertices);
        let (true_normals, estimated) = (points.normals.clone().unwrap(), still.normals.unwrap());
        let agree = |i: usize| {
            (0..3).map(|k| true_normals[i][k] * estimated[i][k]).sum::<f32>().abs() > 0.99
        };
        let off_the_edges = |p: [f32; 3]| {
            // How far inside the box each coordinate is: ~0 on the point's own face; the next
            // smallest is the distance to the nearest edge.
            let mut margins = [1.0 - p[0].abs(), 0.5 - p[1].abs(), 0.5 - p[2].abs()];
            margins.sort_by(f32::total_cmp);
            margins[1] > 0.2
        };
        let (inner, edge): (Vec<usize>, Vec<usize>) =
            (0..points.vertices.len()).partition(|&i| off_the_edges(points.vertices[i]));
        assert!(inner.len() > 1000 && inner.iter().all(|&i| agree(i)));
        assert!(edge.iter().any(|&i| !agree(i)));
        // With noise up to 1% of the 2-long side, each sample draws its own: never more, and
        // not always the same.
        let moved: Vec<f32> = (0..20)
            .map(|_| rms_moved(&as_scanned(box_points(), 0.01, &mut rng), &box_points()))
            .collect();
        // The per-point distance's RMS is sqrt(3) sigma, sigma at most 0.02.
        assert!(moved.iter().all(|&m| m <= 0.02 * 3f32.sqrt() * 1.1), "{moved:?}");
        assert!(moved.iter().any(|&m| m > 0.01) && moved.iter().any(|&m| m < 0.01), "{moved:?}");
    }

    #[test]
    fn the_scanned_share_is_the_share_of_samples_scanned() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(6);
        let points =
            crate::mesh::sample_surface(&crate::mesh::primitives::cuboid([1.0; 3]), 64, 0).unwrap();
        let scanned = |cfg: &AugmentConfig, rng: &mut rand_chacha::ChaCha8Rng| {
            (0..400).filter(|_| maybe_scanned(points.clone(), cfg, rng) != points).count()
        };
        let half = AugmentConfig { scanned_share: 0.5, scan_noise: 0.01, ..Default::default() };
        let n = scanned(&half, &mut rng);
        assert!((160..240).contains(&n), "{n} of 400");
        // A share of 0 draws no number: the next draws are those of a run without the option.
        let before = rng.clone().random::<u64>();
        assert_eq!(scanned(&AugmentConfig::default(), &mut rng), 0);
        assert_eq!(rng.random::<u64>(), before);
    }

    #[test]
    fn upright_keeps_up_pointing_up() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let cfg = AugmentConfig { flip_probability: 1.0, ..AugmentConfig::default() };
        let mut up = [0.0; 3];
        up[UP] = 1.0;
        for _ in 0..50 {
            let m = random_transform(&cfg, &mut rng);
            let v = crate::mesh::transform::mat_vec(&m, up);
            assert!(v[UP] >= 0.75 - 1e-5, "{v:?}");
            assert!(v.iter().enumerate().all(|(i, c)| i == UP || c.abs() < 1e-5), "{v:?}");
        }
    }
}
