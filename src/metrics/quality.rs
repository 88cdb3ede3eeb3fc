//! What an answer can say of itself without a ground truth: how it is put together (open and
//! non-manifold edges, connected parts, whether it is watertight) and how far it lies from the
//! points it was made from. Every answer of the service carries it, so that a pipeline can
//! accept, retry or flag a mesh without looking at it.

use serde::Serialize;
use utoipa::ToSchema;

use crate::candidates::input_distance;
use crate::mesh::Mesh;

use super::topology::topology;

/// The build of one answer and its distance to its input.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, ToSchema)]
pub struct MeshQuality {
    /// Distinct undirected edges, corners welded by exact position.
    pub edges: usize,
    /// Edges used by one face: holes and open borders.
    pub boundary_edges: usize,
    /// Edges used by three or more faces: fins, overlaps, repeated faces.
    pub non_manifold_edges: usize,
    /// Sets of faces connected through shared corners.
    pub parts: usize,
    /// Every edge shared by exactly two faces (and at least one face): a closed surface.
    pub watertight: bool,
    /// The Chamfer distance between the answer and its input points, in the frame where the
    /// input's longest side spans 2 (DESIGN.md's, as the model card's CD): 0.02 is about 1%
    /// of that side. `None` for an answer made from a picture or without area.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub input_chamfer: Option<f64>,
}

/// Seed of the surface samples the distance is measured with: one answer always measures the
/// same.
const SAMPLE_SEED: u64 = 0;

impl MeshQuality {
    /// Measures `mesh` against the `input` points it was made from, both in the normalized
    /// frame (only the distance needs that frame). CPU work of a few milliseconds with input
    /// points: run it off the async runtime.
    pub fn measure(mesh: &Mesh, input: Option<&[[f32; 3]]>) -> Self {
        let t = topology(mesh);
        let input_chamfer =
            input.map(|points| input_distance(mesh, points, SAMPLE_SEED)).filter(|d| d.is_finite());
        Self {
            edges: t.edges,
            boundary_edges: t.boundary_edges,
            non_manifold_edges: t.non_manifold_edges,
            parts: t.parts,
            watertight: t.faces > 0 && t.boundary_edges == 0 && t.non_manifold_edges == 0,
            input_chamfer,
        }
    }
}

/// "3 parts, 12 of 180 edges open, 2 non-manifold, input CD 0.0312", as the CLI prints it.
impl std::fmt::Display for MeshQuality {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let parts = if self.parts == 1 { "1 part".into() } else { format!("{} parts", self.parts) };
        if self.watertight {
            write!(f, "{parts}, watertight")?;
        } else {
            write!(
                f,
                "{parts}, {} of {} edges open, {} non-manifold",
                self.boundary_edges, self.edges, self.non_manifold_edges
            )?;
        }
        match self.input_chamfer {
            Some(cd) => write!(f, ", input CD {cd:.4}"),
            None => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::cuboid;
    use crate::mesh::sample_surface;

    #[test]
    fn a_closed_box_is_watertight_and_close_to_its_own_surface() {
        let mesh = cuboid([1.0, 0.6, 0.4]);
        let points = sample_surface(&mesh, 4096, 1).unwrap().vertices;
        let q = MeshQuality::measure(&mesh, Some(&points));
        assert_eq!((q.edges, q.boundary_edges, q.non_manifold_edges, q.parts), (18, 0, 0, 1));
        assert!(q.watertight);
        let cd = q.input_chamfer.unwrap();
        assert!(cd > 0.0 && cd < 0.05, "{cd}");
        assert!(q.to_string().starts_with("1 part, watertight, input CD 0.0"), "{q}");
    }

    #[test]
    fn an_open_box_and_a_stray_face_are_not() {
        let mut mesh = cuboid([1.0; 3]);
        mesh.faces.truncate(10);
        let far = mesh.vertices.len() as u32;
        mesh.vertices.extend([[5.0, 5.0, 5.0], [6.0, 5.0, 5.0], [5.0, 6.0, 5.0]]);
        mesh.faces.push([far, far + 1, far + 2]);
        let q = MeshQuality::measure(&mesh, None);
        assert_eq!((q.boundary_edges, q.non_manifold_edges, q.parts), (4 + 3, 0, 2));
        assert!(!q.watertight);
        assert_eq!(q.input_chamfer, None);
        assert_eq!(q.to_string(), format!("2 parts, 7 of {} edges open, 0 non-manifold", q.edges));
    }

    #[test]
    fn the_distance_grows_with_the_gap_to_the_input() {
        let mesh = cuboid([1.0; 3]);
        let points = sample_surface(&mesh, 4096, 1).unwrap().vertices;
        let moved: Vec<[f32; 3]> = points.iter().map(|p| [p[0] + 0.2, p[1], p[2]]).collect();
        let near = MeshQuality::measure(&mesh, Some(&points)).input_chamfer.unwrap();
        let far = MeshQuality::measure(&mesh, Some(&moved)).input_chamfer.unwrap();
        assert!(far > near + 0.1, "{near} {far}");
    }

    #[test]
    fn no_faces_are_neither_watertight_nor_measured() {
        let empty = Mesh::new(vec![], vec![]);
        let q = MeshQuality::measure(&empty, Some(&[[0.0; 3]]));
        assert_eq!((q.edges, q.parts, q.watertight, q.input_chamfer), (0, 0, false, None));
        // Serialized without the distance it does not have.
        let json = serde_json::to_value(q).unwrap();
        assert!(json.get("input_chamfer").is_none(), "{json}");
    }
}
