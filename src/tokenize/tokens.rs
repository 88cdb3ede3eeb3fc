//! Mesh <-> face tokens.

use std::collections::{HashMap, HashSet};

use crate::mesh::{Mesh, Normalization};

use super::order::{ZyxVertex, face_vertices, swap_xz, vertex_set_key};
use super::{
    FaceToken, Quantizer, TokenizeError, canonical_face, canonical_polygons, is_canonical_face,
};

/// A mesh as its canonical face sequence, with what the tokenizer removed on the way.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Tokenized {
    /// Canonical faces in ZYX order (see [`is_canonical_sequence`]).
    pub faces: Vec<FaceToken>,
    /// Input vertices that fell into a cell an earlier vertex already occupied and were merged
    /// into it (input vertices minus occupied cells).
    pub welded_vertices: usize,
    /// Faces dropped because two of their corners quantized to the same cell. A face with an
    /// out-of-range vertex index has no geometry either and is counted here; validate the mesh
    /// first ([`tokenize_mesh`] does) to reject such input instead.
    pub collapsed_faces: usize,
    /// Faces dropped because another face has the same three vertices (in either orientation).
    pub duplicate_faces: usize,
}

/// Tokenizes a mesh ALREADY in the normalized frame: quantizes, welds vertices sharing a cell,
/// drops collapsed faces and faces that repeat another (same three vertices in any order or
/// orientation: the smallest token is kept, so the result does not depend on the input's face
/// order), re-splits every flat convex polygon as a fan from its smallest corner
/// ([`canonical_polygons`]), then sorts the faces in ZYX order.
///
/// Coordinates outside [-1, 1] are clamped to the border cells; a NaN lands in cell 0
/// (`Mesh::validate` rejects those first).
pub fn tokenize(mesh: &Mesh, q: Quantizer) -> Tokenized {
    let cells: Vec<[u16; 3]> = mesh.vertices.iter().map(|v| v.map(|c| q.quantize(c))).collect();
    let occupied: HashSet<&[u16; 3]> = cells.iter().collect();
    let welded_vertices = cells.len() - occupied.len();

    let mut collapsed_faces = 0;
    let mut tokens = Vec::with_capacity(mesh.faces.len());
    for face in &mesh.faces {
        let corners = face.map(|i| cells.get(i as usize).copied());
        match corners {
            [Some(a), Some(b), Some(c)] => match canonical_face([a, b, c]) {
                Some(token) => tokens.push(token),
                None => collapsed_faces += 1,
            },
            _ => collapsed_faces += 1,
        }
    }
    // Repeats go before polygons are re-split (an edge of a repeated face has too many faces
    // for a region to form across it) and again after: two sides of a sheet that were split
    // differently repeat each other once both are fans.
    let (tokens, repeats) = without_repeats(tokens);
    let (mut faces, new_repeats) = without_repeats(canonical_polygons(&tokens));
    let duplicate_faces = repeats + new_repeats;
    faces.sort_unstable();
    Tokenized { faces, welded_vertices, collapsed_faces, duplicate_faces }
}

/// The faces with each group of repeats (same three vertices) reduced to its smallest token,
/// so the result does not depend on the input's face order; and how many were dropped.
fn without_repeats(faces: Vec<FaceToken>) -> (Vec<FaceToken>, usize) {
    let mut keyed: Vec<_> = faces.into_iter().map(|t| (vertex_set_key(&t), t)).collect();
    // Sorting by (vertex set, token) puts each group of repeats together with its smallest
    // token first, which `dedup_by_key` keeps.
    keyed.sort_unstable();
    let before = keyed.len();
    keyed.dedup_by_key(|(key, _)| *key);
    let dropped = before - keyed.len();
    (keyed.into_iter().map(|(_, token)| token).collect(), dropped)
}

/// Tokenizes a mesh in any coordinates: validates it, normalizes it (`Mesh::normalized`), then
/// tokenizes; returns the normalization too, to put decoded meshes back in the caller's frame.
pub fn tokenize_mesh(
    mesh: &Mesh,
    q: Quantizer,
) -> Result<(Tokenized, Normalization), TokenizeError> {
    mesh.validate()?;
    let (normalized, normalization) = mesh.normalized()?;
    Ok((tokenize(&normalized, q), normalization))
}

/// The inverse of [`tokenize`]: a welded mesh in the normalized frame. Identical quantized
/// vertices share one index, vertices are numbered in order of first appearance, faces keep
/// the sequence's order and winding.
///
/// Nothing is checked: a non-canonical or collapsed face is reproduced as it is, and a
/// coordinate past the last level is clamped to it (and welded with that level's vertex).
pub fn detokenize(faces: &[FaceToken], q: Quantizer) -> Mesh {
    let last = q.levels() - 1;
    let mut index: HashMap<[u16; 3], u32> = HashMap::new();
    let mut vertices = Vec::new();
    let mut mesh_faces = Vec::with_capacity(faces.len());
    for face in faces {
        let corners = face_vertices(face).map(|zyx| {
            let zyx = zyx.map(|c| c.min(last));
            *index.entry(zyx).or_insert_with(|| {
                vertices.push(corner_position(zyx, q));
                // Saturating only matters past 2^32 distinct vertices, i.e. more than 1.4e9
                // faces (25 GB of tokens): far beyond any configured face limit.
                u32::try_from(vertices.len() - 1).unwrap_or(u32::MAX)
            })
        });
        mesh_faces.push(corners);
    }
    Mesh::new(vertices, mesh_faces)
}

/// The three corners of a face in the normalized frame, (x, y, z) each, as [`detokenize`]
/// places them.
pub fn face_positions(face: &FaceToken, q: Quantizer) -> [[f32; 3]; 3] {
    let last = q.levels() - 1;
    face_vertices(face).map(|zyx| corner_position(zyx.map(|c| c.min(last)), q))
}

fn corner_position(zyx: ZyxVertex, q: Quantizer) -> [f32; 3] {
    swap_xz(zyx).map(|c| q.dequantize(c))
}

/// Every face canonical, faces strictly increasing in ZYX order, and no two faces on the same
/// three vertices (not even with opposite windings): the order [`tokenize`] makes, which
/// decoding keeps to. (How flat polygons are split is not checked: a decoder may split them
/// either way.)
pub fn is_canonical_sequence(faces: &[FaceToken]) -> bool {
    let increasing = faces.windows(2).all(|w| w[0] < w[1]);
    let mut seen = HashSet::with_capacity(faces.len());
    increasing && faces.iter().all(|f| is_canonical_face(f) && seen.insert(vertex_set_key(f)))
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use proptest::prelude::*;

    use super::*;
    use crate::mesh::{triangle_area, triangle_normal};

    /// Corners of [-1, 1]^3 at x, y or z = +1 (and the origin corner), outward windings.
    /// Quantized at 128 levels: P0 = (0,0,0), P1 = (127,0,0), P2 = (0,127,0), P3 = (0,0,127).
    fn tetrahedron() -> Mesh {
        Mesh::new(
            vec![[-1.0, -1.0, -1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]],
            vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        )
    }

    /// The tetrahedron's sequence, worked out by hand. ZYX vertices: P0 = [0,0,0],
    /// P1 = [0,0,127], P2 = [0,127,0], P3 = [127,0,0], so P0 < P1 < P2 < P3. Faces rotated to
    /// their smallest vertex: (P0,P2,P1), (P0,P1,P3), (P0,P3,P2), (P1,P2,P3); sorted by v1 among
    /// the three starting at P0, then the one starting at P1.
    const TETRAHEDRON_TOKENS: [FaceToken; 4] = [
        [0, 0, 0, 0, 0, 127, 127, 0, 0],
        [0, 0, 0, 0, 127, 0, 0, 0, 127],
        [0, 0, 0, 127, 0, 0, 0, 127, 0],
        [0, 0, 127, 0, 127, 0, 127, 0, 0],
    ];

    #[test]
    fn tetrahedron_has_the_hand_computed_sequence() {
        let t = tokenize(&tetrahedron(), Quantizer::default());
        assert_eq!(t.faces, TETRAHEDRON_TOKENS);
        assert_eq!((t.welded_vertices, t.collapsed_faces, t.duplicate_faces), (0, 0, 0));
        assert!(is_canonical_sequence(&t.faces));
    }

    #[test]
    fn welds_collapses_and_duplicates_are_removed_and_counted() {
        let mut m = tetrahedron();
        // P4 is 0.001 from P0: (0.001 / 2) x 127 = 0.06 of a cell, so it welds onto P0.
        m.vertices.push([-0.999, -1.0, -1.0]);
        m.faces.push([4, 3, 1]); // (P0, P3, P1) after welding: face [0, 1, 3] reversed
        m.faces.push([0, 4, 2]); // P0 twice: collapsed
        m.faces.push([0, 1, 7]); // no vertex 7: no geometry
        m.faces.reverse();
        let t = tokenize(&m, Quantizer::default());
        assert_eq!(t.welded_vertices, 1);
        assert_eq!(t.collapsed_faces, 2);
        assert_eq!(t.duplicate_faces, 1);
        // Of (P0,P1,P3) and (P0,P3,P1) the smaller token stays: [0,0,0, 0,0,127, 127,0,0].
        assert_eq!(t.faces, TETRAHEDRON_TOKENS);
    }

    #[test]
    fn tokenize_mesh_normalizes_first() {
        // The tetrahedron scaled by 5 and moved to x = 10.
        let mut m = tetrahedron();
        for v in &mut m.vertices {
            *v = [v[0] * 5.0 + 10.0, v[1] * 5.0, v[2] * 5.0];
        }
        let (t, n) = tokenize_mesh(&m, Quantizer::default()).unwrap();
        assert_eq!(t.faces, TETRAHEDRON_TOKENS);
        assert_eq!((n.center, n.half_extent), ([10.0, 0.0, 0.0], 5.0));

        m.faces.push([0, 1, 9]);
        assert!(matches!(tokenize_mesh(&m, Quantizer::default()), Err(TokenizeError::Mesh(_))));
        assert!(tokenize_mesh(&Mesh::default(), Quantizer::default()).is_err());
    }

    #[test]
    fn detokenize_welds_in_first_appearance_order() {
        let m = detokenize(&TETRAHEDRON_TOKENS, Quantizer::default());
        // First face: ZYX [0,0,0] = P0, [0,0,127] = P1, [127,0,0] = P3; then P2.
        let expected =
            [[-1.0, -1.0, -1.0], [1.0, -1.0, -1.0], [-1.0, -1.0, 1.0], [-1.0, 1.0, -1.0]];
        assert_eq!(m.vertices, expected);
        assert_eq!(m.faces, [[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]]);
        // Same outward normals as the input tetrahedron (P0 -> 0, P1 -> 1, P2 -> 3, P3 -> 2).
        let original = tetrahedron();
        let mut normals_in = original.face_normals();
        let mut normals_out = m.face_normals();
        normals_in.sort_by(|a, b| a.partial_cmp(b).unwrap());
        normals_out.sort_by(|a, b| a.partial_cmp(b).unwrap());
        assert_eq!(normals_in, normals_out);
    }

    #[test]
    fn canonical_sequence_rules() {
        assert!(is_canonical_sequence(&[]));
        assert!(is_canonical_sequence(&TETRAHEDRON_TOKENS));
        let mut unsorted = TETRAHEDRON_TOKENS;
        unsorted.swap(0, 1);
        assert!(!is_canonical_sequence(&unsorted));
        let repeated = [TETRAHEDRON_TOKENS[0], TETRAHEDRON_TOKENS[0]];
        assert!(!is_canonical_sequence(&repeated));
        // The same three vertices in both orientations: sorted and canonical, still a repeat.
        let flipped = [[0, 0, 0, 0, 0, 1, 0, 1, 0], [0, 0, 0, 0, 1, 0, 0, 0, 1]];
        assert!(flipped.iter().all(is_canonical_face));
        assert!(!is_canonical_sequence(&flipped));
        assert!(!is_canonical_sequence(&[[0, 0, 1, 0, 0, 0, 0, 1, 0]]));
    }

    #[test]
    fn detokenize_clamps_and_welds_coordinates_past_the_last_level() {
        let q = Quantizer::default();
        let m = detokenize(&[[0, 0, 0, 0, 0, 127, 0, 5, 0], [0, 0, 0, 0, 0, 900, 0, 0, 9]], q);
        assert_eq!(m.vertices.len(), 4);
        assert_eq!(m.faces, [[0, 1, 2], [0, 1, 3]]);
        assert_eq!(m.vertices[1], [1.0, -1.0, -1.0]);
    }

    #[test]
    fn hostile_coordinates_do_not_panic() {
        let m = Mesh::new(
            vec![[f32::NAN, 0.0, 0.0], [f32::INFINITY, 5.0, -7.0], [0.0, f32::NEG_INFINITY, 1.0]],
            vec![[0, 1, 2], [2, 1, 0], [u32::MAX, 0, 1]],
        );
        let t = tokenize(&m, Quantizer::default());
        assert!(is_canonical_sequence(&t.faces));
        assert_eq!(t.faces.len() + t.collapsed_faces + t.duplicate_faces, 3);
    }

    // ----- property tests -----

    fn quantizer() -> impl Strategy<Value = Quantizer> {
        prop_oneof![Just(128u16), Just(256), Just(1024)].prop_map(|l| Quantizer::new(l).unwrap())
    }

    /// A canonical sequence built without the tokenizer: canonical faces over a small pool of
    /// grid vertices (so they share vertices), one per vertex set, sorted.
    fn canonical_sequence() -> impl Strategy<Value = (Quantizer, Vec<FaceToken>)> {
        quantizer().prop_flat_map(|q| {
            let l = q.levels();
            let pool = prop::collection::vec(prop::array::uniform3(0..l), 3..12);
            let faces = pool.prop_flat_map(|pool| {
                let n = pool.len();
                prop::collection::vec(prop::array::uniform3(0..n), 0..40).prop_map(move |fs| {
                    let mut by_set = BTreeMap::new();
                    for f in fs {
                        if let Some(t) = canonical_face(f.map(|i| pool[i])) {
                            by_set.entry(vertex_set_key(&t)).or_insert(t);
                        }
                    }
                    let mut seq: Vec<FaceToken> = by_set.into_values().collect();
                    seq.sort_unstable();
                    seq
                })
            });
            (Just(q), faces)
        })
    }

    /// A random mesh in the normalized frame; coordinates on a coarse grid of 9 values per axis
    /// so that welds, collapses and repeats all happen often. The values are centres of cells
    /// 0, 15, .., 120 at 128 levels, so quantizing at 128 levels moves no vertex.
    fn coarse_mesh() -> impl Strategy<Value = Mesh> {
        let cell = |i: u16| Quantizer::default().dequantize(15 * i);
        let vertex = prop::array::uniform3((0..9u16).prop_map(cell));
        prop::collection::vec(vertex, 3..16).prop_flat_map(|vs| {
            let n = vs.len() as u32;
            prop::collection::vec(prop::array::uniform3(0..n), 0..40)
                .prop_map(move |fs| Mesh::new(vs.clone(), fs))
        })
    }

    /// A permutation of 0..n from a proptest-chosen shuffle.
    fn permutation(n: usize) -> impl Strategy<Value = Vec<usize>> {
        Just((0..n).collect::<Vec<_>>()).prop_shuffle()
    }

    fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
        a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    }

    proptest! {
        #[test]
        fn detokenize_then_tokenize_changes_only_the_split_of_flat_polygons(
            (q, seq) in canonical_sequence()
        ) {
            prop_assert!(is_canonical_sequence(&seq));
            let t = tokenize(&detokenize(&seq, q), q);
            // Two sides of a sheet split differently become repeats once both are fans.
            let (mut expected, repeats) = without_repeats(canonical_polygons(&seq));
            expected.sort_unstable();
            prop_assert_eq!(t.faces, expected);
            prop_assert_eq!((t.welded_vertices, t.collapsed_faces, t.duplicate_faces), (0, 0, repeats));
        }

        #[test]
        fn a_tokenized_mesh_tokenizes_to_itself(m in coarse_mesh(), q in quantizer()) {
            let once = tokenize(&m, q);
            let twice = tokenize(&detokenize(&once.faces, q), q);
            prop_assert_eq!(twice.faces, once.faces);
            prop_assert_eq!((twice.collapsed_faces, twice.duplicate_faces), (0, 0));
        }

        #[test]
        fn output_is_always_a_canonical_sequence(m in coarse_mesh(), q in quantizer()) {
            let t = tokenize(&m, q);
            prop_assert!(is_canonical_sequence(&t.faces));
            prop_assert!(t.faces.iter().all(|f| q.fits(f)));
            prop_assert_eq!(t.faces.len() + t.collapsed_faces + t.duplicate_faces, m.faces.len());
        }

        #[test]
        fn invariant_to_face_order_renumbering_and_rotation(
            (m, face_perm, vertex_perm, rotations) in coarse_mesh().prop_flat_map(|m| {
                let (nf, nv) = (m.faces.len(), m.vertices.len());
                (Just(m), permutation(nf), permutation(nv), prop::collection::vec(0..3usize, nf))
            })
        ) {
            let q = Quantizer::default();
            // Vertex old i moves to new position vertex_perm[i].
            let mut vertices = vec![[0.0; 3]; m.vertices.len()];
            for (old, &new) in vertex_perm.iter().enumerate() {
                vertices[new] = m.vertices[old];
            }
            let faces = face_perm
                .iter()
                .map(|&f| {
                    let [a, b, c] = m.faces[f].map(|i| vertex_perm[i as usize] as u32);
                    match rotations[f] {
                        0 => [a, b, c],
                        1 => [b, c, a],
                        _ => [c, a, b],
                    }
                })
                .collect();
            let shuffled = Mesh::new(vertices, faces);
            prop_assert_eq!(tokenize(&shuffled, q), tokenize(&m, q));
        }

        #[test]
        fn winding_survives(m in coarse_mesh()) {
            // At 128 levels the coarse grid quantizes exactly: each output face is an input
            // face's triangle, so its normal is that face's normal or its opposite.
            let q = Quantizer::default();
            let out = detokenize(&tokenize(&m, q).faces, q);
            let key_of = |t: [[f32; 3]; 3]| {
                let mut k = t.map(|v| v.map(|c| q.quantize(c)));
                k.sort_unstable();
                k
            };
            let mut input_normals: HashMap<[[u16; 3]; 3], Vec<[f32; 3]>> = HashMap::new();
            // Zero-area (collinear) faces have no direction: their "normal" is rounding noise
            // blown up to unit length, so they are left out by area, not by normal length.
            let has_area = |t: [[f32; 3]; 3]| triangle_area(t) > 1e-6;
            for f in &m.faces {
                let t = m.triangle(f);
                if has_area(t) {
                    input_normals.entry(key_of(t)).or_default().push(triangle_normal(t));
                }
            }
            for f in &out.faces {
                let t = out.triangle(f);
                let Some(oriented) = input_normals.get(&key_of(t)) else { continue };
                // A face whose input had both orientations keeps one of them; skip it.
                let one_way = oriented.windows(2).all(|w| dot(w[0], w[1]) > 0.0);
                let n_out = triangle_normal(t);
                if one_way {
                    prop_assert!(dot(n_out, oriented[0]) > 0.99, "{n_out:?} vs {:?}", oriented[0]);
                }
            }
        }
    }
}
