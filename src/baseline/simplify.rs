//! Bringing a baseline's surface down to the model's face budget with meshoptimizer.

use meshopt::{SimplifyOptions, optimize_vertex_fetch, simplify_decoder, simplify_sloppy_decoder};

use super::BaselineError;
use crate::mesh::Mesh;

/// Relative error (a fraction of the mesh's extent) the simplifier may introduce: any, since
/// the face budget, not the error, is what the comparison fixes.
const ANY_ERROR: f32 = 1.0;

/// The mesh with at most `max_faces` faces and no unused vertices. Meshoptimizer's
/// edge-collapse simplification runs first; it keeps the topology, so when that stops it above
/// the budget (many components, handles) the sloppy vertex-clustering simplifier, which always
/// reaches its target, takes over from the original mesh.
pub fn simplify_to_budget(mesh: &Mesh, max_faces: usize) -> Result<Mesh, BaselineError> {
    simplify_within(mesh, max_faces, 0.0)
}

/// [`simplify_to_budget`], and below the budget as far as edges collapse within `tolerance`
/// (meshoptimizer's relative error, a fraction of the mesh's extent): the faces a flat side
/// needs, not the many slivers a hull of sampled points has on it.
pub fn simplify_within(
    mesh: &Mesh,
    max_faces: usize,
    tolerance: f32,
) -> Result<Mesh, BaselineError> {
    if max_faces == 0 {
        return Err(BaselineError::InvalidOption("the face budget must be at least 1".into()));
    }
    // meshoptimizer asserts (and aborts) on out-of-range indices; validate first.
    mesh.validate().map_err(|e| BaselineError::InvalidMesh(e.to_string()))?;
    let mut indices: Vec<u32> = mesh.faces.iter().flatten().copied().collect();
    if indices.len() > max_faces * 3 {
        let target = max_faces * 3;
        indices = simplify_decoder(
            &indices,
            &mesh.vertices,
            target,
            ANY_ERROR,
            SimplifyOptions::None,
            None,
        );
        if indices.len() > target {
            let all: Vec<u32> = mesh.faces.iter().flatten().copied().collect();
            indices = simplify_sloppy_decoder(&all, &mesh.vertices, target, ANY_ERROR, None);
        }
    }
    if tolerance > 0.0 {
        let options = SimplifyOptions::None;
        indices = simplify_decoder(&indices, &mesh.vertices, 0, tolerance, options, None);
    }
    let faces = indices.len() / 3;
    if faces == 0 {
        return Err(BaselineError::SimplifiedAway);
    }
    if faces > max_faces {
        return Err(BaselineError::OverBudget { faces, budget: max_faces });
    }
    let vertices = optimize_vertex_fetch(&mut indices, &mesh.vertices);
    let faces = indices.chunks_exact(3).map(|f| [f[0], f[1], f[2]]).collect();
    Ok(Mesh::new(vertices, faces))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::{cuboid, torus, uv_sphere};
    use crate::metrics::{MetricOptions, mesh_distances};

    #[test]
    fn meshes_come_down_to_the_budget_and_stay_close() {
        let sphere = uv_sphere(1.0, 64, 32);
        let small = simplify_to_budget(&sphere, 200).unwrap();
        assert!(small.faces.len() <= 200 && small.faces.len() > 100, "{}", small.faces.len());
        assert!(small.validate().is_ok());
        let d =
            mesh_distances(&small, &sphere, &MetricOptions { samples: 10_000, seed: 0 }).unwrap();
        // Two samplings of the sphere itself differ by CD 0.036 at 10,000 points.
        assert!(d.chamfer < 0.07, "{d:?}");
        // Twenty tori: the edge collapser cannot drop components, so the sloppy one has to.
        let mut many = Mesh::default();
        for i in 0..20 {
            many.append(&torus(1.0, 0.3, 24, 12).translated([3.0 * i as f32, 0.0, 0.0]));
        }
        let few = simplify_to_budget(&many, 50).unwrap();
        assert!(!few.faces.is_empty() && few.faces.len() <= 50, "{}", few.faces.len());
    }

    #[test]
    fn flat_sides_come_down_further_within_the_tolerance_and_curved_ones_do_not() {
        // The hull of points on a box: slivers on every side, each side flat, small bevels
        // where no point fell on a corner.
        let points = crate::mesh::sample_surface(&cuboid([2.0, 1.0, 1.0]), 2000, 0).unwrap();
        let hull = crate::baseline::convex_hull(&points.vertices).unwrap();
        assert!(hull.faces.len() > 100, "{}", hull.faces.len());
        assert_eq!(simplify_to_budget(&hull, 100).unwrap().faces.len(), 100);
        let flat = simplify_within(&hull, 100, 0.01).unwrap();
        assert!(flat.faces.len() <= 32, "{}", flat.faces.len());
        assert!(flat.validate().is_ok());
        let options = MetricOptions { samples: 10_000, seed: 0 };
        let d = mesh_distances(&flat, &cuboid([2.0, 1.0, 1.0]), &options).unwrap();
        // Two samplings of the box itself differ by about as much.
        assert!(d.hausdorff < 0.1, "{d:?}");
        let sphere = uv_sphere(1.0, 64, 32);
        let round = simplify_within(&sphere, 200, 0.01).unwrap();
        assert!(round.faces.len() > 150, "{}", round.faces.len());
    }

    #[test]
    fn small_meshes_are_kept_and_bad_input_is_an_error() {
        let cube = cuboid([1.0; 3]);
        assert_eq!(simplify_to_budget(&cube, 12).unwrap().faces.len(), 12);
        assert!(matches!(simplify_to_budget(&cube, 0), Err(BaselineError::InvalidOption(_))));
        let mut broken = cube.clone();
        broken.faces.push([0, 1, 99]);
        assert!(matches!(simplify_to_budget(&broken, 5), Err(BaselineError::InvalidMesh(_))));
    }
}
