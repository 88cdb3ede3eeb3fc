//! One triangulation per planar polygon: a flat convex region of a mesh (a box's side, a
//! wedge's slope, an n-gon cap without a centre vertex) is re-split as a fan from its smallest
//! corner in ZYX order.
//!
//! How a flat quad is split into two triangles leaves no trace in the surface, so nothing in
//! the input points can tell the decoder which diagonal the ground truth used: with arbitrary
//! splits in the training data, every flat quad is a coin toss the model can never learn, and a
//! rebuilt box matches its ground truth face for face only by luck. A fan from the smallest
//! corner is one fixed choice, and the one that fits the sequence order: all its triangles
//! start at that corner. DESIGN.md's order makes one mesh one sequence; this makes one surface
//! one sequence.
//!
//! Regions are found exactly: corners are integer grid cells, so "flat" is a zero determinant,
//! not a tolerance. Quads that rounding to the grid bent are added only when they stand alone
//! ([`near_flat`]). Regions that are not a single strictly convex polygon without inner vertices
//! (non-convex caps, fans around a centre vertex, edges shared by more than two faces) are left
//! as they are.

use std::collections::{HashMap, HashSet};

use crate::mesh::{DisjointSets, Mesh, Normalization};

use super::order::{ZyxVertex, face_from_vertices, face_vertices, vertex_set_key};
use super::{FaceToken, Quantizer, canonical_face};

mod near_flat;

use near_flat::{EdgeFaces, edge_key, rounding_bent_quads};

type Vector = [i64; 3];

/// The faces with every flat convex region re-split as a fan from its smallest corner. Faces
/// outside such regions come back as they are; a region's fan has as many faces as the region
/// had (a convex polygon without inner vertices of n corners has n - 2 triangles either way) and
/// the same winding. The result does not depend on how the input split its regions, and is
/// its own fixed point.
pub fn canonical_polygons(faces: &[FaceToken]) -> Vec<FaceToken> {
    let triangles: Vec<[ZyxVertex; 3]> = faces.iter().map(face_vertices).collect();
    let by_edge = edges_to_faces(&triangles);
    let mut sets = exactly_flat_regions(&triangles, &by_edge);
    let flat = Regions::of(&mut sets, triangles.len());
    for quad in rounding_bent_quads(&triangles, &by_edge, &flat) {
        let [i, j] = quad.faces;
        sets.union(i, j);
    }
    let regions = Regions::of(&mut sets, triangles.len());

    // A fan must not repeat a face outside its region (one folded over it, the other side of a
    // sheet): that region then keeps its faces, so no face's winding is lost to the re-split.
    let taken: HashSet<[ZyxVertex; 3]> = faces.iter().map(vertex_set_key).collect();
    let mut out = Vec::with_capacity(faces.len());
    for (i, face) in faces.iter().enumerate() {
        let region = regions.members(i);
        if region.len() == 1 {
            out.push(*face);
        } else if region[0] == i {
            // A region is handled once, at its first face.
            let corners: Vec<[ZyxVertex; 3]> = region.iter().map(|&f| triangles[f]).collect();
            let own: HashSet<[ZyxVertex; 3]> =
                region.iter().map(|&f| vertex_set_key(&faces[f])).collect();
            let fan = convex_fan(&corners)
                .map(|fan| fan.into_iter().map(face_from_vertices).collect::<Vec<_>>())
                .filter(|fan| {
                    fan.iter().map(vertex_set_key).all(|k| own.contains(&k) || !taken.contains(&k))
                });
            match fan {
                Some(fan) => out.extend(fan),
                None => out.extend(region.iter().map(|&f| faces[f])),
            }
        }
    }
    out
}

/// Faces grouped into regions: every face's region, in face order.
struct Regions {
    of: Vec<usize>,
    members: HashMap<usize, Vec<usize>>,
}

impl Regions {
    fn of(sets: &mut DisjointSets, faces: usize) -> Regions {
        // Every index is in range, so `find` always has an answer.
        let of: Vec<usize> = (0..faces).map(|i| sets.find(i).unwrap_or(i)).collect();
        let mut members: HashMap<usize, Vec<usize>> = HashMap::new();
        for (i, &region) in of.iter().enumerate() {
            members.entry(region).or_default().push(i);
        }
        Regions { of, members }
    }

    /// The faces of face `f`'s region, in face order.
    fn members(&self, f: usize) -> &[usize] {
        &self.members[&self.of[f]]
    }
}

/// The mesh with [`canonical_polygons`] applied, its vertices untouched: for meshes that are
/// ground truth themselves (procedural shapes), so that their triangulation is the one the
/// model learns. Flatness (exact, and within rounding) and order are judged on `q`'s grid in
/// the mesh's normalized frame, the grid the model tokenizes on. A mesh with vertices that
/// share a cell there, or that cannot be normalized, is returned as it is.
pub fn canonical_triangulation(mesh: &Mesh, q: Quantizer) -> Mesh {
    let Ok(frame) = Normalization::fit(&mesh.vertices) else { return mesh.clone() };
    let cells = mesh.vertices.iter().map(|&v| frame.apply(v).map(|c| q.quantize(c))).collect();
    triangulation_on_cells(mesh, cells)
}

/// [`canonical_triangulation`] for a mesh whose corners lie near `q`'s grid but not on it: a
/// decoded mesh after its corners were fitted to the input points. The fit moves a corner
/// wherever the points say, so corners that the ground truth has in one plane (a box's side,
/// both ends of a cap's edge) come out a few hundredths of a step apart, and plain rounding
/// sends those on either side of a half step to different cells: the order that picks a
/// polygon's fan corner then turns on the fit's noise. Here the coordinates along each axis
/// that lie within half a step of their neighbour share one cell (their mean's).
pub fn canonical_triangulation_near_grid(mesh: &Mesh, q: Quantizer) -> Mesh {
    let Ok(frame) = Normalization::fit(&mesh.vertices) else { return mesh.clone() };
    let normalized: Vec<[f32; 3]> = mesh.vertices.iter().map(|&v| frame.apply(v)).collect();
    let mut cells = vec![[0u16; 3]; normalized.len()];
    let half_step = 1.0 / f32::from(q.levels() - 1);
    for axis in 0..3 {
        let mut order: Vec<usize> = (0..normalized.len()).collect();
        order.sort_by(|&a, &b| normalized[a][axis].total_cmp(&normalized[b][axis]));
        for group in order.chunk_by(|&a, &b| normalized[b][axis] - normalized[a][axis] < half_step)
        {
            let mean = group.iter().map(|&i| normalized[i][axis]).sum::<f32>() / group.len() as f32;
            for &i in group {
                cells[i][axis] = q.quantize(mean);
            }
        }
    }
    triangulation_on_cells(mesh, cells)
}

/// [`canonical_polygons`] with each vertex at the given grid cell.
fn triangulation_on_cells(mesh: &Mesh, cells: Vec<[u16; 3]>) -> Mesh {
    // ZYX cell -> vertex index; welded vertices would make the mapping back ambiguous.
    let index: HashMap<ZyxVertex, u32> =
        cells.iter().enumerate().map(|(i, &[x, y, z])| ([z, y, x], i as u32)).collect();
    if index.len() != cells.len() {
        return mesh.clone();
    }
    let corner = |i: u32| cells.get(i as usize).copied();
    let tokens: Option<Vec<FaceToken>> = mesh
        .faces
        .iter()
        .map(|&[a, b, c]| canonical_face([corner(a)?, corner(b)?, corner(c)?]))
        .collect();
    let Some(tokens) = tokens else { return mesh.clone() };
    let faces =
        canonical_polygons(&tokens).iter().map(|t| face_vertices(t).map(|v| index[&v])).collect();
    Mesh::new(mesh.vertices.clone(), faces)
}

fn edges_to_faces(triangles: &[[ZyxVertex; 3]]) -> EdgeFaces {
    let mut by_edge = EdgeFaces::new();
    for (i, t) in triangles.iter().enumerate() {
        for (a, b) in edges(t) {
            by_edge.entry(edge_key(a, b)).or_default().push(i);
        }
    }
    by_edge
}

/// The faces joined into regions across [`flat_neighbours`].
fn exactly_flat_regions(triangles: &[[ZyxVertex; 3]], by_edge: &EdgeFaces) -> DisjointSets {
    let mut sets = DisjointSets::new(triangles.len());
    for (i, j) in flat_neighbours(triangles, by_edge) {
        sets.union(i, j);
    }
    sets
}

/// Pairs of faces across an edge that exactly two faces share, in opposite directions (a
/// consistently wound surface), whose normals point the same way: the two lie flat together.
fn flat_neighbours(triangles: &[[ZyxVertex; 3]], by_edge: &EdgeFaces) -> Vec<(usize, usize)> {
    let normals: Vec<Vector> = triangles.iter().map(normal).collect();
    by_edge
        .iter()
        .filter_map(|(&(a, b), faces)| match faces[..] {
            [i, j] if runs(&triangles[i], a, b) != runs(&triangles[j], a, b) => Some((i, j)),
            _ => None,
        })
        .filter(|&(i, j)| {
            let (n, m) = (normals[i], normals[j]);
            cross(n, m) == [0; 3] && dot(n, m) > 0
        })
        .collect()
}

/// The triangle's three directed edges.
fn edges(t: &[ZyxVertex; 3]) -> [(ZyxVertex, ZyxVertex); 3] {
    [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])]
}

/// Whether the triangle walks its edge {a, b} from a to b.
fn runs(t: &[ZyxVertex; 3], a: ZyxVertex, b: ZyxVertex) -> bool {
    edges(t).contains(&(a, b))
}

/// The fan from the smallest corner of a flat region, if the region is one strictly convex
/// polygon whose corners are all on its boundary.
fn convex_fan(region: &[[ZyxVertex; 3]]) -> Option<Vec<[ZyxVertex; 3]>> {
    let directed: HashSet<(ZyxVertex, ZyxVertex)> = region.iter().flat_map(edges).collect();
    let mut next: HashMap<ZyxVertex, ZyxVertex> = HashMap::new();
    for &(a, b) in &directed {
        // An edge without its reverse is on the boundary; a corner the boundary leaves twice
        // pinches the region into two loops.
        if !directed.contains(&(b, a)) && next.insert(a, b).is_some() {
            return None;
        }
    }
    let corners: HashSet<ZyxVertex> = region.iter().flatten().copied().collect();
    let start = *corners.iter().min()?;
    let mut boundary = vec![start];
    let mut at = *next.get(&start)?;
    while at != start {
        if boundary.len() > next.len() {
            return None;
        }
        boundary.push(at);
        at = *next.get(&at)?;
    }
    // One loop through every corner, and the count of a disk's triangulation.
    if boundary.len() != next.len()
        || boundary.len() != corners.len()
        || boundary.len() != region.len() + 2
    {
        return None;
    }
    let up = normal(&region[0]);
    let n = boundary.len();
    let strictly_convex = (0..n).all(|k| {
        let [p, q, r] = [boundary[k], boundary[(k + 1) % n], boundary[(k + 2) % n]];
        dot(cross(sub(q, p), sub(r, q)), up) > 0
    });
    strictly_convex.then(|| (1..n - 1).map(|k| [start, boundary[k], boundary[k + 1]]).collect())
}

fn normal(t: &[ZyxVertex; 3]) -> Vector {
    cross(sub(t[1], t[0]), sub(t[2], t[0]))
}

fn sub(a: ZyxVertex, b: ZyxVertex) -> Vector {
    std::array::from_fn(|k| i64::from(a[k]) - i64::from(b[k]))
}

// Grid cells are below 2^10, so edge vectors below 2^11, normals below 2^23 and their cross
// products below 2^47: exact in i64.
fn cross(a: Vector, b: Vector) -> Vector {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

fn dot(a: Vector, b: Vector) -> i64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::near_flat::Quad;
    use super::*;
    use crate::mesh::primitives::{cuboid, cuboid_split, frustum};
    use crate::tokenize::{is_canonical_face, tokenize};

    /// The box with each side split along the diagonal that `diagonals` picks (bit per side).
    fn box_split(diagonals: u32) -> Mesh {
        cuboid_split([0.9, 0.5, 0.3], diagonals)
    }

    fn sorted(mut faces: Vec<FaceToken>) -> Vec<FaceToken> {
        faces.sort_unstable();
        faces
    }

    fn tokens(mesh: &Mesh) -> Vec<FaceToken> {
        let q = Quantizer::default();
        let frame = Normalization::fit(&mesh.vertices).unwrap();
        let corner = |i: u32| frame.apply(mesh.vertices[i as usize]).map(|c| q.quantize(c));
        mesh.faces
            .iter()
            .map(|&[a, b, c]| canonical_face([corner(a), corner(b), corner(c)]).unwrap())
            .collect()
    }

    #[test]
    fn every_split_of_a_box_gives_one_sequence() {
        let first = tokenize(&box_split(0).normalized().unwrap().0, Quantizer::default()).faces;
        for diagonals in 1..64 {
            let t = tokenize(&box_split(diagonals).normalized().unwrap().0, Quantizer::default());
            assert_eq!(t.faces, first, "split {diagonals:06b}");
        }
        // Each side is a fan from its smallest corner: both its faces start there, and 12
        // faces start at one of the box's 6 "smallest corner of a side" vertices.
        assert_eq!(first.len(), 12);
        let mut starts: HashMap<ZyxVertex, usize> = HashMap::new();
        for f in &first {
            *starts.entry(face_vertices(f)[0]).or_default() += 1;
        }
        assert!(starts.values().all(|&n| n % 2 == 0), "{starts:?}");
    }

    #[test]
    fn regions_that_are_not_one_convex_polygon_are_left_alone() {
        // All in the plane z = 0, wound counter-clockwise seen from +z.
        let v = |x: f32, y: f32| [x, y, 0.0];
        let cases = [
            // An L: six corners, one of them reflex.
            Mesh::new(
                vec![v(0., 0.), v(2., 0.), v(2., 1.), v(1., 1.), v(1., 2.), v(0., 2.)],
                vec![[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5]],
            ),
            // A square around a centre vertex.
            Mesh::new(
                vec![v(0., 0.), v(2., 0.), v(2., 2.), v(0., 2.), v(1., 1.)],
                vec![[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]],
            ),
            // A square with a corner in the middle of a side: not strictly convex.
            Mesh::new(
                vec![v(0., 0.), v(1., 0.), v(2., 0.), v(2., 2.), v(0., 2.)],
                vec![[1, 2, 3], [1, 3, 4], [1, 4, 0]],
            ),
        ];
        for mesh in cases {
            let before = tokens(&mesh);
            assert_eq!(sorted(canonical_polygons(&before)), sorted(before.clone()));
        }
    }

    #[test]
    fn prism_sides_and_caps_become_fans_from_their_smallest_corner() {
        // `frustum` splits its 7-gon caps from their first corner, which is not their smallest
        // in ZYX order.
        let prism = frustum(0.5, 0.5, 0.8, 7);
        let after = canonical_polygons(&tokens(&prism));
        let mut planes: HashMap<Vector, Vec<FaceToken>> = HashMap::new();
        for f in &after {
            let n = normal(&face_vertices(f));
            let g = n.iter().fold(0, |g, &c| gcd(g, c.abs()));
            planes.entry(n.map(|c| c / g)).or_default().push(*f);
        }
        assert_eq!(planes.len(), 9, "7 sides and 2 caps");
        let mut sizes: Vec<usize> = planes.values().map(Vec::len).collect();
        sizes.sort_unstable();
        assert_eq!(sizes, [2, 2, 2, 2, 2, 2, 2, 5, 5]);
        for faces in planes.values() {
            let smallest = faces.iter().flat_map(face_vertices).min().unwrap();
            assert!(faces.iter().all(|f| face_vertices(f)[0] == smallest), "{faces:?}");
        }
    }

    /// `frustum`'s mesh with each side quad split along its other diagonal.
    fn frustum_split_the_other_way(segments: u32) -> Mesh {
        let mesh = frustum(0.8, 0.45, 0.9, segments);
        let (n, top) = (segments, segments);
        let sides = (0..n).flat_map(|i| {
            let j = (i + 1) % n;
            [[i, j, top + i], [j, top + j, top + i]]
        });
        let caps = mesh
            .faces
            .iter()
            .copied()
            .filter(|f| f.iter().all(|&v| v < top) || f.iter().all(|&v| v >= top));
        Mesh::new(mesh.vertices.clone(), caps.chain(sides).collect())
    }

    /// The quads flat within rounding that `canonical_polygons` re-splits.
    fn bent_quads(faces: &[FaceToken]) -> Vec<Quad> {
        let triangles: Vec<[ZyxVertex; 3]> = faces.iter().map(face_vertices).collect();
        let by_edge = edges_to_faces(&triangles);
        let mut sets = exactly_flat_regions(&triangles, &by_edge);
        rounding_bent_quads(&triangles, &by_edge, &Regions::of(&mut sets, triangles.len()))
    }

    #[test]
    fn frustum_sides_bent_by_rounding_get_one_split() {
        let segments = 7;
        let (one, other) =
            (frustum(0.8, 0.45, 0.9, segments), frustum_split_the_other_way(segments));
        let (one, other) = (tokens(&one), tokens(&other));
        assert_ne!(sorted(one.clone()), sorted(other.clone()));
        // The 128-level grid bends some of the slanted sides; without this the test is empty.
        let bent = bent_quads(&one);
        assert!(bent.len() >= 2, "{bent:?}");
        let after = sorted(canonical_polygons(&one));
        assert_eq!(after, sorted(canonical_polygons(&other)));
        // Every side, bent or not, is a fan from its smallest corner.
        for quad in bent {
            let [i, j] = quad.faces;
            let (a, b) = (face_vertices(&one[i]), face_vertices(&one[j]));
            let smallest = a.iter().chain(&b).min().copied().unwrap();
            let fan: Vec<&FaceToken> = after
                .iter()
                .filter(|f| face_vertices(f).iter().all(|v| a.contains(v) || b.contains(v)))
                .collect();
            assert_eq!(fan.len(), 2);
            assert!(fan.iter().all(|f| face_vertices(f)[0] == smallest), "{fan:?}");
        }
    }

    #[test]
    fn a_field_of_quads_bent_by_rounding_is_not_split_quad_by_quad() {
        // A tilted plane rounded to the grid: every square is bent by under half a cell, and
        // each lies within rounding of its neighbours, so which of them pair up would depend on
        // the input's splits. None is treated as a quad of its own.
        for diagonals in [0, u64::MAX, 0b1011_0110] {
            let faces = heightfield(4, 10, [0.15, 0.45], &[0], diagonals);
            // Each square's two faces come in turn.
            let bent = faces.chunks(2).filter(|pair| {
                let (t, u) = (face_vertices(&pair[0]), face_vertices(&pair[1]));
                let d = u.into_iter().find(|v| !t.contains(v)).unwrap();
                dot(normal(&t), sub(d, t[0])) != 0
            });
            assert_eq!(bent.count(), 9);
            assert!(bent_quads(&faces).is_empty());
        }
    }

    /// The quad's faces split along its other diagonal, corners 1-3.
    fn flipped(faces: &[FaceToken], quad: &Quad) -> Vec<FaceToken> {
        let [x, q, y, p] = quad.corners;
        let zyx = |t: [ZyxVertex; 3]| canonical_face(t.map(|[z, y, x]| [x, y, z])).unwrap();
        let mut out = faces.to_vec();
        out[quad.faces[0]] = zyx([q, y, p]);
        out[quad.faces[1]] = zyx([p, x, q]);
        out
    }

    /// A heightfield over an n x n grid of corners `spacing` cells apart: a tilted plane rounded
    /// to the grid (every quad flat but for rounding) plus bumps at some corners, each square
    /// split along the diagonal its bit picks, wound counter-clockwise seen from above.
    fn heightfield(
        n: usize,
        spacing: u16,
        tilt: [f64; 2],
        bumps: &[u16],
        diagonals: u64,
    ) -> Vec<FaceToken> {
        let corner = |i: usize, j: usize| -> [u16; 3] {
            let (x, y) = (i as u16 * spacing, j as u16 * spacing);
            let plane = (tilt[0] * f64::from(x) + tilt[1] * f64::from(y)).round() as u16;
            [x, y, 200 + plane + bumps[(i * n + j) % bumps.len()]]
        };
        let mut faces = Vec::new();
        for i in 0..n - 1 {
            for j in 0..n - 1 {
                let [a, b, c, d] =
                    [corner(i, j), corner(i + 1, j), corner(i + 1, j + 1), corner(i, j + 1)];
                let split = if diagonals >> ((i * n + j) % 64) & 1 == 0 {
                    [[a, b, c], [a, c, d]]
                } else {
                    [[a, b, d], [b, c, d]]
                };
                faces.extend(split.into_iter().filter_map(canonical_face));
            }
        }
        faces
    }

    fn gcd(a: i64, b: i64) -> i64 {
        if b == 0 { a } else { gcd(b, a % b) }
    }

    /// `box_split(diagonals)` as a fit leaves a box: its y sides on a half step of the grid
    /// (cells 30.5 and 96.5), each corner a hundredth of a step off, up or down.
    fn fitted_box(diagonals: u32) -> Mesh {
        let mut mesh = box_split(diagonals);
        // box_split's box is 0.9 long in x, so the normalized frame scales by 1 / 0.45.
        let half_step = 0.45 / 127.0;
        let on_half_step = 0.45 * (1.0 - 61.0 / 127.0);
        for (i, v) in mesh.vertices.iter_mut().enumerate() {
            let noise = if i % 3 == 0 { 0.02 * half_step } else { -0.02 * half_step };
            v[1] = v[1].signum() * on_half_step + noise;
        }
        mesh
    }

    #[test]
    fn corners_near_the_grid_get_one_split_where_rounding_splits_them_at_random() {
        let q = Quantizer::default();
        let rounded: HashSet<Vec<[u32; 3]>> =
            (0..64).map(|d| canonical_triangulation(&fitted_box(d), q).faces).collect();
        // Rounding sends a side's corners to two cells, and the split follows the noise.
        assert!(rounded.len() > 1);
        let near: HashSet<Vec<[u32; 3]>> =
            (0..64).map(|d| canonical_triangulation_near_grid(&fitted_box(d), q).faces).collect();
        assert_eq!(near.len(), 1, "{near:?}");
        let fitted = canonical_triangulation_near_grid(&fitted_box(5), q);
        assert_eq!(fitted.vertices, fitted_box(5).vertices);
    }

    #[test]
    fn canonical_triangulation_keeps_vertices_and_fixes_the_split() {
        let reference = canonical_triangulation(&box_split(0), Quantizer::default());
        assert_eq!(reference.vertices, box_split(0).vertices);
        let as_sets = |m: &Mesh| sorted(tokens(m));
        for diagonals in [1, 22, 63] {
            assert_eq!(
                as_sets(&canonical_triangulation(&box_split(diagonals), Quantizer::default())),
                as_sets(&reference)
            );
        }
        // Unusable input comes back as it is.
        let flat = Mesh::new(vec![[1.0; 3]; 3], vec![[0, 1, 2]]);
        assert_eq!(canonical_triangulation(&flat, Quantizer::default()), flat);
        let dangling = Mesh::new(cuboid([1.0; 3]).vertices, vec![[0, 1, 9]]);
        assert_eq!(canonical_triangulation(&dangling, Quantizer::default()), dangling);
    }

    /// A strictly convex polygon: corners on the parabola y = t^2 in the plane z = 5 (ZYX
    /// cells [5, t^2, t]), counter-clockwise, split as a fan from corner `start`.
    fn parabola_fan(ts: &[u16], start: usize) -> Vec<FaceToken> {
        let corners: Vec<ZyxVertex> = ts.iter().map(|&t| [5, t * t, t]).collect();
        let n = corners.len();
        (1..n - 1)
            .map(|k| {
                let c = |i: usize| corners[(start + i) % n];
                let [a, b, d] = [c(0), c(k), c(k + 1)];
                // Back to file order (x, y, z) for `canonical_face`.
                canonical_face([a, b, d].map(|[z, y, x]| [x, y, z])).unwrap()
            })
            .collect()
    }

    proptest! {
        #[test]
        fn a_convex_polygon_gets_one_fan_whatever_its_split(
            ts in prop::collection::btree_set(0u16..32, 3..12),
            starts in prop::array::uniform2(0usize..12),
        ) {
            let ts: Vec<u16> = ts.into_iter().collect();
            let n = ts.len();
            let a = sorted(canonical_polygons(&parabola_fan(&ts, starts[0] % n)));
            let b = sorted(canonical_polygons(&parabola_fan(&ts, starts[1] % n)));
            prop_assert_eq!(&a, &b);
            prop_assert_eq!(a, sorted(parabola_fan(&ts, 0)), "t = {:?} starts the fan", ts[0]);
        }

        #[test]
        fn re_splitting_a_rounding_bent_quad_changes_nothing(
            n in 2usize..7,
            spacing in 2u16..40,
            tilt in prop::array::uniform2(-1.5f64..1.5),
            bumps in prop::collection::vec(prop_oneof![3 => Just(0u16), 1 => 0u16..4, 1 => 0u16..60], 1..40),
            diagonals: u64,
            flips: u64,
        ) {
            let faces = heightfield(n, spacing, tilt, &bumps, diagonals);
            let expected = sorted(canonical_polygons(&faces));
            let mut other = faces.clone();
            for (k, quad) in bent_quads(&faces).iter().enumerate() {
                if flips >> (k % 64) & 1 == 1 {
                    other = flipped(&other, quad);
                }
            }
            prop_assert_eq!(sorted(canonical_polygons(&other)), expected.clone());
            prop_assert_eq!(sorted(canonical_polygons(&expected)), expected);
        }

        #[test]
        fn re_splitting_keeps_the_surface_and_is_its_own_fixed_point(
            faces in prop::collection::vec(
                prop::array::uniform3(prop::array::uniform3(0u16..4)), 0..40)
        ) {
            let tokens: Vec<FaceToken> = faces.into_iter().filter_map(canonical_face).collect();
            let once = canonical_polygons(&tokens);
            prop_assert_eq!(once.len(), tokens.len());
            prop_assert!(once.iter().all(is_canonical_face));
            // The summed normals (twice the vector area) of the whole input are kept exactly.
            let area = |fs: &[FaceToken]| {
                fs.iter().map(|f| normal(&face_vertices(f))).fold([0; 3], |s, n| {
                    [s[0] + n[0], s[1] + n[1], s[2] + n[2]]
                })
            };
            prop_assert_eq!(area(&once), area(&tokens));
            prop_assert_eq!(sorted(canonical_polygons(&once)), sorted(once));
        }
    }
}
