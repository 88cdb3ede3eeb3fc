//! Best-of-N, welded and fitted requests (`DecodeOptions::candidates`, `weld_radius`,
//! `fit_rounds`): the candidates run as ordinary requests, each reading its own draw of the
//! input's points, batched with everything else, and a task streams the one that ends closest
//! to the input points once all have finished (see `crate::candidates`), its near corners
//! welded and its corners fitted to those points when asked. Its faces therefore arrive
//! together at the end, not one by one; with `DecodeOptions::drafts` the first candidate's
//! faces come before them as they are decoded.

use std::sync::Arc;
use std::time::Instant;

use futures_util::future::join_all;
use tokio::sync::mpsc;

use crate::candidates::{EndedHull, Ending, Finished, Judge, candidate_sampling, hull_wins};
use crate::mesh::{DEFAULT_MAX_HOLE_EDGES, FitOptions};
use crate::model::{FaceToken, FinishReason};
use crate::tokenize::{Quantizer, canonical_face, canonical_start};

use super::offload::off_runtime;
use super::{
    Completed, Conditioning, DecodeOptions, Engine, EngineError, Event, Request, RequestStream,
    StreamedFace,
};

/// Submits `n` candidates of `request` (a points request, checked by the caller) and returns
/// the stream of the one that ends closest to the input's reference points. Refused as a
/// whole when any candidate is (the others are then cancelled). Needs a tokio runtime for its
/// task.
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
    let face_budget = request.options.max_faces.unwrap_or_else(|| engine.face_limit());
    let ending = Ending {
        weld_radius: request.options.weld_radius.unwrap_or(0),
        fit,
        max_hole_edges: request.options.max_hole_edges.unwrap_or(DEFAULT_MAX_HOLE_EDGES),
        hull_faces: Ending::hull_faces_for(
            fit,
            request.options.hull_faces.unwrap_or(engine.shared.config.hull_faces),
            face_budget,
        ),
    };
    let judged = n + usize::from(ending.hull_faces.is_some());
    let normalization = prepared.normalization;
    let (seed, drafts) = (request.options.sampling.seed, request.options.drafts);
    let started = Instant::now();
    let candidates = candidate_sampling(&request.options.sampling, n)
        .into_iter()
        .enumerate()
        .map(|(i, sampling)| {
            // Built, not cloned from the request: its conditioning carries every draw.
            engine.submit_one(Request {
                id: format!("{}/candidate-{i}", request.id),
                conditioning: Conditioning::Points(prepared.for_candidate(i)),
                options: DecodeOptions {
                    sampling,
                    candidates: None,
                    fit_rounds: None,
                    weld_radius: None,
                    max_hole_edges: None,
                    hull_faces: None,
                    drafts: false,
                    ..request.options.clone()
                },
                deadline: request.deadline,
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    let (tx, rx) = mpsc::channel(engine.shared.config.stream_buffer);
    let q = engine.quantizer;
    let metrics = Arc::clone(&engine.shared.metrics);
    runtime.spawn(async move {
        // Prepared while the candidates decode.
        let prepared = off_runtime(&metrics, move || Judge::new(q, cloud, ending, seed, judged));
        let judge = match prepared.await {
            Ok(judge) => Arc::new(judge),
            Err(e) => {
                let _ = tx.send(Event::Failed(e)).await;
                return;
            }
        };
        // Each candidate is ended as soon as it is decoded, while the others still decode.
        let ended = candidates.into_iter().enumerate().map(|(index, candidate)| {
            let (judge, metrics) = (judge.clone(), Arc::clone(&metrics));
            // The first candidate's faces go to a client who asked for drafts as they come;
            // one that is behind misses some rather than hold the decoding up.
            let drafts = (drafts && index == 0).then(|| tx.clone());
            async move {
                let completed = candidate
                    .collect_watching(|face| {
                        if let Some(tx) = &drafts {
                            let _ = tx.try_send(Event::Draft(face.clone()));
                        }
                    })
                    .await?;
                off_runtime(&metrics, move || {
                    let finished = judge.end(index, &completed.tokens);
                    (completed, finished)
                })
                .await
            }
        });
        let ended = tokio::select! {
            all = join_all(ended) => all,
            // The client left: dropping the candidates' streams cancels them.
            () = tx.closed() => return,
        };
        let hull = {
            let judge = judge.clone();
            off_runtime(&metrics, move || judge.end_hull(n)).await
        };
        // The winner's fit goes on in full: every candidate was judged after a cheaper fit.
        let won = match (pick(ended), hull) {
            (Ok((best, ended)), Ok(hull)) => {
                let (best, ended) = closer_of(best, ended, hull);
                off_runtime(&metrics, move || (best, judge.finish(ended))).await
            }
            (Err(e), _) | (_, Err(e)) => Err(e),
        };
        let event = match won {
            Ok((mut best, ended)) => {
                let faces = ended_faces(&ended, q);
                // Ending may drop faces (stray parts): the answer is what is streamed.
                best.summary.faces = faces.len();
                for (index, (token, corners)) in faces.into_iter().enumerate() {
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

/// The faces to stream for a candidate as it `ended`: each face's grid cells and its corners
/// (normalized frame). A fitted mesh keeps the decoded one's vertices in order (its flat
/// polygons split again, [`crate::candidates::fitted_mesh`]), so a face's cells are those its
/// fitted corners were decoded (and welded) at; an unfitted one is the decoded mesh itself.
fn ended_faces(ended: &Finished, q: Quantizer) -> Vec<(FaceToken, [[f32; 3]; 3])> {
    let (decoded, mesh) = (&ended.decoded, &ended.mesh);
    let cell = |v: u32| decoded.vertices.get(v as usize).map(|p| p.map(|c| q.quantize(c)));
    mesh.faces
        .iter()
        .filter_map(|face| {
            let cells = [cell(face[0])?, cell(face[1])?, cell(face[2])?];
            let (token, first) = (canonical_face(cells)?, canonical_start(cells)?);
            let corners = mesh.triangle(face);
            Some((token, std::array::from_fn(|i| corners[(first + i) % 3])))
        })
        .collect()
}

/// The decoded winner, or the convex hull candidate when that ended closer to the input
/// points by the margin ([`hull_wins`]), its summary's finish reason then saying so.
fn closer_of(best: Completed, ended: Finished, hull: Option<EndedHull>) -> (Completed, Finished) {
    match hull {
        Some(hull) if hull_wins(&hull, &ended) => {
            let mut best = best;
            best.summary.finish = FinishReason::ConvexHull;
            (best, hull.finished)
        }
        _ => (best, ended),
    }
}

/// The candidate that ended closest to the input points (the first on ties) and how it
/// ended; the first error when none finished.
fn pick(
    ended: Vec<Result<(Completed, Finished), EngineError>>,
) -> Result<(Completed, Finished), EngineError> {
    let mut first_error = None;
    let mut best: Option<(Completed, Finished)> = None;
    for result in ended {
        match result {
            Ok(next) => {
                let nearer = |b: &Finished| (next.1.distance, next.1.index) < (b.distance, b.index);
                if best.as_ref().is_none_or(|(_, b)| nearer(b)) {
                    best = Some(next);
                }
            }
            Err(e) => {
                first_error.get_or_insert(e);
            }
        }
    }
    best.ok_or_else(|| first_error.unwrap_or(EngineError::Stopped))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::candidates::closest_finished;
    use crate::mesh::primitives::{cuboid, cuboid_split};
    use crate::mesh::sample_surface;
    use crate::tokenize::{canonical_triangulation, face_positions};

    #[test]
    fn fitted_faces_stream_with_the_truths_splits_and_their_own_cells() {
        let q = Quantizer::default();
        let truth = cuboid([2.0, 1.2, 0.8]);
        let cloud = sample_surface(&truth, 4096, 0).unwrap();
        let faces_of = |corners: &mut dyn Iterator<Item = [[f32; 3]; 3]>| {
            let mut tokens: Vec<FaceToken> = corners
                .map(|c| canonical_face(c.map(|p| p.map(|x| q.quantize(x)))).unwrap())
                .collect();
            tokens.sort_unstable();
            tokens
        };
        let right = canonical_triangulation(&truth, q);
        let expected = faces_of(&mut right.faces.iter().map(|f| right.triangle(f)));
        // Decoded a little small.
        let small: Vec<[f32; 3]> = truth.vertices.iter().map(|v| v.map(|c| c * 0.97)).collect();
        for diagonals in 0..64u32 {
            let faces = cuboid_split([2.0, 1.2, 0.8], diagonals).faces;
            // As a model may decode them: each side split as it comes, not as training splits.
            let cell = |v: u32| small[v as usize].map(|c| q.quantize(c));
            let decoded: Vec<FaceToken> = faces
                .iter()
                .map(|&[a, b, c]| canonical_face([cell(a), cell(b), cell(c)]).unwrap())
                .collect();
            let ending =
                Ending { weld_radius: 0, fit: Some(FitOptions::default()), ..Ending::default() };
            let ended = closest_finished([&decoded[..]].into_iter(), q, &cloud, &ending, 0);
            let streamed = ended_faces(&ended.unwrap(), q);
            assert_eq!(faces_of(&mut streamed.iter().map(|(_, c)| *c)), expected, "{diagonals}");
            for (token, corners) in &streamed {
                // The token is the face on the decoded grid, corner for corner.
                let cells = face_positions(token, q);
                for (cell, corner) in cells.iter().zip(corners) {
                    let gap = (0..3).map(|i| (cell[i] - corner[i]).abs()).fold(0.0, f32::max);
                    assert!(gap < 0.06, "{diagonals}: {token:?} against {corners:?}");
                }
            }
        }
    }
}
