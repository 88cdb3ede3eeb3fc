//! Folded faces: a face that lies on other faces of the mesh, next to an edge that three or
//! more faces share. The shipped model often decodes a surface twice where two of its layers
//! meet, and the extra faces make edges non-manifold without adding any surface.

use std::collections::BTreeMap;

use parry3d_f64::bounding_volume::{Aabb, BoundingVolume};
use parry3d_f64::na::{Point3, Vector3};

use super::{Mesh, triangle_area};

/// A face lies on another when their planes are within this angle (degrees), either way round.
const FOLD_DEGREES: f64 = 10.0;

/// How far (as barycentric weight) a point may lie outside a face and still count as on it.
const COVER_SLACK: f64 = 0.05;

/// A face's points checked for cover are its barycentric grid with this many steps a side
/// (its corners, points along its edges and inside: 15 for 4).
const COVER_STEPS: usize = 4;

type Point = Vector3<f64>;

/// `mesh` without the faces that lie on other faces next to a non-manifold edge, where
/// dropping them opens no more edges than it closes. A face goes when one of its edges has
/// three or more faces; every point of a grid on it lies, projected, within some other face
/// whose plane is within `FOLD_DEGREES` of its own, and near that plane; and of its edges no
/// more have two faces (they would open) than one (they close). Faces are tried smallest
/// first, again until none goes, so that of two faces on each other one stays. The vertices
/// stay as they are (see [`super::without_stray_parts`]); indices must be valid
/// ([`Mesh::validate`]).
pub fn without_folded_faces(mesh: &Mesh) -> Mesh {
    let first = mesh.first_vertex_at_each_position();
    let faces: Vec<[usize; 3]> =
        mesh.faces.iter().map(|f| f.map(|c| first[c as usize] as usize)).collect();
    let planes: Vec<Option<Plane>> = faces
        .iter()
        .map(|f| Plane::of(f.map(|c| Vector3::from(mesh.vertices[c].map(f64::from)))))
        .collect();
    let mut on_edge: BTreeMap<[usize; 2], Vec<usize>> = BTreeMap::new();
    for (i, f) in faces.iter().enumerate() {
        if planes[i].is_some() {
            for e in edges(f) {
                on_edge.entry(e).or_default().push(i);
            }
        }
    }
    // Faces without area are in no edge's list and are left as they are.
    let mut order: Vec<usize> = (0..faces.len())
        .filter(|&i| planes[i].is_some() && edges(&faces[i]).iter().any(|e| on_edge[e].len() > 2))
        .collect();
    let area = |f: usize| triangle_area(mesh.triangle(&mesh.faces[f]));
    order.sort_by(|&f, &g| area(f).total_cmp(&area(g)).then(f.cmp(&g)));
    let mut dropped = vec![false; faces.len()];
    let mut changed = true;
    while changed {
        changed = false;
        for &f in &order {
            if dropped[f] {
                continue;
            }
            let counts = edges(&faces[f]).map(|e| live(&on_edge[&e], &dropped));
            let opens = counts.iter().filter(|&&n| n == 2).count();
            let closes = counts.iter().filter(|&&n| n == 1).count();
            if counts.iter().any(|&n| n > 2)
                && opens <= closes
                && lies_on_others(f, &planes, |g| g != f && !dropped[g])
            {
                dropped[f] = true;
                changed = true;
            }
        }
    }
    let kept = mesh.faces.iter().zip(&dropped).filter(|(_, d)| !**d).map(|(f, _)| *f);
    Mesh { faces: kept.collect(), ..mesh.clone() }
}

fn edges(&[a, b, c]: &[usize; 3]) -> [[usize; 2]; 3] {
    [[a.min(b), a.max(b)], [b.min(c), b.max(c)], [a.min(c), a.max(c)]]
}

/// Faces of `faces` not dropped.
fn live(faces: &[usize], dropped: &[bool]) -> usize {
    faces.iter().filter(|&&f| !dropped[f]).count()
}

/// Whether every point of face `f`'s grid lies on some face `is_other` accepts whose plane is
/// within `FOLD_DEGREES` of its own.
fn lies_on_others(f: usize, planes: &[Option<Plane>], is_other: impl Fn(usize) -> bool) -> bool {
    let Some(face) = &planes[f] else { return false };
    let (sin, cos) = FOLD_DEGREES.to_radians().sin_cos();
    // Half as far as the far corner of a face folded by the whole angle about its longest
    // side: 48 dev meshes lost CD 0.0005 with the whole distance, 0.0001 with half for
    // nearly as many non-manifold edges gone (docs/decisions.md, "Stray parts").
    let reach = face.longest_side() * sin / 2.0;
    let others: Vec<&Plane> = (0..planes.len())
        .filter(|&g| is_other(g))
        .filter_map(|g| planes[g].as_ref())
        .filter(|other| other.normal.dot(&face.normal).abs() > cos && other.near(face, reach))
        .collect();
    face.grid().all(|p| others.iter().any(|other| other.holds(&p, reach)))
}

/// A face's corners, unit normal and bounding box.
struct Plane {
    corners: [Point; 3],
    normal: Point,
    bounds: Aabb,
}

impl Plane {
    /// None for a face without area.
    fn of(corners: [Point; 3]) -> Option<Plane> {
        let [a, b, c] = corners;
        let normal = (b - a).cross(&(c - a)).try_normalize(0.0)?;
        let bounds = Aabb::from_points(&corners.map(Point3::from));
        Some(Plane { corners, normal, bounds })
    }

    /// Whether the box around this face, grown by as far as [`Self::holds`] reaches (`reach`
    /// off the plane, `COVER_SLACK` past the sides), meets the box around `other`: a cheap test
    /// that leaves most faces of a large mesh out before any point is checked.
    fn near(&self, other: &Plane, reach: f64) -> bool {
        let margin = Vector3::repeat(reach + 2.0 * COVER_SLACK * self.longest_side());
        let grown = Aabb::new(self.bounds.mins - margin, self.bounds.maxs + margin);
        grown.intersects(&other.bounds)
    }

    fn longest_side(&self) -> f64 {
        let [a, b, c] = self.corners;
        (b - a).norm().max((c - b).norm()).max((a - c).norm())
    }

    /// The face's corners, points along its sides and inside it, on a barycentric grid.
    fn grid(&self) -> impl Iterator<Item = Point> + '_ {
        let [a, b, c] = self.corners;
        let step = 1.0 / COVER_STEPS as f64;
        (0..=COVER_STEPS).flat_map(move |i| {
            (0..=COVER_STEPS - i)
                .map(move |j| a + (b - a) * (i as f64 * step) + (c - a) * (j as f64 * step))
        })
    }

    /// Whether `p` lies on the face: within `reach` of its plane and, projected onto it, within
    /// the face (its barycentric weights all at least -`COVER_SLACK`).
    fn holds(&self, p: &Point, reach: f64) -> bool {
        let [a, b, c] = self.corners;
        if (p - a).dot(&self.normal).abs() > reach {
            return false;
        }
        let (u, v, w) = (b - a, c - a, p - a);
        let (uu, uv, vv, wu, wv) = (u.dot(&u), u.dot(&v), v.dot(&v), w.dot(&u), w.dot(&v));
        let det = uu * vv - uv * uv;
        if det <= 0.0 {
            return false;
        }
        let (s, t) = ((vv * wu - uv * wv) / det, (uu * wv - uv * wu) / det);
        s >= -COVER_SLACK && t >= -COVER_SLACK && s + t <= 1.0 + COVER_SLACK
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::cuboid;
    use crate::metrics::topology;

    /// A closed box with one of its faces decoded again, turned by `degrees` about the edge
    /// it shares with a neighbour, towards the inside, and its third corner `reach` times as
    /// far from that edge: a fin folded onto the box's side.
    fn box_with_a_fin(degrees: f64, reach: f64) -> Mesh {
        let cube = cuboid([1.0, 1.0, 1.0]);
        let mut mesh = Mesh::from_triangles(cube.faces.iter().map(|f| cube.triangle(f)));
        let [a, b, c] = mesh.triangle(&mesh.faces[0]).map(|p| Vector3::from(p.map(f64::from)));
        let along = (b - a).normalize();
        let foot = a + along * (c - a).dot(&along);
        let across = c - foot;
        // The box is centred at the origin: its inside is towards -a.
        let normal = along.cross(&across).normalize();
        let inward = if normal.dot(&a) < 0.0 { normal } else { -normal };
        let (sin, cos) = degrees.to_radians().sin_cos();
        let turned = foot + (across * cos + inward * (across.norm() * sin)) * reach;
        mesh.vertices.push([turned.x as f32, turned.y as f32, turned.z as f32]);
        let fin = [mesh.faces[0][0], mesh.faces[0][1], (mesh.vertices.len() - 1) as u32];
        mesh.faces.push(fin);
        mesh
    }

    #[test]
    fn a_fin_folded_onto_a_side_goes_and_one_standing_off_it_stays() {
        let folded = box_with_a_fin(5.0, 1.0);
        assert_eq!(topology(&folded).non_manifold_edges, 1);
        let cleaned = without_folded_faces(&folded);
        assert_eq!(cleaned.faces.len(), 12);
        assert_eq!(topology(&cleaned).non_manifold_edges, 0);
        assert_eq!(topology(&cleaned).boundary_edges, 0);
        let standing = box_with_a_fin(45.0, 1.0);
        assert_eq!(without_folded_faces(&standing), standing);
    }

    #[test]
    fn a_fin_that_reaches_past_the_side_it_is_folded_onto_stays() {
        // Its far corner is beyond the side: it adds surface.
        let reaching = box_with_a_fin(5.0, 1.5);
        assert_eq!(without_folded_faces(&reaching), reaching);
        assert_eq!(without_folded_faces(&box_with_a_fin(5.0, 0.7)).faces.len(), 12);
    }

    #[test]
    fn a_face_that_two_faces_cover_together_goes() {
        // A side of a box decoded again as the triangle across its other diagonal: half of it
        // lies on each of the side's two faces, and neither covers it alone.
        let cube = cuboid([1.0, 1.0, 1.0]);
        let mut mesh = Mesh::from_triangles(cube.faces.iter().map(|f| cube.triangle(f)));
        let first = mesh.first_vertex_at_each_position();
        let side = [mesh.faces[0], mesh.faces[1]].map(|f| f.map(|c| first[c as usize]));
        let corners: std::collections::BTreeSet<u32> = side.iter().flatten().copied().collect();
        assert_eq!(corners.len(), 4, "faces 0 and 1 make one side");
        let diagonal: Vec<u32> = side[0].into_iter().filter(|c| side[1].contains(c)).collect();
        let across: Vec<u32> = corners.iter().copied().filter(|c| !diagonal.contains(c)).collect();
        mesh.faces.push([diagonal[0], across[0], across[1]]);
        assert_eq!(topology(&mesh).non_manifold_edges, 2);
        let cleaned = without_folded_faces(&mesh);
        assert_eq!(cleaned.faces.len(), 12);
        assert_eq!(topology(&cleaned).non_manifold_edges, 0);
        assert_eq!(topology(&cleaned).boundary_edges, 0);
    }

    #[test]
    fn a_face_without_area_on_a_shared_edge_is_left_alone() {
        let mut mesh = box_with_a_fin(5.0, 1.0);
        let [a, b, _] = mesh.faces[0];
        mesh.faces.push([a, b, a]);
        let cleaned = without_folded_faces(&mesh);
        assert_eq!(cleaned.faces.len(), 13);
        assert!(cleaned.faces.contains(&[a, b, a]));
    }

    proptest::proptest! {
        #[test]
        fn dropping_folded_faces_opens_nothing_and_keeps_the_rest_in_order(
            corners in proptest::collection::vec([0u8..3, 0u8..3, 0u8..2], 8..40),
        ) {
            // Corners on a small grid, so that faces share edges, fold and repeat.
            let grid: Vec<[f32; 3]> =
                (0..3).flat_map(|x| (0..3).flat_map(move |y| (0..2).map(move |z| [x, y, z])))
                    .map(|p: [u8; 3]| p.map(f32::from))
                    .collect();
            let index = |[x, y, z]: [u8; 3]| u32::from(x) * 6 + u32::from(y) * 2 + u32::from(z);
            let faces: Vec<[u32; 3]> =
                corners.chunks_exact(3).map(|c| [index(c[0]), index(c[1]), index(c[2])]).collect();
            let mesh = Mesh::new(grid, faces);
            let cleaned = without_folded_faces(&mesh);
            let (before, after) = (topology(&mesh), topology(&cleaned));
            proptest::prop_assert!(after.boundary_edges <= before.boundary_edges);
            proptest::prop_assert!(after.non_manifold_edges <= before.non_manifold_edges);
            let mut rest = mesh.faces.iter();
            proptest::prop_assert!(cleaned.faces.iter().all(|f| rest.any(|g| g == f)));
        }
    }
}
