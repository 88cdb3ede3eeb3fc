//! Quads that are flat but for the grid's rounding: a frustum's slanted side, a box turned by an
//! arbitrary angle. Snapped to the grid, their corners are no longer exactly coplanar, so the
//! exact test of the parent module keeps whatever diagonal the input drew; yet the bend is
//! below the grid's resolution, so the points cannot show it and a model cannot learn it.
//!
//! Such a quad is split canonically only when it stands alone: re-splitting it must not create
//! or break a near-flat pairing with any neighbour, in either of its splits and in any split
//! the rules may give the neighbour. That keeps the result independent of the input's split and
//! its own fixed point, which a plain "near-flat pair" rule is not: re-splitting one quad can
//! pair a face with a different neighbour. Strips and fields of near-flat quads (a finely
//! tessellated gentle curve) are left as they are.

use std::collections::HashMap;

use super::{Regions, ZyxVertex, cross, dot, normal, sub};

/// Faces by undirected edge: the smaller corner first.
pub(super) type EdgeFaces = HashMap<(ZyxVertex, ZyxVertex), Vec<usize>>;

pub(super) fn edge_key(a: ZyxVertex, b: ZyxVertex) -> (ZyxVertex, ZyxVertex) {
    (a.min(b), a.max(b))
}

/// Two faces across an edge whose four corners make a strictly convex quad that is flat within
/// the grid's rounding but not exactly.
#[derive(Debug)]
pub(super) struct Quad {
    pub(super) faces: [usize; 2],
    /// Counter-clockwise seen from the faces' side; the input's diagonal is corners 0-2.
    pub(super) corners: [ZyxVertex; 4],
}

impl Quad {
    /// The quad of face `i` = (x, y, p) and face `j` = (y, x, q), if they make one.
    fn across(triangles: &[[ZyxVertex; 3]], i: usize, j: usize) -> Option<Quad> {
        let (ti, tj) = (triangles[i], triangles[j]);
        let (x, y, p) = (0..3)
            .map(|k| (ti[k], ti[(k + 1) % 3], ti[(k + 2) % 3]))
            .find(|&(x, y, _)| (0..3).any(|k| tj[k] == y && tj[(k + 1) % 3] == x))?;
        let q = *tj.iter().find(|&&v| v != x && v != y)?;
        if p == q {
            return None;
        }
        let corners = [x, q, y, p];
        let splits = [[x, y, p], [y, x, q], [q, y, p], [p, x, q]];
        // Convex seen from every triangle of either split, so the parent's fan accepts it
        // whichever face comes first.
        let convex = (0..4).all(|k| {
            let [a, b, c] = [corners[k], corners[(k + 1) % 4], corners[(k + 2) % 4]];
            let turn = cross(sub(b, a), sub(c, b));
            splits.iter().all(|t| dot(turn, normal(t)) > 0)
        });
        (convex && bend(x, y, p, q) == Bend::Rounding).then_some(Quad { faces: [i, j], corners })
    }

    /// The two corners off the boundary edge `k` -> `k + 1`: the apexes its face can have.
    fn apexes(&self, k: usize) -> [ZyxVertex; 2] {
        [self.corners[(k + 2) % 4], self.corners[(k + 3) % 4]]
    }

    fn has_face(&self, f: usize) -> bool {
        self.faces.contains(&f)
    }
}

#[derive(Debug, PartialEq)]
enum Bend {
    /// Exactly coplanar, or too degenerate to measure (parallel lines).
    None,
    /// Under half a grid cell: what rounding a flat quad's corners to the grid can do.
    Rounding,
    Real,
}

/// How far apart the lines a-b and p-q are (a quad's two diagonals, or an edge and the line
/// joining the apexes of the faces on either side of it). Unlike the angle between the faces,
/// this does not depend on which diagonal the quad was split along.
fn bend(a: ZyxVertex, b: ZyxVertex, p: ZyxVertex, q: ZyxVertex) -> Bend {
    let (ab, pq) = (sub(b, a), sub(q, p));
    let common = cross(ab, pq);
    let det = i128::from(dot(ab, cross(sub(p, a), sub(q, a))));
    let span: i128 = common.iter().map(|&c| i128::from(c) * i128::from(c)).sum();
    // The distance is |det| / |ab x pq|; compared squared, in integers.
    if det == 0 || span == 0 {
        Bend::None
    } else if 4 * det * det < span {
        Bend::Rounding
    } else {
        Bend::Real
    }
}

/// The quads flat within the grid's rounding that stand alone, each of faces that are alone in
/// their exact flat region.
pub(super) fn rounding_bent_quads(
    triangles: &[[ZyxVertex; 3]],
    by_edge: &EdgeFaces,
    flat: &Regions,
) -> Vec<Quad> {
    let lone = |f: usize| flat.members(f).len() == 1;
    let quads: Vec<Quad> = by_edge
        .values()
        .filter_map(|faces| match faces[..] {
            [i, j] if lone(i) && lone(j) => Quad::across(triangles, i, j),
            _ => None,
        })
        .collect();
    let mut quads_of: HashMap<usize, Vec<&Quad>> = HashMap::new();
    for quad in &quads {
        for &f in &quad.faces {
            quads_of.entry(f).or_default().push(quad);
        }
    }
    let context = Context { triangles, by_edge, flat, quads_of };
    let alone: Vec<bool> = quads.iter().map(|q| context.stands_alone(q)).collect();
    quads.into_iter().zip(alone).filter_map(|(q, alone)| alone.then_some(q)).collect()
}

struct Context<'a> {
    triangles: &'a [[ZyxVertex; 3]],
    by_edge: &'a EdgeFaces,
    flat: &'a Regions,
    quads_of: HashMap<usize, Vec<&'a Quad>>,
}

impl Context<'_> {
    /// No face of the quad, in either split, lies flat (exactly or within rounding) against any
    /// face its neighbours can have; no other face uses either diagonal; no boundary edge is
    /// shared by more than one outside face.
    fn stands_alone(&self, quad: &Quad) -> bool {
        let c = quad.corners;
        if self.by_edge.contains_key(&edge_key(c[1], c[3])) {
            return false;
        }
        (0..4).all(|k| {
            let (u, v) = (c[k], c[(k + 1) % 4]);
            let outside: Vec<usize> = self.by_edge[&edge_key(u, v)]
                .iter()
                .copied()
                .filter(|&f| !quad.has_face(f))
                .collect();
            match outside[..] {
                [] => true,
                [k_face] => {
                    let theirs = self.apexes_of(k_face, u, v, quad);
                    quad.apexes(k)
                        .iter()
                        .all(|&s| theirs.iter().all(|&r| bend(u, v, s, r) == Bend::Real))
                }
                _ => false,
            }
        })
    }

    /// Every apex the face on edge u-v outside `quad` can have once its own region or quad is
    /// re-split: any corner of its flat region, or its own apex and the far corners of the
    /// near-flat quads it belongs to.
    fn apexes_of(&self, face: usize, u: ZyxVertex, v: ZyxVertex, quad: &Quad) -> Vec<ZyxVertex> {
        let region = self.flat.members(face);
        let corners: Vec<ZyxVertex> = if region.len() > 1 {
            region.iter().flat_map(|&f| self.triangles[f]).collect()
        } else {
            let theirs = self.quads_of.get(&face).into_iter().flatten();
            // A quad of this face with one of `quad`'s faces exists in one split only; it is
            // judged directly, as this face's own apex against `quad`'s.
            let others = theirs.filter(|q| !q.faces.iter().any(|&f| quad.has_face(f)));
            self.triangles[face].into_iter().chain(others.flat_map(|q| q.corners)).collect()
        };
        let mut apexes: Vec<ZyxVertex> =
            corners.into_iter().filter(|&r| r != u && r != v).collect();
        apexes.sort_unstable();
        apexes.dedup();
        apexes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bend_is_the_distance_between_the_diagonals_in_cells() {
        // The square 4 x 4 at z = 0 with one corner raised by h: its diagonals are about h / 2
        // apart (0.49 and 0.97 cells).
        let raised = |h: u16| bend([0, 0, 0], [0, 4, 4], [0, 0, 4], [h, 4, 0]);
        assert_eq!(raised(0), Bend::None);
        assert_eq!(raised(1), Bend::Rounding);
        assert_eq!(raised(2), Bend::Real);
        // Parallel lines cannot be measured.
        assert_eq!(bend([0, 0, 0], [0, 0, 4], [0, 1, 0], [0, 1, 4]), Bend::None);
    }
}
