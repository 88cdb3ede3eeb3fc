//! The ZYX order: a vertex is compared as the tuple (z, y, x), a face starts at its smallest
//! vertex, and faces sort lexicographically. Fixing this order makes the sequence canonical.

/// One face = 9 integers (z0 y0 x0 z1 y1 x1 z2 y2 x2): vertex v = (z, y, x).
///
/// Because each vertex is stored as (z, y, x), the derived array order of `[u16; 9]` is exactly
/// the (v0, v1, v2) ZYX order of DESIGN.md.
pub type FaceToken = [u16; 9];

/// A quantized vertex in ZYX order: `[z, y, x]`, compared lexicographically.
pub type ZyxVertex = [u16; 3];

/// `[x, y, z]` (the order of files) to `[z, y, x]`, and back: the swap is its own inverse.
pub fn swap_xz([a, b, c]: [u16; 3]) -> [u16; 3] {
    [c, b, a]
}

/// The three ZYX vertices of a face token.
pub fn face_vertices(f: &FaceToken) -> [ZyxVertex; 3] {
    [[f[0], f[1], f[2]], [f[3], f[4], f[5]], [f[6], f[7], f[8]]]
}

pub(crate) fn face_from_vertices([a, b, c]: [ZyxVertex; 3]) -> FaceToken {
    [a[0], a[1], a[2], b[0], b[1], b[2], c[0], c[1], c[2]]
}

/// Canonical face from three quantized vertices given as (x, y, z) order-in-file: converts each
/// to (z, y, x), rotates cyclically so the smallest (z, y, x) vertex comes first (the winding is
/// kept); `None` if two vertices are equal (the face collapsed).
pub fn canonical_face(v: [[u16; 3]; 3]) -> Option<FaceToken> {
    let first = canonical_start(v)?;
    let v = v.map(swap_xz);
    Some(face_from_vertices([v[first], v[(first + 1) % 3], v[(first + 2) % 3]]))
}

/// Which of the three (x, y, z) vertices [`canonical_face`] puts first; `None` if two are
/// equal.
pub fn canonical_start(v: [[u16; 3]; 3]) -> Option<usize> {
    let v = v.map(swap_xz);
    if v[0] == v[1] || v[1] == v[2] || v[0] == v[2] {
        return None;
    }
    (0..3).min_by_key(|&i| v[i])
}

/// The face starts at its strictly smallest vertex and no two vertices are equal. (Whether the
/// coordinates fit the quantizer is [`super::Quantizer::fits`].)
pub fn is_canonical_face(f: &FaceToken) -> bool {
    let [a, b, c] = face_vertices(f);
    a < b && a < c && b != c
}

/// The vertex set of a canonical face regardless of its orientation: faces with equal keys
/// repeat each other.
pub(crate) fn vertex_set_key(f: &FaceToken) -> [ZyxVertex; 3] {
    let [a, b, c] = face_vertices(f);
    // A canonical face's first vertex is already its smallest.
    [a, b.min(c), b.max(c)]
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn rotates_to_the_smallest_zyx_vertex_keeping_the_winding() {
        // (x, y, z) in file order; ZYX: A = [0,0,5], B = [1,0,0], C = [0,2,0].
        let a = [5, 0, 0];
        let b = [0, 0, 1];
        let c = [0, 2, 0];
        // Smallest ZYX vertex is A ([0,0,5]) < C ([0,2,0]) < B ([1,0,0]).
        let expected = [0, 0, 5, 1, 0, 0, 0, 2, 0];
        assert_eq!(canonical_face([a, b, c]), Some(expected));
        assert_eq!(canonical_face([b, c, a]), Some(expected));
        assert_eq!(canonical_face([c, a, b]), Some(expected));
        // The other orientation is a different face.
        assert_eq!(canonical_face([a, c, b]), Some([0, 0, 5, 0, 2, 0, 1, 0, 0]));
        assert!(is_canonical_face(&expected));
    }

    #[test]
    fn collapsed_faces_are_none() {
        assert_eq!(canonical_face([[1, 2, 3], [1, 2, 3], [4, 5, 6]]), None);
        assert_eq!(canonical_face([[1, 2, 3], [4, 5, 6], [4, 5, 6]]), None);
        assert_eq!(canonical_face([[4, 5, 6], [1, 2, 3], [4, 5, 6]]), None);
    }

    #[test]
    fn non_canonical_faces_are_recognized() {
        assert!(!is_canonical_face(&[1, 0, 0, 0, 0, 0, 2, 0, 0])); // v1 < v0
        assert!(!is_canonical_face(&[0, 0, 0, 1, 0, 0, 1, 0, 0])); // v1 == v2
        assert!(!is_canonical_face(&[0; 9]));
    }

    proptest! {
        #[test]
        fn canonical_faces_are_canonical(v in prop::array::uniform3(prop::array::uniform3(0u16..4))) {
            match canonical_face(v) {
                Some(f) => {
                    prop_assert!(is_canonical_face(&f));
                    // Same cyclic order: the face is one of the three rotations of the input.
                    let z = v.map(swap_xz);
                    let rotations = (0..3).map(|r| face_from_vertices([z[r], z[(r + 1) % 3], z[(r + 2) % 3]]));
                    prop_assert!(rotations.into_iter().any(|g| g == f));
                }
                None => prop_assert!(v[0] == v[1] || v[1] == v[2] || v[0] == v[2]),
            }
        }
    }
}
