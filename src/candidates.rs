//! Best-of-N reconstruction: decode several meshes from the same latents and keep the one
//! closest to the input points.
//!
//! Why: a reconstruction has a verifier that generation from an image lacks, its own input.
//! Greedy decoding often ends a mesh early or takes a wrong turn; a few sampled alternatives,
//! judged by their Chamfer distance to the input points, recover much of that (measured in
//! `docs/decisions.md`, "Decoding"). The candidates decode as one batch, so N of them cost
//! less than N single decodes.

use candle_core::Tensor;

use crate::mesh::{FitOptions, Mesh, fit_to_points, sample_surface};
use crate::metrics::point_set_distances;
use crate::model::{
    FaceModel, FaceToken, FinishReason, GenerateOptions, Generation, ModelError, SamplingParams,
    step_generations,
};
use crate::tokenize::{Quantizer, canonical_triangulation_near_grid, detokenize};

/// The most candidates a reconstruction may ask for: each is a decoder row.
pub const MAX_CANDIDATES: usize = 16;

/// The sampling temperature of the alternatives to a greedy decode (chosen on the tuning
/// shapes of `scripts/sweep-face-beam.sh`, see `docs/decisions.md`): hotter candidates differ
/// more from the greedy one, so the pick has more to choose from.
pub const CANDIDATE_TEMPERATURE: f32 = 1.2;

/// Candidates of a reconstruction that does not say and whose faces nobody watches arrive: the
/// CLI's, and HTTP requests answered with a whole mesh (a server setting). Four cost about
/// twice one decode and take a fifth off the dev split's Chamfer distance (the model card).
pub const DEFAULT_CANDIDATES: usize = 4;

/// Points sampled on each candidate's surface to compare it with the input points.
const FIT_SAMPLES: usize = 4096;

/// One decoded mesh.
#[derive(Debug, Clone, PartialEq)]
pub struct Candidate {
    pub faces: Vec<FaceToken>,
    pub finish: FinishReason,
}

/// The sampling of `n` candidates: the first is `base` itself; one is greedy (the second,
/// when `base` samples); the others sample with seeds after `base`'s, at `base`'s
/// temperature, or at [`CANDIDATE_TEMPERATURE`] when `base` is greedy.
///
/// Why a greedy one always: greedy decoding rebuilds simple shapes best and sampling the
/// rest; judged against the points, the pick takes whichever fits. On the tuning shapes
/// (`docs/decisions.md`, "Decoding") four candidates scored 0.134 with one greedy and 0.156
/// with four sampled.
pub fn candidate_sampling(base: &SamplingParams, n: usize) -> Vec<SamplingParams> {
    let temperature = match base.temperature {
        0.0 => CANDIDATE_TEMPERATURE,
        t => t,
    };
    let greedy = SamplingParams { temperature: 0.0, ..base.clone() };
    (0..n.max(1))
        .map(|i| match i {
            0 => base.clone(),
            1 if base.temperature > 0.0 => greedy.clone(),
            i => SamplingParams {
                temperature,
                seed: base.seed.wrapping_add(i as u64),
                ..base.clone()
            },
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

/// Decodes one candidate per options, all from `latents` ((K, latent_dim)), in one batch;
/// `on_face` sees every face of every candidate as it is decoded.
pub fn decode_candidates(
    model: &FaceModel,
    latents: &Tensor,
    options: Vec<GenerateOptions>,
    mut on_face: impl FnMut(),
) -> Result<Vec<Candidate>, ModelError> {
    if !(1..=MAX_CANDIDATES).contains(&options.len()) {
        return Err(ModelError::BadInput(format!(
            "{} candidates: a reconstruction takes 1..={MAX_CANDIDATES}",
            options.len()
        )));
    }
    let mut gens = options
        .into_iter()
        .map(|o| Generation::new(model, latents, o))
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

/// How far a candidate is from the input `points` (normalized frame): the Chamfer distance
/// between them and points sampled on its faces. Infinite for a candidate without area.
pub fn input_distance(faces: &[FaceToken], q: Quantizer, points: &[[f32; 3]], seed: u64) -> f64 {
    match sample_surface(&detokenize(faces, q), FIT_SAMPLES, seed) {
        Ok(samples) => point_set_distances(&samples.vertices, points).chamfer,
        Err(_) => f64::INFINITY,
    }
}

/// The index of the face sequence closest to `points` (the first on ties); `None` for none.
pub fn closest_to_input<'a>(
    candidates: impl ExactSizeIterator<Item = &'a [FaceToken]>,
    q: Quantizer,
    points: &[[f32; 3]],
    seed: u64,
) -> Option<usize> {
    if candidates.len() == 1 {
        return Some(0); // nothing to compare
    }
    let distances: Vec<f64> =
        candidates.map(|faces| input_distance(faces, q, points, seed)).collect();
    (0..distances.len()).min_by(|&a, &b| distances[a].total_cmp(&distances[b]))
}

/// The `decoded` mesh (normalized frame) with its corners fitted to the input `cloud` (see
/// [`fit_to_points`]) and its flat polygons split again for the moved corners (see
/// [`canonical_triangulation_near_grid`]; vertices keep their order): how a reconstruction
/// ends, once its candidate is chosen. A mesh with no area has nothing to fit and comes as
/// decoded.
pub fn fitted_mesh(
    decoded: &Mesh,
    q: Quantizer,
    cloud: &Mesh,
    options: &FitOptions,
    seed: u64,
) -> Mesh {
    match fit_to_points(decoded, cloud, options, seed) {
        Ok(fitted) => canonical_triangulation_near_grid(&fitted, q),
        Err(e) => {
            tracing::debug!("the mesh is not fitted: {e}");
            decoded.clone()
        }
    }
}

/// Decodes `n` candidates from options `base` (see [`candidate_options`]) and returns the one
/// closest to the input `points`, placed on grid `q`; `on_face` sees every decoded face.
pub fn best_of(
    model: &FaceModel,
    latents: &Tensor,
    base: &GenerateOptions,
    n: usize,
    points: &[[f32; 3]],
    q: Quantizer,
    on_face: impl FnMut(),
) -> Result<Candidate, ModelError> {
    let mut candidates = decode_candidates(model, latents, candidate_options(base, n), on_face)?;
    let faces = candidates.iter().map(|c| c.faces.as_slice());
    let best = closest_to_input(faces, q, points, base.sampling.seed).unwrap_or(0);
    Ok(candidates.swap_remove(best))
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
    fn the_first_candidate_is_the_request_and_the_others_sample() {
        let base = GenerateOptions { face_beam: 2, ..GenerateOptions::default() };
        let options = candidate_options(&base, 3);
        assert_eq!(options[0], base);
        for (i, o) in options.iter().enumerate().skip(1) {
            assert_eq!(o.sampling.temperature, CANDIDATE_TEMPERATURE);
            assert_eq!(o.sampling.seed, i as u64);
            assert_eq!(o.face_beam, 2);
        }
        // A sampled request gets one greedy candidate, second; the rest sample as it does.
        let mut sampled = base.clone();
        sampled.sampling.temperature = 0.8;
        let temperatures: Vec<f32> =
            candidate_options(&sampled, 4).iter().map(|o| o.sampling.temperature).collect();
        assert_eq!(temperatures, [0.8, 0.0, 0.8, 0.8]);
        assert_eq!(candidate_options(&sampled, 1), [sampled]);
        assert_eq!(candidate_options(&base, 0), [base]);
    }

    #[test]
    fn candidates_decode_as_they_would_alone() {
        let mut cfg = FaceConfig::micro();
        cfg.quant_levels = 128;
        let (_, model) = random_model(&cfg);
        let latents = random_latents(&cfg, 1, 5);
        let base = GenerateOptions { max_faces: 12, ..GenerateOptions::default() };
        let options = candidate_options(&base, 3);
        let mut seen = 0;
        let candidates =
            decode_candidates(&model, &latents, options.clone(), || seen += 1).unwrap();
        assert_eq!(candidates.len(), 3);
        assert_eq!(seen, candidates.iter().map(|c| c.faces.len()).sum::<usize>());
        for (c, o) in candidates.iter().zip(options) {
            let (faces, finish) =
                crate::model::generate(&model, &latents, o, |_| ControlFlow::Continue(())).unwrap();
            assert_eq!((&c.faces, c.finish), (&faces, finish));
        }
        for n in [0, MAX_CANDIDATES + 1] {
            let options = vec![base.clone(); n];
            assert!(decode_candidates(&model, &latents, options, || ()).is_err(), "{n}");
        }
    }

    #[test]
    fn the_candidate_closest_to_the_input_points_wins() {
        let q = Quantizer::new(128).unwrap();
        let cube = cuboid([1.6, 1.6, 1.6]);
        let points = sample_surface(&cube, 1024, 3).unwrap().vertices;
        let whole = tokenize(&cube, q).faces;
        let candidate = |faces: &[FaceToken]| Candidate {
            faces: faces.to_vec(),
            finish: FinishReason::EndOfMesh,
        };
        // Half a cube, the whole cube, and nothing at all.
        let candidates = [candidate(&whole[..6]), candidate(&whole), candidate(&[])];
        let faces = candidates.iter().map(|c| c.faces.as_slice());
        assert_eq!(closest_to_input(faces, q, &points, 0), Some(1));
        assert!(input_distance(&whole, q, &points, 0) < 0.1);
        assert_eq!(input_distance(&[], q, &points, 0), f64::INFINITY);
        assert_eq!(closest_to_input(std::iter::empty(), q, &points, 0), None);
    }
}
