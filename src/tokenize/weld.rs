//! Welding near corners. A decoder that puts a corner shared by several faces one grid cell
//! off on one of them leaves a crack: two faces that should meet along an edge have no edge in
//! common, and the mesh falls apart into slivers once its corners are fitted one by one.
//! Merging corners a cell or so apart closes such cracks; on the grid a low-poly mesh has
//! almost no two distinct corners that close (see `docs/decisions.md`, "Welding").

use std::collections::hash_map::Entry;
use std::collections::{HashMap, HashSet};

use parry3d_f64::na::Vector3;

use super::order::{FaceToken, ZyxVertex, canonical_face, face_vertices, swap_xz, vertex_set_key};

/// `faces` with every corner within `radius` cells (on each axis) of a more used corner moved
/// onto it where that stitches faces together, then every face split at a corner within
/// `radius` cells of one of its open edges where that stitches faces together, in canonical ZYX
/// order, without faces that were collapsed or repeated as given. A radius of 0 changes nothing
/// but that.
///
/// Corners are taken from the most used down (ties in ZYX order); each either joins the
/// nearest kept corner within the radius that it can join, or is kept itself, so a weld never
/// chains corners further than the radius from where they are kept. A corner joins another
/// only where one of its faces then shares an edge that had one face (a crack closes), no edge
/// gets a third face, and no face collapses or repeats another. Why: the two sides of a crack
/// are one corner decoded twice, on faces that should meet along an edge; two corners of one
/// face a cell apart are an edge the mesh has (a bevel), and two faces a cell apart with no
/// edge between them are the two sides of something thin, or parts that only touch.
///
/// A face is split at a corner on its edge (a T-junction: the faces across the edge meet it at
/// a corner between its ends) under the same rule, so that the two halves of the edge are
/// shared where the whole edge was not ([`Welded::split_edges_at_corners`]).
pub fn weld_near_corners(faces: &[FaceToken], radius: u16) -> Vec<FaceToken> {
    let mut welded = Welded::of(faces);
    let mut corners: Vec<(ZyxVertex, usize)> =
        welded.faces_of.iter().map(|(&c, faces)| (c, faces.len())).collect();
    corners.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    let mut kept: HashSet<ZyxVertex> = HashSet::new();
    for (corner, _) in corners {
        let joins = |target: &ZyxVertex| kept.contains(target) && welded.can_move(corner, *target);
        match nearest(corner, radius, joins) {
            Some(target) => welded.move_corner(corner, target),
            None => {
                kept.insert(corner);
            }
        }
    }
    if radius > 0 {
        welded.split_edges_at_corners(f64::from(radius));
    }
    let mut seen = HashSet::new();
    let mut result: Vec<FaceToken> = welded
        .faces
        .iter()
        // `canonical_face` reads (x, y, z) corners: None for a face collapsed as given.
        .filter_map(|corners| canonical_face(corners.map(swap_xz)))
        .filter(|face| seen.insert(vertex_set_key(face)))
        .collect();
    result.sort_unstable();
    result
}

/// Faces as the weld has moved their corners so far, and how often each set of three corners
/// and each edge occurs among them.
struct Welded {
    faces: Vec<[ZyxVertex; 3]>,
    faces_of: HashMap<ZyxVertex, Vec<usize>>,
    occurs: HashMap<[ZyxVertex; 3], usize>,
    edges: HashMap<[ZyxVertex; 2], usize>,
}

impl Welded {
    fn of(faces: &[FaceToken]) -> Self {
        let faces: Vec<[ZyxVertex; 3]> = faces.iter().map(face_vertices).collect();
        let mut welded =
            Self { faces, faces_of: HashMap::new(), occurs: HashMap::new(), edges: HashMap::new() };
        for i in 0..welded.faces.len() {
            for corner in welded.faces[i] {
                welded.faces_of.entry(corner).or_default().push(i);
            }
            welded.count(i, 1);
        }
        welded
    }

    /// Adds `delta` (1 or -1) to the counts of face `i`'s corner set and edges.
    fn count(&mut self, i: usize, delta: isize) {
        let face = self.faces[i];
        let set = corner_set(&face);
        let edges = [[set[0], set[1]], [set[1], set[2]], [set[0], set[2]]];
        add(&mut self.occurs, set, delta);
        for edge in edges {
            add(&mut self.edges, edge, delta);
        }
    }

    /// `face` with `from` moved to `to`.
    fn moved(face: &[ZyxVertex; 3], from: ZyxVertex, to: ZyxVertex) -> [ZyxVertex; 3] {
        face.map(|c| if c == from { to } else { c })
    }

    /// Whether moving `from` onto `to` joins one of `from`'s faces to another face along an
    /// edge that had one face (closing a crack), leaves no edge with three faces, and leaves
    /// every face with three corners and none on the same corners as another face.
    fn can_move(&self, from: ZyxVertex, to: ZyxVertex) -> bool {
        let moving = self.faces_of.get(&from).map_or(&[][..], Vec::as_slice);
        let mut made = HashSet::new();
        // The moving faces' own edges run through `from`, not `to`: the counts of edges
        // through `to` are other faces', plus what the moving faces add here.
        let mut added: HashMap<[ZyxVertex; 2], usize> = HashMap::new();
        let mut stitched = false;
        for &i in moving {
            let face = Self::moved(&self.faces[i], from, to);
            let set = corner_set(&face);
            let collapsed = set[0] == set[1] || set[1] == set[2];
            if collapsed || self.occurs.contains_key(&set) || !made.insert(set) {
                return false;
            }
            for &other in face.iter().filter(|&&c| c != to) {
                let e = edge(other, to);
                let before = self.edges.get(&e).copied().unwrap_or(0);
                let here = added.entry(e).or_default();
                *here += 1;
                if before + *here > 2 {
                    return false;
                }
                stitched |= before == 1;
            }
        }
        stitched
    }

    /// Splits each face whose edge has no other face at a corner of other faces that lies on
    /// that edge (within `tolerance` cells of it, strictly between its ends), where a half of
    /// the edge then joins an edge that had one face: a T-junction. The halves split again as
    /// long as a face can be; each split leaves one open edge fewer, so this ends. It comes
    /// after the corners are welded, and leaves `faces_of` (the weld's) as it was.
    fn split_edges_at_corners(&mut self, tolerance: f64) {
        let mut corners: Vec<ZyxVertex> = self.faces_of.keys().copied().collect();
        corners.sort_unstable();
        let mut work: Vec<usize> = (0..self.faces.len()).rev().collect();
        while let Some(i) = work.pop() {
            let face = self.faces[i];
            // A face collapsed as given has no edges to split (and is dropped at the end).
            if face[0] == face[1] || face[1] == face[2] || face[0] == face[2] {
                continue;
            }
            for k in 0..3 {
                let (p, q, r) = (face[k], face[(k + 1) % 3], face[(k + 2) % 3]);
                if self.edges.get(&edge(p, q)) != Some(&1) {
                    continue;
                }
                let Some(v) = self.corner_on_edge(p, q, r, &corners, tolerance) else { continue };
                let mut near_p = face;
                near_p[(k + 1) % 3] = v;
                let mut near_q = face;
                near_q[k] = v;
                self.count(i, -1);
                self.faces[i] = near_p;
                self.count(i, 1);
                self.faces.push(near_q);
                self.count(self.faces.len() - 1, 1);
                work.extend([self.faces.len() - 1, i]);
                break;
            }
        }
    }

    /// The corner that splits edge `p`-`q` of face (`p`, `q`, `r`): within `tolerance` cells of
    /// the segment, strictly between its ends, and such that the split joins an edge that had
    /// one face, gives no edge a third face, and makes no flat or repeated face. The nearest to
    /// the segment wins (ties: nearer `p`, then ZYX order).
    fn corner_on_edge(
        &self,
        p: ZyxVertex,
        q: ZyxVertex,
        r: ZyxVertex,
        corners: &[ZyxVertex],
        tolerance: f64,
    ) -> Option<ZyxVertex> {
        let reach = tolerance.ceil() as u16;
        let low = |k: usize| p[k].min(q[k]).saturating_sub(reach);
        let high = |k: usize| p[k].max(q[k]).saturating_add(reach);
        let start = corners.partition_point(|c| c[0] < low(0));
        let end = corners.partition_point(|c| c[0] <= high(0));
        let along = position(q) - position(p);
        let length2 = along.norm_squared();
        let mut best: Option<(f64, f64, ZyxVertex)> = None;
        for &v in &corners[start..end] {
            if v == p || v == q || v == r || (1..3).any(|k| v[k] < low(k) || v[k] > high(k)) {
                continue;
            }
            let to_v = position(v) - position(p);
            let t = to_v.dot(&along) / length2;
            let off = to_v.norm_squared() - t * t * length2;
            if t <= 0.0 || t >= 1.0 || off > tolerance * tolerance + 1e-9 {
                continue;
            }
            if best.is_some_and(|b| (off, t, v) >= b) || !self.can_split(p, q, r, v) {
                continue;
            }
            best = Some((off, t, v));
        }
        best.map(|(_, _, v)| v)
    }

    /// Whether splitting face (`p`, `q`, `r`) at `v` on its edge `p`-`q` closes a crack and
    /// keeps the mesh as clean as it was (see [`Self::corner_on_edge`]).
    fn can_split(&self, p: ZyxVertex, q: ZyxVertex, r: ZyxVertex, v: ZyxVertex) -> bool {
        let uses = |a, b| self.edges.get(&edge(a, b)).copied().unwrap_or(0);
        let halves = [uses(p, v), uses(v, q)];
        let new_faces = [[p, v, r], [v, q, r]];
        halves.iter().all(|&n| n <= 1)
            && halves.contains(&1)
            && uses(v, r) == 0
            && new_faces.iter().all(|f| !flat(f) && !self.occurs.contains_key(&corner_set(f)))
    }

    fn move_corner(&mut self, from: ZyxVertex, to: ZyxVertex) {
        let Some(moving) = self.faces_of.remove(&from) else { return };
        for &i in &moving {
            self.count(i, -1);
            self.faces[i] = Self::moved(&self.faces[i], from, to);
            self.count(i, 1);
        }
        self.faces_of.entry(to).or_default().extend(moving);
    }
}

/// Adds `delta` to `key`'s count, dropping it at 0.
fn add<K: std::hash::Hash + Eq>(counts: &mut HashMap<K, usize>, key: K, delta: isize) {
    match counts.entry(key) {
        Entry::Occupied(mut e) => match e.get().saturating_add_signed(delta) {
            0 => {
                e.remove();
            }
            n => *e.get_mut() = n,
        },
        Entry::Vacant(e) => {
            if let Ok(n @ 1..) = usize::try_from(delta) {
                e.insert(n);
            }
        }
    }
}

fn position(v: ZyxVertex) -> Vector3<f64> {
    Vector3::from(v.map(f64::from))
}

/// Whether a face's corners lie on one line (exactly, on the grid).
fn flat([a, b, c]: &[ZyxVertex; 3]) -> bool {
    let (u, w) = (position(*b) - position(*a), position(*c) - position(*a));
    u.cross(&w) == Vector3::zeros()
}

/// An edge whatever its direction.
fn edge(a: ZyxVertex, b: ZyxVertex) -> [ZyxVertex; 2] {
    [a.min(b), a.max(b)]
}

/// A face's corners in order, whatever its winding and first corner.
fn corner_set(face: &[ZyxVertex; 3]) -> [ZyxVertex; 3] {
    let mut set = *face;
    set.sort_unstable();
    set
}

/// The corner nearest to `corner` (squared cells; ties in ZYX order), other than itself, with
/// every coordinate within `radius` of its own and `accepts`.
fn nearest(
    corner: ZyxVertex,
    radius: u16,
    accepts: impl Fn(&ZyxVertex) -> bool,
) -> Option<ZyxVertex> {
    let span = |c: u16| c.saturating_sub(radius)..=c.saturating_add(radius);
    let mut best: Option<(u32, ZyxVertex)> = None;
    for z in span(corner[0]) {
        for y in span(corner[1]) {
            for x in span(corner[2]) {
                let candidate = [z, y, x];
                if candidate == corner || !accepts(&candidate) {
                    continue;
                }
                let d: u32 =
                    (0..3).map(|k| u32::from(corner[k].abs_diff(candidate[k])).pow(2)).sum();
                if best.is_none_or(|b| (d, candidate) < b) {
                    best = Some((d, candidate));
                }
            }
        }
    }
    best.map(|(_, c)| c)
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;
    use crate::mesh::primitives::cuboid;
    use crate::metrics::topology;
    use crate::tokenize::{Quantizer, detokenize, is_canonical_sequence, tokenize};

    fn box_tokens() -> Vec<FaceToken> {
        tokenize(&cuboid([1.2, 0.8, 1.0]), Quantizer::new(128).unwrap()).faces
    }

    /// Moves corner `c` of face `f` by `delta` cells on every axis.
    fn nudged(mut faces: Vec<FaceToken>, f: usize, c: usize, delta: i32) -> Vec<FaceToken> {
        for k in 0..3 {
            let v = &mut faces[f][3 * c + k];
            *v = (i32::from(*v) + delta) as u16;
        }
        faces
    }

    #[test]
    fn a_corner_a_cell_off_welds_back_and_closes_the_box() {
        let q = Quantizer::new(128).unwrap();
        let truth = box_tokens();
        let cracked = nudged(truth.clone(), 3, 1, 1);
        assert!(topology(&detokenize(&cracked, q)).boundary_edges > 0);
        let welded = weld_near_corners(&cracked, 1);
        assert_eq!(welded, truth);
        assert!(is_canonical_sequence(&welded));
        assert_eq!(topology(&detokenize(&welded, q)).boundary_edges, 0);
        // Two cells off is beyond a radius of 1.
        let far = nudged(truth.clone(), 3, 1, 2);
        assert_ne!(weld_near_corners(&far, 1), truth);
        assert_eq!(weld_near_corners(&far, 2), truth);
    }

    #[test]
    fn radius_zero_keeps_every_face_and_collapsed_and_repeated_faces_go() {
        let mut faces = box_tokens();
        let mut reversed = faces[0];
        reversed.swap(3, 6);
        reversed.swap(4, 7);
        reversed.swap(5, 8);
        faces.push(reversed);
        let mut sorted = faces.clone();
        sorted.sort_unstable();
        // The reversed copy repeats face 0 on the same corners: dropped even at radius 0.
        assert_eq!(weld_near_corners(&sorted, 0).len(), 12);
        // A sliver whose corners are a cell apart is an edge the mesh has: it stays.
        let sliver = [10, 10, 10, 10, 10, 11, 40, 40, 40];
        assert_eq!(weld_near_corners(&[sliver], 1), [sliver]);
        assert_eq!(weld_near_corners(&[], 1), Vec::<FaceToken>::new());
    }

    #[test]
    fn thin_parts_keep_their_faces() {
        // Two triangles a cell apart, one above the other: moving one onto the other would
        // make them one face.
        let below = [10, 10, 10, 10, 10, 40, 10, 40, 10];
        let above = [11, 10, 10, 11, 10, 40, 11, 40, 10];
        assert_eq!(weld_near_corners(&[below, above], 1), [below, above]);
    }

    #[test]
    fn welds_stitch_and_do_not_chain() {
        // Face p = (a, b, c); face q was decoded with a one cell off, at a1, so p and q share
        // only the corner b; face r has a2, two cells from a and one from a1.
        let (a, a1, a2) = ([0, 0, 10], [0, 0, 11], [0, 0, 12]);
        let (b, c, d, e) = ([0, 50, 10], [50, 0, 10], [50, 50, 30], [60, 60, 60]);
        let face = |v: [ZyxVertex; 3]| canonical_face(v.map(swap_xz)).unwrap();
        let (p, q, r) = (face([a, b, c]), face([a1, b, d]), face([a2, d, e]));
        let welded = weld_near_corners(&[p, q, r], 1);
        // a1 joins a, stitching q to p along a-b; a2 is kept: it is two cells from a, and a1
        // is not kept.
        let mut expected = vec![p, face([a, b, d]), r];
        expected.sort_unstable();
        assert_eq!(welded, expected);
    }

    /// ZYX corners of a tetrahedron: its edge a-b runs along x.
    const A: ZyxVertex = [0, 0, 0];
    const B: ZyxVertex = [0, 0, 40];
    const C: ZyxVertex = [0, 40, 0];
    const D: ZyxVertex = [40, 0, 0];

    fn face(v: [ZyxVertex; 3]) -> FaceToken {
        canonical_face(v.map(swap_xz)).unwrap()
    }

    fn open_edges(faces: &[FaceToken]) -> usize {
        topology(&detokenize(faces, Quantizer::new(128).unwrap())).boundary_edges
    }

    /// The tetrahedron with its face a-b-d split at the corners `on_ab` along a-b, so that face
    /// a-b-c meets them in T-junctions.
    fn tetrahedron_split_along_ab(on_ab: &[ZyxVertex]) -> Vec<FaceToken> {
        let along: Vec<ZyxVertex> = [A].iter().chain(on_ab).chain([&B]).copied().collect();
        let mut faces: Vec<FaceToken> = along.windows(2).map(|w| face([w[0], w[1], D])).collect();
        faces.extend([face([A, B, C]), face([A, C, D]), face([B, C, D])]);
        faces.sort_unstable();
        faces
    }

    #[test]
    fn a_face_splits_at_corners_on_its_open_edge_and_the_tetrahedron_closes() {
        for on_ab in [&[[0, 0, 20]][..], &[[0, 0, 10], [0, 0, 30]], &[[0, 1, 20]]] {
            let faces = tetrahedron_split_along_ab(on_ab);
            assert_eq!(open_edges(&faces), 1 + on_ab.len() + 1);
            let welded = weld_near_corners(&faces, 1);
            assert_eq!(open_edges(&welded), 0, "{on_ab:?}");
            // a-b-c split in as many faces as a-b-d was; the faces keep their winding.
            assert_eq!(welded.len(), 2 * (on_ab.len() + 1) + 2);
            assert!(welded.contains(&face([A, on_ab[0], C])));
            assert!(is_canonical_sequence(&welded));
            // A radius of 0 leaves the junctions open.
            assert_eq!(weld_near_corners(&faces, 0), faces);
        }
    }

    #[test]
    fn a_corner_splits_only_within_the_radius_of_the_edge() {
        let faces = tetrahedron_split_along_ab(&[[0, 2, 20]]);
        assert_eq!(weld_near_corners(&faces, 1), faces);
        assert_eq!(open_edges(&weld_near_corners(&faces, 2)), 0);
    }

    #[test]
    fn a_corner_on_an_edge_that_stitches_nothing_splits_nothing() {
        // A face whose corner lies on a-b without an edge along it: parts that touch.
        let faces = [face([A, B, C]), face([[0, 0, 20], [30, 30, 20], [30, 0, 25]])];
        let mut sorted = faces.to_vec();
        sorted.sort_unstable();
        assert_eq!(weld_near_corners(&sorted, 1), sorted);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]

        /// On a small grid, where corners and edges often land on each other: welding never
        /// opens an edge or gives one a third face that deduplicating alone would not, and its
        /// faces keep their corners on the grid, whole and canonical.
        #[test]
        fn welding_closes_cracks_and_opens_none(
            corners in proptest::collection::vec([0u16..6, 0u16..6, 0u16..6], 9..45),
            radius in 1u16..3,
        ) {
            let mut faces: Vec<FaceToken> = corners
                .chunks_exact(3)
                .filter_map(|c| canonical_face([c[0], c[1], c[2]]))
                .collect();
            faces.sort_unstable();
            let q = Quantizer::new(128).unwrap();
            let plain = topology(&detokenize(&weld_near_corners(&faces, 0), q));
            let welded = weld_near_corners(&faces, radius);
            let after = topology(&detokenize(&welded, q));
            prop_assert!(after.boundary_edges <= plain.boundary_edges);
            prop_assert!(after.non_manifold_edges <= plain.non_manifold_edges);
            prop_assert!(is_canonical_sequence(&welded));
            prop_assert!(welded.iter().flatten().all(|&c| c < 6));
        }
    }

    #[test]
    fn corners_that_stitch_nothing_stay_apart() {
        // Two faces with a corner each a cell apart but no edge to share: parts that touch.
        let left = [0, 0, 10, 0, 40, 0, 40, 0, 0];
        let right = [0, 0, 11, 0, 40, 30, 40, 0, 30];
        assert_eq!(weld_near_corners(&[left, right], 1), [left, right]);
    }
}
