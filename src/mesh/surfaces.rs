//! Surfaces: a mesh's faces joined across the edges that exactly two of them share, corners
//! welded by position (files split vertices along seams), each set wound alike. Facing out
//! turns whole surfaces; stray sheets weighs them as pieces.

use std::collections::{HashMap, VecDeque};

use super::{Mesh, undirected};

/// Each undirected edge of a mesh's faces (corners welded by position, faces that collapse
/// to an edge or a point left out) with the faces along it, and whether each runs along it
/// from its lower corner to its higher. Indices must be valid ([`Mesh::validate`]).
pub(crate) fn welded_edges(mesh: &Mesh) -> HashMap<(u32, u32), Vec<(usize, bool)>> {
    let canonical = mesh.first_vertex_at_each_position();
    let mut along: HashMap<(u32, u32), Vec<(usize, bool)>> = HashMap::new();
    for (f, face) in mesh.faces.iter().enumerate() {
        let [a, b, c] = face.map(|i| canonical[i as usize]);
        if a != b && b != c && c != a {
            for (p, q) in [(a, b), (b, c), (c, a)] {
                along.entry(undirected(p, q)).or_default().push((f, p < q));
            }
        }
    }
    along
}

/// The faces joined across edges that exactly two of them share, each set wound alike.
pub(crate) struct Surfaces {
    /// Each surface's faces, its first (lowest) face first. A face that collapses is in none.
    pub members: Vec<Vec<usize>>,
    /// Whether a face has to turn to agree with the first face of its surface.
    pub turned_alike: Vec<bool>,
}

impl Surfaces {
    /// The surfaces of `faces` faces whose edges are `edges` ([`welded_edges`]).
    pub fn along(edges: &HashMap<(u32, u32), Vec<(usize, bool)>>, faces: usize) -> Self {
        let mut neighbours: Vec<Vec<(usize, bool)>> = vec![Vec::new(); faces];
        let mut on_an_edge = vec![false; faces];
        for along in edges.values() {
            for &(f, _) in along {
                on_an_edge[f] = true;
            }
            if let [(f, f_up), (g, g_up)] = along[..] {
                // Two faces wound alike run along their shared edge in opposite directions.
                let alike = f_up != g_up;
                neighbours[f].push((g, alike));
                neighbours[g].push((f, alike));
            }
        }
        // In face order, not the map's, which differs from run to run: on a surface that
        // cannot be wound alike the walk's order decides, and an answer must not change.
        for faces in &mut neighbours {
            faces.sort_unstable();
        }
        let mut seen = vec![false; faces];
        let mut turned_alike = vec![false; faces];
        let mut members = Vec::new();
        // Started from the lowest face not yet seen, so each surface's first face is its lowest.
        for start in (0..faces).filter(|&f| on_an_edge[f]) {
            if seen[start] {
                continue;
            }
            seen[start] = true;
            let mut surface = vec![start];
            let mut queue = VecDeque::from([start]);
            while let Some(f) = queue.pop_front() {
                for &(g, alike) in &neighbours[f] {
                    // On a one-sided surface (a Moebius strip) the first way round wins.
                    if !seen[g] {
                        seen[g] = true;
                        turned_alike[g] = turned_alike[f] ^ !alike;
                        surface.push(g);
                        queue.push_back(g);
                    }
                }
            }
            members.push(surface);
        }
        Self { members, turned_alike }
    }

    /// The surfaces of `mesh`'s faces; indices must be valid ([`Mesh::validate`]).
    pub fn of(mesh: &Mesh) -> Self {
        Self::along(&welded_edges(mesh), mesh.faces.len())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn faces_join_across_two_face_edges_only_and_learn_which_turn() {
        let mesh = Mesh {
            // Vertex 4 sits where vertex 1 does, as a seam splits it.
            vertices: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [1.0, 1.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.5, 0.5, 1.0],
                [0.5, 0.5, -1.0],
                [-1.0, 0.5, 0.5],
            ],
            faces: vec![
                // 0 and 1 share the edge 1-2 (1 through its seam copy), 1 wound against 0.
                [0, 1, 2],
                [4, 2, 3],
                // 2 collapses; 3, 4 and 5 are three faces on the edge 0-2: no surface joins them.
                [0, 4, 1],
                [0, 2, 5],
                [0, 2, 6],
                [2, 0, 7],
            ],
            normals: None,
        };
        let surfaces = Surfaces::of(&mesh);
        assert_eq!(surfaces.members, vec![vec![0, 1], vec![3], vec![4], vec![5]]);
        assert_eq!(surfaces.turned_alike[..2], [false, true]);
        let edges = welded_edges(&mesh);
        assert_eq!(edges[&(0, 2)].len(), 4, "the three faces and face 0");
        assert!(edges.values().flatten().all(|&(f, _)| f != 2), "the collapsed face has no edge");
    }
}
