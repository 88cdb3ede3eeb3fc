//! Faces that face out: the winding of a reconstruction's faces made to agree across its
//! edges, each surface turned to face the side it can be seen from.
//!
//! Why: the shipped model winds many faces the wrong way (on the dev split 5.1% of its
//! answers' edges have both faces wound the same way along them, against 0.1% in the ground
//! truth). Viewers that draw only the front of a face, glTF's default, show each such face as
//! a hole, and a closed surface with mixed winding has no inside for a pipeline to fill
//! (`docs/decisions.md`, "Faces that face out").

use parry3d_f64::na::{Point3, Unit, Vector3};
use parry3d_f64::query::{Ray, RayCast};
use parry3d_f64::shape::TriMesh;

use super::surfaces::Surfaces;
use super::{Mesh, triangle_area, triangle_normal};

/// Directions each face looks in on each of its sides: along its normal and 8 around it, 45
/// degrees off, so that one ray grazing a neighbour does not decide.
const LOOKS: usize = 9;

/// `mesh` with its faces wound alike across every edge that two of them share (corners
/// welded by position), each such surface turned to face out, and how many faces were turned.
///
/// A surface faces out where rays from its faces travel further before they meet the mesh
/// on their front side than on their back (averaged over its faces, weighted by area): the
/// front of a closed surface sees out, the front of a wall sees the open room. A surface
/// whose sides cannot be told apart that way keeps the winding most of its area was decoded
/// with. Vertices stay as they are; faces keep their places and corners, two of which swap
/// on a turned face. Indices must be valid ([`Mesh::validate`]).
pub fn with_faces_facing_out(mesh: &Mesh) -> (Mesh, usize) {
    let Some(rays) = Rays::new(mesh) else {
        return (mesh.clone(), 0);
    };
    let Surfaces { members, turned_alike: mut turned } = Surfaces::of(mesh);
    for faces in &members {
        // How much further the surface sees on its front, wound alike, than on its back; and
        // its area that keeps its decoded winding, less the area that turns.
        let (mut look, mut net_kept_area) = (0.0, 0.0);
        for &f in faces {
            let area = triangle_area(mesh.triangle(&mesh.faces[f]));
            let sign = if turned[f] { -1.0 } else { 1.0 };
            look += sign * area * rays.front_minus_back(f);
            net_kept_area += sign * area;
        }
        let flip = if look != 0.0 { look < 0.0 } else { net_kept_area < 0.0 };
        if flip {
            for &f in faces {
                turned[f] = !turned[f];
            }
        }
    }
    let mut out = mesh.clone();
    for (face, _) in out.faces.iter_mut().zip(&turned).filter(|(_, t)| **t) {
        face.swap(1, 2);
    }
    (out, turned.iter().filter(|t| **t).count())
}

/// A mesh's faces ready for ray casts, with its bounding box's centre and diagonal.
pub(crate) struct RayTarget {
    pub shape: TriMesh,
    pub centre: Point3<f64>,
    pub diagonal: f64,
}

impl RayTarget {
    /// `None` for a mesh without faces or size; indices must be valid.
    pub fn new(mesh: &Mesh) -> Option<Self> {
        let (lo, hi) = mesh.bounds()?;
        let diagonal = (0..3).map(|k| f64::from(hi[k] - lo[k]).powi(2)).sum::<f64>().sqrt();
        if mesh.faces.is_empty() || diagonal <= 0.0 || !diagonal.is_finite() {
            return None;
        }
        let centre = Point3::from([0, 1, 2].map(|k| (f64::from(lo[k]) + f64::from(hi[k])) / 2.0));
        let vertices = mesh.vertices.iter().map(|v| Point3::from(v.map(f64::from))).collect();
        let shape = TriMesh::new(vertices, mesh.faces.clone()).ok()?;
        Some(Self { shape, centre, diagonal })
    }
}

/// Two unit vectors across `n` (a unit vector), at right angles to it and to each other.
pub(crate) fn axes_across(n: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    // Any vector not along n gives the plane across it.
    let helper = if n.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    let u = n.cross(&helper).normalize();
    (u, n.cross(&u))
}

/// Rays cast from a mesh's faces into the mesh.
struct Rays<'a> {
    mesh: &'a Mesh,
    target: RayTarget,
    /// How far a ray goes at most: the mesh's size, so that rays into the open all count
    /// the same.
    reach: f64,
    /// How far off its face a ray starts, so that it does not meet that face.
    lift: f64,
}

impl<'a> Rays<'a> {
    /// `None` for a mesh without faces or size.
    fn new(mesh: &'a Mesh) -> Option<Self> {
        let target = RayTarget::new(mesh)?;
        let reach = target.diagonal;
        Some(Self { mesh, target, reach, lift: 1e-5 * reach })
    }

    /// How much further, on average over [`LOOKS`] directions, rays from face `f`'s centre
    /// travel on its front side than on its back; 0 for a face without area.
    fn front_minus_back(&self, f: usize) -> f64 {
        let [a, b, c] = self.mesh.triangle(&self.mesh.faces[f]);
        let normal = Vector3::from(triangle_normal([a, b, c]).map(f64::from));
        let Some(normal) = Unit::try_new(normal, 1e-12) else { return 0.0 };
        let centre = Point3::from([0, 1, 2].map(|k| f64::from(a[k] + b[k] + c[k]) / 3.0));
        let side = |n: Unit<Vector3<f64>>| {
            let travelled: f64 = looks_around(n)
                .map(|dir| {
                    let ray = Ray::new(centre + dir * self.lift, dir);
                    self.target.shape.cast_local_ray(&ray, self.reach, false).unwrap_or(self.reach)
                })
                .sum();
            travelled / LOOKS as f64
        };
        side(normal) - side(-normal)
    }
}

/// [`LOOKS`] unit directions: `n` and 8 evenly round it, 45 degrees off.
fn looks_around(n: Unit<Vector3<f64>>) -> impl Iterator<Item = Vector3<f64>> {
    let (u, v) = axes_across(&n);
    let around = (0..LOOKS - 1).map(move |i| {
        let angle = std::f64::consts::TAU * i as f64 / (LOOKS - 1) as f64;
        (n.into_inner() + u * angle.cos() + v * angle.sin()).normalize()
    });
    std::iter::once(n.into_inner()).chain(around)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::{cuboid, uv_sphere};
    use crate::metrics::topology;

    #[test]
    fn a_surface_that_cannot_be_wound_alike_comes_out_the_same_on_every_run() {
        // A Moebius strip: its last quad joins the first one turned over.
        let n = 24;
        let mut strip = Mesh::default();
        for i in 0..n {
            let t = std::f32::consts::TAU * i as f32 / n as f32;
            let centre = [t.cos(), t.sin(), 0.0];
            let across = [t.cos() * (t / 2.0).cos(), t.sin() * (t / 2.0).cos(), (t / 2.0).sin()];
            for side in [0.3, -0.3] {
                strip.vertices.push(std::array::from_fn(|k| centre[k] + side * across[k]));
            }
        }
        let (a, b) = (|i: u32| 2 * (i % n), |i: u32| 2 * (i % n) + 1);
        for i in 0..n - 1 {
            strip.faces.extend([[a(i), b(i), a(i + 1)], [b(i), b(i + 1), a(i + 1)]]);
        }
        strip.faces.extend([[a(n - 1), b(n - 1), b(0)], [b(n - 1), a(0), b(0)]]);
        let first = with_faces_facing_out(&strip);
        // Each call hashes the edges with other keys, as each request does.
        for _ in 0..16 {
            assert_eq!(with_faces_facing_out(&strip), first);
        }
    }

    /// `mesh` with the faces `which` picks wound the other way.
    fn turned(mesh: &Mesh, which: impl Fn(usize) -> bool) -> Mesh {
        let mut out = mesh.clone();
        for (i, face) in out.faces.iter_mut().enumerate() {
            if which(i) {
                face.swap(1, 2);
            }
        }
        out
    }

    #[test]
    fn a_closed_surface_with_faces_turned_in_faces_out_again() {
        for shape in [cuboid([1.0, 2.0, 0.5]), uv_sphere(1.0, 12, 7)] {
            let scrambled = turned(&shape, |i| i % 3 == 1);
            assert!(topology(&scrambled).misoriented_edges > 0);
            let (fixed, count) = with_faces_facing_out(&scrambled);
            assert_eq!(fixed, shape);
            assert_eq!(count, (0..shape.faces.len()).filter(|i| i % 3 == 1).count());
            // All of it inside out: every face turns.
            let inside_out = turned(&shape, |_| true);
            assert_eq!(with_faces_facing_out(&inside_out), (shape.clone(), shape.faces.len()));
        }
    }

    #[test]
    fn a_box_inside_a_box_faces_out_each_and_a_right_mesh_stays_as_it_is() {
        let mut nested = cuboid([2.0; 3]);
        nested.append(&cuboid([0.5; 3]));
        assert_eq!(with_faces_facing_out(&nested), (nested.clone(), 0));
        let (fixed, count) = with_faces_facing_out(&turned(&nested, |i| i >= 12));
        assert_eq!((fixed, count), (nested, 12));
    }

    #[test]
    fn an_open_box_faces_out_where_its_outside_sees_further() {
        // A box without its top: its inside sees out through the top, but less far on
        // average than its outside does.
        let mut open = cuboid([1.0; 3]);
        let top: Vec<usize> = (0..open.faces.len())
            .filter(|&f| open.triangle(&open.faces[f]).iter().all(|p| p[2] > 0.0))
            .collect();
        assert_eq!(top.len(), 2);
        open.faces =
            (0..open.faces.len()).filter(|f| !top.contains(f)).map(|f| open.faces[f]).collect();
        let (fixed, count) = with_faces_facing_out(&turned(&open, |_| true));
        assert_eq!((fixed, count), (open, 10));
    }

    #[test]
    fn a_flat_sheet_keeps_the_winding_most_of_its_area_has() {
        // Two squares side by side, the bigger one wound up, the smaller down: from either
        // side rays all go into the open.
        let sheet = Mesh::new(
            vec![
                [0.0, 0.0, 0.0],
                [2.0, 0.0, 0.0],
                [2.0, 2.0, 0.0],
                [0.0, 2.0, 0.0],
                [3.0, 0.0, 0.0],
            ],
            vec![[0, 1, 2], [0, 2, 3], [1, 2, 4]],
        );
        let (fixed, count) = with_faces_facing_out(&sheet);
        assert_eq!(count, 1);
        assert_eq!(fixed.faces, [[0, 1, 2], [0, 2, 3], [1, 4, 2]]);
        assert_eq!(topology(&fixed).misoriented_edges, 0);
    }

    #[test]
    fn nothing_to_turn_comes_back_as_it_is() {
        let cloud = Mesh::new(vec![[0.0; 3], [1.0; 3]], Vec::new());
        assert_eq!(with_faces_facing_out(&cloud), (cloud.clone(), 0));
        let collapsed = Mesh::new(vec![[0.0; 3], [1.0, 0.0, 0.0]], vec![[0, 0, 1], [0, 1, 1]]);
        assert_eq!(with_faces_facing_out(&collapsed), (collapsed.clone(), 0));
        assert_eq!(with_faces_facing_out(&Mesh::default()), (Mesh::default(), 0));
    }
}
