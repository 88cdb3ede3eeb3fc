//! Small closed meshes with known geometry, for tests (a procedural shape generator elsewhere
//! may replace these).

use super::Mesh;

/// The axis-aligned cube `[lo, hi]^3`, 12 triangles wound outward.
pub(crate) fn cube(lo: f32, hi: f32) -> Mesh {
    let vertices = (0..8)
        .map(|i| [i & 1, (i >> 1) & 1, (i >> 2) & 1].map(|b| if b == 1 { hi } else { lo }))
        .collect();
    // Vertex i has x = bit 0, y = bit 1, z = bit 2. Each quad is listed counter-clockwise seen
    // from outside.
    let quads = [
        [0, 2, 3, 1], // z = lo
        [4, 5, 7, 6], // z = hi
        [0, 1, 5, 4], // y = lo
        [2, 6, 7, 3], // y = hi
        [0, 4, 6, 2], // x = lo
        [1, 3, 7, 5], // x = hi
    ];
    let faces = quads.iter().flat_map(|&[a, b, c, d]| [[a, b, c], [a, c, d]]).collect();
    Mesh::new(vertices, faces)
}

/// A UV sphere of the given radius around the origin: `rings` latitude bands (poles
/// included) and `segments` longitudes, wound outward.
pub(crate) fn uv_sphere(radius: f32, rings: u32, segments: u32) -> Mesh {
    use std::f64::consts::PI;
    let mut vertices = vec![[0.0, 0.0, radius]];
    for r in 1..rings {
        let theta = PI * f64::from(r) / f64::from(rings);
        for s in 0..segments {
            let phi = 2.0 * PI * f64::from(s) / f64::from(segments);
            let p = [theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()];
            vertices.push(p.map(|c| (c * f64::from(radius)) as f32));
        }
    }
    vertices.push([0.0, 0.0, -radius]);
    let south = vertices.len() as u32 - 1;
    let ring = |r: u32, s: u32| 1 + (r - 1) * segments + s % segments;
    let mut faces = Vec::new();
    for s in 0..segments {
        faces.push([0, ring(1, s), ring(1, s + 1)]);
        faces.push([south, ring(rings - 1, s + 1), ring(rings - 1, s)]);
        for r in 1..rings - 1 {
            let (a, b, c, d) = (ring(r, s), ring(r + 1, s), ring(r + 1, s + 1), ring(r, s + 1));
            faces.push([a, b, c]);
            faces.push([a, c, d]);
        }
    }
    Mesh::new(vertices, faces)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
        a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    }

    /// Outward winding: each face normal points away from the centre (the origin).
    fn outward(m: &Mesh) -> bool {
        m.faces.iter().zip(m.face_normals()).all(|(f, n)| {
            let [a, b, c] = m.triangle(f);
            let centroid = [0, 1, 2].map(|k| (a[k] + b[k] + c[k]) / 3.0);
            dot(n, centroid) > 0.0
        })
    }

    #[test]
    fn cube_is_closed_outward_and_has_the_right_area() {
        let m = cube(-1.0, 1.0);
        assert!(m.validate().is_ok());
        assert_eq!(m.faces.len(), 12);
        assert!((m.area() - 24.0).abs() < 1e-9);
        assert!(outward(&m));
    }

    #[test]
    fn sphere_is_outward_and_close_to_the_analytic_area() {
        let m = uv_sphere(2.0, 32, 64);
        assert!(m.validate().is_ok());
        assert_eq!(m.faces.len(), 2 * 64 * 31);
        assert!(outward(&m));
        let exact = 4.0 * std::f64::consts::PI * 4.0;
        assert!((m.area() - exact).abs() / exact < 0.01);
    }
}
