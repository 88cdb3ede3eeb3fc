//! The convex hull of the input points: the simplest closed surface around them.

use parry3d_f64::na::Point3;
use parry3d_f64::transformation::try_convex_hull;

use super::points::{checked_points, require_volume};
use super::{BaselineError, catch_solver_panic};
use crate::mesh::Mesh;

/// The convex hull of `points` as a closed triangle mesh, faces wound counter-clockwise seen
/// from outside (normals point outward).
///
/// Fewer than 4 points, non-finite coordinates, and sets that do not span three dimensions
/// (all equal, collinear, coplanar, duplicates of such) are errors.
pub fn convex_hull(points: &[[f32; 3]]) -> Result<Mesh, BaselineError> {
    let points = checked_points(points, "a convex hull", 4)?;
    require_volume(&points)?;
    let input: Vec<Point3<f64>> = points.iter().map(|&p| Point3::from(p)).collect();
    let (vertices, faces) = catch_solver_panic(|| try_convex_hull(&input))
        .map_err(BaselineError::Hull)?
        .map_err(|e| BaselineError::Hull(e.to_string()))?;
    if faces.len() < 4 {
        return Err(BaselineError::Hull(format!("{} faces is not a closed hull", faces.len())));
    }
    let centroid =
        vertices.iter().fold(Point3::origin(), |sum, p| sum + p.coords) / vertices.len() as f64;
    let faces = faces.into_iter().map(|f| facing_out(&vertices, centroid, f)).collect();
    let vertices = vertices.iter().map(|p| [p.x as f32, p.y as f32, p.z as f32]).collect();
    Ok(Mesh::new(vertices, faces))
}

/// `face` wound to face away from `centroid`, the mean of the hull's `vertices`, which lies
/// inside a convex hull. Why: on nearly flat inputs (a tetrahedron of volume 0.3 spanning 15
/// units, found by the property test below) parry winds some faces inward.
fn facing_out(vertices: &[Point3<f64>], centroid: Point3<f64>, [a, b, c]: [u32; 3]) -> [u32; 3] {
    let [pa, pb, pc] = [a, b, c].map(|i| vertices[i as usize]);
    let normal = (pb - pa).cross(&(pc - pa));
    let outward =
        (pa - centroid).dot(&normal) + (pb - centroid).dot(&normal) + (pc - centroid).dot(&normal);
    if outward < 0.0 { [a, c, b] } else { [a, b, c] }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::cuboid;
    use crate::mesh::sample_surface;
    use crate::metrics::{MetricOptions, mesh_distances};
    use proptest::prelude::*;

    fn outward(mesh: &Mesh) -> bool {
        let n = mesh.vertices.len() as f32;
        let c: [f32; 3] =
            std::array::from_fn(|k| mesh.vertices.iter().map(|v| v[k]).sum::<f32>() / n);
        mesh.faces.iter().zip(mesh.face_normals()).all(|(f, normal)| {
            let t = mesh.triangle(f);
            let centre: [f32; 3] = std::array::from_fn(|k| (t[0][k] + t[1][k] + t[2][k]) / 3.0);
            (0..3).map(|k| (centre[k] - c[k]) * normal[k]).sum::<f32>() > 0.0
        })
    }

    #[test]
    fn hull_of_a_sampled_cube_is_the_cube_with_outward_faces() {
        let cube = cuboid([2.0; 3]);
        let points = sample_surface(&cube, 1024, 7).unwrap().vertices;
        let hull = convex_hull(&points).unwrap();
        assert!(hull.validate().is_ok());
        assert!(outward(&hull), "a face points inward");
        // The sampled points sit on the cube, so the hull can only cut its corners slightly.
        let d = mesh_distances(&hull, &cube, &MetricOptions { samples: 20_000, seed: 1 }).unwrap();
        assert!(d.chamfer < 0.05 && d.hausdorff < 0.15, "{d:?}");
        assert!((hull.area() - cube.area()).abs() < 0.05 * cube.area(), "{}", hull.area());
    }

    #[test]
    fn degenerate_inputs_are_errors() {
        let o = [0.0f32; 3];
        let (x, y, z) = ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]);
        assert!(matches!(convex_hull(&[o, x, y]), Err(BaselineError::TooFewPoints { got: 3, .. })));
        assert_eq!(convex_hull(&[o, o, o, o, o]), Err(BaselineError::Flat("all equal")));
        assert_eq!(convex_hull(&[o, x, x, o, x]), Err(BaselineError::Flat("collinear")));
        assert_eq!(
            convex_hull(&[o, x, y, [1.0, 1.0, 0.0], x]),
            Err(BaselineError::Flat("coplanar"))
        );
        assert_eq!(
            convex_hull(&[o, x, y, [f32::NAN, 0.0, 0.0], z]),
            Err(BaselineError::NonFinite { index: 3 })
        );
        // Duplicates of a valid tetrahedron still give the tetrahedron.
        let tetra = convex_hull(&[o, x, y, z, o, x, y, z]).unwrap();
        assert_eq!(tetra.faces.len(), 4);
        assert!(outward(&tetra));
    }

    proptest! {
        #[test]
        fn any_input_gives_an_outward_hull_or_an_error(
            pts in prop::collection::vec(prop::array::uniform3(-10.0f32..10.0), 0..60)
        ) {
            if let Ok(hull) = convex_hull(&pts) {
                prop_assert!(hull.validate().is_ok());
                prop_assert!(outward(&hull));
            }
        }
    }
}
