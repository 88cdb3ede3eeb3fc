//! The stage before decoding for image requests: one diffusion batch that requests join when
//! admitted and leave when their latents are ready (or when they are cancelled or expire).
//! Every scheduler iteration takes one Euler step for the whole batch; rows may be at
//! different steps of different step counts (see [`LatentSampling`]).

use std::time::{Duration, Instant};

use candle_core::{Device, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::diffusion::{DiffusionModel, LatentSampling, images_to_tensor};

use super::EngineError;
use super::metrics::Metrics;
use super::request::{Conditioning, ImagePrompt};
use super::scheduler::Pending;
use super::stream::Event;

/// A request whose latents are being sampled.
struct Diffusing {
    pending: Pending,
    queued: Duration,
    started: Instant,
}

/// A request whose latents are ready: it joins the decode batch.
pub(super) struct Sampled {
    pub pending: Pending,
    /// (K, latent_dim), in the autoencoder's scale.
    pub latents: Tensor,
    pub queued: Duration,
    /// Time in this stage, from joining to the last step.
    pub prepare: Duration,
}

pub(super) struct DiffusionStage {
    model: DiffusionModel,
    run: Option<LatentSampling>,
    /// Row i of `run` belongs to `rows[i]`.
    rows: Vec<Diffusing>,
}

impl DiffusionStage {
    pub fn new(model: DiffusionModel) -> Self {
        Self { model, run: None, rows: Vec::new() }
    }

    pub fn len(&self) -> usize {
        self.rows.len()
    }

    pub fn faces_reserved(&self) -> usize {
        self.rows.iter().map(|r| r.pending.faces).sum()
    }

    /// Starts sampling for an image request (its image is encoded now) and adds it to the
    /// batch; a request that cannot start is failed at once.
    pub fn join(&mut self, pending: Pending, now: Instant, metrics: &Metrics) {
        let started = match &pending.request.conditioning {
            Conditioning::Image(prompt) => self.start(prompt).and_then(|run| self.append(run)),
            Conditioning::Points(_) => Err(EngineError::Model("not an image request".into())),
        };
        match started {
            Ok(()) => {
                let queued = now - pending.submitted;
                self.rows.push(Diffusing { pending, queued, started: now });
            }
            Err(e) => {
                metrics.fail(e.code());
                let _ = pending.tx.try_send(Event::Failed(e));
            }
        }
    }

    fn start(&self, prompt: &ImagePrompt) -> Result<LatentSampling, EngineError> {
        let image = images_to_tensor(std::slice::from_ref(&prompt.image), &Device::Cpu)?;
        let mut rng = ChaCha8Rng::seed_from_u64(prompt.seed);
        Ok(self.model.start(&image, vec![prompt.guidance], prompt.steps, &mut rng)?)
    }

    fn append(&mut self, run: LatentSampling) -> Result<(), EngineError> {
        match &mut self.run {
            Some(current) => current.append(run)?,
            None => self.run = Some(run),
        }
        Ok(())
    }

    /// Drops the rows whose client went away or whose deadline passed, takes one step for
    /// the others, tells each client how far it is, and returns the requests whose latents
    /// are ready.
    pub fn step(&mut self, metrics: &Metrics) -> Vec<Sampled> {
        let now = Instant::now();
        let keep: Vec<bool> =
            self.rows.iter().map(|r| still_wanted(&r.pending, now, metrics)).collect();
        let rows = std::mem::take(&mut self.rows);
        self.rows = rows.into_iter().zip(&keep).filter(|(_, k)| **k).map(|(r, _)| r).collect();
        if let Err(e) = self.retain_run(&keep) {
            self.fail_all(e, metrics);
            return Vec::new();
        }
        let Some(run) = &mut self.run else {
            return Vec::new();
        };
        metrics.diffusion_batch_size.observe(run.len() as f64);
        if let Err(e) = self.model.step(run) {
            self.fail_all(e.into(), metrics);
            return Vec::new();
        }
        metrics.diffusion_steps.inc();
        for (row, progress) in self.rows.iter().zip(run.rows()) {
            // Progress is advisory: a client that is behind skips some.
            let event = Event::Progress { step: progress.step, steps: progress.steps };
            let _ = row.pending.tx.try_send(event);
        }
        self.take_finished(metrics)
    }

    /// Moves the rows that took their last step out of the batch.
    fn take_finished(&mut self, metrics: &Metrics) -> Vec<Sampled> {
        let Some(run) = &self.run else {
            return Vec::new();
        };
        let done: Vec<bool> = run.rows().iter().map(|r| r.is_done()).collect();
        if !done.contains(&true) {
            return Vec::new();
        }
        let latents = match self.model.latents(run) {
            Ok(latents) => latents,
            Err(e) => {
                self.fail_all(e.into(), metrics);
                return Vec::new();
            }
        };
        let now = Instant::now();
        let mut ready = Vec::new();
        for (i, (row, done)) in std::mem::take(&mut self.rows).into_iter().zip(&done).enumerate() {
            if !done {
                self.rows.push(row);
                continue;
            }
            match latents.get(i) {
                Ok(latents) => ready.push(Sampled {
                    pending: row.pending,
                    latents,
                    queued: row.queued,
                    prepare: now - row.started,
                }),
                Err(e) => {
                    let error = EngineError::from(e);
                    metrics.fail(error.code());
                    let _ = row.pending.tx.try_send(Event::Failed(error));
                }
            }
        }
        let keep: Vec<bool> = done.iter().map(|d| !d).collect();
        if let Err(e) = self.retain_run(&keep) {
            self.fail_all(e, metrics);
        }
        ready
    }

    /// Keeps the run's rows where `keep` is true (the caller keeps `rows` in step).
    fn retain_run(&mut self, keep: &[bool]) -> Result<(), EngineError> {
        if !keep.contains(&true) {
            self.run = None;
        } else if let Some(run) = &mut self.run {
            run.retain(keep)?;
        }
        Ok(())
    }

    /// Ends every request in the stage with `error` (a failed step, or shutdown).
    pub fn fail_all(&mut self, error: EngineError, metrics: &Metrics) {
        for row in self.rows.drain(..) {
            metrics.fail(error.code());
            let _ = row.pending.tx.try_send(Event::Failed(error.clone()));
        }
        self.run = None;
    }
}

/// False (after telling the client and the metrics) when a request's client went away or its
/// deadline passed.
fn still_wanted(pending: &Pending, now: Instant, metrics: &Metrics) -> bool {
    if pending.tx.is_closed() {
        metrics.finish("cancelled");
        false
    } else if pending.request.deadline.is_some_and(|d| now >= d) {
        let _ = pending.tx.try_send(Event::Failed(EngineError::DeadlineExceeded(0)));
        metrics.fail("deadline_exceeded");
        false
    } else {
        true
    }
}
