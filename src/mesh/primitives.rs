//! Simple closed primitives, built as artists build them: few segments, consistent outward
//! winding. Benchmarks, tests and the procedural training shapes start from these.

use std::f64::consts::TAU;

use super::Mesh;

/// An axis-aligned box centred at the origin with the given side lengths.
pub fn cuboid(size: [f32; 3]) -> Mesh {
    let [hx, hy, hz] = size.map(|s| s / 2.0);
    let vertices = (0..8)
        .map(|i| {
            let s = |bit: usize, h: f32| if i & bit != 0 { h } else { -h };
            [s(1, hx), s(2, hy), s(4, hz)]
        })
        .collect();
    // Two triangles per side, counter-clockwise seen from outside.
    let faces = vec![
        [0, 2, 1],
        [1, 2, 3], // z-
        [4, 5, 6],
        [5, 7, 6], // z+
        [0, 1, 4],
        [1, 5, 4], // y-
        [2, 6, 3],
        [3, 6, 7], // y+
        [0, 4, 2],
        [2, 4, 6], // x-
        [1, 3, 5],
        [3, 7, 5], // x+
    ];
    Mesh::new(vertices, faces)
}

/// `cuboid(size)` with each side split along the diagonal that `diagonals` picks (a bit per
/// side): the 64 ways to triangulate one box, for tests of what must not depend on that.
#[cfg(test)]
pub(crate) fn cuboid_split(size: [f32; 3], diagonals: u32) -> Mesh {
    // The sides as corner loops, counter-clockwise seen from outside.
    const SIDES: [[u32; 4]; 6] =
        [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
    let faces = SIDES
        .iter()
        .enumerate()
        .flat_map(|(side, &[a, b, c, d])| {
            if diagonals >> side & 1 == 0 { [[a, b, c], [a, c, d]] } else { [[b, c, d], [b, d, a]] }
        })
        .collect();
    Mesh::new(cuboid(size).vertices, faces)
}

/// A frustum along z from `-height/2` to `height/2` with `segments` sides: a prism when the
/// radii are equal, a cone or pyramid when `top_radius` is 0 (the apex is then one vertex).
///
/// Caps are flat n-gons split as a fan from their first corner, with no centre vertex (an
/// editor's n-gon cap): a vertex in the middle of a flat cap leaves no trace in the surface,
/// so a model could only guess where it is, and a shape with one could never be rebuilt face
/// for face from its points.
pub fn frustum(bottom_radius: f32, top_radius: f32, height: f32, segments: u32) -> Mesh {
    let n = segments.max(3);
    let ring = |r: f32, z: f32| -> Vec<[f32; 3]> {
        (0..n)
            .map(|i| {
                let [x, y] = circle_point(i, n);
                [r * x, r * y, z]
            })
            .collect()
    };
    let (zb, zt) = (-height / 2.0, height / 2.0);
    let mut vertices = ring(bottom_radius, zb);
    // The bottom cap faces down, so its fan turns clockwise seen from above.
    let mut faces: Vec<[u32; 3]> = (1..n - 1).map(|i| [0, i + 1, i]).collect();
    if top_radius > 0.0 {
        let top = vertices.len() as u32;
        vertices.extend(ring(top_radius, zt));
        for i in 0..n {
            let j = (i + 1) % n;
            faces.push([i, j, top + j]);
            faces.push([i, top + j, top + i]);
        }
        faces.extend((1..n - 1).map(|i| [top, top + i, top + i + 1]));
    } else {
        let apex = push(&mut vertices, [0.0, 0.0, zt]);
        for i in 0..n {
            faces.push([i, (i + 1) % n, apex]);
        }
    }
    Mesh::new(vertices, faces)
}

/// A UV sphere: `segments` around the z axis, `rings` from pole to pole (at least 2).
pub fn uv_sphere(radius: f32, segments: u32, rings: u32) -> Mesh {
    let (n, r) = (segments.max(3), rings.max(2));
    let mut vertices = vec![[0.0, 0.0, -radius]];
    for k in 1..r {
        // Half a turn from pole to pole: the k-th of 2r corners of a circle.
        let [cos_polar, sin_polar] = circle_point(k, 2 * r);
        let (z, rho) = (-radius * cos_polar, radius * sin_polar);
        for i in 0..n {
            let [x, y] = circle_point(i, n);
            vertices.push([rho * x, rho * y, z]);
        }
    }
    let top = push(&mut vertices, [0.0, 0.0, radius]);
    let at = |k: u32, i: u32| 1 + (k - 1) * n + i % n;
    let mut faces = Vec::new();
    for i in 0..n {
        faces.push([0, at(1, i + 1), at(1, i)]);
        faces.push([top, at(r - 1, i), at(r - 1, i + 1)]);
    }
    for k in 1..r - 1 {
        for i in 0..n {
            faces.push([at(k, i), at(k, i + 1), at(k + 1, i + 1)]);
            faces.push([at(k, i), at(k + 1, i + 1), at(k + 1, i)]);
        }
    }
    Mesh::new(vertices, faces)
}

/// A torus around the z axis: `major` radius to the tube's centre, `minor` tube radius.
pub fn torus(major: f32, minor: f32, segments: u32, sides: u32) -> Mesh {
    let (n, m) = (segments.max(3), sides.max(3));
    let mut vertices = Vec::with_capacity((n * m) as usize);
    for i in 0..n {
        let [x, y] = circle_point(i, n);
        for j in 0..m {
            let [cos_b, sin_b] = circle_point(j, m);
            let rho = major + minor * cos_b;
            vertices.push([rho * x, rho * y, minor * sin_b]);
        }
    }
    let at = |i: u32, j: u32| (i % n) * m + j % m;
    let mut faces = Vec::with_capacity((2 * n * m) as usize);
    for i in 0..n {
        for j in 0..m {
            faces.push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
            faces.push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
        }
    }
    Mesh::new(vertices, faces)
}

/// A prism over a simple polygon (in the xy plane, either orientation) along z from
/// `-height/2` to `height/2`: caps triangulated by ear clipping, a quad per side. `None` for
/// fewer than 3 corners or a polygon without area.
pub fn extrusion(polygon: &[[f32; 2]], height: f32) -> Option<Mesh> {
    let n = polygon.len();
    let twice_area: f32 = (0..n)
        .map(|i| {
            let (a, b) = (polygon[i], polygon[(i + 1) % n]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum();
    if n < 3 || twice_area.abs() <= f32::EPSILON {
        return None;
    }
    // Counter-clockwise corners make the side quads below face outwards.
    let ccw: Vec<[f32; 2]> =
        if twice_area > 0.0 { polygon.to_vec() } else { polygon.iter().rev().copied().collect() };
    let mut cap = Vec::new();
    earcut::Earcut::new().earcut(ccw.iter().copied(), &[] as &[u32], &mut cap);
    if cap.len() < 3 {
        return None;
    }
    let (zb, zt) = (-height / 2.0, height / 2.0);
    let n = n as u32;
    let mut vertices: Vec<[f32; 3]> = ccw.iter().map(|p| [p[0], p[1], zb]).collect();
    vertices.extend(ccw.iter().map(|p| [p[0], p[1], zt]));
    let mut faces = Vec::with_capacity(cap.len() * 2 / 3 + 2 * n as usize);
    for t in cap.chunks_exact(3) {
        let [a, b, c] = [t[0], t[1], t[2]];
        // Orient each cap triangle by its own 2-D area: down for the bottom, up for the top.
        let (pa, pb, pc) = (ccw[a as usize], ccw[b as usize], ccw[c as usize]);
        let up = (pb[0] - pa[0]) * (pc[1] - pa[1]) - (pb[1] - pa[1]) * (pc[0] - pa[0]) > 0.0;
        let (b, c) = if up { (b, c) } else { (c, b) };
        faces.push([a, c, b]);
        faces.push([n + a, n + b, n + c]);
    }
    for i in 0..n {
        let j = (i + 1) % n;
        faces.push([i, j, n + j]);
        faces.push([i, n + j, n + i]);
    }
    Some(Mesh::new(vertices, faces))
}

/// The `i`-th of `n` corners of the unit circle, counter-clockwise from (1, 0), with mirror
/// images exact mirrors and corners on an axis exactly on it. Why: `f32` sine and cosine leave
/// noise there (cos(pi/2) = -4.4e-8), and a shape's centre lies on a quantization boundary
/// (the grid's middle), so that noise would decide which cell a corner falls in, and with it
/// the faces a model is asked to rebuild. Computed in `f64` and rounded to a 2^-30 grid, which
/// leaves no noise and changes no corner visibly.
fn circle_point(i: u32, n: u32) -> [f32; 2] {
    let (s, c) = (TAU * f64::from(i) / f64::from(n)).sin_cos();
    let snap = |v: f64| ((v * 2f64.powi(30)).round() / 2f64.powi(30)) as f32;
    [snap(c), snap(s)]
}

fn push(vertices: &mut Vec<[f32; 3]>, v: [f32; 3]) -> u32 {
    vertices.push(v);
    (vertices.len() - 1) as u32
}

impl Mesh {
    /// Moves every vertex by `offset`.
    pub fn translated(mut self, offset: [f32; 3]) -> Mesh {
        for v in &mut self.vertices {
            for k in 0..3 {
                v[k] += offset[k];
            }
        }
        self
    }

    /// Appends another mesh's vertices and faces (as separate, possibly overlapping parts).
    pub fn append(&mut self, other: &Mesh) {
        let base = self.vertices.len() as u32;
        self.vertices.extend_from_slice(&other.vertices);
        self.faces.extend(other.faces.iter().map(|f| f.map(|i| i + base)));
        self.normals = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Signed volume by the divergence theorem: positive for a closed mesh wound outwards.
    fn volume(m: &Mesh) -> f64 {
        m.faces
            .iter()
            .map(|f| {
                let [a, b, c] = m.triangle(f).map(|p| p.map(f64::from));
                (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                    + a[2] * (b[0] * c[1] - b[1] * c[0]))
                    / 6.0
            })
            .sum()
    }

    /// Every edge of a closed, consistently wound mesh appears once in each direction.
    fn is_closed_and_oriented(m: &Mesh) -> bool {
        let mut edges = std::collections::HashMap::new();
        for f in &m.faces {
            for k in 0..3 {
                *edges.entry((f[k], f[(k + 1) % 3])).or_insert(0) += 1;
            }
        }
        edges.iter().all(|(&(a, b), &n)| n == 1 && edges.get(&(b, a)) == Some(&1))
    }

    #[test]
    fn primitives_are_closed_outward_and_of_the_right_volume() {
        // An L: a 2 x 2 square without its 1 x 1 top-right quarter, 0.5 high.
        let l_shape = [[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [1.0, 1.0], [1.0, 2.0], [0.0, 2.0]];
        let l_clockwise: Vec<[f32; 2]> = l_shape.iter().rev().copied().collect();
        let cases: [(Mesh, f64, f64); 8] = [
            (extrusion(&l_shape, 0.5).unwrap(), 1.5, 1e-6),
            (extrusion(&l_clockwise, 0.5).unwrap(), 1.5, 1e-6),
            (cuboid([2.0, 3.0, 4.0]), 24.0, 1e-9),
            (frustum(1.0, 1.0, 2.0, 4), 4.0, 1e-5), // a square prism of side sqrt(2)
            (frustum(1.0, 0.0, 3.0, 4), 2.0, 1e-5), // a square pyramid: base 2, height 3
            (frustum(1.0, 0.0, 4.0, 3), 3f64.sqrt(), 1e-5), // base 3 sqrt(3) / 4, height 4
            (uv_sphere(1.0, 64, 32), 4.0 / 3.0 * std::f64::consts::PI, 0.02),
            (torus(2.0, 0.5, 64, 32), 2.0 * std::f64::consts::PI.powi(2) * 2.0 * 0.25, 0.02),
        ];
        for (mesh, expected, tol) in cases {
            assert!(mesh.validate().is_ok());
            assert!(is_closed_and_oriented(&mesh));
            let v = volume(&mesh);
            assert!((v - expected).abs() <= tol * expected.max(1.0), "{v} vs {expected}");
        }
    }

    #[test]
    fn round_primitives_are_exactly_mirror_symmetric() {
        // Mirrored across y = 0 (i -> n - i): every corner's mirror image is a corner, bit for
        // bit, and corners on the x or y axis are exactly on it.
        for n in 3..=16 {
            for mesh in [frustum(0.37, 0.37, 1.0, n), uv_sphere(0.41, n, 5), torus(0.5, 0.13, n, 4)]
            {
                let bits = crate::mesh::position_key;
                let corners: std::collections::HashSet<_> =
                    mesh.vertices.iter().map(|&p| bits(p)).collect();
                for &[x, y, z] in &mesh.vertices {
                    assert!(corners.contains(&bits([x, -y, z])), "n = {n}: ({x}, {y}, {z})");
                    assert!(x.abs() > 1e-6 || x == 0.0, "n = {n}: x = {x}");
                    assert!(y.abs() > 1e-6 || y == 0.0, "n = {n}: y = {y}");
                }
            }
        }
    }

    #[test]
    fn frustum_caps_have_no_centre_vertex() {
        for n in 3..=12 {
            let prism = frustum(0.5, 0.3, 1.0, n);
            assert_eq!(
                (prism.vertices.len(), prism.faces.len()),
                (2 * n as usize, 4 * n as usize - 4)
            );
            let pyramid = frustum(0.5, 0.0, 1.0, n);
            assert_eq!(
                (pyramid.vertices.len(), pyramid.faces.len()),
                (n as usize + 1, 2 * n as usize - 2)
            );
            assert!(is_closed_and_oriented(&prism) && is_closed_and_oriented(&pyramid), "n = {n}");
        }
    }

    #[test]
    fn extrusion_rejects_degenerate_polygons() {
        assert!(extrusion(&[[0.0, 0.0], [1.0, 0.0]], 1.0).is_none());
        assert!(extrusion(&[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], 1.0).is_none());
    }

    #[test]
    fn append_offsets_indices() {
        let mut m = cuboid([1.0; 3]);
        m.append(&cuboid([1.0; 3]).translated([3.0, 0.0, 0.0]));
        assert_eq!(m.vertices.len(), 16);
        assert_eq!(m.faces.len(), 24);
        assert!(m.validate().is_ok());
        assert_eq!(m.bounds().unwrap().1[0], 3.5);
    }
}
