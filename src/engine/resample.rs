//! Image requests whose mesh comes out empty are sampled again (`EngineConfig::image_attempts`).
//! The image model's sample sometimes lands where the decoder ends at once: 4 of the 220 dev
//! pictures at one seed, which decode to a mesh at another. The next attempt starts the
//! sampler from the next seed (so a request stays reproducible) and is queued behind the
//! requests already waiting; its diffusion progress is streamed again from step 1. An
//! attempt that ends with faces, fails, or is the last is what the client gets.

use std::time::Instant;

use tokio::sync::mpsc;

use super::{Conditioning, Engine, EngineError, Event, Request, RequestStream, Summary};

/// Submits `request` (an image request, checked by the caller) for up to `attempts` samples.
/// Needs a tokio runtime for the task that forwards the attempts' events.
pub(super) fn submit(
    engine: &Engine,
    request: Request,
    attempts: usize,
) -> Result<RequestStream, EngineError> {
    let runtime = tokio::runtime::Handle::try_current().map_err(|_| {
        EngineError::Unsupported("resampled image requests need a tokio runtime".into())
    })?;
    let started = Instant::now();
    let mut stream = engine.submit_one(request.clone())?;
    let (tx, rx) = mpsc::channel(engine.shared.config.stream_buffer);
    let engine = engine.clone();
    let id = request.id.clone();
    runtime.spawn(async move {
        for attempt in 1.. {
            let attempt_started = Instant::now();
            let last = loop {
                let event = tokio::select! {
                    event = stream.next() => event.unwrap_or(Event::Failed(EngineError::Stopped)),
                    // The client left: dropping the attempt's stream cancels it.
                    () = tx.closed() => return,
                };
                match event {
                    Event::Finished(summary) => break summary,
                    Event::Failed(e) => {
                        let _ = tx.send(Event::Failed(e)).await;
                        return;
                    }
                    event => {
                        if tx.send(event).await.is_err() {
                            return;
                        }
                    }
                }
            };
            let next = (last.faces == 0 && attempt < attempts)
                .then(|| engine.submit_one(next_attempt(&request, attempt)));
            match next {
                Some(Ok(next)) => {
                    engine.shared.metrics.image_resamples.inc();
                    stream = next;
                }
                // Faces, or none and no further attempt (or none accepted): the answer.
                _ => {
                    let summary = as_requested(last, started, attempt_started);
                    let _ = tx.send(Event::Finished(summary)).await;
                    return;
                }
            }
        }
    });
    Ok(RequestStream::new(id, rx))
}

/// Attempt `attempt` (from 1) of `request`: its sampler's seed moved on by as much.
pub(super) fn next_attempt(request: &Request, attempt: usize) -> Request {
    let mut next = request.clone();
    next.id = format!("{}/attempt-{attempt}", request.id);
    if let Conditioning::Image(prompt) = &mut next.conditioning {
        prompt.seed = prompt.seed.wrapping_add(attempt as u64);
    }
    next
}

/// The last attempt's summary as the client saw the request: timed from its submission.
fn as_requested(mut summary: Summary, started: Instant, attempt_started: Instant) -> Summary {
    let earlier = attempt_started - started;
    summary.queued += earlier;
    summary.time_to_first_face = summary.time_to_first_face.map(|t| t + earlier);
    summary.total = started.elapsed();
    summary
}
