//! Best-of-N reconstruction: decode several meshes, each from its own draw of the input's
//! points, and keep the one that ends closest to the input points.
//!
//! Why: a reconstruction has a verifier that generation from an image lacks, its own input.
//! Greedy decoding often ends a mesh early or takes a wrong turn, and what it decodes depends
//! on where the encoder's points fall; a few alternatives, judged by their Chamfer distance
//! to the input points, recover much of that (measured in `docs/decisions.md`, "Decoding").
//! The candidates decode as one batch, so N of them cost less than N single decodes.

use std::sync::Arc;

use candle_core::Tensor;
use rayon::prelude::*;

use crate::baseline::{convex_hull, simplify_to_budget, simplify_within};
use crate::mesh::{
    FitOptions, FitTarget, Mesh, fit_to_target, sample_surface, with_faces_facing_out,
    with_small_holes_filled, without_folded_faces, without_stray_parts, without_stray_sheets,
};
use crate::metrics::point_set_distances;
use crate::model::{
    FaceModel, FaceToken, FinishReason, GenerateOptions, Generation, ModelError, SamplingParams,
    step_generations,
};
use crate::tokenize::{
    Quantizer, canonical_triangulation_near_grid, detokenize, weld_near_corners,
};

/// The most candidates a reconstruction may ask for: each is a decoder row.
pub const MAX_CANDIDATES: usize = 16;

/// Candidates of a reconstruction that does not say and whose faces nobody watches arrive: the
/// CLI's, and HTTP requests answered with a whole mesh (a server setting). Four cost about
/// twice one decode and take a fifth off the dev split's Chamfer distance (the model card).
pub const DEFAULT_CANDIDATES: usize = 4;

/// Corners a whole mesh's candidates merge when within this many grid cells of each other, when
/// a request does not say (a server setting for HTTP whole meshes; streams keep their faces as
/// decoded): one cell closes the cracks the shipped model leaves between faces that should
/// share a corner (`docs/decisions.md`, "Welding").
pub const DEFAULT_WELD_RADIUS: u16 = 1;

/// The most faces of the convex hull a fitted reconstruction judges beside its decoded
/// candidates, when the server or the CLI does not say ([`hull_candidate`]): about as many as
/// the shipped model's answers have (on the dev split 99.2 faces a mesh with it, 96.4
/// without; 200 came a little closer for a third more faces, `docs/decisions.md`, "The convex
/// hull as a candidate").
pub const DEFAULT_HULL_FACES: usize = 100;

/// The widest weld a request may ask for: past a few cells welding flattens small parts.
pub const MAX_WELD_RADIUS: u16 = 4;

/// How a reconstruction ends each candidate before judging it: its corners welded, then
/// fitted to the input points (and the winner's folded faces, stray parts and sheets dropped).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Ending {
    /// Corners within this many grid cells merge, and faces split at corners this close to
    /// their open edges ([`weld_near_corners`]); 0 keeps them apart.
    pub weld_radius: u16,
    /// Fitting to the input points, after which the winner drops its folded faces and the
    /// parts and sheets the points do not need ([`without_folded_faces`],
    /// [`without_stray_parts`], [`without_stray_sheets`]); `None` keeps the corners on the
    /// grid and every face.
    pub fit: Option<FitOptions>,
    /// A fitted winner's loops of at most this many open edges are closed where the input
    /// points cover them ([`with_small_holes_filled`]); below 3 none are.
    pub max_hole_edges: usize,
    /// A candidate that is not decoded joins the others: the convex hull of the input points
    /// on the grid, with at most this many faces ([`hull_candidate`]); `None` for none.
    pub hull_faces: Option<usize>,
}

impl Ending {
    /// The hull's faces for an ending with `fit`, a setting of `hull_faces` (0: never) and a
    /// request's `face_budget`: only beside fitted candidates, since unfitted ones are the
    /// model's as decoded, and never past the budget.
    pub fn hull_faces_for(
        fit: Option<FitOptions>,
        hull_faces: usize,
        face_budget: usize,
    ) -> Option<usize> {
        (fit.is_some() && hull_faces > 0).then_some(hull_faces.min(face_budget))
    }
}

/// Points sampled on each candidate's surface to compare it with the input points.
const FIT_SAMPLES: usize = 4096;

/// Candidates are judged after a cheaper fit than the one their winner gets: against every
/// this-many-th reference point, with fewer samples ([`JUDGING_SAMPLE_STEP`]), for
/// [`JUDGING_ROUNDS_SHARE`] of the rounds, and only the winner's fit then goes on in full. Why:
/// fitting every candidate in full cost more than decoding them (`docs/decisions.md`,
/// "Fitting").
const JUDGING_POINT_STEP: usize = 4;

/// Candidates are judged after a fit with this-many-times fewer surface samples a round: with
/// [`JUDGING_POINT_STEP`], its points' matching of the samples had become most of the cost.
const JUDGING_SAMPLE_STEP: usize = 4;

/// The share of a request's fit rounds a candidate gets before it is judged.
const JUDGING_ROUNDS_SHARE: f32 = 0.5;

/// One decoded mesh.
#[derive(Debug, Clone, PartialEq)]
pub struct Candidate {
    pub faces: Vec<FaceToken>,
    pub finish: FinishReason,
}

/// The sampling of `n` candidates: the first is `base` itself. A greedy `base` makes every
/// candidate greedy, each reading its own draw of the input's points (see
/// [`crate::mesh::input_clouds`]); a sampling one makes the second greedy and the others
/// sample at its temperature with the seeds after its own.
///
/// Why: greedy decoding rebuilds simple shapes best, and which faces it finds depends on
/// where the encoder's points fall: fitted, four greedy decodes of four draws rebuilt 702 of
/// 710 boxes, prisms and pyramids where the greedy one plus three samples rebuilt 631. On real
/// meshes samples cover more but make a soup of slivers, hence the greedy default
/// (`docs/decisions.md`, "Decoding").
pub fn candidate_sampling(base: &SamplingParams, n: usize) -> Vec<SamplingParams> {
    let greedy = SamplingParams { temperature: 0.0, ..base.clone() };
    (0..n.max(1))
        .map(|i| match i {
            0 => base.clone(),
            _ if base.temperature == 0.0 => greedy.clone(),
            1 => greedy.clone(),
            i => SamplingParams { seed: base.seed.wrapping_add(i as u64), ..base.clone() },
        })
        .collect()
}

/// The options of `n` candidates: `base` with each of [`candidate_sampling`].
pub fn candidate_options(base: &GenerateOptions, n: usize) -> Vec<GenerateOptions> {
    candidate_sampling(&base.sampling, n)
        .into_iter()
        .map(|sampling| GenerateOptions { sampling, ..base.clone() })
        .collect()
}

/// Decodes one candidate per options in one batch, candidate `i` from `latents[i % len]`
/// (each (K, latent_dim): one per draw of the input's points); `on_face` sees every face of
/// every candidate as it is decoded.
pub fn decode_candidates(
    model: &FaceModel,
    latents: &[Tensor],
    options: Vec<GenerateOptions>,
    mut on_face: impl FnMut(),
) -> Result<Vec<Candidate>, ModelError> {
    if !(1..=MAX_CANDIDATES).contains(&options.len()) || latents.is_empty() {
        return Err(ModelError::BadInput(format!(
            "{} candidates from {} latent sets: a reconstruction takes 1..={MAX_CANDIDATES} \
             from at least one",
            options.len(),
            latents.len()
        )));
    }
    let mut gens = options
        .into_iter()
        .enumerate()
        .map(|(i, o)| Generation::new(model, &latents[i % latents.len()], o))
        .collect::<Result<Vec<_>, _>>()?;
    while gens.iter().any(|g| !g.is_finished()) {
        let mut rows: Vec<&mut Generation> = gens.iter_mut().collect();
        for event in step_generations(model, &mut rows)? {
            if event.face.is_some() {
                on_face();
            }
        }
    }
    Ok(gens
        .into_iter()
        .map(|g| Candidate {
            faces: g.faces().to_vec(),
            finish: g.finish_reason().unwrap_or(FinishReason::Cancelled),
        })
        .collect())
}

/// How far `mesh` is from the input `points` (normalized frame): the Chamfer distance between
/// them and points sampled on its faces. Infinite for a mesh without area.
pub fn input_distance(mesh: &Mesh, points: &[[f32; 3]], seed: u64) -> f64 {
    match sample_surface(mesh, FIT_SAMPLES, seed) {
        Ok(samples) => point_set_distances(&samples.vertices, points).chamfer,
        Err(_) => f64::INFINITY,
    }
}

/// A candidate as a reconstruction ends it.
#[derive(Debug, Clone, PartialEq)]
pub struct Finished {
    /// Its place among the candidates.
    pub index: usize,
    /// Its faces as decoded and welded (normalized frame, on the grid).
    pub decoded: Mesh,
    /// What the reconstruction returns: `decoded` fitted to the input ([`fitted_mesh`]), or
    /// `decoded` itself when not fitted.
    pub mesh: Mesh,
    /// How far it ends from the input points ([`input_distance`]); 0 when it is not judged.
    pub distance: f64,
}

/// The convex hull candidate ended and judged ([`Judge::end_hull`]).
#[derive(Debug, Clone)]
pub struct EndedHull {
    /// The form of the hull that answers if the hull wins.
    pub finished: Finished,
    /// How far its closest form ends from the input points: what decoded candidates are
    /// measured against ([`hull_wins`]), so that the lighter form changes how the hull
    /// answers, never whether.
    pub closest: f64,
}

/// How one reconstruction ends its candidates (welded, then fitted to its input points when
/// asked) and judges them: prepared once, so that every candidate fits to the same prepared
/// points, and each candidate can be ended on its own as soon as it is decoded ([`Self::end`]).
/// When several are compared, each is judged after a cheaper fit and only the winner's fit
/// goes on in full ([`Self::finish`]; see `JUDGING_POINT_STEP`).
pub struct Judge {
    q: Quantizer,
    cloud: Arc<Mesh>,
    ending: Ending,
    /// The prepared cloud when fitting; `None` also for a cloud that cannot be fitted to
    /// (the candidates then end as decoded).
    target: Option<FitTarget>,
    /// What candidates are fitted to before they are judged: `target` thinned.
    judging_target: Option<FitTarget>,
    seed: u64,
    /// One candidate has nothing to be compared with, and is not judged.
    compare: bool,
}

impl Judge {
    /// For `candidates` candidates judged against `cloud` (normalized frame) with `seed`.
    pub fn new(
        q: Quantizer,
        cloud: Arc<Mesh>,
        ending: Ending,
        seed: u64,
        candidates: usize,
    ) -> Self {
        let compare = candidates > 1;
        let target = ending.fit.and_then(|_| match FitTarget::new(&cloud) {
            Ok(target) => Some(target),
            Err(e) => {
                tracing::debug!("the candidates are not fitted: {e}");
                None
            }
        });
        let judging_target = match &target {
            Some(target) if compare => target.thinned(JUDGING_POINT_STEP).ok(),
            _ => None,
        };
        Self { q, cloud, ending, target, judging_target, seed, compare }
    }

    /// Candidate `index` with `faces`, ended and judged: fitted as it is judged when several
    /// are compared (the winner then goes to [`Self::finish`]), else fitted in full.
    pub fn end(&self, index: usize, faces: &[FaceToken]) -> Finished {
        let decoded = detokenize(&weld_near_corners(faces, self.ending.weld_radius), self.q);
        self.end_mesh(index, decoded)
    }

    /// The convex hull candidate ([`hull_candidate`]) ended and judged as candidate `index`,
    /// and its lighter form ([`lighter_hull`]) beside it, which is kept unless the full hull
    /// ends closer by the margin ([`HULL_MARGIN`]); `None` when not asked for or when the
    /// points span no volume.
    pub fn end_hull(&self, index: usize) -> Option<EndedHull> {
        let hull = hull_candidate(&self.cloud, self.q, self.ending.hull_faces?)?;
        let light = lighter_hull(&hull);
        let full = self.end_mesh(index, hull);
        let closest = full.distance;
        let finished = match light.map(|light| self.end_mesh(index, light)) {
            Some(light) if !closer_by_margin(full.distance, light.distance) => light,
            _ => full,
        };
        Some(EndedHull { finished, closest })
    }

    /// Candidate `index`, decoded (and welded) as `decoded`, ended and judged.
    fn end_mesh(&self, index: usize, decoded: Mesh) -> Finished {
        let started = std::time::Instant::now();
        let faces = decoded.faces.len();
        let judging = self.ending.fit.map(|fit| FitOptions {
            rounds: judging_rounds(&fit),
            samples: (fit.samples / JUDGING_SAMPLE_STEP).max(1),
            ..fit
        });
        let mesh = match (self.compare, &judging, &self.judging_target) {
            (true, Some(fit), Some(target)) => {
                fitted_mesh(&decoded, self.q, target, fit, self.seed)
            }
            (true, _, _) => decoded.clone(),
            (false, _, _) => self.fitted(&decoded),
        };
        let fitted = started.elapsed();
        let distance =
            if self.compare { input_distance(&mesh, &self.cloud.vertices, self.seed) } else { 0.0 };
        tracing::debug!(
            index,
            faces,
            distance,
            fit_ms = fitted.as_secs_f64() * 1e3,
            judge_ms = (started.elapsed() - fitted).as_secs_f64() * 1e3,
            "candidate ended"
        );
        Finished { index, decoded, mesh, distance }
    }

    /// The candidate that won, as it is returned: when it was judged after the cheaper fit,
    /// its fit goes on from there against every point for the rounds that fit left.
    ///
    /// Why go on rather than fit its decoded corners afresh: the cheaper fit has already
    /// done most of the moving, and refitting cost about as much as fitting all candidates.
    ///
    /// A fitted winner then loses the faces that lie on other faces ([`without_folded_faces`])
    /// and the parts and sheets its input points do not need ([`without_stray_parts`],
    /// [`without_stray_sheets`]), has its small holes closed ([`with_small_holes_filled`])
    /// and its faces turned to face out ([`with_faces_facing_out`]).
    pub fn finish(&self, winner: Finished) -> Finished {
        let finished = self.finish_fit(winner);
        match (&self.ending.fit, &self.target) {
            (Some(_), Some(target)) => {
                let unfolded = without_folded_faces(&finished.mesh);
                let kept = without_stray_parts(&unfolded, &self.cloud.vertices, self.seed);
                let kept = without_stray_sheets(&kept, &self.cloud.vertices, self.seed);
                let (closed, holes) =
                    with_small_holes_filled(&kept, target, self.ending.max_hole_edges);
                // Last, so that the faces that closed holes turn with their surfaces.
                let (mesh, turned) = with_faces_facing_out(&closed);
                tracing::debug!(holes, turned, "small holes filled, faces turned out");
                Finished { mesh, ..finished }
            }
            _ => finished,
        }
    }

    /// The winner's fit, gone on or done in full.
    fn finish_fit(&self, winner: Finished) -> Finished {
        match (self.compare, &self.ending.fit, &self.target, &self.judging_target) {
            (true, Some(fit), Some(target), Some(_)) => {
                let done = judging_rounds(fit);
                let rest = FitOptions { rounds: fit.rounds.saturating_sub(done).max(1), ..*fit };
                // Rounds draw their samples from the seed plus their number: these go on.
                let seed = self.seed.wrapping_add(done as u64);
                Finished { mesh: fitted_mesh(&winner.mesh, self.q, target, &rest, seed), ..winner }
            }
            (true, ..) => Finished { mesh: self.fitted(&winner.decoded), ..winner },
            (false, ..) => winner,
        }
    }

    /// `decoded` fitted in full when fitting, else as it is.
    fn fitted(&self, decoded: &Mesh) -> Mesh {
        match (&self.ending.fit, &self.target) {
            (Some(fit), Some(target)) => fitted_mesh(decoded, self.q, target, fit, self.seed),
            _ => decoded.clone(),
        }
    }
}

/// The rounds of a fit with `fit`'s options that a candidate gets before it is judged.
fn judging_rounds(fit: &FitOptions) -> usize {
    ((fit.rounds as f32 * JUDGING_ROUNDS_SHARE).ceil() as usize).max(1)
}

/// The finished candidate closest to the input points: the first (lowest index) on ties.
pub fn closest(finished: impl IntoIterator<Item = Finished>) -> Option<Finished> {
    finished.into_iter().reduce(|best, next| {
        let nearer = (next.distance, next.index) < (best.distance, best.index);
        if nearer { next } else { best }
    })
}

/// Ends each candidate as `ending` says (welded, then fitted to `cloud` when asked) and keeps
/// the one that ends closest to the cloud's points (the first on ties); `None` for none.
///
/// Why judged once fitted: a decoded corner sits on the grid, often a step or more off, so
/// judged as decoded the pick weighed that noise as much as the faces; judged as they end,
/// four candidates took the dev split from 0.037 to 0.030 (`docs/decisions.md`, "Decoding").
pub fn closest_finished<'a>(
    candidates: impl ExactSizeIterator<Item = &'a [FaceToken]>,
    q: Quantizer,
    cloud: &Mesh,
    ending: &Ending,
    seed: u64,
) -> Option<Finished> {
    // The hull is judged with the decoded candidates: one of those alone is compared with it.
    let judged = candidates.len() + usize::from(ending.hull_faces.is_some());
    let judge = Judge::new(q, Arc::new(cloud.clone()), *ending, seed, judged);
    // Each candidate's fit and judgement is its own: they run in parallel.
    let candidates: Vec<&[FaceToken]> = candidates.collect();
    let hull = candidates.len();
    let (ended, hull): (Vec<Finished>, _) = rayon::join(
        || candidates.into_par_iter().enumerate().map(|(i, faces)| judge.end(i, faces)).collect(),
        || judge.end_hull(hull),
    );
    let best = closest(ended)?;
    let winner = match hull {
        Some(hull) if hull_wins(&hull, &best) => hull.finished,
        _ => best,
    };
    Some(judge.finish(winner))
}

/// The convex hull candidate wins only when it ends this share closer to the input points than
/// the closest decoded candidate, and the full hull only when it ends this share closer than
/// its lighter form. Why: where the two are about as close, the other is the lighter,
/// artist-like mesh (a box of 12 faces against a hull of 100 with bevelled corners); on the
/// dev split the margin took the hull's wins from 111 to 73 for the same closeness
/// (`docs/decisions.md`, "The convex hull as a candidate").
pub const HULL_MARGIN: f64 = 0.1;

/// Whether distance `a` to the input points is closer than `b` by [`HULL_MARGIN`].
fn closer_by_margin(a: f64, b: f64) -> bool {
    a < (1.0 - HULL_MARGIN) * b
}

/// Whether the `hull` candidate, ended and judged, is the answer rather than the closest
/// `decoded` one: when its closest form is closer by [`HULL_MARGIN`].
pub fn hull_wins(hull: &EndedHull, decoded: &Finished) -> bool {
    closer_by_margin(hull.closest, decoded.distance)
}

/// How far (meshoptimizer's relative error, a share of the hull's extent) the lighter form of
/// the hull may lie from the full one: about one cell of the shipped model's grid (128 cells
/// across an extent of 2). Why: points on a flat side snap to the grid within half a cell of
/// it, and the hull of them covers the side with slivers that follow that noise; within a cell,
/// a side is one polygon again.
const HULL_FLATNESS: f32 = 0.01;

/// The convex hull of `cloud`'s points with its corners on grid `q`, brought down to at most
/// `max_faces` faces: a closed candidate that convex inputs (rocks, gems, barrels) are often
/// closest to, where the model's decodes leave holes. `None` when the points span no volume.
pub fn hull_candidate(cloud: &Mesh, q: Quantizer, max_faces: usize) -> Option<Mesh> {
    let on_grid: Vec<[f32; 3]> =
        cloud.vertices.iter().map(|p| p.map(|c| q.dequantize(q.quantize(c)))).collect();
    let hull = convex_hull(&on_grid).ok()?;
    simplify_to_budget(&hull, max_faces).ok()
}

/// `hull` with its flat sides' slivers collapsed ([`HULL_FLATNESS`]); `None` when that drops
/// no face.
pub fn lighter_hull(hull: &Mesh) -> Option<Mesh> {
    let light = simplify_within(hull, hull.faces.len(), HULL_FLATNESS).ok()?;
    (light.faces.len() < hull.faces.len()).then_some(light)
}

/// The `decoded` mesh (normalized frame) with its corners fitted to the input `target` (see
/// [`fit_to_target`]) and its flat polygons split again for the moved corners (see
/// [`canonical_triangulation_near_grid`]; vertices keep their order). A mesh with no area
/// has nothing to fit and comes as decoded.
pub fn fitted_mesh(
    decoded: &Mesh,
    q: Quantizer,
    target: &FitTarget,
    options: &FitOptions,
    seed: u64,
) -> Mesh {
    match fit_to_target(decoded, target, options, seed) {
        Ok(fitted) => canonical_triangulation_near_grid(&fitted, q),
        Err(e) => {
            tracing::debug!("the mesh is not fitted: {e}");
            decoded.clone()
        }
    }
}

/// Decodes a candidate per options (see [`candidate_options`]; candidate `i` from
/// `latents[i % len]`) and returns the one that ends closest to the input `cloud` (see
/// [`closest_finished`]; judged with the first options' seed) with how it ends, placed on
/// grid `q`; `on_face` sees every decoded face.
pub fn best_of(
    model: &FaceModel,
    latents: &[Tensor],
    options: Vec<GenerateOptions>,
    cloud: &Mesh,
    ending: &Ending,
    q: Quantizer,
    on_face: impl FnMut(),
) -> Result<(Option<Candidate>, Mesh), ModelError> {
    let seed = options.first().map_or(0, |o| o.sampling.seed);
    let mut candidates = decode_candidates(model, latents, options, on_face)?;
    let faces = candidates.iter().map(|c| c.faces.as_slice());
    let best = closest_finished(faces, q, cloud, ending, seed)
        .ok_or_else(|| ModelError::BadInput("no candidates".into()))?;
    // The hull comes after the decoded candidates.
    let winner = (best.index < candidates.len()).then(|| candidates.swap_remove(best.index));
    Ok((winner, best.mesh))
}

#[cfg(test)]
mod tests {
    use std::ops::ControlFlow;

    use super::*;
    use crate::mesh::primitives::cuboid;
    use crate::model::FaceConfig;
    use crate::model::testing::{random_latents, random_model};
    use crate::tokenize::tokenize;

    #[test]
    fn greedy_requests_decode_every_candidate_greedily_and_sampled_ones_add_one_greedy() {
        let base = GenerateOptions { face_beam: 2, ..GenerateOptions::default() };
        // Greedy: every candidate as asked (each reads its own draw of the points).
        assert_eq!(candidate_options(&base, 3), vec![base.clone(); 3]);
        // Sampled: one greedy candidate, second; the rest sample as the request does, with
        // the seeds after its own.
        let mut sampled = base.clone();
        sampled.sampling.temperature = 0.8;
        sampled.sampling.seed = 10;
        let options = candidate_options(&sampled, 4);
        let temperatures: Vec<f32> = options.iter().map(|o| o.sampling.temperature).collect();
        assert_eq!(temperatures, [0.8, 0.0, 0.8, 0.8]);
        let seeds: Vec<u64> = options.iter().map(|o| o.sampling.seed).collect();
        assert_eq!(seeds, [10, 10, 12, 13]);
        assert!(options.iter().all(|o| o.face_beam == 2));
        assert_eq!(candidate_options(&sampled, 1), [sampled]);
        assert_eq!(candidate_options(&base, 0), [base]);
    }

    #[test]
    fn candidates_decode_as_they_would_alone_each_from_its_own_latents() {
        let mut cfg = FaceConfig::micro();
        cfg.quant_levels = 128;
        let (_, model) = random_model(&cfg);
        let latents = [random_latents(&cfg, 1, 5), random_latents(&cfg, 1, 6)];
        let mut base = GenerateOptions { max_faces: 12, ..GenerateOptions::default() };
        base.sampling.temperature = 1.0;
        let options = candidate_options(&base, 3);
        let mut seen = 0;
        let candidates =
            decode_candidates(&model, &latents, options.clone(), || seen += 1).unwrap();
        assert_eq!(candidates.len(), 3);
        assert_eq!(seen, candidates.iter().map(|c| c.faces.len()).sum::<usize>());
        for (i, (c, o)) in candidates.iter().zip(options).enumerate() {
            let alone =
                crate::model::generate(&model, &latents[i % 2], o, |_| ControlFlow::Continue(()))
                    .unwrap();
            assert_eq!((&c.faces, c.finish), (&alone.0, alone.1), "candidate {i}");
        }
        for n in [0, MAX_CANDIDATES + 1] {
            let options = vec![base.clone(); n];
            assert!(decode_candidates(&model, &latents, options, || ()).is_err(), "{n}");
        }
        let one = vec![base];
        assert!(decode_candidates(&model, &[], one, || ()).is_err());
    }

    /// The 128-level grid, points on a cube's surface, and the cube's faces on the grid.
    fn cube_and_its_points() -> (Quantizer, Mesh, Vec<FaceToken>) {
        let q = Quantizer::new(128).unwrap();
        let cube = cuboid([1.6, 1.6, 1.6]);
        (q, sample_surface(&cube, 4096, 3).unwrap(), tokenize(&cube, q).faces)
    }

    #[test]
    fn the_candidate_that_ends_closest_to_the_input_points_wins() {
        let (q, cloud, whole) = cube_and_its_points();
        // Half a cube, the whole cube, and nothing at all.
        let candidates = [&whole[..6], &whole[..], &[]];
        let as_decoded = Ending::default();
        let best = closest_finished(candidates.into_iter(), q, &cloud, &as_decoded, 0).unwrap();
        assert_eq!(best.index, 1);
        assert_eq!(best.mesh, best.decoded);
        assert!(input_distance(&best.mesh, &cloud.vertices, 0) < 0.1);
        assert_eq!(input_distance(&detokenize(&[], q), &cloud.vertices, 0), f64::INFINITY);
        assert_eq!(closest_finished(std::iter::empty(), q, &cloud, &as_decoded, 0), None);
        // A whole cube decoded a fifth too small, and the right one with one side half
        // missing: as decoded the second is closer, fitted (as the reconstruction ends them)
        // the first, which ends closer than the second as decoded.
        let small = tokenize(&cuboid([1.28, 1.28, 1.28]), q).faces;
        let holed = &whole[..whole.len() - 1];
        let candidates = [&small[..], holed];
        let judge =
            |ending| closest_finished(candidates.into_iter(), q, &cloud, &ending, 0).unwrap();
        let decoded = judge(as_decoded);
        assert_eq!(decoded.index, 1);
        let fitted = judge(Ending { fit: Some(FitOptions::default()), ..as_decoded });
        assert_eq!(fitted.index, 0);
        let distance = |mesh: &Mesh| input_distance(mesh, &cloud.vertices, 0);
        assert!(distance(&fitted.mesh) < distance(&decoded.mesh));
        // One candidate is not judged: it ends as it is, whatever it is.
        let alone = closest_finished([&[][..]].into_iter(), q, &cloud, &as_decoded, 0).unwrap();
        assert_eq!(alone.index, 0);
    }

    #[test]
    fn the_hull_of_the_points_is_closed_on_the_grid_and_within_its_faces() {
        let (q, cloud, _) = cube_and_its_points();
        let hull = hull_candidate(&cloud, q, 40).unwrap();
        assert!(hull.faces.len() <= 40 && hull.faces.len() >= 12, "{}", hull.faces.len());
        // Its lighter form: about the cube's 12 faces.
        let light = lighter_hull(&hull).unwrap();
        assert!(light.faces.len() <= 16, "{}", light.faces.len());
        let distance = |mesh: &Mesh| input_distance(mesh, &cloud.vertices, 0);
        let cube = distance(&cuboid([1.6; 3]));
        let on_grid = |c: f32| q.dequantize(q.quantize(c)) == c;
        for hull in [hull, light] {
            let quality = crate::metrics::MeshQuality::measure(&hull, None);
            assert!(quality.watertight, "{quality:?}");
            // As close to the points as the cube they were sampled on.
            assert!(distance(&hull) < 1.05 * cube, "{} against {cube}", distance(&hull));
            assert!(hull.vertices.iter().flatten().all(|&c| on_grid(c)));
        }
        let flat = Mesh::new(cloud.vertices.iter().map(|p| [p[0], p[1], 0.0]).collect(), vec![]);
        assert_eq!(hull_candidate(&flat, q, 40), None, "flat points have no hull");
    }

    #[test]
    fn the_hull_answers_in_its_lighter_form_unless_the_full_one_ends_closer_by_the_margin() {
        let q = Quantizer::new(128).unwrap();
        let ended = |shape: &Mesh| {
            let cloud = sample_surface(shape, 16384, 3).unwrap();
            let fitted = Ending {
                fit: Some(FitOptions::default()),
                hull_faces: Some(100),
                ..Ending::default()
            };
            let judge = Judge::new(q, Arc::new(cloud), fitted, 0, 2);
            judge.end_hull(0).unwrap()
        };
        // A slab: its lighter form is a box of 12 faces, as close as the full hull.
        let slab = ended(&cuboid([2.0, 2.0, 0.06]));
        assert!(slab.finished.decoded.faces.len() <= 12, "{}", slab.finished.decoded.faces.len());
        // A thin spindle: collapsed within a cell, its round sides end a fifth further.
        let mut spindle = crate::mesh::primitives::uv_sphere(1.0, 64, 32);
        for v in &mut spindle.vertices {
            (v[0], v[2]) = (0.1 * v[0], 0.1 * v[2]);
        }
        let spindle = ended(&spindle);
        assert_eq!(spindle.finished.decoded.faces.len(), 100);
        assert_eq!(spindle.closest, spindle.finished.distance);
    }

    #[test]
    fn the_hull_wins_where_it_ends_closer_than_every_decoded_candidate() {
        let (q, cloud, whole) = cube_and_its_points();
        let half = &whole[..6];
        let fitted = Ending { fit: Some(FitOptions::default()), ..Ending::default() };
        let with_hull = Ending { hull_faces: Some(40), ..fitted };
        let judged = |ending| closest_finished([half].into_iter(), q, &cloud, &ending, 0).unwrap();
        let best = judged(with_hull);
        assert_eq!(best.index, 1, "the hull comes after the decoded candidates");
        // In its lighter form, as close as the full one.
        assert!(best.mesh.faces.len() <= 16, "{}", best.mesh.faces.len());
        let distance = |mesh: &Mesh| input_distance(mesh, &cloud.vertices, 0);
        assert!(distance(&best.mesh) < 1.05 * distance(&cuboid([1.6; 3])));
        assert_eq!(judged(fitted).index, 0, "without the hull the half cube is all there is");
    }

    #[test]
    fn candidates_are_judged_after_a_cheaper_fit_and_the_winner_s_fit_goes_on_in_full() {
        let q = Quantizer::new(128).unwrap();
        let cloud = sample_surface(&cuboid([1.6, 1.6, 1.6]), 4096, 3).unwrap();
        let small = tokenize(&cuboid([1.28, 1.28, 1.28]), q).faces;
        // Half a cube: no fit covers the other half.
        let half = &tokenize(&cuboid([1.6, 1.6, 1.6]), q).faces[..6];
        let fit = FitOptions::default();
        let ending = Ending { fit: Some(fit), ..Ending::default() };
        let judge = Judge::new(q, Arc::new(cloud.clone()), ending, 0, 2);
        let ended = [judge.end(0, &small), judge.end(1, half)];
        let target = FitTarget::new(&cloud).unwrap();
        let in_full = |f: &Finished| fitted_mesh(&f.decoded, q, &target, &fit, 0);
        // Judged as the cheaper fit left them: not the full fit.
        assert!(ended.iter().all(|f| f.mesh != in_full(f)));
        let winner = closest(ended.clone()).unwrap();
        assert_eq!(winner.index, 0);
        let finished = judge.finish(winner.clone());
        // The rounds the cheaper fit left, against every point, from where it ended.
        let done = judging_rounds(&fit);
        let rest = FitOptions { rounds: fit.rounds - done, ..fit };
        assert_eq!(finished.mesh, fitted_mesh(&winner.mesh, q, &target, &rest, done as u64));
        let distance = |m: &Mesh| input_distance(m, &cloud.vertices, 0);
        assert!(distance(&finished.mesh) < distance(&winner.mesh));
        assert_eq!((finished.index, finished.distance), (winner.index, winner.distance));
        let best = closest_finished([&small[..], half].into_iter(), q, &cloud, &ending, 0);
        assert_eq!(best, Some(finished));
        // Alone, a candidate is fitted in full as it ends.
        let alone = Judge::new(q, Arc::new(cloud.clone()), ending, 0, 1);
        let ended = alone.end(0, &small);
        assert_eq!(ended.mesh, in_full(&ended));
        assert_eq!(alone.finish(ended.clone()), ended);
    }

    #[test]
    fn the_closest_wins_and_the_first_on_ties_in_any_order_of_finishing() {
        let q = Quantizer::new(128).unwrap();
        let finished = |index, distance| Finished {
            index,
            decoded: detokenize(&[], q),
            mesh: detokenize(&[], q),
            distance,
        };
        let pick = |all: Vec<Finished>| closest(all).map(|f| f.index);
        assert_eq!(pick(vec![finished(2, 0.5), finished(1, 0.3), finished(0, 0.3)]), Some(0));
        assert_eq!(pick(vec![finished(0, f64::INFINITY), finished(1, 0.9)]), Some(1));
        assert_eq!(pick(vec![]), None);
    }

    #[test]
    fn a_fitted_winner_loses_the_parts_its_points_do_not_need() {
        let (q, cloud, whole) = cube_and_its_points();
        // Its bottom decoded again two cells below it: a layer of its own over the surface,
        // which no point needs once fitted.
        let bottom = whole.iter().map(|f| f[0]).min().unwrap();
        let layer = whole.iter().filter(|f| [f[0], f[3], f[6]] == [bottom; 3]).map(|f| {
            let mut lower = *f;
            for k in [0, 3, 6] {
                lower[k] -= 2;
            }
            lower
        });
        let mut cluttered: Vec<FaceToken> = whole.iter().copied().chain(layer).collect();
        cluttered.sort_unstable();
        let end = |fit| {
            let ending = Ending { weld_radius: 0, fit, ..Ending::default() };
            closest_finished([&cluttered[..]].into_iter(), q, &cloud, &ending, 0).unwrap()
        };
        let fitted = end(Some(FitOptions::default()));
        assert_eq!(fitted.mesh.faces.len(), whole.len());
        assert_eq!(crate::metrics::topology(&fitted.mesh).parts, 1);
        // Unfitted, the mesh is the decoded one, layer and all.
        assert_eq!(end(None).mesh.faces.len(), cluttered.len());
    }

    #[test]
    fn candidates_are_welded_before_they_are_fitted_and_judged() {
        let (q, cloud, whole) = cube_and_its_points();
        // One face's corner a cell off: a crack the weld closes, so fitting moves that corner
        // once for every face on it.
        let mut cracked = whole.clone();
        cracked[5][3..6].iter_mut().for_each(|c| *c -= 1);
        let ending = |weld_radius| Ending {
            weld_radius,
            fit: Some(FitOptions::default()),
            ..Ending::default()
        };
        let end = |weld| closest_finished([&cracked[..]].into_iter(), q, &cloud, &ending(weld), 0);
        let welded = end(1).unwrap();
        assert_eq!(welded.decoded, detokenize(&whole, q));
        assert_eq!(crate::metrics::topology(&welded.mesh).boundary_edges, 0);
        let apart = end(0).unwrap();
        assert!(crate::metrics::topology(&apart.mesh).boundary_edges > 0);
    }
}
