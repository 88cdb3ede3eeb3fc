//! Parts of a mesh: connected components of faces that share vertices, each with a flat
//! colour, so that previews show how a generated mesh is put together.

use crate::mesh::{DisjointSets, Mesh};

/// Twelve colours that stay distinct under shading (Tableau 10 plus two); parts beyond twelve
/// reuse them in order.
const PALETTE: [[u8; 3]; 12] = [
    [78, 121, 167],
    [242, 142, 43],
    [225, 87, 89],
    [118, 183, 178],
    [89, 161, 79],
    [237, 201, 72],
    [176, 122, 161],
    [255, 157, 167],
    [156, 117, 95],
    [186, 176, 172],
    [31, 119, 180],
    [148, 103, 189],
];

/// The colour of part number `part`.
pub fn part_color(part: usize) -> [u8; 3] {
    PALETTE[part % PALETTE.len()]
}

/// The part of each face: parts are numbered 0, 1, ... in the order of their first face, so
/// the numbering (and the colours) depend only on the mesh. Indices must be valid
/// ([`Mesh::validate`]); a face with an index out of range is its own part.
pub fn face_parts(mesh: &Mesh) -> Vec<usize> {
    let mut sets = DisjointSets::new(mesh.vertices.len());
    for f in &mesh.faces {
        sets.union(f[0] as usize, f[1] as usize);
        sets.union(f[0] as usize, f[2] as usize);
    }
    let mut part_of_root = vec![usize::MAX; mesh.vertices.len()];
    let mut parts = 0;
    mesh.faces
        .iter()
        .map(|f| {
            let Some(slot) = sets.find(f[0] as usize).and_then(|r| part_of_root.get_mut(r)) else {
                parts += 1;
                return parts - 1;
            };
            if *slot == usize::MAX {
                *slot = parts;
                parts += 1;
            }
            *slot
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::cuboid;

    #[test]
    fn disjoint_boxes_are_parts_in_order_of_their_first_face() {
        let a = cuboid([1.0; 3]);
        let b = cuboid([1.0; 3]).translated([3.0, 0.0, 0.0]);
        let offset = a.vertices.len() as u32;
        let mut mesh = a.clone();
        mesh.vertices.extend(&b.vertices);
        // Interleave the faces: b's first face comes second.
        mesh.faces = a
            .faces
            .iter()
            .zip(&b.faces)
            .flat_map(|(fa, fb)| [*fa, fb.map(|i| i + offset)])
            .collect();
        let parts = face_parts(&mesh);
        assert_eq!(parts.len(), 24);
        assert!(parts.iter().step_by(2).all(|&p| p == 0));
        assert!(parts.iter().skip(1).step_by(2).all(|&p| p == 1));
        assert_ne!(part_color(0), part_color(1));
        assert_eq!(part_color(0), part_color(PALETTE.len()));
    }

    #[test]
    fn faces_joined_through_a_shared_vertex_are_one_part_and_bad_indices_do_not_panic() {
        let v = vec![[0.0; 3]; 5];
        let mesh = Mesh::new(v.clone(), vec![[0, 1, 2], [2, 3, 4]]);
        assert_eq!(face_parts(&mesh), vec![0, 0]);
        let bad = Mesh::new(v, vec![[0, 1, 2], [9, 3, 4], [3, 4, 7]]);
        assert_eq!(face_parts(&bad), vec![0, 1, 2]);
    }
}
