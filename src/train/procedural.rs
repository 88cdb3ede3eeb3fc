//! An endless, seeded stream of low-poly shapes as artists build them: primitives with few
//! segments, extruded profiles, and furniture-like assemblies of overlapping parts.
//!
//! Shapes come centred near the origin in a canonical pose with random proportions; the
//! training pipeline's augmentation (rotation, flips, per-axis scale) varies them further.

use std::collections::BTreeMap;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::mesh::Mesh;
use crate::mesh::primitives::{cuboid, extrusion, frustum, torus, uv_sphere};
use crate::mesh::transform::rotation;
use crate::tokenize::{Quantizer, canonical_triangulation};

/// What kind of shape a sample is, for logs, for stratified evaluation and for weighting the
/// training mix.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    PartialOrd,
    Ord,
    Hash,
    serde::Serialize,
    serde::Deserialize,
    clap::ValueEnum,
)]
pub enum ShapeKind {
    Box,
    Prism,
    Cylinder,
    Cone,
    Pyramid,
    Frustum,
    Wedge,
    Stairs,
    LExtrusion,
    TExtrusion,
    UExtrusion,
    PolygonExtrusion,
    Sphere,
    Torus,
    Table,
    Chair,
    Shelf,
    Tower,
    Cluster,
}

impl ShapeKind {
    pub const ALL: [ShapeKind; 19] = [
        ShapeKind::Box,
        ShapeKind::Prism,
        ShapeKind::Cylinder,
        ShapeKind::Cone,
        ShapeKind::Pyramid,
        ShapeKind::Frustum,
        ShapeKind::Wedge,
        ShapeKind::Stairs,
        ShapeKind::LExtrusion,
        ShapeKind::TExtrusion,
        ShapeKind::UExtrusion,
        ShapeKind::PolygonExtrusion,
        ShapeKind::Sphere,
        ShapeKind::Torus,
        ShapeKind::Table,
        ShapeKind::Chair,
        ShapeKind::Shelf,
        ShapeKind::Tower,
        ShapeKind::Cluster,
    ];

    /// The simple primitives (one closed part each), which a trained model should rebuild
    /// face for face.
    pub const PRIMITIVES: [ShapeKind; 6] = [
        ShapeKind::Box,
        ShapeKind::Prism,
        ShapeKind::Pyramid,
        ShapeKind::Wedge,
        ShapeKind::Frustum,
        ShapeKind::Cone,
    ];
}

/// The endless stream; the same seed gives the same shapes.
pub struct ProceduralShapes {
    rng: ChaCha8Rng,
    max_faces: usize,
    kinds: Vec<ShapeKind>,
    grid: Quantizer,
}

impl ProceduralShapes {
    /// Shapes of every kind with at most `max_faces` faces each.
    pub fn new(seed: u64, max_faces: usize) -> Self {
        Self::of_kinds(seed, max_faces, &ShapeKind::ALL)
    }

    /// Shapes of the given kinds only (all kinds if the list is empty).
    pub fn of_kinds(seed: u64, max_faces: usize, kinds: &[ShapeKind]) -> Self {
        let kinds = if kinds.is_empty() { ShapeKind::ALL.to_vec() } else { kinds.to_vec() };
        Self {
            rng: ChaCha8Rng::seed_from_u64(seed),
            max_faces: max_faces.max(4),
            kinds,
            grid: Quantizer::default(),
        }
    }

    /// Flat polygons split as tokenization on `grid` splits them (the default grid unless
    /// told): what is flat, and within rounding, depends on the grid.
    pub fn on_grid(self, grid: Quantizer) -> Self {
        Self { grid, ..self }
    }

    /// Shapes of every kind, each drawn in proportion to its weight (1 for a kind not listed,
    /// 0 to leave a kind out, at most [`MAX_KIND_WEIGHT`]). Without weights this is
    /// [`Self::new`], draw for draw.
    pub fn weighted(
        seed: u64,
        max_faces: usize,
        weights: &BTreeMap<ShapeKind, u32>,
    ) -> Result<Self, KindWeightsError> {
        if let Some((&kind, &weight)) = weights.iter().find(|(_, w)| **w > MAX_KIND_WEIGHT) {
            return Err(KindWeightsError::TooLarge { kind, weight });
        }
        // A kind listed w times in the uniform draw is drawn w times as often; this keeps the
        // unweighted stream (and so the held-aside shapes) exactly as it was.
        let kinds: Vec<ShapeKind> = ShapeKind::ALL
            .iter()
            .flat_map(|&kind| std::iter::repeat_n(kind, *weights.get(&kind).unwrap_or(&1) as usize))
            .collect();
        if kinds.is_empty() {
            return Err(KindWeightsError::AllZero);
        }
        Ok(Self::of_kinds(seed, max_faces, &kinds))
    }
}

/// The largest weight of one kind: the mix is drawn from a list with a kind repeated as often
/// as its weight, so weights are kept to ratios a mix needs.
pub const MAX_KIND_WEIGHT: u32 = 1000;

#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum KindWeightsError {
    #[error("every procedural shape kind has weight 0, so there is nothing to draw")]
    AllZero,
    #[error("{kind:?} has weight {weight}; at most {MAX_KIND_WEIGHT}")]
    TooLarge { kind: ShapeKind, weight: u32 },
}

impl Iterator for ProceduralShapes {
    type Item = (ShapeKind, Mesh);

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            let kind = self.kinds[self.rng.random_range(0..self.kinds.len())];
            let mesh = shape(kind, &mut self.rng, self.grid);
            // Every kind can draw a small enough variant, so this loop ends quickly.
            if !mesh.faces.is_empty() && mesh.faces.len() <= self.max_faces {
                return Some((kind, mesh));
            }
        }
    }
}

/// One random shape of a kind, standing on the data's vertical axis (y, see
/// [`super::augment::UP`]), its flat polygons split as tokenization on `grid` splits them.
pub fn shape(kind: ShapeKind, rng: &mut impl Rng, grid: Quantizer) -> Mesh {
    // Split the one way tokenization splits them, so that a shape used as ground truth has the
    // faces a model can learn to rebuild.
    canonical_triangulation(&standing(kind, rng), grid)
}

/// Built with z up (profiles are drawn in xy and extruded along z), then turned so that z goes
/// to y: -90 degrees about x.
fn standing(kind: ShapeKind, rng: &mut impl Rng) -> Mesh {
    z_up(kind, rng).transformed(&rotation([1.0, 0.0, 0.0], -std::f32::consts::FRAC_PI_2), [0.0; 3])
}

fn z_up(kind: ShapeKind, rng: &mut impl Rng) -> Mesh {
    match kind {
        ShapeKind::Box => cuboid([
            rng.random_range(0.2..1.0),
            rng.random_range(0.2..1.0),
            rng.random_range(0.2..1.0),
        ]),
        ShapeKind::Prism => {
            let (rad, h) = (rng.random_range(0.2..0.6), rng.random_range(0.2..1.2));
            frustum(rad, rad, h, rng.random_range(3..9))
        }
        ShapeKind::Cylinder => {
            let (rad, h) = (rng.random_range(0.15..0.5), rng.random_range(0.2..1.2));
            frustum(rad, rad, h, rng.random_range(8..17))
        }
        ShapeKind::Cone => frustum(
            rng.random_range(0.2..0.6),
            0.0,
            rng.random_range(0.3..1.2),
            rng.random_range(6..17),
        ),
        ShapeKind::Pyramid => frustum(
            rng.random_range(0.3..0.7),
            0.0,
            rng.random_range(0.3..1.0),
            rng.random_range(3..5),
        ),
        ShapeKind::Frustum => {
            let bottom = rng.random_range(0.3..0.7);
            frustum(
                bottom,
                bottom * rng.random_range(0.3..0.9),
                rng.random_range(0.2..1.0),
                rng.random_range(4..13),
            )
        }
        ShapeKind::Wedge => upright(profile(
            &[[0.0, 0.0], [rng.random_range(0.4..1.0), 0.0], [0.0, rng.random_range(0.3..1.0)]],
            rng.random_range(0.2..1.0),
        )),
        ShapeKind::Stairs => upright(profile(&stairs(rng), rng.random_range(0.3..1.0))),
        ShapeKind::LExtrusion => letter(rng, Letter::L),
        ShapeKind::TExtrusion => letter(rng, Letter::T),
        ShapeKind::UExtrusion => letter(rng, Letter::U),
        ShapeKind::PolygonExtrusion => profile(&star_polygon(rng), rng.random_range(0.1..0.8)),
        ShapeKind::Sphere => {
            uv_sphere(rng.random_range(0.3..0.6), rng.random_range(6..13), rng.random_range(4..9))
        }
        ShapeKind::Torus => {
            let major = rng.random_range(0.3..0.6);
            torus(
                major,
                major * rng.random_range(0.15..0.45),
                rng.random_range(6..13),
                rng.random_range(3..7),
            )
        }
        ShapeKind::Table => table(rng),
        ShapeKind::Chair => chair(rng),
        ShapeKind::Shelf => shelf(rng),
        ShapeKind::Tower => tower(rng),
        ShapeKind::Cluster => cluster(rng),
    }
}

/// An extruded profile (a degenerate profile falls back to a box, so a draw never fails).
fn profile(polygon: &[[f32; 2]], depth: f32) -> Mesh {
    extrusion(polygon, depth).unwrap_or_else(|| cuboid([0.5, 0.5, depth]))
}

/// Turns a profile drawn in xy and extruded along z so that its y axis points up (z).
fn upright(mesh: Mesh) -> Mesh {
    mesh.transformed(&rotation([1.0, 0.0, 0.0], std::f32::consts::FRAC_PI_2), [0.0; 3])
}

fn stairs(rng: &mut impl Rng) -> Vec<[f32; 2]> {
    let steps = rng.random_range(2..7);
    let (run, rise) = (rng.random_range(0.1..0.3), rng.random_range(0.1..0.3));
    let mut outline = vec![[0.0, 0.0], [run * steps as f32, 0.0]];
    for k in (1..=steps).rev() {
        outline.push([run * k as f32, rise * (steps - k + 1) as f32]);
        outline.push([run * (k - 1) as f32, rise * (steps - k + 1) as f32]);
    }
    outline.pop();
    outline.push([0.0, rise * steps as f32]);
    outline
}

enum Letter {
    L,
    T,
    U,
}

fn letter(rng: &mut impl Rng, letter: Letter) -> Mesh {
    let (w, h) = (rng.random_range(0.5..1.0), rng.random_range(0.5..1.0));
    let t = rng.random_range(0.1..0.25f32).min(w / 3.0).min(h / 3.0);
    let outline: Vec<[f32; 2]> = match letter {
        Letter::L => vec![[0.0, 0.0], [w, 0.0], [w, t], [t, t], [t, h], [0.0, h]],
        Letter::T => {
            let (a, b) = ((w - t) / 2.0, (w + t) / 2.0);
            vec![
                [a, 0.0],
                [b, 0.0],
                [b, h - t],
                [w, h - t],
                [w, h],
                [0.0, h],
                [0.0, h - t],
                [a, h - t],
            ]
        }
        Letter::U => {
            vec![[0.0, 0.0], [w, 0.0], [w, h], [w - t, h], [w - t, t], [t, t], [t, h], [0.0, h]]
        }
    };
    upright(profile(&outline, rng.random_range(0.1..0.8)))
}

/// A random simple polygon: corners at increasing angles with random radii (star-shaped
/// around the origin, hence never self-intersecting).
fn star_polygon(rng: &mut impl Rng) -> Vec<[f32; 2]> {
    let n = rng.random_range(5..10);
    let mut angles: Vec<f32> =
        (0..n).map(|_| rng.random_range(0.0..std::f32::consts::TAU)).collect();
    angles.sort_by(f32::total_cmp);
    angles.dedup_by(|a, b| (*a - *b).abs() < 0.05);
    angles
        .iter()
        .map(|a| {
            let r = rng.random_range(0.25..0.6);
            [r * a.cos(), r * a.sin()]
        })
        .collect()
}

/// Four legs under a board, overlapping it as modellers do.
fn legs_under(rng: &mut impl Rng, mesh: &mut Mesh, w: f32, d: f32, top_z: f32, leg: f32) {
    let round = rng.random_bool(0.4);
    let seg = rng.random_range(4..9);
    for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
        let part = if round {
            frustum(leg / 2.0, leg / 2.0, top_z, seg)
        } else {
            cuboid([leg, leg, top_z])
        };
        mesh.append(&part.translated([sx * (w / 2.0 - leg), sy * (d / 2.0 - leg), top_z / 2.0]));
    }
}

fn table(rng: &mut impl Rng) -> Mesh {
    let (w, d, h) =
        (rng.random_range(0.6..1.2), rng.random_range(0.4..1.0), rng.random_range(0.4..0.9));
    let (thick, leg) = (rng.random_range(0.03..0.1), rng.random_range(0.04..0.12));
    let mut mesh = cuboid([w, d, thick]).translated([0.0, 0.0, h - thick / 2.0]);
    legs_under(rng, &mut mesh, w, d, h - thick / 4.0, leg);
    mesh
}

fn chair(rng: &mut impl Rng) -> Mesh {
    let (w, seat_h) = (rng.random_range(0.4..0.7), rng.random_range(0.35..0.6));
    let (thick, leg) = (rng.random_range(0.04..0.08), rng.random_range(0.04..0.08));
    let back_h = rng.random_range(0.3..0.7);
    let mut mesh = cuboid([w, w, thick]).translated([0.0, 0.0, seat_h]);
    legs_under(rng, &mut mesh, w, w, seat_h, leg);
    mesh.append(&cuboid([w, thick, back_h]).translated([
        0.0,
        w / 2.0 - thick / 2.0,
        seat_h + back_h / 2.0,
    ]));
    mesh
}

fn shelf(rng: &mut impl Rng) -> Mesh {
    let (w, d, h) =
        (rng.random_range(0.5..1.0), rng.random_range(0.2..0.5), rng.random_range(0.6..1.4));
    let t = rng.random_range(0.02..0.06);
    let boards = rng.random_range(2..6);
    let mut mesh = Mesh::default();
    for sx in [-1.0, 1.0] {
        mesh.append(&cuboid([t, d, h]).translated([sx * (w / 2.0 - t / 2.0), 0.0, h / 2.0]));
    }
    for k in 0..boards {
        let z = t / 2.0 + (h - t) * k as f32 / (boards - 1) as f32;
        mesh.append(&cuboid([w - t, d, t]).translated([0.0, 0.0, z]));
    }
    if rng.random_bool(0.5) {
        mesh.append(&cuboid([w, t, h]).translated([0.0, d / 2.0, h / 2.0]));
    }
    mesh
}

fn tower(rng: &mut impl Rng) -> Mesh {
    let seg = rng.random_range(4..9);
    let levels = rng.random_range(2..5);
    let mut radius = rng.random_range(0.3..0.5);
    let mut z = 0.0;
    let mut mesh = Mesh::default();
    for _ in 0..levels {
        let h = rng.random_range(0.2..0.5);
        let top = radius * rng.random_range(0.7..1.0);
        // Each level sinks slightly into the one below.
        mesh.append(&frustum(radius, top, h, seg).translated([0.0, 0.0, z + h / 2.0]));
        z += h * 0.95;
        radius = top;
    }
    let roof_h = rng.random_range(0.2..0.6);
    mesh.append(&frustum(radius * 1.2, 0.0, roof_h, seg).translated([0.0, 0.0, z + roof_h / 2.0]));
    mesh
}

fn cluster(rng: &mut impl Rng) -> Mesh {
    let parts = rng.random_range(2..5);
    let mut mesh = Mesh::default();
    for _ in 0..parts {
        let kind = ShapeKind::PRIMITIVES[rng.random_range(0..ShapeKind::PRIMITIVES.len())];
        // Turned at random, a part's split is moot: the assembly is split as a whole.
        let part = standing(kind, rng);
        let turn = rotation([0.0, 0.0, 1.0], rng.random_range(0.0..std::f32::consts::TAU));
        let offset =
            [rng.random_range(-0.4..0.4), rng.random_range(-0.4..0.4), rng.random_range(0.0..0.4)];
        mesh.append(&part.transformed(&turn, offset));
    }
    mesh
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_shapes_and_every_kind_is_valid() {
        let a: Vec<_> = ProceduralShapes::new(7, 400).take(200).collect();
        let b: Vec<_> = ProceduralShapes::new(7, 400).take(200).collect();
        assert_eq!(a, b);
        let mut seen = std::collections::HashSet::new();
        for (kind, mesh) in &a {
            seen.insert(*kind);
            assert!(mesh.validate().is_ok(), "{kind:?}");
            assert!(!mesh.faces.is_empty() && mesh.faces.len() <= 400, "{kind:?}");
            assert!(mesh.area() > 0.0, "{kind:?}");
        }
        assert_eq!(seen.len(), ShapeKind::ALL.len(), "200 draws should cover every kind");
    }

    #[test]
    fn shapes_stand_on_the_vertical_axis() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for _ in 0..10 {
            // A cone's apex is its only highest vertex, above the middle of its base.
            let cone = standing(ShapeKind::Cone, &mut rng);
            let up = super::super::augment::UP;
            let top = cone.vertices.iter().map(|v| v[up]).fold(f32::MIN, f32::max);
            let apex: Vec<_> = cone.vertices.iter().filter(|v| v[up] > top - 1e-4).collect();
            assert_eq!(apex.len(), 1, "{apex:?}");
            let bottom = cone.vertices.iter().map(|v| v[up]).fold(f32::MAX, f32::min);
            assert!(top - bottom > 0.29, "height {}", top - bottom);
        }
    }

    #[test]
    fn primitives_come_split_as_tokenization_splits_them() {
        // A model learns tokenized faces; held-aside shapes can be rebuilt face for face only if
        // their own triangles are those faces.
        use crate::tokenize::{Quantizer, detokenize, tokenize};
        let q = Quantizer::default();
        let corner_sets = |m: &Mesh| {
            let mut sets: Vec<_> = m
                .faces
                .iter()
                .map(|f| {
                    let mut t = m.triangle(f).map(|v| v.map(|c| q.quantize(c)));
                    t.sort_unstable();
                    t
                })
                .collect();
            sets.sort_unstable();
            sets
        };
        let mut boxes = 0;
        for (kind, mesh) in ProceduralShapes::of_kinds(9, 400, &ShapeKind::PRIMITIVES).take(60) {
            let (normalized, _) = mesh.normalized().unwrap();
            let tokenized = detokenize(&tokenize(&normalized, q).faces, q);
            assert_eq!(corner_sets(&normalized), corner_sets(&tokenized), "{kind:?}");
            boxes += usize::from(kind == ShapeKind::Box);
        }
        assert!(boxes > 0);
    }

    #[test]
    fn weights_change_the_mix_and_none_keeps_the_stream() {
        let plain: Vec<_> = ProceduralShapes::new(9, 400).take(50).collect();
        let unweighted: Vec<_> =
            ProceduralShapes::weighted(9, 400, &BTreeMap::new()).unwrap().take(50).collect();
        assert_eq!(plain, unweighted);

        let boxes_only: BTreeMap<_, _> =
            ShapeKind::ALL.iter().map(|&k| (k, u32::from(k == ShapeKind::Box))).collect();
        let shapes = ProceduralShapes::weighted(9, 400, &boxes_only).unwrap();
        assert!(shapes.take(30).all(|(kind, _)| kind == ShapeKind::Box));

        let more_boxes = BTreeMap::from([(ShapeKind::Box, 19)]);
        let boxes = ProceduralShapes::weighted(9, 400, &more_boxes)
            .unwrap()
            .take(2000)
            .filter(|(kind, _)| *kind == ShapeKind::Box)
            .count();
        // Box is 19 of 37 draws: about 1,027 of 2,000.
        assert!((900..1150).contains(&boxes), "{boxes} boxes");
    }

    #[test]
    fn weights_that_leave_nothing_or_are_too_large_are_errors() {
        let none: BTreeMap<_, _> = ShapeKind::ALL.iter().map(|&k| (k, 0)).collect();
        let result = ProceduralShapes::weighted(1, 400, &none);
        assert_eq!(result.err(), Some(KindWeightsError::AllZero));
        let huge = BTreeMap::from([(ShapeKind::Cone, u32::MAX)]);
        let result = ProceduralShapes::weighted(1, 400, &huge);
        assert!(matches!(result, Err(KindWeightsError::TooLarge { kind: ShapeKind::Cone, .. })));
    }

    #[test]
    fn face_budget_is_respected() {
        for (_, mesh) in ProceduralShapes::new(3, 40).take(100) {
            assert!(mesh.faces.len() <= 40);
        }
    }
}
