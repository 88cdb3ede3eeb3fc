//! Small holes: closing the short loops of open edges that a reconstruction leaves where its
//! input points say there is surface.
//!
//! Why: the shipped model's answers are full of cracks, a missing triangle or quad between
//! faces that are otherwise closed, and a user sees each as a hole in the mesh (and a tool
//! that needs a closed mesh refuses it). Filling such a loop adds no surface where the input
//! has none, since every new face must lie on the input points; an opening the input shows
//! (a mug's rim, a tube's end) has no points across it and stays open
//! (`docs/decisions.md`, "Small holes").

use std::collections::hash_map::Entry;
use std::collections::{HashMap, HashSet};

use super::{FitTarget, Mesh, edge_uses, triangle_area, triangle_normal, undirected};

/// The longest loop of open edges that is filled, when a caller does not say: longer loops
/// are mostly missing surface the model did not decode, which a few flat triangles would
/// not bring back.
pub const DEFAULT_MAX_HOLE_EDGES: usize = 8;

/// A filling face may always lie this many times the input points' spacing (their mean
/// distance to their nearest neighbour) from them ([`reach`]).
const SUPPORT_SPACINGS: f32 = 3.0;

/// A filling face may lie as far from the input points as this share of the mesh's own faces
/// ([`reach`]).
const OWN_FACES_SHARE: f32 = 0.9;

/// The longest loop a request may ask to close: the least-area triangulation takes the cube
/// of a loop's corners.
pub const MAX_HOLE_EDGES: usize = 32;

/// Triangles with less area than this share of the hole's bounding box's squared diagonal
/// are not made: a zero-area face is an open edge of its own to every tool.
const MIN_AREA_SHARE: f64 = 1e-6;

/// `mesh` with its loops of at most `max_edges` open edges closed by new faces, wound like the
/// faces around them, where the input points of `target` (in the mesh's frame) say there is
/// surface; also how many loops were closed. Shorter loops go first, and a loop is closed
/// only when its triangulation of least area ([`least_area_fan`]) adds no edge the mesh
/// already has and every new face lies as near the points as most of the mesh's own
/// ([`reach`]). Corners are welded by exact position first; vertices are kept as they are and
/// the new faces come after the old ones. Indices must be valid ([`Mesh::validate`]).
pub fn with_small_holes_filled(mesh: &Mesh, target: &FitTarget, max_edges: usize) -> (Mesh, usize) {
    let welded = mesh.welded_faces();
    let uses = edge_uses(&welded);
    let mut rims = OpenEdges::of(&welded, &uses);
    if max_edges < 3 || rims.sorted.is_empty() {
        return (mesh.clone(), 0);
    }
    let mut edges: HashSet<(u32, u32)> = uses.into_keys().collect();
    let reach = reach(mesh, &welded, target);
    let mut faces = mesh.faces.clone();
    let mut filled = 0;
    // Shortest first: where several loops meet at a corner, the short ones are the holes.
    for length in 3..=max_edges {
        for start in rims.sorted.clone() {
            let Some(hole) = rims.shortest_loop(start, length).filter(|h| h.len() == length) else {
                continue;
            };
            let corners: Vec<[f32; 3]> = hole.iter().map(|&v| mesh.vertices[v as usize]).collect();
            let Some(fan) =
                least_area_fan(&corners, |i, j| !edges.contains(&undirected(hole[i], hole[j])))
            else {
                continue;
            };
            if fan.iter().any(|t| distance_from_input(target, t.map(|i| corners[i])) > reach)
                || folds_back(mesh, &rims, &hole, &fan)
            {
                continue;
            }
            for [i, k, j] in fan {
                // The loop runs as the open edges of the faces around it run; a face that
                // closes it runs the other way.
                faces.push([hole[j], hole[k], hole[i]]);
                edges.extend([undirected(hole[i], hole[k]), undirected(hole[k], hole[j])]);
            }
            rims.close(&hole);
            filled += 1;
        }
    }
    (Mesh { faces, ..mesh.clone() }, filled)
}

/// The open edges (used by one face) of a mesh, each directed as the face using it runs
/// along it, so that a hole's rim is a directed loop of them.
struct OpenEdges {
    /// Every open edge not closed yet, in order.
    sorted: Vec<(u32, u32)>,
    /// The open edges leaving each corner.
    leaving: HashMap<u32, Vec<u32>>,
    /// The third corner of the face along each open edge.
    apex: HashMap<(u32, u32), u32>,
}

impl OpenEdges {
    /// Of `faces`, whose edges' [`edge_uses`] are `uses`.
    fn of(faces: &[[u32; 3]], uses: &HashMap<(u32, u32), usize>) -> Self {
        let apex: HashMap<(u32, u32), u32> = faces
            .iter()
            .flat_map(|&[a, b, c]| [((a, b), c), ((b, c), a), ((c, a), b)])
            .filter(|&((p, q), _)| uses.get(&undirected(p, q)) == Some(&1))
            .collect();
        let mut sorted: Vec<(u32, u32)> = apex.keys().copied().collect();
        sorted.sort_unstable();
        let mut leaving: HashMap<u32, Vec<u32>> = HashMap::new();
        for &(p, q) in &sorted {
            leaving.entry(p).or_default().push(q);
        }
        Self { sorted, leaving, apex }
    }

    /// The corners of the shortest loop of open edges through `(a, b)` with at most `limit`
    /// edges, from `a` on (a breadth-first search from `b` back to `a`); `None` when none.
    fn shortest_loop(&self, (a, b): (u32, u32), limit: usize) -> Option<Vec<u32>> {
        let mut came_from: HashMap<u32, u32> = HashMap::from([(b, b)]);
        let mut frontier = vec![b];
        for _ in 1..limit {
            let mut next = Vec::new();
            for &v in &frontier {
                for &w in self.leaving.get(&v).into_iter().flatten() {
                    if w == a {
                        let mut back = vec![v];
                        while let Some(&u) =
                            back.last().filter(|&&u| u != b).and_then(|u| came_from.get(u))
                        {
                            back.push(u);
                        }
                        back.push(a);
                        back.reverse();
                        return Some(back);
                    }
                    if let Entry::Vacant(e) = came_from.entry(w) {
                        e.insert(v);
                        next.push(w);
                    }
                }
            }
            frontier = next;
        }
        None
    }

    /// Takes the open edges along `hole` (as [`Self::shortest_loop`] gives it) out.
    fn close(&mut self, hole: &[u32]) {
        let along: HashSet<(u32, u32)> =
            hole.iter().zip(hole.iter().cycle().skip(1)).map(|(&p, &q)| (p, q)).collect();
        self.sorted.retain(|e| !along.contains(e));
        for (p, q) in along {
            if let Some(out) = self.leaving.get_mut(&p) {
                out.retain(|&w| w != q);
            }
        }
    }
}

/// Whether a face of `fan` (closing `hole`, as [`with_small_holes_filled`] adds it) folds back
/// onto the face on the other side of its rim edge, by more than [`MAX_FOLD_COS`]. Why: the
/// rim of a lone triangle or quad is a short loop too, and closing it would lay a second,
/// reversed layer on it (a sliver made two-sided, not a hole closed); a hole in a surface is
/// closed by faces that go on from the faces around it.
fn folds_back(mesh: &Mesh, rims: &OpenEdges, hole: &[u32], fan: &[[usize; 3]]) -> bool {
    let n = hole.len();
    let at = |v: u32| mesh.vertices[v as usize];
    fan.iter().any(|&[i, k, j]| {
        let added = triangle_normal([at(hole[j]), at(hole[k]), at(hole[i])]);
        let mut rim_sides = [(i, k), (k, j), (j, i)]
            .into_iter()
            .filter(|&(a, b)| b == (a + 1) % n || a == (b + 1) % n);
        rim_sides.any(|(a, b)| {
            // The side as the rim runs: from a corner to the next.
            let (p, q) = if b == (a + 1) % n { (hole[a], hole[b]) } else { (hole[b], hole[a]) };
            rims.apex.get(&(p, q)).is_some_and(|&c| {
                let there = triangle_normal([at(p), at(q), at(c)]);
                (0..3).map(|x| added[x] * there[x]).sum::<f32>() < MAX_FOLD_COS
            })
        })
    })
}

/// A face closing a hole may turn from the face across its rim edge by at most 120 degrees
/// (the cosine between their normals, wound alike, at least -0.5): a box's corner turns 90.
const MAX_FOLD_COS: f32 = -0.5;

/// The triangulation of the polygon `corners` (in order) of least total area, each triangle
/// as indices `[i, k, j]` with `i < k < j`, using as diagonals only pairs `allowed` says;
/// `None` when none exists without a triangle of (nearly) no area. Why least area: it is
/// the surface a hole's rim spans most tightly, and over a few corners it is found exactly
/// (every triangulation of a polygon, in O(n^3)), however bent the rim is.
fn least_area_fan(
    corners: &[[f32; 3]],
    allowed: impl Fn(usize, usize) -> bool,
) -> Option<Vec<[usize; 3]>> {
    let n = corners.len();
    let (lo, hi) = super::bounds(corners)?;
    let diagonal: f64 = (0..3).map(|a| f64::from(hi[a] - lo[a]).powi(2)).sum();
    let min_area = diagonal * MIN_AREA_SHARE;
    let side = |i: usize, j: usize| j == i + 1 || (i == 0 && j == n - 1) || allowed(i, j);
    // best[i][j]: least area spanning corners i..=j closed by the chord (i, j), and its apex.
    let mut best = vec![vec![None::<(f64, usize)>; n]; n];
    for i in 0..n - 1 {
        best[i][i + 1] = Some((0.0, i));
    }
    for span in 2..n {
        for i in 0..n - span {
            let j = i + span;
            if !side(i, j) {
                continue;
            }
            best[i][j] = (i + 1..j)
                .filter_map(|k| {
                    let area = triangle_area([corners[i], corners[k], corners[j]]);
                    let (left, _) = best[i][k]?;
                    let (right, _) = best[k][j]?;
                    (area > min_area).then_some((left + right + area, k))
                })
                .min_by(|a, b| a.0.total_cmp(&b.0));
        }
    }
    best[0][n - 1]?;
    let mut fan = Vec::with_capacity(n - 2);
    let mut spans = vec![(0, n - 1)];
    while let Some((i, j)) = spans.pop() {
        if j > i + 1 {
            let (_, k) = best[i][j]?;
            fan.push([i, k, j]);
            spans.extend([(i, k), (k, j)]);
        }
    }
    Some(fan)
}

/// How far triangle `t` lies from the input points of `target`: the furthest of its centroid
/// and the points halfway from it to each corner from its nearest point.
fn distance_from_input(target: &FitTarget, t: [[f32; 3]; 3]) -> f32 {
    let centroid: [f32; 3] = std::array::from_fn(|a| (t[0][a] + t[1][a] + t[2][a]) / 3.0);
    let halfway = t.map(|c| std::array::from_fn(|a| (c[a] + centroid[a]) / 2.0));
    std::iter::once(centroid).chain(halfway).map(|p| target.distance_to(p)).fold(0.0, f32::max)
}

/// How far from the input points a filling face may lie: as far as most of the mesh's own
/// faces do ([`OWN_FACES_SHARE`] of them, by [`distance_from_input`]), and at least
/// [`SUPPORT_SPACINGS`] of the points' spacing. Why the mesh's own: a face spanning a hole
/// in a curved surface is as far from it as the faces around it, which are flat too.
fn reach(mesh: &Mesh, faces: &[[u32; 3]], target: &FitTarget) -> f32 {
    let mut own: Vec<f32> = faces
        .iter()
        .map(|f| distance_from_input(target, f.map(|i| mesh.vertices[i as usize])))
        .collect();
    let floor = SUPPORT_SPACINGS * target.spacing();
    let rank = ((own.len() as f32 * OWN_FACES_SHARE) as usize).min(own.len().saturating_sub(1));
    if own.is_empty() {
        return floor;
    }
    own.select_nth_unstable_by(rank, f32::total_cmp).1.max(floor)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::{cuboid, frustum};
    use crate::mesh::sample_surface;

    /// Points on `mesh`'s surface, as a request sends them.
    fn points_on(mesh: &Mesh) -> FitTarget {
        FitTarget::new(&sample_surface(mesh, 4096, 7).unwrap()).unwrap()
    }

    fn without_faces(mesh: &Mesh, gone: &[usize]) -> Mesh {
        let faces = (0..mesh.faces.len()).filter(|f| !gone.contains(f));
        Mesh { faces: faces.map(|f| mesh.faces[f]).collect(), ..mesh.clone() }
    }

    /// Every edge used once each way: closed and consistently wound.
    fn closed_and_wound_alike(mesh: &Mesh) -> bool {
        let mut directed: HashMap<(u32, u32), usize> = HashMap::new();
        for &[a, b, c] in &mesh.welded_faces() {
            for edge in [(a, b), (b, c), (c, a)] {
                *directed.entry(edge).or_default() += 1;
            }
        }
        directed.iter().all(|(&(a, b), &n)| n == 1 && directed.get(&(b, a)) == Some(&1))
    }

    #[test]
    fn a_missing_triangle_or_side_on_the_input_is_closed_and_wound_like_the_rest() {
        let full = cuboid([2.0, 1.0, 1.5]);
        let target = points_on(&full);
        for gone in [&[0][..], &[2, 3], &[4, 5]] {
            let open = without_faces(&full, gone);
            let (closed, holes) = with_small_holes_filled(&open, &target, DEFAULT_MAX_HOLE_EDGES);
            assert_eq!(holes, 1, "without faces {gone:?}");
            assert_eq!(closed.faces.len(), full.faces.len());
            assert_eq!(closed.faces[..open.faces.len()], open.faces[..]);
            assert!(closed_and_wound_alike(&closed), "without faces {gone:?}: {:?}", closed.faces);
            assert!((closed.area() - full.area()).abs() < 1e-5);
        }
    }

    #[test]
    fn an_opening_the_input_does_not_cover_stays_open() {
        // A box without its top, sampled as such: a tray, not a box with a hole.
        let tray = without_faces(&cuboid([1.0, 1.0, 1.0]), &[2, 3]);
        let (same, holes) = with_small_holes_filled(&tray, &points_on(&tray), 8);
        assert_eq!((holes, same), (0, tray));
    }

    #[test]
    fn a_lone_triangle_or_quad_is_not_made_two_sided() {
        // A box's side and a triangle apart, on points of the whole box: their rims are
        // short loops on the input, but closing them would only lay the faces on themselves.
        let full = cuboid([1.0, 1.0, 1.0]);
        let target = points_on(&full);
        for keep in [&[0][..], &[0, 1]] {
            let lone =
                Mesh { faces: keep.iter().map(|&f| full.faces[f]).collect(), ..full.clone() };
            assert_eq!(with_small_holes_filled(&lone, &target, 8), (lone.clone(), 0), "{keep:?}");
        }
    }

    #[test]
    fn loops_longer_than_the_limit_stay_open() {
        // A twelve-sided prism without its top cap: a loop of 12 open edges.
        let prism = frustum(1.0, 1.0, 1.0, 12);
        let cap: Vec<usize> = (0..prism.faces.len())
            .filter(|&f| prism.triangle(&prism.faces[f]).iter().all(|c| c[2] > 0.49))
            .collect();
        assert_eq!(cap.len(), 10);
        let open = without_faces(&prism, &cap);
        let target = points_on(&prism);
        assert_eq!(with_small_holes_filled(&open, &target, 11).1, 0);
        let (closed, holes) = with_small_holes_filled(&open, &target, 12);
        assert_eq!(holes, 1);
        assert!(closed_and_wound_alike(&closed));
        assert!((closed.area() - prism.area()).abs() < 1e-4);
    }

    #[test]
    fn holes_that_meet_at_a_corner_are_closed_each_on_its_own() {
        // Two triangles whose holes share only corner 1, where two open edges leave it: the
        // rims run on as two loops of 3, not one of 6.
        let full = cuboid([1.0, 1.0, 1.0]);
        let open = without_faces(&full, &[0, 5]);
        let (closed, holes) = with_small_holes_filled(&open, &points_on(&full), 8);
        assert_eq!(holes, 2);
        assert_eq!(closed.faces.len(), full.faces.len());
        assert!(closed_and_wound_alike(&closed), "{:?}", closed.faces);
    }

    #[test]
    fn the_least_area_triangulation_spans_a_bent_rim_tightly() {
        // A square with one corner lifted: its two splits differ in area.
        let rim = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.5], [0.0, 1.0, 0.0]];
        let area = |fan: &[[usize; 3]]| -> f64 {
            fan.iter().map(|t| triangle_area(t.map(|i| rim[i]))).sum()
        };
        let (through_0_2, through_1_3) =
            (area(&[[0, 1, 2], [0, 2, 3]]), area(&[[0, 1, 3], [1, 2, 3]]));
        assert!(through_1_3 < through_0_2 - 1e-3);
        let fan = least_area_fan(&rim, |_, _| true).unwrap();
        assert_eq!(fan.len(), 2);
        assert!((area(&fan) - through_1_3).abs() < 1e-9, "{fan:?}");
        // Without that diagonal, the other one.
        let fan = least_area_fan(&rim, |i, j| (i, j) != (1, 3)).unwrap();
        assert!((area(&fan) - through_0_2).abs() < 1e-9, "{fan:?}");
        // Without any diagonal a quad cannot be split; collinear corners give no area.
        assert_eq!(least_area_fan(&rim, |_, _| false), None);
        let line = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]];
        assert_eq!(least_area_fan(&line, |_, _| true), None);
    }

    #[test]
    fn nothing_to_fill_leaves_the_mesh_as_it_is() {
        let full = cuboid([1.0, 1.0, 1.0]);
        let target = points_on(&full);
        assert_eq!(with_small_holes_filled(&full, &target, 8), (full.clone(), 0));
        let open = without_faces(&full, &[0]);
        assert_eq!(with_small_holes_filled(&open, &target, 2), (open.clone(), 0));
        assert_eq!(with_small_holes_filled(&Mesh::default(), &target, 8), (Mesh::default(), 0));
    }
}
