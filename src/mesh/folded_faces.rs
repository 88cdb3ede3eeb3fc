//! Folded faces: a face that lies folded onto a neighbour across an edge that three or more
//! faces share. The shipped model often decodes a surface twice where two of its layers meet,
//! and the extra face makes the edge non-manifold without adding any surface.

use std::collections::BTreeMap;

use parry3d_f64::na::Vector3;

use super::{Mesh, triangle_area};

/// Two faces on one edge are folded onto each other when the directions from the edge to their
/// third corners are within this angle (degrees).
const FOLD_DEGREES: f64 = 10.0;

/// How far (as barycentric weight) a folded face's third corner may lie outside the face it is
/// folded onto and still count as covered by it.
const COVER_SLACK: f64 = 0.05;

/// `mesh` without the faces folded onto a neighbour that covers them, across a non-manifold
/// edge, where dropping them opens no edge: each of the face's edges has one face (it goes) or
/// three or more (it becomes less non-manifold), none has two. Folded: the directions from the
/// edge to the two faces' third corners are within `FOLD_DEGREES`; covered: the face's third
/// corner lies within the other face once projected onto it. Of a pair the smaller face is
/// tried first; the edges are taken in order of their corners, once each, and a pair whose
/// other face has gone no longer counts. The vertices stay as they are (see
/// [`super::without_stray_parts`]); indices must be valid ([`Mesh::validate`]).
pub fn without_folded_faces(mesh: &Mesh) -> Mesh {
    let first = mesh.first_vertex_at_each_position();
    let faces: Vec<[usize; 3]> =
        mesh.faces.iter().map(|f| f.map(|c| first[c as usize] as usize)).collect();
    let mut on_edge: BTreeMap<[usize; 2], Vec<usize>> = BTreeMap::new();
    for (i, f) in faces.iter().enumerate() {
        if f[0] != f[1] && f[1] != f[2] && f[0] != f[2] {
            for e in edges(f) {
                on_edge.entry(e).or_default().push(i);
            }
        }
    }
    let mut dropped = vec![false; faces.len()];
    let shared: Vec<[usize; 2]> =
        on_edge.iter().filter(|(_, fs)| fs.len() > 2).map(|(&e, _)| e).collect();
    for e in shared {
        for f in folded_on(mesh, &faces, e, &on_edge[&e], &dropped) {
            let opens = edges(&faces[f]).iter().any(|edge| live(&on_edge[edge], &dropped) == 2);
            if !dropped[f] && !opens && live(&on_edge[&e], &dropped) > 2 {
                dropped[f] = true;
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

/// The faces on edge `e` (not dropped) folded onto another of them that covers them, each
/// pair's smaller first.
fn folded_on(
    mesh: &Mesh,
    faces: &[[usize; 3]],
    [a, b]: [usize; 2],
    on_edge: &[usize],
    dropped: &[bool],
) -> Vec<usize> {
    let point = |v: usize| Vector3::from(mesh.vertices[v].map(f64::from));
    let start = point(a);
    let along = (point(b) - start).normalize();
    // The direction from the edge to a face's third corner, square to the edge.
    let wing = |f: usize| {
        let third = faces[f].into_iter().find(|&v| v != a && v != b)?;
        let to = point(third) - start;
        (to - along * to.dot(&along)).try_normalize(0.0)
    };
    let alive: Vec<(usize, Vector3<f64>)> =
        on_edge.iter().filter(|&&f| !dropped[f]).filter_map(|&f| Some((f, wing(f)?))).collect();
    let cos = FOLD_DEGREES.to_radians().cos();
    let area = |f: usize| triangle_area(mesh.triangle(&mesh.faces[f]));
    let third = |f: usize| faces[f].into_iter().find(|&v| v != a && v != b).map(point);
    // Whether face `f` lies within face `g` once folded onto it: its third corner does.
    let covered = |f: usize, g: usize| match (third(f), third(g)) {
        (Some(cf), Some(cg)) => within_triangle(cf, [start, point(b), cg]),
        _ => false,
    };
    let mut folded = Vec::new();
    for (i, (f, wf)) in alive.iter().enumerate() {
        for (g, wg) in &alive[i + 1..] {
            if wf.dot(wg) > cos {
                let (small, large) = if area(*f) <= area(*g) { (*f, *g) } else { (*g, *f) };
                // Nearly equal faces may each lie within the other: the smaller is tried first.
                for (x, y) in [(small, large), (large, small)] {
                    if covered(x, y) {
                        folded.push(x);
                    }
                }
            }
        }
    }
    folded
}

/// Whether `p`, projected onto the plane of triangle `t`, lies within it (its barycentric
/// weights all at least -`COVER_SLACK`).
fn within_triangle(p: Vector3<f64>, [a, b, c]: [Vector3<f64>; 3]) -> bool {
    let (u, v, w) = (b - a, c - a, p - a);
    let (uu, uv, vv, wu, wv) = (u.dot(&u), u.dot(&v), v.dot(&v), w.dot(&u), w.dot(&v));
    let det = uu * vv - uv * uv;
    if det <= 0.0 {
        return false;
    }
    let (s, t) = ((vv * wu - uv * wv) / det, (uu * wv - uv * wu) / det);
    s >= -COVER_SLACK && t >= -COVER_SLACK && s + t <= 1.0 + COVER_SLACK
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
}
