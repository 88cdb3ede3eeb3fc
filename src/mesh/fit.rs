//! Fitting a mesh's corners to the points it should pass through, keeping its faces.
//!
//! Why: a decoder places corners on its grid and, being small, often a grid step or two off
//! the surface its input points describe (a box 2 steps short on one side); a reconstruction
//! has those points at hand. Each round moves every corner by the least-squares shift of the
//! pulls on it from two nearest-neighbour matches, as Chamfer distance weighs them: points sampled on the surface
//! towards their nearest input point (the surface lies where the points are), and each input
//! point's nearest surface sample towards it (every point is covered). A sample pulls its
//! face's corners by its barycentric weights. The pull is mostly along the input point's
//! normal, towards its tangent plane: a thousand points lie about 0.05 apart on a shape of
//! size 2, so pulling samples onto the points themselves would rather gather them around the
//! points (and shrink the shape at its edges) than move them onto the surface.
//!
//! Corners move at most `max_shift` from where they started and stay within the bounds of
//! the points and the mesh together, widened by the points' spacing: a pull towards a tangent
//! plane must not carry a corner out past the shape, but sampled points stop short of its
//! tips by about their spacing (see [`BOUNDS_MARGIN`]). On the tuning shapes a larger
//! `max_shift` always scored better (`docs/decisions.md`, "Fitting"), so the default lets
//! corners go anywhere in the frame.

use std::num::NonZeroUsize;

use kiddo::{ImmutableKdTree, SquaredEuclidean};

use super::sample::{SurfaceSample, surface_samples};
use super::transform::{Mat3, cofactor, determinant, mat_vec};
use super::{Mesh, MeshError, NORMAL_NEIGHBOURS, bounds, estimate_normals, normalized};

/// The most rounds a server request may ask for: each costs about as much as judging a
/// candidate.
pub const MAX_FIT_ROUNDS: usize = 200;

/// How hard a fit tries.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitOptions {
    /// The most rounds of matching and moving.
    pub rounds: usize,
    /// A fit ends before `rounds` once this many rounds in a row moved its corners no less
    /// on average than the least a round had moved them before (0: every round runs). The
    /// mean move levels off at the sampling noise within a few rounds (a sixth to a third of
    /// a cell on the shipped model's meshes, by the mesh: no fixed threshold fits all), yet
    /// the later rounds still bring the mesh closer; see `PATIENCE`.
    pub patience: usize,
    /// Surface samples per round.
    pub samples: usize,
    /// The furthest a corner may end up from where it started, in the mesh's units.
    pub max_shift: f32,
    /// The share of its least-squares shift a corner moves by in one round (1: all of it).
    pub step: f32,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self { rounds: 40, patience: PATIENCE, samples: 4096, max_shift: 1.0, step: 1.0 }
    }
}

/// [`FitOptions::patience`]'s default: every round runs. A patience of 5 ended fits after 27
/// of 40 rounds on average but cost 44 dev meshes' Chamfer distance +0.0013 (standard error
/// 0.0003; `docs/decisions.md`, "Fitting").
pub const PATIENCE: usize = 0;

/// How far corners may go past the bounds of the points and the mesh, in the points' mean
/// spacing (the distance from a point to its nearest neighbour). Why: points sampled on a
/// surface stop short of its tips by about their spacing, so a pyramid's apex lies above its
/// highest point, and bounds through the outermost points held it below where its sides meet:
/// from 2,000 points the held-aside pyramids all came out with their apex off
/// (`docs/decisions.md`, "Fitting").
pub const BOUNDS_MARGIN: f32 = 1.0;

/// Points whose nearest-neighbour distance is averaged for the spacing: a subsample is as
/// good an estimate and keeps the cost bounded for large clouds.
const SPACING_PROBES: usize = 1000;

/// The most input points that pull in one round: with more, each round takes every k-th of
/// them from a start that moves on each round, so that every point pulls once in k rounds.
/// Why: finding each of a reconstruction's 16,384 reference points its nearest sample cost
/// four times the samples' own matching. A 400-face fit took 72-78 ms against 155-204
/// (`meshstream bench mesh`), and 44 dev meshes' Chamfer distance moved -0.0003 (standard
/// error 0.0003; `docs/decisions.md`, "Fitting"). A fixed quarter of the points had cost
/// +0.0011 (0.0004).
const POINTS_PER_ROUND: usize = 2048;

/// The share of a pull that goes along the surface rather than towards its tangent plane:
/// a little, so that corners do not drift freely along flat sides.
const TANGENTIAL_SHARE: f32 = 0.1;

/// `mesh` with its corners moved to fit the point cloud `cloud` (same faces, same vertex
/// order); the cloud's normals are estimated when it has none (their sign does not matter).
/// Errors as [`super::sample_surface`] for a mesh without area, and for an empty or invalid
/// cloud (see [`Mesh::validate`]). Several meshes fitted to one cloud share a [`FitTarget`]
/// ([`fit_to_target`]).
pub fn fit_to_points(
    mesh: &Mesh,
    cloud: &Mesh,
    options: &FitOptions,
    seed: u64,
) -> Result<Mesh, MeshError> {
    fit_to_target(mesh, &FitTarget::new(cloud)?, options, seed)
}

/// [`fit_to_points`] with the cloud prepared once.
pub fn fit_to_target(
    mesh: &Mesh,
    target: &FitTarget,
    options: &FitOptions,
    seed: u64,
) -> Result<Mesh, MeshError> {
    let Some((lo, hi)) = bounds(&mesh.vertices) else {
        return Err(MeshError::invalid("no corners to fit"));
    };
    let (lo, hi) = (
        std::array::from_fn::<f32, 3, _>(|k| lo[k].min(target.lo[k]) - target.margin()),
        std::array::from_fn::<f32, 3, _>(|k| hi[k].max(target.hi[k]) + target.margin()),
    );
    let mut fitted = Mesh { normals: None, ..mesh.clone() };
    let (mut least, mut since_least) = (f32::INFINITY, 0);
    for round in 0..options.rounds {
        let samples = surface_samples(&fitted, options.samples, seed.wrapping_add(round as u64))?;
        let pulls = Pulls::of(&fitted, &samples, target, round)?;
        let mut moved_by = 0.0f32;
        for (v, shift) in pulls.shifts().into_iter().enumerate() {
            let Some(shift) = shift else { continue };
            let moved: [f32; 3] =
                std::array::from_fn(|k| fitted.vertices[v][k] + options.step * shift[k]);
            let near = within(mesh.vertices[v], moved, options.max_shift);
            // Inside a box that holds the start, so this only brings the corner closer to it.
            let placed = std::array::from_fn(|k| near[k].clamp(lo[k], hi[k]));
            moved_by += distance(fitted.vertices[v], placed);
            fitted.vertices[v] = placed;
        }
        let mean = moved_by / fitted.vertices.len().max(1) as f32;
        tracing::trace!(round, mean, "fit round");
        if mean < least {
            (least, since_least) = (mean, 0);
        } else {
            since_least += 1;
        }
        if options.patience > 0 && since_least >= options.patience {
            tracing::debug!(rounds = round + 1, "the fit settled");
            break;
        }
    }
    Ok(fitted)
}

fn distance(a: [f32; 3], b: [f32; 3]) -> f32 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f32>().sqrt()
}

/// What corners are fitted to, prepared once for every round and every mesh fitted to the
/// same cloud (a reconstruction's candidates): its points, their unit normals (estimated when
/// the cloud has none; zero where a given one is) and their k-d tree, and the bounds corners
/// stay in (the cloud's, widened by `BOUNDS_MARGIN` of its spacing).
///
/// Every point pulls, if not in every round (see `POINTS_PER_ROUND`).
pub struct FitTarget {
    points: Vec<[f32; 3]>,
    normals: Vec<[f32; 3]>,
    tree: ImmutableKdTree<f32, 3>,
    lo: [f32; 3],
    hi: [f32; 3],
    /// The points' mean distance to their nearest neighbour ([`spacing`]).
    spacing: f32,
}

impl FitTarget {
    /// Errors for an empty or invalid cloud (see [`Mesh::validate`]).
    pub fn new(cloud: &Mesh) -> Result<Self, MeshError> {
        cloud.validate()?;
        let points = cloud.vertices.clone();
        let Some((lo, hi)) = bounds(&points) else {
            return Err(MeshError::invalid("no points to fit the mesh to"));
        };
        let normals = match &cloud.normals {
            Some(normals) => normals.iter().map(|&n| normalized(n)).collect(),
            None => {
                estimate_normals(&points, NORMAL_NEIGHBOURS).into_iter().map(normalized).collect()
            }
        };
        let tree = tree_of(&points)?;
        let spacing = spacing(&points, &tree);
        Ok(Self { points, normals, tree, lo, hi, spacing })
    }

    /// This target with only every `step`-th of its points (the same bounds): a cheaper,
    /// rougher fit.
    pub fn thinned(&self, step: usize) -> Result<Self, MeshError> {
        let every = |set: &[[f32; 3]]| -> Vec<[f32; 3]> {
            set.iter().step_by(step.max(1)).copied().collect()
        };
        let points = every(&self.points);
        let tree = tree_of(&points)?;
        Ok(Self { normals: every(&self.normals), points, tree, ..*self })
    }

    /// How far past the points' bounds a fitted corner may go ([`BOUNDS_MARGIN`] spacings).
    fn margin(&self) -> f32 {
        BOUNDS_MARGIN * self.spacing
    }

    /// The points' mean distance to their nearest neighbour.
    pub fn spacing(&self) -> f32 {
        self.spacing
    }

    /// How far `p` lies from the nearest of the points.
    pub fn distance_to(&self, p: [f32; 3]) -> f32 {
        self.tree.query(&p).nearest_one::<SquaredEuclidean<f32>>().execute().distance.sqrt()
    }
}

/// The mean distance of `points` (in `tree`) to their nearest neighbour (over up to
/// [`SPACING_PROBES`] of them, evenly taken); 0 for a single point.
fn spacing(points: &[[f32; 3]], tree: &ImmutableKdTree<f32, 3>) -> f32 {
    let probes: Vec<[f32; 3]> =
        points.iter().step_by(points.len().div_ceil(SPACING_PROBES)).copied().collect();
    let two = NonZeroUsize::new(2).unwrap_or(NonZeroUsize::MIN);
    // The nearest of a point is itself; the second is its neighbour.
    let nearest = tree.query_batch(&probes).nearest_n::<SquaredEuclidean<f32>>(two).execute();
    let distances: Vec<f32> = (0..probes.len())
        .filter_map(|i| nearest.get(i)?.get(1).map(|n| n.distance.sqrt()))
        .collect();
    match distances.len() {
        0 => 0.0,
        n => distances.iter().sum::<f32>() / n as f32,
    }
}

/// Every corner's least-squares problem in one round: the shift `s` that best moves the
/// samples on its faces (each by its barycentric weight b of `s`) along their pulls,
/// `A s = r`. Solved per corner rather than as a mean pull because a corner is pulled along
/// different normals by its different faces: on a box's corner each side's samples decide
/// one axis, where a mean would let the settled sides dilute the pull of the one still off.
struct Pulls {
    a: Vec<Mat3>,
    r: Vec<[f32; 3]>,
}

impl Pulls {
    fn of(
        mesh: &Mesh,
        samples: &[SurfaceSample],
        target: &FitTarget,
        round: usize,
    ) -> Result<Self, MeshError> {
        let (points, normals) = (target.points.as_slice(), &target.normals);
        let n = mesh.vertices.len();
        let mut pulls = Pulls { a: vec![[[0.0; 3]; 3]; n], r: vec![[0.0; 3]; n] };
        let positions: Vec<[f32; 3]> = samples.iter().map(|s| s.position(mesh)).collect();
        // The two directions weigh alike, however many samples and points each has.
        let per_sample = 1.0 / samples.len() as f32;
        for (i, nearest) in nearest_in(&target.tree, &positions).into_iter().enumerate() {
            let to = (points[nearest], normals[nearest]);
            pulls.add(mesh, &samples[i], positions[i], to, per_sample);
        }
        let share: Vec<usize> = pulling_points(points.len(), round).collect();
        let queries: Vec<[f32; 3]> = share.iter().map(|&j| points[j]).collect();
        let per_point = 1.0 / share.len().max(1) as f32;
        let sample_tree = tree_of(&positions)?;
        for (&j, nearest) in share.iter().zip(nearest_in(&sample_tree, &queries)) {
            let to = (points[j], normals[j]);
            pulls.add(mesh, &samples[nearest], positions[nearest], to, per_point);
        }
        Ok(pulls)
    }

    /// `sample`, at `from`, is pulled with weight `w` towards the point `to` (with its unit
    /// normal; a zero normal pulls straight at the point): onto the point's tangent plane, and
    /// [`TANGENTIAL_SHARE`] of the rest of the way, i.e. by `M d` with
    /// `M = t I + (1 - t) n n^T` and `d = to - from`.
    fn add(
        &mut self,
        mesh: &Mesh,
        sample: &SurfaceSample,
        from: [f32; 3],
        (to, normal): ([f32; 3], [f32; 3]),
        w: f32,
    ) {
        let t = TANGENTIAL_SHARE;
        let m: Mat3 = std::array::from_fn(|i| {
            std::array::from_fn(|j| {
                (1.0 - t) * normal[i] * normal[j] + if i == j { t } else { 0.0 }
            })
        });
        let pull = mat_vec(&m, std::array::from_fn(|k| to[k] - from[k]));
        for (corner, &bary) in mesh.faces[sample.face].iter().zip(&sample.weights) {
            let (v, b) = (*corner as usize, w * bary as f32);
            for ((r, a), (pull, m)) in
                self.r[v].iter_mut().zip(&mut self.a[v]).zip(pull.iter().zip(&m))
            {
                *r += b * pull;
                for (a, m) in a.iter_mut().zip(m) {
                    *a += b * m;
                }
            }
        }
    }

    /// Each corner's shift; `None` for a corner nothing pulled.
    fn shifts(&self) -> Vec<Option<[f32; 3]>> {
        self.a.iter().zip(&self.r).map(|(a, r)| solve(a, *r)).collect()
    }
}

/// `x` with `a x = r` for a symmetric positive semi-definite `a`; `None` when `a` is 0 or
/// singular.
fn solve(a: &Mat3, r: [f32; 3]) -> Option<[f32; 3]> {
    // Scaled to a unit trace first: the entries are sums of tiny weights.
    let trace = a[0][0] + a[1][1] + a[2][2];
    if trace <= 0.0 {
        return None;
    }
    let a = a.map(|row| row.map(|x| x / trace));
    let det = determinant(&a);
    // M's smallest eigenvalue is t, so a sum of them has a determinant of at least t^3 / 27
    // at unit trace; far below that, rounding has made it singular.
    if det <= 1e-9 {
        return None;
    }
    // a is symmetric, so its cofactor matrix is the transpose of its adjugate as well.
    let x = mat_vec(&cofactor(&a), r);
    Some(x.map(|c| c / (det * trace)))
}

/// The input points that pull in `round` of a fit to `count` of them: all of them up to
/// [`POINTS_PER_ROUND`], else every k-th from a start that moves on by one each round.
fn pulling_points(count: usize, round: usize) -> std::iter::StepBy<std::ops::Range<usize>> {
    let step = count.div_ceil(POINTS_PER_ROUND).max(1);
    (round % step..count).step_by(step)
}

fn tree_of(set: &[[f32; 3]]) -> Result<ImmutableKdTree<f32, 3>, MeshError> {
    ImmutableKdTree::new_from_slice(set)
        .map_err(|e| MeshError::invalid(format!("too many points to fit to: {e}")))
}

/// For each of `queries`, the index of its nearest point in `tree`.
fn nearest_in(tree: &ImmutableKdTree<f32, 3>, queries: &[[f32; 3]]) -> Vec<usize> {
    let nearest = tree.query_batch(queries).nearest_one::<SquaredEuclidean<f32>>().execute();
    nearest.iter().map(|n| n.item as usize).collect()
}

/// `p` moved back towards `origin` until it is at most `radius` away.
fn within(origin: [f32; 3], p: [f32; 3], radius: f32) -> [f32; 3] {
    let d: [f32; 3] = std::array::from_fn(|k| p[k] - origin[k]);
    let length = d.iter().map(|c| c * c).sum::<f32>().sqrt();
    if length <= radius {
        return p;
    }
    std::array::from_fn(|k| origin[k] + d[k] * radius / length)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::cuboid;
    use crate::mesh::sample_surface;
    use crate::metrics::point_set_distances;

    /// Chamfer distance between two surfaces, densely sampled.
    fn chamfer(a: &Mesh, b: &Mesh) -> f64 {
        let dense = |m: &Mesh, seed| sample_surface(m, 20_000, seed).unwrap().vertices;
        point_set_distances(&dense(a, 3), &dense(b, 4)).chamfer
    }

    #[test]
    fn a_box_a_little_off_fits_its_points() {
        let truth = cuboid([1.0, 0.6, 0.8]);
        let off = cuboid([0.94, 0.65, 0.8]).translated([0.02, 0.0, -0.01]);
        // Also with more points than pull in one round.
        for points in [1024, 4 * POINTS_PER_ROUND + 3] {
            let cloud = sample_surface(&truth, points, 1).unwrap();
            let fitted = fit_to_points(&off, &cloud, &FitOptions::default(), 0).unwrap();
            assert_eq!(fitted.faces, off.faces);
            for (v, w) in fitted.vertices.iter().zip(&truth.vertices) {
                for k in 0..3 {
                    assert!((v[k] - w[k]).abs() < 0.01, "{points} points: corner {v:?}, not {w:?}");
                }
            }
            let (before, after) = (chamfer(&off, &truth), chamfer(&fitted, &truth));
            assert!(after < 0.5 * before, "{points} points: Chamfer distance {before}, {after}");
        }
    }

    #[test]
    fn every_point_pulls_once_in_as_many_rounds_as_it_takes_shares() {
        for count in [0, 1, POINTS_PER_ROUND, POINTS_PER_ROUND + 1, 16_384, 50_001] {
            let step = count.div_ceil(POINTS_PER_ROUND).max(1);
            let mut pulled = vec![0; count];
            for round in 7..7 + step {
                let share: Vec<usize> = pulling_points(count, round).collect();
                assert!(share.len() <= POINTS_PER_ROUND, "{count} points: {} pull", share.len());
                share.into_iter().for_each(|j| pulled[j] += 1);
            }
            assert!(pulled.iter().all(|&n| n == 1), "{count} points");
        }
    }

    #[test]
    fn corners_move_at_most_max_shift() {
        let cloud = sample_surface(&cuboid([2.0; 3]), 1024, 1).unwrap();
        let small = cuboid([0.5; 3]);
        let options = FitOptions { max_shift: 0.05, ..FitOptions::default() };
        let fitted = fit_to_points(&small, &cloud, &options, 0).unwrap();
        for (v, w) in fitted.vertices.iter().zip(&small.vertices) {
            let d = (0..3).map(|k| (v[k] - w[k]).powi(2)).sum::<f32>().sqrt();
            assert!(d <= 0.05 + 1e-6, "moved {d}");
            assert!(d > 0.04, "moved only {d} towards points 0.75 away");
        }
    }

    /// The bounds of `cloud` and `mesh` together, widened by [`BOUNDS_MARGIN`] spacings.
    fn widened_bounds(cloud: &Mesh, mesh: &Mesh) -> ([f32; 3], [f32; 3]) {
        let margin = FitTarget::new(cloud).unwrap().margin();
        let all = [cloud.vertices.as_slice(), &mesh.vertices].concat();
        let (lo, hi) = crate::mesh::bounds(&all).unwrap();
        (lo.map(|c| c - margin), hi.map(|c| c + margin))
    }

    #[test]
    fn corners_stay_within_the_points_and_the_mesh() {
        // A long thin slab across a small box's points: pulled onto the box's side planes,
        // its ends would slide out along them.
        let cloud = sample_surface(&cuboid([0.4; 3]), 1024, 1).unwrap();
        let slab = cuboid([1.6, 0.1, 0.1]).translated([0.0, 0.5, 0.0]);
        let fitted = fit_to_points(&slab, &cloud, &FitOptions::default(), 0).unwrap();
        let (lo, hi) = widened_bounds(&cloud, &slab);
        for v in &fitted.vertices {
            assert!((0..3).all(|k| lo[k] <= v[k] && v[k] <= hi[k]), "{v:?} out of {lo:?}..{hi:?}");
        }
    }

    #[test]
    fn an_apex_above_the_highest_point_is_reached() {
        // A square pyramid, apex at y = 0.8, seen through 120 points: the highest lies well
        // below the apex, and a decoder placed the apex at that height.
        let base = [[-0.8, -0.5, -0.8], [0.8, -0.5, -0.8], [0.8, -0.5, 0.8], [-0.8, -0.5, 0.8]];
        let pyramid = |apex: f32| {
            let mut vertices = base.to_vec();
            vertices.push([0.0, apex, 0.0]);
            let faces = vec![[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]];
            Mesh::new(vertices, faces)
        };
        let cloud = sample_surface(&pyramid(0.8), 120, 5).unwrap();
        let highest = cloud.vertices.iter().map(|p| p[1]).fold(f32::MIN, f32::max);
        assert!(highest < 0.75, "the points reach {highest}");
        let fitted = fit_to_points(&pyramid(highest), &cloud, &FitOptions::default(), 0).unwrap();
        let apex = fitted.vertices[4][1];
        assert!(apex > highest + 0.5 * (0.8 - highest), "apex at {apex}, points to {highest}");
    }

    #[test]
    fn a_fit_ends_once_its_corners_stop_moving_less() {
        let cloud = sample_surface(&cuboid([1.0, 0.6, 0.8]), 1024, 1).unwrap();
        let off = cuboid([0.94, 0.65, 0.8]);
        let fit = |rounds, patience| {
            let options = FitOptions { rounds, patience, ..FitOptions::default() };
            fit_to_points(&off, &cloud, &options, 0).unwrap()
        };
        // A box settles in a few rounds; with no patience every round runs.
        let settled = (1..=40).find(|&rounds| fit(rounds, 0) == fit(40, 5));
        assert!(settled.is_some_and(|r| r < 30), "settled after {settled:?} rounds");
        assert_ne!(fit(40, 0), fit(40, 5));
        assert_eq!(fit(40, PATIENCE), fit(40, 0), "the default runs every round");
        // Settled, the fit is as good as all 40 rounds.
        for (a, b) in fit(40, 5).vertices.iter().zip(&fit(40, 0).vertices) {
            assert!(distance(*a, *b) < 0.005, "{a:?} against {b:?}");
        }
    }

    proptest::proptest! {
        /// Any mesh, any points and normals: no panic, and every corner finite, within bounds.
        #[test]
        fn any_input_fits_without_panic_inside_the_bounds(
            corners in proptest::collection::vec(proptest::array::uniform3(-1.0f32..1.0), 3..12),
            faces in proptest::collection::vec(proptest::array::uniform3(0u32..12), 1..16),
            points in proptest::collection::vec(proptest::array::uniform3(-2.0f32..2.0), 1..40),
            normals in proptest::collection::vec(proptest::array::uniform3(-1e3f32..1e3), 40),
        ) {
            let n = corners.len() as u32;
            let faces = faces.into_iter().map(|f| f.map(|i| i % n)).collect();
            let mesh = Mesh::new(corners, faces);
            let normals = normals[..points.len()].to_vec();
            let cloud = Mesh { vertices: points, faces: vec![], normals: Some(normals) };
            let options = FitOptions { rounds: 3, samples: 64, ..FitOptions::default() };
            if let Ok(fitted) = fit_to_points(&mesh, &cloud, &options, 0) {
                let (lo, hi) = widened_bounds(&cloud, &mesh);
                proptest::prop_assert_eq!(&fitted.faces, &mesh.faces);
                for v in &fitted.vertices {
                    proptest::prop_assert!((0..3).all(|k| lo[k] <= v[k] && v[k] <= hi[k]));
                }
            }
        }
    }

    #[test]
    fn no_points_or_no_area_is_an_error() {
        let m = cuboid([1.0; 3]);
        let options = FitOptions::default();
        assert!(fit_to_points(&m, &Mesh::default(), &options, 0).is_err());
        let flat = Mesh::new(vec![[0.0; 3]; 3], vec![[0, 1, 2]]);
        let one_point = Mesh::new(vec![[0.0; 3]], vec![]);
        assert!(fit_to_points(&flat, &one_point, &options, 0).is_err());
    }
}
