//! Best-of-N and fitted requests (`DecodeOptions::candidates`, `fit_rounds`): the candidates
//! run as ordinary requests, batched with everything else, and a task streams the one closest
//! to the input points once all have finished (see `crate::candidates`), its corners fitted to
//! those points when asked. Its faces therefore arrive together at the end, not one by one.

use std::time::Instant;

use futures_util::future::join_all;
use tokio::sync::mpsc;

use crate::candidates::{candidate_sampling, closest_to_input, fitted_mesh};
use crate::mesh::{FitOptions, Mesh};
use crate::model::FaceToken;
use crate::tokenize::{Quantizer, face_positions};

use super::{
    Completed, Conditioning, Engine, EngineError, Event, Request, RequestStream, StreamedFace,
};

/// Submits `n` candidates of `request` (a points request, checked by the caller) and returns
/// the stream of the one that fits the input's reference points best. Refused as a whole when any
/// candidate is (the others are then cancelled). Needs a tokio runtime for its task.
pub(super) fn submit(
    engine: &Engine,
    request: Request,
    n: usize,
) -> Result<RequestStream, EngineError> {
    let Conditioning::Points(prepared) = &request.conditioning else {
        return Err(EngineError::InvalidInput(
            "candidates are judged against input points: an image request takes 1".into(),
        ));
    };
    let runtime = tokio::runtime::Handle::try_current()
        .map_err(|_| EngineError::Unsupported("best-of-N requests need a tokio runtime".into()))?;
    let cloud = prepared.reference.clone();
    let fit = match request.options.fit_rounds.unwrap_or(0) {
        0 => None,
        rounds => Some(FitOptions { rounds, ..FitOptions::default() }),
    };
    let normalization = prepared.normalization;
    let seed = request.options.sampling.seed;
    let started = Instant::now();
    let candidates = candidate_sampling(&request.options.sampling, n)
        .into_iter()
        .enumerate()
        .map(|(i, sampling)| {
            let mut candidate = request.clone();
            candidate.id = format!("{}/candidate-{i}", request.id);
            candidate.options.sampling = sampling;
            candidate.options.candidates = None;
            candidate.options.fit_rounds = None;
            engine.submit_one(candidate)
        })
        .collect::<Result<Vec<_>, _>>()?;
    let (tx, rx) = mpsc::channel(engine.shared.config.stream_buffer);
    let q = engine.quantizer;
    runtime.spawn(async move {
        let finished = tokio::select! {
            all = join_all(candidates.into_iter().map(RequestStream::collect)) => all,
            // The client left: dropping the candidates' streams cancels them.
            () = tx.closed() => return,
        };
        // Judging and fitting are CPU work: off the async runtime.
        let chosen = tokio::task::spawn_blocking(move || {
            let best = pick(finished, q, &cloud.vertices, seed)?;
            let corners = corners(&best.tokens, q, &cloud, fit.as_ref(), seed);
            Ok((best, corners))
        })
        .await
        .unwrap_or_else(|e| Err(EngineError::Model(format!("choosing a candidate failed: {e}"))));
        let event = match chosen {
            Ok((mut best, corners)) => {
                for (index, (&token, corners)) in best.tokens.iter().zip(corners).enumerate() {
                    let vertices = corners.map(|p| normalization.invert(p));
                    let face = StreamedFace { index, token, vertices };
                    if tx.send(Event::Face(face)).await.is_err() {
                        return;
                    }
                }
                // The request as the client saw it: every face came at the end.
                best.summary.total = started.elapsed();
                best.summary.time_to_first_face = Some(best.summary.total);
                Event::Finished(best.summary)
            }
            Err(e) => Event::Failed(e),
        };
        let _ = tx.send(event).await;
    });
    Ok(RequestStream::new(request.id, rx))
}

/// The corners of `tokens`' faces (normalized frame), fitted to `cloud` when `fit` is given.
fn corners(
    tokens: &[FaceToken],
    q: Quantizer,
    cloud: &Mesh,
    fit: Option<&FitOptions>,
    seed: u64,
) -> Vec<[[f32; 3]; 3]> {
    match fit {
        None => tokens.iter().map(|t| face_positions(t, q)).collect(),
        Some(fit) => {
            let mesh = fitted_mesh(tokens, q, cloud, fit, seed);
            mesh.faces.iter().map(|f| mesh.triangle(f)).collect()
        }
    }
}

/// The finished candidate closest to `points` (the first on ties); the first error when none
/// finished.
fn pick(
    finished: Vec<Result<Completed, EngineError>>,
    q: Quantizer,
    points: &[[f32; 3]],
    seed: u64,
) -> Result<Completed, EngineError> {
    let (completed, failed): (Vec<_>, Vec<_>) = finished.into_iter().partition(Result::is_ok);
    let mut completed: Vec<Completed> = completed.into_iter().flatten().collect();
    let faces = completed.iter().map(|c| c.tokens.as_slice());
    match closest_to_input(faces, q, points, seed) {
        Some(best) => Ok(completed.swap_remove(best)),
        None => Err(failed.into_iter().find_map(Result::err).unwrap_or(EngineError::Stopped)),
    }
}
