//! Augmentation as in the paper: random rotation, random flips, independent scaling per axis.

use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::mesh::Mesh;
use crate::mesh::transform::{Mat3, mat_mul, rotation, rotation_from_quaternion, scaling};

/// The vertical axis: y, as in glTF and in the low-poly data set (whose meshes stand on
/// y = 0); procedural shapes are built the same way.
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
    };
}

impl Default for AugmentConfig {
    fn default() -> Self {
        Self {
            rotation: Rotation::Upright,
            flip_probability: 0.5,
            scale_jitter: 0.25,
            any_angle_share: 0.25,
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
