//! How a mesh is put together, apart from where its surface lies: the share of edges on a
//! boundary (used by one face), non-manifold (used by three or more) or between two faces
//! wound opposite ways, and how many connected parts it has. The Chamfer distance cannot
//! tell a closed box from a box-shaped heap of unconnected slivers; these can, and they are
//! what a user sees first.

use std::collections::HashMap;

use crate::mesh::{DisjointSets, Mesh, edge_uses};

use super::faces::ratio;

/// The edges and parts of one mesh, its corners welded by exact position first: files split
/// vertices along seams (normals, UVs), which is not a hole in the surface.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Topology {
    /// Faces with three distinct corners once welded (others have no edges of their own).
    pub faces: usize,
    /// Distinct undirected edges of those faces.
    pub edges: usize,
    /// Edges used by exactly one face: holes and open borders.
    pub boundary_edges: usize,
    /// Edges used by three or more faces: fins, overlaps, repeated faces.
    pub non_manifold_edges: usize,
    /// Edges used by two faces that run along them the same way: one of the two is wound
    /// the other way round, and a viewer drawing front sides only shows it as a hole.
    #[serde(default)]
    pub misoriented_edges: usize,
    /// Sets of faces connected through shared corners.
    pub parts: usize,
}

impl Topology {
    pub fn boundary_share(&self) -> f64 {
        ratio(self.boundary_edges, self.edges)
    }

    pub fn non_manifold_share(&self) -> f64 {
        ratio(self.non_manifold_edges, self.edges)
    }

    pub fn misoriented_share(&self) -> f64 {
        ratio(self.misoriented_edges, self.edges)
    }
}

/// The topology of `mesh`; indices must be valid ([`Mesh::validate`]), faces with an index
/// out of range are skipped.
pub fn topology(mesh: &Mesh) -> Topology {
    let welded = mesh.welded_faces();
    let uses = edge_uses(&welded);
    // How many faces run along each edge from its lower corner to its higher one: 1 of 2
    // when the two are wound alike.
    let mut upward: HashMap<(u32, u32), usize> = HashMap::new();
    for &[a, b, c] in &welded {
        for (p, q) in [(a, b), (b, c), (c, a)].into_iter().filter(|(p, q)| p < q) {
            *upward.entry((p, q)).or_default() += 1;
        }
    }
    let mut sets = DisjointSets::new(mesh.vertices.len());
    for &[a, b, c] in &welded {
        sets.union(a as usize, b as usize);
        sets.union(a as usize, c as usize);
    }
    let mut roots: Vec<usize> = welded.iter().filter_map(|f| sets.find(f[0] as usize)).collect();
    roots.sort_unstable();
    roots.dedup();
    Topology {
        faces: welded.len(),
        edges: uses.len(),
        boundary_edges: uses.values().filter(|&&n| n == 1).count(),
        non_manifold_edges: uses.values().filter(|&&n| n > 2).count(),
        misoriented_edges: uses
            .iter()
            .filter(|&(edge, &n)| n == 2 && upward.get(edge).copied().unwrap_or(0) != 1)
            .count(),
        parts: roots.len(),
    }
}

/// Topology over a set of meshes: means of the per-mesh shares and of the parts, next to the
/// ground truth's where it is known.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TopologySummary {
    pub meshes: usize,
    /// `None` when there are no meshes.
    pub boundary_share_mean: Option<f64>,
    pub non_manifold_share_mean: Option<f64>,
    #[serde(default)]
    pub misoriented_share_mean: Option<f64>,
    pub parts_mean: Option<f64>,
}

/// "open edges 38.0%, non-manifold 7.3%, misoriented 4.1%, parts 3.4", as training logs
/// print it.
impl std::fmt::Display for TopologySummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let share = |v: Option<f64>| v.map_or_else(|| "-".into(), |v| format!("{:.1}%", 100.0 * v));
        let parts = self.parts_mean.map_or_else(|| "-".into(), |v| format!("{v:.1}"));
        write!(
            f,
            "open edges {}, non-manifold {}, misoriented {}, parts {parts}",
            share(self.boundary_share_mean),
            share(self.non_manifold_share_mean),
            share(self.misoriented_share_mean)
        )
    }
}

pub fn summarize_topology(meshes: &[Topology]) -> TopologySummary {
    let mean = |f: &dyn Fn(&Topology) -> f64| {
        (!meshes.is_empty()).then(|| meshes.iter().map(f).sum::<f64>() / meshes.len() as f64)
    };
    TopologySummary {
        meshes: meshes.len(),
        boundary_share_mean: mean(&Topology::boundary_share),
        non_manifold_share_mean: mean(&Topology::non_manifold_share),
        misoriented_share_mean: mean(&Topology::misoriented_share),
        parts_mean: mean(&|t| t.parts as f64),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::cuboid;

    #[test]
    fn a_summary_reads_as_shares_and_parts() {
        let open = Mesh::new(vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], vec![[0, 1, 2]]);
        let summary = summarize_topology(&[topology(&cuboid([1.0; 3])), topology(&open)]);
        assert_eq!(
            summary.to_string(),
            "open edges 50.0%, non-manifold 0.0%, misoriented 0.0%, parts 1.0"
        );
        assert_eq!(
            summarize_topology(&[]).to_string(),
            "open edges -, non-manifold -, misoriented -, parts -"
        );
    }

    #[test]
    fn a_closed_box_has_no_boundary_and_one_part() {
        let t = topology(&cuboid([1.0, 2.0, 3.0]));
        assert_eq!(
            t,
            Topology {
                faces: 12,
                edges: 18,
                boundary_edges: 0,
                non_manifold_edges: 0,
                misoriented_edges: 0,
                parts: 1
            }
        );
    }

    #[test]
    fn a_face_wound_the_other_way_misorients_its_three_edges() {
        let mut mesh = cuboid([1.0; 3]);
        mesh.faces[0].swap(1, 2);
        let t = topology(&mesh);
        assert_eq!((t.misoriented_edges, t.boundary_edges, t.non_manifold_edges), (3, 0, 0));
        assert!((t.misoriented_share() - 3.0 / 18.0).abs() < 1e-12);
        // Split vertices (a flat-shaded export) weld first.
        let vertices: Vec<[f32; 3]> = mesh.faces.iter().flat_map(|f| mesh.triangle(f)).collect();
        let faces = (0..12).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
        assert_eq!(topology(&Mesh::new(vertices, faces)), t);
        // A report written before edges were counted this way reads as none.
        let old: Topology = serde_json::from_str(
            r#"{"faces":1,"edges":3,"boundary_edges":3,"non_manifold_edges":0,"parts":1}"#,
        )
        .unwrap();
        assert_eq!(old.misoriented_edges, 0);
    }

    #[test]
    fn a_box_with_split_vertices_is_still_closed() {
        // Every face with its own three vertices, as a flat-shaded export writes it.
        let closed = cuboid([1.0; 3]);
        let vertices: Vec<[f32; 3]> =
            closed.faces.iter().flat_map(|f| closed.triangle(f)).collect();
        let faces = (0..12).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
        let soup = Mesh::new(vertices, faces);
        assert_eq!(topology(&soup), topology(&cuboid([1.0; 3])));
    }

    #[test]
    fn slivers_apart_are_all_boundary_and_each_a_part() {
        let triangles = (0..5).map(|i| {
            let x = 2.0 * i as f32;
            [[x, 0.0, 0.0], [x + 1.0, 0.0, 0.0], [x, 1.0, 0.0]]
        });
        let t = topology(&Mesh::from_triangles(triangles));
        assert_eq!((t.edges, t.boundary_edges, t.parts), (15, 15, 5));
        assert_eq!(t.boundary_share(), 1.0);
    }

    #[test]
    fn a_fin_is_non_manifold_and_collapsed_faces_do_not_count() {
        let mut mesh = cuboid([1.0; 3]);
        let [a, b, _] = mesh.faces[0];
        mesh.vertices.push([5.0, 5.0, 5.0]);
        let tip = mesh.vertices.len() as u32 - 1;
        mesh.faces.push([a, b, tip]);
        mesh.faces.push([a, a, tip]);
        let t = topology(&mesh);
        assert_eq!((t.faces, t.non_manifold_edges, t.boundary_edges, t.parts), (13, 1, 2, 1));
        let s = summarize_topology(&[t, topology(&cuboid([1.0; 3]))]);
        assert_eq!(s.parts_mean, Some(1.0));
        assert!((s.non_manifold_share_mean.unwrap() - 0.5 / 20.0).abs() < 1e-12);
        assert_eq!(summarize_topology(&[]).boundary_share_mean, None);
    }

    #[test]
    fn a_point_cloud_has_nothing() {
        let t = topology(&Mesh::new(vec![[0.0; 3]; 4], vec![]));
        assert_eq!((t.faces, t.edges, t.parts), (0, 0, 0));
        assert_eq!(t.boundary_share(), 0.0);
    }
}
