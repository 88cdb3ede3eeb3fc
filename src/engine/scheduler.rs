//! The scheduler loop, on a thread of its own: admit waiting requests, run their stage before
//! decoding together (the encoder is their "prefill"), then step every running sequence by one
//! face, in parallel parts of the batch, and send each face to its client at once.

use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use candle_core::Tensor;
use tokio::sync::mpsc;

use super::memory;
use crate::diffusion::DiffusionModel;
use crate::mesh::Normalization;
use crate::model::{DEFAULT_FACE_BEAM, FaceModel, FinishReason, GenerateOptions, Generation};
use crate::tokenize::{Quantizer, face_positions};

use super::admission::{Candidate, Capacity, admit};
use super::diffusion_stage::DiffusionStage;
use super::encode_stage::EncodeStage;
use super::metrics::{Metrics, Stage};
use super::pools::DecodePools;
use super::request::{Conditioning, Request};
use super::stream::{Event, StreamedFace, Summary};
use super::{EngineConfig, EngineError};

/// The longest the scheduler waits for an encoded batch before it looks at the queue again
/// (timeouts, shutdown); a finished batch wakes it at once.
const ENCODING_WAIT: Duration = Duration::from_millis(50);

/// A request accepted into the queue.
pub(super) struct Pending {
    pub request: Request,
    pub tx: mpsc::Sender<Event>,
    pub submitted: Instant,
    /// The face budget it reserves once running.
    pub faces: usize,
}

pub(super) struct QueueState {
    pub waiting: VecDeque<Pending>,
    pub running: usize,
    /// Set by shutdown: nothing new is accepted, and whatever is unfinished then fails.
    pub closing: Option<Instant>,
    pub stopped: bool,
}

pub(super) struct Shared {
    pub queue: Mutex<QueueState>,
    pub wake: Condvar,
    pub config: EngineConfig,
    pub metrics: Arc<Metrics>,
}

impl Shared {
    /// An empty queue.
    pub fn new(config: EngineConfig, metrics: Arc<Metrics>) -> Self {
        let queue =
            QueueState { waiting: VecDeque::new(), running: 0, closing: None, stopped: false };
        Self { queue: Mutex::new(queue), wake: Condvar::new(), config, metrics }
    }

    /// The queue, even if a thread panicked while holding it (its state stays consistent:
    /// every change is a single push, pop or assignment).
    pub fn lock(&self) -> MutexGuard<'_, QueueState> {
        self.queue.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

/// A sequence being decoded, and where its faces go.
struct Active {
    generation: Generation,
    tx: mpsc::Sender<Event>,
    normalization: Normalization,
    faces_reserved: usize,
    submitted: Instant,
    queued: Duration,
    prepare: Duration,
    decode_start: Instant,
    first_face: Option<Instant>,
    last_face: Instant,
    deadline: Option<Instant>,
    /// Since when its client has had no room for a face (see `ready`).
    stalled_since: Option<Instant>,
    done: bool,
}

impl Active {
    fn finish(&mut self, event: Event) {
        // The stepped rows always have room for a face and the final event (see `ready`).
        let _ = self.tx.try_send(event);
        self.done = true;
    }

    fn summary(&self, finish: FinishReason, now: Instant) -> Summary {
        Summary {
            faces: self.generation.faces().len(),
            finish,
            queued: self.queued,
            prepare: self.prepare,
            decode: now - self.decode_start,
            time_to_first_face: self.first_face.map(|t| t - self.submitted),
            total: now - self.submitted,
            quality: None,
        }
    }

    /// Stepped only when its client has room for one face and the final event.
    fn ready(&self) -> bool {
        self.tx.capacity() >= 2
    }
}

pub(super) struct Scheduler {
    model: FaceModel,
    quantizer: Quantizer,
    shared: Arc<Shared>,
    pools: DecodePools,
    running: Vec<Active>,
    /// Point requests before decoding.
    encoding: EncodeStage,
    /// Image requests before decoding; `None` when the engine has no image model.
    diffusion: Option<DiffusionStage>,
}

impl Scheduler {
    pub fn new(
        model: FaceModel,
        diffusion: Option<DiffusionModel>,
        quantizer: Quantizer,
        shared: Arc<Shared>,
        pools: DecodePools,
    ) -> Result<Self, EngineError> {
        let diffusion = diffusion.map(DiffusionStage::new);
        let encoding = EncodeStage::start(model.clone(), Arc::clone(&shared))?;
        Ok(Self { model, quantizer, shared, pools, running: Vec::new(), encoding, diffusion })
    }

    pub fn run(mut self) {
        while let Some(admitted) = self.next_admissions() {
            let admitted_any = !admitted.is_empty();
            self.start(admitted);
            self.begin_encoded();
            if admitted_any {
                // Seen before their first face, so a status never lags behind the stream.
                self.publish_running();
            }
            self.diffuse();
            self.step();
        }
        self.fail_everything();
        let mut q = self.shared.lock();
        q.running = 0;
        q.stopped = true;
        self.shared.metrics.running_sequences.set(0);
    }

    /// Ends every started request (shutdown): decoding and diffusing alike.
    fn fail_everything(&mut self) {
        let metrics = &self.shared.metrics;
        for a in &mut self.running {
            a.finish(Event::Failed(EngineError::ShuttingDown));
            metrics.fail("shutting_down");
        }
        self.running.clear();
        self.encoding.fail_all(EngineError::ShuttingDown, metrics);
        if let Some(stage) = &mut self.diffusion {
            stage.fail_all(EngineError::ShuttingDown, metrics);
        }
    }

    /// Started requests: decoding, or in a stage before it (encoding, diffusion).
    fn started(&self) -> usize {
        self.running.len()
            + self.encoding.len()
            + self.diffusion.as_ref().map_or(0, DiffusionStage::len)
    }

    /// Whether only encoder passes are under way: nothing to step or diffuse meanwhile.
    fn only_encoding(&self) -> bool {
        self.running.is_empty()
            && self.diffusion.as_ref().is_none_or(|d| d.len() == 0)
            && self.encoding.len() > 0
    }

    fn publish_running(&self) {
        self.shared.lock().running = self.started();
        self.shared.metrics.running_sequences.set(self.started() as i64);
    }

    /// Requests to start now; waits while there is nothing to do; `None` when the engine has
    /// shut down.
    fn next_admissions(&mut self) -> Option<Vec<Pending>> {
        let shared = Arc::clone(&self.shared);
        let cfg = &shared.config;
        let metrics = &shared.metrics;
        let mut q = shared.lock();
        // Whether this idle spell has handed its freed memory back yet.
        let mut trimmed = false;
        loop {
            let now = Instant::now();
            let past_deadline = q.closing.is_some_and(|t| now >= t);
            q.waiting.retain(|p| {
                let waited = now - p.submitted;
                let failure = if p.tx.is_closed() {
                    Some(None)
                } else if past_deadline {
                    Some(Some(EngineError::ShuttingDown))
                } else if waited >= cfg.queue_timeout {
                    Some(Some(EngineError::QueueTimeout(waited)))
                } else {
                    None
                };
                match failure {
                    None => true,
                    Some(error) => {
                        metrics.reject(error.as_ref().map_or("cancelled", EngineError::code));
                        if let Some(error) = error {
                            let _ = p.tx.try_send(Event::Failed(error));
                        }
                        false
                    }
                }
            });
            if past_deadline {
                self.fail_everything();
            }
            q.running = self.started();
            metrics.running_sequences.set(self.started() as i64);
            metrics.queue_depth.set(q.waiting.len() as i64);
            if self.started() == 0 && q.waiting.is_empty() {
                if q.closing.is_some() {
                    return None;
                }
                if trimmed {
                    q = shared.wake.wait(q).unwrap_or_else(|poisoned| poisoned.into_inner());
                    continue;
                }
                let (guard, waited) = shared
                    .wake
                    .wait_timeout(q, memory::TRIM_AFTER_IDLE)
                    .unwrap_or_else(|poisoned| poisoned.into_inner());
                q = guard;
                if waited.timed_out() {
                    // Without the lock: submitters need not wait for the allocator.
                    drop(q);
                    memory::release_free_memory();
                    trimmed = true;
                    q = shared.lock();
                }
                continue;
            }
            let reserved: usize = self.running.iter().map(|a| a.faces_reserved).sum::<usize>()
                + self.encoding.faces_reserved()
                + self.diffusion.as_ref().map_or(0, DiffusionStage::faces_reserved);
            let free = Capacity {
                slots: cfg.max_running.saturating_sub(self.started()),
                faces: cfg.max_batch_faces.saturating_sub(reserved),
                starts: cfg.max_encodes_per_iteration,
            };
            let candidates: Vec<Candidate> = q
                .waiting
                .iter()
                .map(|p| Candidate { faces: p.faces, waited: now - p.submitted })
                .collect();
            let picked = admit(&candidates, free, cfg.aging);
            if picked.is_empty() && self.only_encoding() && !self.encoding.has_results() {
                // Nothing to admit, step or hand on until a batch is encoded (or a request
                // comes): wait for it rather than spin. The bound re-checks the queue's
                // timeouts and shutdown meanwhile.
                let (guard, _) = shared
                    .wake
                    .wait_timeout(q, ENCODING_WAIT)
                    .unwrap_or_else(|poisoned| poisoned.into_inner());
                q = guard;
                continue;
            }
            // Remove from the back so earlier indices stay valid, then restore queue order.
            let mut admitted: Vec<Pending> =
                picked.iter().rev().filter_map(|&i| q.waiting.remove(i)).collect();
            admitted.reverse();
            metrics.queue_depth.set(q.waiting.len() as i64);
            return Some(admitted);
        }
    }

    /// Point requests: sent to the encoder thread in one batch. Image requests: join the
    /// diffusion batch.
    fn start(&mut self, admitted: Vec<Pending>) {
        let now = Instant::now();
        let (points, images): (Vec<Pending>, Vec<Pending>) = admitted
            .into_iter()
            .partition(|p| matches!(p.request.conditioning, Conditioning::Points(_)));
        let metrics = Arc::clone(&self.shared.metrics);
        for p in images {
            match &mut self.diffusion {
                Some(stage) => stage.join(p, now, &metrics),
                None => {
                    let e = EngineError::Unsupported("this engine has no image model".into());
                    metrics.fail(e.code());
                    let _ = p.tx.try_send(Event::Failed(e));
                }
            }
        }
        self.encoding.submit(points, now, &metrics);
    }

    /// The point requests whose latents have come back from the encoder thread start
    /// decoding.
    fn begin_encoded(&mut self) {
        for e in self.encoding.take(Instant::now()) {
            self.begin_decoding(e.pending, e.latents, e.queued, e.prepare);
        }
    }

    /// One diffusion step for the image requests; those whose latents are ready start
    /// decoding.
    fn diffuse(&mut self) {
        let Some(stage) = &mut self.diffusion else {
            return;
        };
        if stage.len() == 0 {
            return;
        }
        let metrics = Arc::clone(&self.shared.metrics);
        let ready =
            metrics.time(Stage::Diffuse, || self.pools.wide().install(|| stage.step(&metrics)));
        for s in ready {
            self.begin_decoding(s.pending, Ok(s.latents), s.queued, s.prepare);
        }
    }

    /// Adds a request whose latents (K, latent_dim) are ready to the running sequences.
    fn begin_decoding(
        &mut self,
        p: Pending,
        latents: Result<Tensor, EngineError>,
        queued: Duration,
        prepare: Duration,
    ) {
        let started = latents.and_then(|l| {
            let options = GenerateOptions {
                sampling: p.request.options.sampling.clone(),
                max_faces: p.faces,
                face_beam: p.request.options.face_beam.unwrap_or(DEFAULT_FACE_BEAM),
                ..GenerateOptions::default()
            };
            Ok(Generation::new(&self.model, &l, options)?)
        });
        match started {
            Ok(generation) => self.running.push(Active {
                generation,
                normalization: p.request.conditioning.normalization(),
                faces_reserved: p.faces,
                queued,
                prepare,
                decode_start: Instant::now(),
                first_face: None,
                last_face: Instant::now(),
                deadline: p.request.deadline,
                stalled_since: None,
                submitted: p.submitted,
                tx: p.tx,
                done: false,
            }),
            Err(e) => {
                self.shared.metrics.fail(e.code());
                let _ = p.tx.try_send(Event::Failed(e));
            }
        }
    }

    /// One face for every running sequence whose client has room; finished, cancelled and
    /// expired sequences leave the batch at once.
    fn step(&mut self) {
        let metrics = Arc::clone(&self.shared.metrics);
        let idle_limit = self.shared.config.stream_idle_timeout;
        let now = Instant::now();
        for a in &mut self.running {
            a.stalled_since = if a.ready() { None } else { Some(a.stalled_since.unwrap_or(now)) };
            if a.tx.is_closed() {
                a.generation.cancel();
                a.done = true;
                metrics.finish("cancelled");
            } else if a.deadline.is_some_and(|d| now >= d) {
                a.finish(Event::Failed(EngineError::DeadlineExceeded(a.generation.faces().len())));
                metrics.fail("deadline_exceeded");
            } else if a.stalled_since.is_some_and(|t| now - t >= idle_limit) {
                // A stepped row always leaves room for the final event, so the client finds
                // this error after its faces whenever it reads again.
                a.generation.cancel();
                a.finish(Event::Failed(EngineError::StreamIdle(idle_limit)));
                metrics.fail("stream_idle");
            }
        }
        self.running.retain(|a| !a.done);
        let mut rows: Vec<&mut Active> = self.running.iter_mut().filter(|a| a.ready()).collect();
        if rows.is_empty() {
            if !self.running.is_empty() {
                // Every client is behind: give them a moment rather than spin.
                std::thread::sleep(Duration::from_millis(1));
            }
            return;
        }
        metrics.observe_step(rows.len());
        let part = self.pools.part_size(rows.len());
        let results = metrics
            .time(Stage::Decode, || self.pools.step(&self.model, &mut rows, |a| &mut a.generation));
        let now = Instant::now();
        for (part, result) in rows.chunks_mut(part).zip(results) {
            match result {
                Ok(events) => {
                    for (a, event) in part.iter_mut().zip(events) {
                        if let Some(token) = event.face {
                            let index = a.generation.faces().len() - 1;
                            let vertices = face_positions(&token, self.quantizer)
                                .map(|p| a.normalization.invert(p));
                            let _ =
                                a.tx.try_send(Event::Face(StreamedFace { index, token, vertices }));
                            metrics.faces_generated.inc();
                            match a.first_face {
                                None => {
                                    a.first_face = Some(now);
                                    metrics
                                        .time_to_first_face
                                        .observe((now - a.submitted).as_secs_f64());
                                }
                                Some(_) => metrics
                                    .time_between_faces
                                    .observe((now - a.last_face).as_secs_f64()),
                            }
                            a.last_face = now;
                        }
                        if let Some(reason) = event.finished {
                            let summary = a.summary(reason, now);
                            metrics.request_duration.observe(summary.total.as_secs_f64());
                            metrics.finish(reason.name());
                            a.finish(Event::Finished(summary));
                        }
                    }
                }
                Err(e) => {
                    let error = EngineError::from(e);
                    for a in part.iter_mut() {
                        metrics.fail(error.code());
                        a.finish(Event::Failed(error.clone()));
                    }
                }
            }
        }
        self.running.retain(|a| !a.done);
    }
}
