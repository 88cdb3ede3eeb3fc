//! How much of what a viewer sees of a mesh from around it is the back of a face: what a
//! viewer that draws front sides only (glTF's default) shows as a hole. A closed surface
//! wound outward shows none; an open sheet shows its back from half the views however it is
//! wound, so the ground truth's own share is the floor to compare with.

use parry3d_f64::na::Vector3;
use parry3d_f64::query::{Ray, RayCast};
use parry3d_f64::shape::FeatureId;

use crate::mesh::{Mesh, RayTarget, axes_across};

/// Directions the mesh is seen from, spread evenly over the sphere.
const VIEWS: usize = 32;

/// Rays across each view's square, per side.
const RAYS_PER_SIDE: usize = 48;

/// The share of the rays cast at `mesh` from [`VIEWS`] directions around it (orthographic,
/// [`RAYS_PER_SIDE`] squared per view over its bounding sphere) that first meet a face from
/// behind; `None` when no ray meets a face (no faces, no area). Indices must be valid
/// ([`Mesh::validate`]).
pub fn back_faces_seen(mesh: &Mesh) -> Option<f64> {
    let RayTarget { shape, centre, diagonal } = RayTarget::new(mesh)?;
    let radius = diagonal / 2.0;
    let faces = mesh.faces.len() as u32;
    let (mut hits, mut backs) = (0usize, 0usize);
    for view in 0..VIEWS {
        let dir = fibonacci_direction(view, VIEWS);
        let (u, v) = axes_across(&dir);
        for i in 0..RAYS_PER_SIDE {
            for j in 0..RAYS_PER_SIDE {
                // Cell centres across [-radius, radius] on both axes of the view's plane.
                let across =
                    |k: usize| radius * (2.0 * (k as f64 + 0.5) / RAYS_PER_SIDE as f64 - 1.0);
                let origin = centre - dir * (2.0 * radius) + u * across(i) + v * across(j);
                let ray = Ray::new(origin, dir);
                if let Some(hit) = shape.cast_local_ray_and_get_normal(&ray, 4.0 * radius, false) {
                    hits += 1;
                    // parry numbers a face met from behind past the last face.
                    backs += usize::from(matches!(hit.feature, FeatureId::Face(id) if id >= faces));
                }
            }
        }
    }
    (hits > 0).then(|| backs as f64 / hits as f64)
}

/// The `i`th of `n` unit directions on a Fibonacci spiral: close to evenly spread.
fn fibonacci_direction(i: usize, n: usize) -> Vector3<f64> {
    let golden_angle = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
    let r = (1.0 - z * z).sqrt();
    let theta = golden_angle * i as f64;
    Vector3::new(r * theta.cos(), r * theta.sin(), z)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::{cuboid, uv_sphere};

    #[test]
    fn a_closed_surface_shows_its_front_and_inside_out_its_back() {
        for shape in [cuboid([1.0, 2.0, 0.5]), uv_sphere(1.0, 16, 9)] {
            assert_eq!(back_faces_seen(&shape), Some(0.0));
            let mut inside_out = shape.clone();
            inside_out.faces.iter_mut().for_each(|f| f.swap(1, 2));
            assert_eq!(back_faces_seen(&inside_out), Some(1.0));
        }
    }

    #[test]
    fn a_sheet_shows_its_back_from_half_the_views_and_nothing_shows_nothing() {
        let sheet = Mesh::new(
            vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]],
            vec![[0, 1, 2], [0, 2, 3]],
        );
        let share = back_faces_seen(&sheet).unwrap();
        assert!((share - 0.5).abs() < 0.1, "{share}");
        assert_eq!(back_faces_seen(&Mesh::default()), None);
        assert_eq!(back_faces_seen(&Mesh::new(vec![[0.0; 3]; 3], vec![[0, 1, 2]])), None);
    }
}
