//! Affine transforms of meshes that keep them well formed: a mirroring transform (negative
//! determinant) reverses every face's winding so outward faces stay outward.

use super::Mesh;

/// A 3 x 3 matrix in row-major order: `p' = M p`.
pub type Mat3 = [[f32; 3]; 3];

pub const IDENTITY: Mat3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

pub fn mat_mul(a: &Mat3, b: &Mat3) -> Mat3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

pub fn mat_vec(m: &Mat3, p: [f32; 3]) -> [f32; 3] {
    std::array::from_fn(|i| m[i][0] * p[0] + m[i][1] * p[1] + m[i][2] * p[2])
}

pub fn determinant(m: &Mat3) -> f32 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

/// The cofactor matrix: proportional to the inverse transpose, which is what normals need
/// (the positive factor is removed by renormalizing).
pub(crate) fn cofactor(m: &Mat3) -> Mat3 {
    let c =
        |r0: usize, r1: usize, c0: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    [
        [c(1, 2, 1, 2), -c(1, 2, 0, 2), c(1, 2, 0, 1)],
        [-c(0, 2, 1, 2), c(0, 2, 0, 2), -c(0, 2, 0, 1)],
        [c(0, 1, 1, 2), -c(0, 1, 0, 2), c(0, 1, 0, 1)],
    ]
}

/// Rotation by `angle` radians about the unit `axis` (right-handed). A quarter turn about a
/// coordinate axis is an exact permutation: `f32` cannot hold pi/2, and the -4.4e-8 its cosine
/// comes out as would move coordinates meant to be 0 off the middle of the quantization grid,
/// which is a cell boundary.
pub fn rotation(axis: [f32; 3], angle: f32) -> Mat3 {
    let [x, y, z] = axis;
    let exact = |v: f32| if v.abs() < 1e-6 { 0.0 } else { v };
    let (s, c) = angle.sin_cos();
    let (s, c) = (exact(s), exact(c));
    let t = 1.0 - c;
    [
        [t * x * x + c, t * x * y - s * z, t * x * z + s * y],
        [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
        [t * x * z - s * y, t * y * z + s * x, t * z * z + c],
    ]
}

/// The rotation of a unit quaternion `(w, x, y, z)`; with four independent standard normal
/// components (normalized) it is a uniformly random rotation.
pub fn rotation_from_quaternion(q: [f32; 4]) -> Mat3 {
    let n = q.iter().map(|c| c * c).sum::<f32>().sqrt();
    let [w, x, y, z] = if n > 0.0 { q.map(|c| c / n) } else { [1.0, 0.0, 0.0, 0.0] };
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

pub fn scaling(s: [f32; 3]) -> Mat3 {
    [[s[0], 0.0, 0.0], [0.0, s[1], 0.0], [0.0, 0.0, s[2]]]
}

impl Mesh {
    /// `p' = M p + t` for every vertex; normals by the inverse transpose; winding reversed
    /// when `M` mirrors (negative determinant).
    pub fn transformed(&self, m: &Mat3, t: [f32; 3]) -> Mesh {
        let vertices = self
            .vertices
            .iter()
            .map(|&p| {
                let q = mat_vec(m, p);
                [q[0] + t[0], q[1] + t[1], q[2] + t[2]]
            })
            .collect();
        let mirrored = determinant(m) < 0.0;
        let faces = if mirrored {
            self.faces.iter().map(|f| [f[0], f[2], f[1]]).collect()
        } else {
            self.faces.clone()
        };
        let normals = self.normals.as_ref().map(|ns| {
            let c = cofactor(m);
            ns.iter()
                .map(|&n| {
                    let v = mat_vec(&c, n);
                    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                    if len > 0.0 { v.map(|x| x / len) } else { [0.0; 3] }
                })
                .collect()
        });
        Mesh { vertices, faces, normals }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::cuboid;

    fn assert_near(a: [f32; 3], b: [f32; 3]) {
        for k in 0..3 {
            assert!((a[k] - b[k]).abs() < 1e-5, "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn rotation_turns_x_into_y() {
        let r = rotation([0.0, 0.0, 1.0], std::f32::consts::FRAC_PI_2);
        assert_near(mat_vec(&r, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0]);
        assert!((determinant(&r) - 1.0).abs() < 1e-6);
        let q = rotation_from_quaternion([0.3, -1.2, 0.5, 2.0]);
        assert_near(mat_vec(&mat_mul(&q, &transpose(&q)), [1.0, 2.0, 3.0]), [1.0, 2.0, 3.0]);
    }

    #[test]
    fn quarter_turns_are_exact_permutations() {
        use std::f32::consts::{FRAC_PI_2, PI};
        let about_x = rotation([1.0, 0.0, 0.0], -FRAC_PI_2);
        assert_eq!(about_x, [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]);
        let half = rotation([0.0, 1.0, 0.0], PI);
        assert_eq!(half, [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]);
        assert_eq!(mat_vec(&about_x, [0.3, 0.0, 0.7]), [0.3, 0.7, 0.0]);
    }

    fn transpose(m: &Mat3) -> Mat3 {
        std::array::from_fn(|i| std::array::from_fn(|j| m[j][i]))
    }

    #[test]
    fn mirroring_keeps_faces_pointing_outwards() {
        let cube = cuboid([1.0; 3]);
        let mirrored = cube.transformed(&scaling([-1.0, 2.0, 1.0]), [0.0; 3]);
        for (f, n) in mirrored.faces.iter().zip(mirrored.face_normals()) {
            let [a, b, c] = mirrored.triangle(f);
            let centroid: [f32; 3] = std::array::from_fn(|k| (a[k] + b[k] + c[k]) / 3.0);
            let outward: f32 = (0..3).map(|k| centroid[k] * n[k]).sum();
            assert!(outward > 0.0, "face {f:?} points inwards");
        }
    }

    #[test]
    fn normals_follow_the_inverse_transpose() {
        let mut m = crate::mesh::Mesh::new(vec![[0.0; 3]], vec![]);
        let s = 1.0 / 2f32.sqrt();
        m.normals = Some(vec![[s, s, 0.0]]);
        // Stretching x by 2 tilts a 45-degree normal towards y.
        let t = m.transformed(&scaling([2.0, 1.0, 1.0]), [1.0, 0.0, 0.0]);
        let n = t.normals.unwrap()[0];
        assert_near(n, [1.0 / 5f32.sqrt(), 2.0 / 5f32.sqrt(), 0.0]);
        assert_eq!(t.vertices[0], [1.0, 0.0, 0.0]);
    }
}
