//! Stray parts and sheets: connected parts of a reconstruction, and sheets hanging off its
//! non-manifold edges, that its input points do not need.
//!
//! Why: the shipped model often decodes a second layer of faces over or inside the surface it
//! already made, or a sliver beside it, each a part of its own or a sheet grown from an edge
//! of the surface (which that edge's third face makes non-manifold). Such a piece brings the
//! mesh no closer to the input points, and a user sees it as clutter (z-fighting, hidden
//! faces, more parts, open and non-manifold edges). Dropping the pieces the points can do
//! without is judged by the Chamfer distance that chooses among candidates, with the points'
//! half measured to the surface itself (`docs/decisions.md`, "Stray parts").

use std::collections::{HashMap, HashSet};

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use parry3d_f64::na::Point3;
use parry3d_f64::query::PointQueryWithLocation;
use parry3d_f64::shape::TriMesh;

use super::sample::surface_samples;
use super::surfaces::{Surfaces, welded_edges};
use super::{DisjointSets, Mesh, triangle_area};

/// Surface samples that stand for a mesh's half of the Chamfer distance.
const SAMPLES: usize = 4096;

/// At most this many of the input points (evenly taken) stand for theirs.
const PROBES: usize = 2048;

/// A part (or a sheet) is dropped when the mesh without it (and without those dropped before
/// it) is at most this share further from the input points, in Chamfer distance, than the
/// mesh it was taken from.
pub const STRAY_TOLERANCE: f64 = 0.01;

/// `mesh` without the connected parts (faces joined through shared vertices) that the input
/// `points` do not need: taken from the smallest in area up, a part goes when the Chamfer
/// distance between the rest and `points` stays within [`STRAY_TOLERANCE`] of the whole mesh's.
/// That distance is the mean over surface samples (drawn with `seed`) of their distance to the
/// nearest point, plus the mean over the points of their distance to the surface: measured to
/// the faces, not to samples, so that two layers over one another are no closer to a point
/// than one. The largest part always stays. The vertices stay as they are, those of dropped
/// faces too, as every ending keeps a decoded mesh's vertices in order
/// ([`Mesh::without_unused_vertices`] drops them for a file). A mesh of one part, without
/// area, or without points comes back as it is; indices must be valid ([`Mesh::validate`]).
pub fn without_stray_parts(mesh: &Mesh, points: &[[f32; 3]], seed: u64) -> Mesh {
    without_unneeded(mesh, &face_parts(mesh), |_| true, points, seed)
}

/// `mesh` without the sheets hanging off its non-manifold edges that the input `points` do
/// not need, judged as [`without_stray_parts`] judges parts. A sheet is a set of faces joined
/// across edges of exactly two faces (corners welded by position); only those with an edge of
/// three or more faces are weighed (a fin, a flap, a second layer grown from the surface's
/// edge), and a sheet stays when the rest would fall into more parts without it (it may be
/// all that joins them).
pub fn without_stray_sheets(mesh: &Mesh, points: &[[f32; 3]], seed: u64) -> Mesh {
    let (sheet_of, hanging) = face_sheets(mesh);
    without_unneeded(mesh, &sheet_of, |sheet| hanging.contains(&sheet), points, seed)
}

/// `mesh` without the pieces (`piece_of` each face) for which `weighed` holds and which the
/// points do not need, smallest in area first: a piece goes when the rest stays within
/// [`STRAY_TOLERANCE`] of the whole mesh's Chamfer distance and makes no more parts than
/// before. The largest piece always stays.
fn without_unneeded(
    mesh: &Mesh,
    piece_of: &[usize],
    weighed: impl Fn(usize) -> bool,
    points: &[[f32; 3]],
    seed: u64,
) -> Mesh {
    let Some(mut weights) = PieceWeights::new(mesh, piece_of, points, seed) else {
        return mesh.clone();
    };
    let mut areas: HashMap<usize, f64> = HashMap::new();
    for (f, &piece) in mesh.faces.iter().zip(piece_of) {
        *areas.entry(piece).or_default() += triangle_area(mesh.triangle(f));
    }
    let mut by_area: Vec<(usize, f64)> = areas.into_iter().collect();
    by_area.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
    by_area.pop();
    let whole = weights.chamfer(&weights.nearest);
    let mut parts = parts_left(mesh, piece_of, &[]);
    for (piece, _) in by_area.into_iter().filter(|&(piece, _)| weighed(piece)) {
        let Some(nearest) = weights.nearest_without(piece) else { continue };
        if weights.chamfer_without(piece, &nearest) > whole * (1.0 + STRAY_TOLERANCE) {
            continue;
        }
        weights.dropped.push(piece);
        let parts_after = parts_left(mesh, piece_of, &weights.dropped);
        if parts_after > parts {
            weights.dropped.pop();
        } else {
            weights.nearest = nearest;
            parts = parts_after;
        }
    }
    let kept = mesh.faces.iter().zip(piece_of).filter(|(_, p)| !weights.dropped.contains(p));
    Mesh { faces: kept.map(|(f, _)| *f).collect(), ..mesh.clone() }
}

/// How many parts the faces of `mesh` make without those of the `dropped` pieces.
fn parts_left(mesh: &Mesh, piece_of: &[usize], dropped: &[usize]) -> usize {
    let kept = mesh.faces.iter().zip(piece_of).filter(|(_, p)| !dropped.contains(p));
    let rest = Mesh { faces: kept.map(|(f, _)| *f).collect(), ..mesh.clone() };
    face_parts(&rest).into_iter().collect::<HashSet<_>>().len()
}

/// Each face's sheet (its surface, named by its first face; a collapsed face is a sheet of
/// its own), and the sheets with an edge of three or more faces; indices must be valid.
fn face_sheets(mesh: &Mesh) -> (Vec<usize>, HashSet<usize>) {
    let edges = welded_edges(mesh);
    let mut sheet_of: Vec<usize> = (0..mesh.faces.len()).collect();
    for faces in Surfaces::along(&edges, mesh.faces.len()).members {
        for &f in &faces {
            sheet_of[f] = faces[0];
        }
    }
    let hanging = edges
        .values()
        .filter(|faces| faces.len() > 2)
        .flatten()
        .map(|&(f, _)| sheet_of[f])
        .collect();
    (sheet_of, hanging)
}

/// Each face's part: the representative of its vertices' set once every face joins its
/// corners and vertices at one position join (files split them along seams); indices must be
/// valid.
fn face_parts(mesh: &Mesh) -> Vec<usize> {
    let mut sets = DisjointSets::new(mesh.vertices.len());
    for (i, first) in mesh.first_vertex_at_each_position().into_iter().enumerate() {
        sets.union(i, first as usize);
    }
    for &[a, b, c] in &mesh.faces {
        sets.union(a as usize, b as usize);
        sets.union(a as usize, c as usize);
    }
    mesh.faces.iter().map(|f| sets.find(f[0] as usize).unwrap_or(0)).collect()
}

/// What the Chamfer distance of a mesh without some of its pieces is computed from.
struct PieceWeights<'a> {
    mesh: &'a Mesh,
    piece_of: &'a [usize],
    /// Surface samples' pieces and distances to the nearest probe.
    sample_pieces: Vec<usize>,
    accuracy: Vec<f64>,
    /// The input points that stand for all of them.
    probes: Vec<Point3<f64>>,
    /// Each probe's distance to the faces of the pieces not dropped, and the piece of the
    /// nearest face.
    nearest: Vec<(f64, usize)>,
    dropped: Vec<usize>,
}

impl<'a> PieceWeights<'a> {
    /// `None` when there is nothing to weigh: one piece, no area, or no points.
    fn new(mesh: &'a Mesh, piece_of: &'a [usize], points: &[[f32; 3]], seed: u64) -> Option<Self> {
        let first = piece_of.first()?;
        if piece_of.iter().all(|p| p == first) || points.is_empty() {
            return None;
        }
        let probes: Vec<[f32; 3]> =
            points.iter().step_by(points.len().div_ceil(PROBES)).copied().collect();
        let drawn = surface_samples(mesh, SAMPLES, seed).ok()?;
        let samples: Vec<[f32; 3]> = drawn.iter().map(|s| s.position(mesh)).collect();
        let tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(&probes).ok()?;
        let nearest_probes =
            tree.query_batch(&samples).nearest_one::<SquaredEuclidean<f32>>().execute();
        let accuracy = nearest_probes.iter().map(|n| f64::from(n.distance).sqrt());
        let mut weights = Self {
            mesh,
            piece_of,
            sample_pieces: drawn.iter().map(|s| piece_of[s.face]).collect(),
            accuracy: accuracy.collect(),
            probes: probes.iter().map(|p| Point3::from(p.map(f64::from))).collect(),
            nearest: Vec::new(),
            dropped: Vec::new(),
        };
        let everything = weights.surface_without(None)?;
        weights.nearest = weights.probes.iter().map(|p| everything.nearest(p)).collect();
        Some(weights)
    }

    /// The faces of the pieces neither dropped nor `piece`; `None` when there are none.
    fn surface_without(&self, piece: Option<usize>) -> Option<Surface> {
        let gone = |p: &usize| self.dropped.contains(p) || piece == Some(*p);
        let faces: Vec<usize> =
            (0..self.mesh.faces.len()).filter(|&f| !gone(&self.piece_of[f])).collect();
        let vertices = self.mesh.vertices.iter().map(|v| Point3::from(v.map(f64::from))).collect();
        let indices = faces.iter().map(|&f| self.mesh.faces[f]).collect();
        let mesh = TriMesh::new(vertices, indices).ok()?;
        Some(Surface { mesh, pieces: faces.iter().map(|&f| self.piece_of[f]).collect() })
    }

    /// Each probe's nearest face without `piece` as well: only probes whose nearest face was
    /// in `piece` move. `None` when no face would be left.
    fn nearest_without(&self, piece: usize) -> Option<Vec<(f64, usize)>> {
        let rest = self.surface_without(Some(piece))?;
        let moved = |(p, &(d, near)): (&Point3<f64>, &(f64, usize))| {
            if near == piece { rest.nearest(p) } else { (d, near) }
        };
        Some(self.probes.iter().zip(&self.nearest).map(moved).collect())
    }

    /// The Chamfer distance with the probes' distances `nearest`, over the samples of the
    /// pieces not dropped.
    fn chamfer(&self, nearest: &[(f64, usize)]) -> f64 {
        self.chamfer_over(nearest, |p| !self.dropped.contains(p))
    }

    /// As [`Self::chamfer`], without `piece`'s samples as well.
    fn chamfer_without(&self, piece: usize, nearest: &[(f64, usize)]) -> f64 {
        self.chamfer_over(nearest, |p| *p != piece && !self.dropped.contains(p))
    }

    fn chamfer_over(&self, nearest: &[(f64, usize)], kept: impl Fn(&usize) -> bool) -> f64 {
        let (sum, n) = self
            .sample_pieces
            .iter()
            .zip(&self.accuracy)
            .filter(|(p, _)| kept(p))
            .fold((0.0, 0usize), |(sum, n), (_, d)| (sum + d, n + 1));
        if n == 0 {
            return f64::INFINITY;
        }
        sum / n as f64 + nearest.iter().map(|(d, _)| d).sum::<f64>() / nearest.len() as f64
    }
}

/// Some of a mesh's faces, ready for nearest-face queries, with each one's piece.
struct Surface {
    mesh: TriMesh,
    pieces: Vec<usize>,
}

impl Surface {
    /// The distance from `point` to the nearest face, and that face's piece.
    fn nearest(&self, point: &Point3<f64>) -> (f64, usize) {
        let (projection, (face, _)) = self.mesh.project_local_point_and_get_location(point, false);
        let piece = self.pieces.get(face as usize).copied().unwrap_or(usize::MAX);
        ((projection.point - point).norm(), piece)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::cuboid;
    use crate::mesh::sample_surface;
    use crate::metrics::topology;

    /// `mesh` with `other`'s faces added as parts of their own.
    fn with_parts(mesh: &Mesh, other: &Mesh) -> Mesh {
        let mut joined = mesh.clone();
        joined.append(other);
        joined
    }

    fn points_on(mesh: &Mesh) -> Vec<[f32; 3]> {
        sample_surface(mesh, 8192, 7).unwrap().vertices
    }

    #[test]
    fn a_box_inside_a_box_and_a_sliver_off_it_go_and_a_second_box_the_points_show_stays() {
        let big = cuboid([1.0, 1.0, 1.0]);
        let hidden = cuboid([0.3, 0.3, 0.3]);
        let sliver =
            Mesh::new(vec![[0.5, 0.2, 0.2], [0.5, 0.25, 0.2], [0.9, 0.2, 0.22]], vec![[0, 1, 2]]);
        let neighbour = big.clone().translated([2.0, 0.0, 0.0]);
        let cluttered = with_parts(&with_parts(&big, &hidden), &sliver);
        let cleaned = without_stray_parts(&cluttered, &points_on(&big), 0);
        assert_eq!(cleaned.faces, big.faces);
        assert_eq!(cleaned.vertices, cluttered.vertices);
        // The points show both boxes: each explains points the other does not.
        let pair = with_parts(&big, &neighbour);
        let points = points_on(&pair);
        assert_eq!(without_stray_parts(&with_parts(&pair, &hidden), &points, 0).faces, pair.faces);
        assert_eq!(topology(&without_stray_parts(&pair, &points, 0)).parts, 2);
    }

    #[test]
    fn a_fin_off_a_box_goes_unless_the_points_show_it() {
        let big = cuboid([1.0, 1.0, 1.0]);
        let mut finned = big.clone();
        finned.vertices.push([0.0, -0.9, -0.9]);
        // On the box's edge from corner 0 to 1, which the fin makes non-manifold.
        finned.faces.push([1, 0, 8]);
        assert_eq!(topology(&finned).non_manifold_edges, 1);
        let cleaned = without_stray_sheets(&finned, &points_on(&big), 0);
        assert_eq!(cleaned.faces, big.faces);
        assert_eq!(cleaned.vertices, finned.vertices);
        assert_eq!(without_stray_sheets(&finned, &points_on(&finned), 0), finned);
    }

    #[test]
    fn sheets_are_named_by_their_first_face() {
        // Named by a union-find root, a sheet's name (and so the order in which sheets of
        // one area are weighed) would follow the order a hash map gives its edges, another
        // on every run.
        let mut finned = cuboid([1.0, 1.0, 1.0]);
        finned.vertices.push([0.0, -0.9, -0.9]);
        finned.faces.insert(5, [1, 0, 8]);
        for _ in 0..8 {
            let (sheet_of, hanging) = face_sheets(&finned);
            let mut expected = vec![0; 13];
            expected[5] = 5;
            assert_eq!(sheet_of, expected);
            assert_eq!(hanging, HashSet::from([0, 5]));
        }
    }

    #[test]
    fn a_sheet_that_joins_two_parts_stays() {
        let mut joined = with_parts(
            &cuboid([1.0, 1.0, 1.0]),
            &cuboid([1.0, 1.0, 1.0]).translated([2.0, 0.0, 0.0]),
        );
        // A bridge from the first box's edge 1-3 to the second's 8-10 (its corners 0 and 2).
        joined.faces.extend([[1, 8, 10], [1, 10, 3]]);
        assert_eq!(topology(&joined).parts, 1);
        let boxes = Mesh { faces: joined.faces[..24].to_vec(), ..joined.clone() };
        assert_eq!(without_stray_sheets(&joined, &points_on(&boxes), 0), joined);
    }

    #[test]
    fn one_part_no_points_or_no_area_come_back_as_they_are() {
        let big = cuboid([1.0, 1.0, 1.0]);
        assert_eq!(without_stray_parts(&big, &points_on(&big), 0), big);
        let two = with_parts(&big, &cuboid([0.3, 0.3, 0.3]));
        assert_eq!(without_stray_parts(&two, &[], 0), two);
        let flat = Mesh::new(
            vec![[0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [5.0; 3]],
            vec![[0, 1, 2], [3, 3, 3]],
        );
        assert_eq!(without_stray_parts(&flat, &points_on(&big), 0), flat);
    }
}
