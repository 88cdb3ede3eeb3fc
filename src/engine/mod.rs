//! The inference engine: a bounded queue of requests and a continuous-batching scheduler on
//! dedicated threads, shared by every interface (HTTP, gRPC, the CLI).
//!
//! ```text
//! submit ──> queue ──admission──> encoder batch ──> running batch ──step──> faces ──> client
//!   (429 when full)  (fits? aged?)   ("prefill")     (one face per row      (bounded channel;
//!                                                      per iteration)        closed = cancel)
//! ```
//! Model work never runs on the async runtime: the scheduler has its own thread, parts of the
//! running batch are stepped in parallel on its own thread pool, and admitted point requests
//! are encoded on a thread of their own meanwhile. A client's channel is bounded; a sequence
//! whose client is behind is not stepped until it catches up, and a dropped
//! [`RequestStream`] cancels its request before the next step.

mod admission;
mod best_of;
mod config;
mod diffusion_stage;
mod encode_stage;
mod error;
mod memory;
mod metrics;
mod offload;
mod pools;
mod request;
mod resample;
mod scheduler;
mod stream;

use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use tokio::sync::mpsc;

use crate::candidates::{MAX_CANDIDATES, MAX_WELD_RADIUS};
use crate::diffusion::{DiffusionModel, DitConfig};
use crate::mesh::{MAX_FIT_ROUNDS, MAX_HOLE_EDGES};
use crate::model::{FaceConfig, FaceModel, MAX_FACE_BEAM};
use crate::tokenize::Quantizer;

pub use config::EngineConfig;
pub use encode_stage::{encode_batch, encode_pass};
pub use error::EngineError;
pub use memory::{MAP_FROM_BYTES, map_large_blocks};
pub use metrics::{Metrics, Stage};
pub use pools::{DecodePools, PartResult};
pub use request::{
    Conditioning, DecodeOptions, EncoderPoints, ImagePrompt, PreparedPoints, Request,
};
pub use stream::{Completed, Event, RequestStream, StreamedFace, Summary};

use scheduler::{Pending, Scheduler, Shared};

/// Guidance scales above this only push the sampler off the data.
pub const MAX_GUIDANCE: f32 = 20.0;

/// What the engine is doing now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EngineStatus {
    pub waiting: usize,
    pub running: usize,
    /// False once shutdown has begun.
    pub accepting: bool,
    /// False once the scheduler has stopped.
    pub alive: bool,
}

/// A handle on a running engine; clones share it.
#[derive(Clone)]
pub struct Engine {
    shared: Arc<Shared>,
    model_config: Arc<FaceConfig>,
    /// The image model's, when the engine has one.
    diffusion_config: Option<Arc<DitConfig>>,
    quantizer: Quantizer,
    thread: Arc<Mutex<Option<JoinHandle<()>>>>,
}

impl Engine {
    /// Starts the scheduler thread and its decode pool. With a diffusion model the engine
    /// also takes image requests; its latents must be the face model's.
    pub fn start(
        model: FaceModel,
        diffusion: Option<DiffusionModel>,
        config: EngineConfig,
        metrics: Arc<Metrics>,
    ) -> Result<Self, EngineError> {
        config.validate()?;
        let model_config = Arc::new(model.config().clone());
        let diffusion_config = diffusion.as_ref().map(|d| Arc::new(d.config().clone()));
        if let Some(d) = &diffusion_config
            && (d.num_latents, d.latent_dim) != (model_config.num_latents, model_config.latent_dim)
        {
            return Err(EngineError::Model(format!(
                "the image model makes {} x {} latents, the face model takes {} x {}",
                d.num_latents, d.latent_dim, model_config.num_latents, model_config.latent_dim
            )));
        }
        let levels = u16::try_from(model_config.quant_levels)
            .map_err(|_| EngineError::Model("quantization levels out of range".into()))?;
        let quantizer = Quantizer::new(levels).map_err(|e| EngineError::Model(e.to_string()))?;
        let pools = DecodePools::new(config.threads())?;
        let shared = Arc::new(Shared::new(config, metrics));
        let scheduler = Scheduler::new(model, diffusion, quantizer, Arc::clone(&shared), pools)?;
        let thread = std::thread::Builder::new()
            .name("engine-scheduler".into())
            .spawn(move || scheduler.run())
            .map_err(|e| EngineError::Model(format!("cannot start the scheduler: {e}")))?;
        Ok(Self {
            shared,
            model_config,
            diffusion_config,
            quantizer,
            thread: Arc::new(Mutex::new(Some(thread))),
        })
    }

    pub fn model_config(&self) -> &FaceConfig {
        &self.model_config
    }

    /// The image model's config; `None` when the engine takes no image requests.
    pub fn diffusion_config(&self) -> Option<&DitConfig> {
        self.diffusion_config.as_deref()
    }

    pub fn config(&self) -> &EngineConfig {
        &self.shared.config
    }

    pub fn metrics(&self) -> &Arc<Metrics> {
        &self.shared.metrics
    }

    /// The largest face budget a request may ask for: the engine's limit or the model's,
    /// whichever is smaller.
    pub fn face_limit(&self) -> usize {
        self.shared.config.max_faces_per_request.min(self.model_config.max_faces)
    }

    /// Queues a request; its faces arrive on the returned stream, then a summary that says
    /// how the answer is built and how far it lies from a points request's input. Refused at
    /// once when the queue is full or the engine is shutting down. A request for several
    /// candidates, or welded or fitted, queues one request per candidate, and an image request
    /// may be sampled again: both need a tokio runtime (see `best_of` and `resample`).
    pub fn submit(&self, request: Request) -> Result<RequestStream, EngineError> {
        let input = match &request.conditioning {
            Conditioning::Points(p) => Some((Arc::clone(&p.reference), p.normalization)),
            Conditioning::Image(_) => None,
        };
        let metrics = Arc::clone(&self.shared.metrics);
        Ok(self.submit_unmeasured(request)?.measured(input, metrics))
    }

    fn submit_unmeasured(&self, request: Request) -> Result<RequestStream, EngineError> {
        let options = &request.options;
        let ended = options.fit_rounds.unwrap_or(0) > 0 || options.weld_radius.unwrap_or(0) > 0;
        let image = matches!(request.conditioning, Conditioning::Image(_));
        let attempts = self.shared.config.image_attempts;
        match (options.candidates.unwrap_or(1), ended) {
            (1, false) if image && attempts > 1 => {
                self.check(&request).inspect_err(|e| self.shared.metrics.reject(e.code()))?;
                resample::submit(self, request, attempts)
            }
            (1, false) => self.submit_one(request),
            (n, _) => {
                self.check(&request).inspect_err(|e| self.shared.metrics.reject(e.code()))?;
                best_of::submit(self, request, n)
            }
        }
    }

    fn submit_one(&self, request: Request) -> Result<RequestStream, EngineError> {
        let metrics = &self.shared.metrics;
        let faces = self.check(&request).inspect_err(|e| metrics.reject(e.code()))?;
        let (tx, rx) = mpsc::channel(self.shared.config.stream_buffer);
        let stream = RequestStream::new(request.id.clone(), rx);
        let mut q = self.shared.lock();
        let refused = if q.closing.is_some() || q.stopped {
            Some(EngineError::ShuttingDown)
        } else if q.waiting.len() >= self.shared.config.max_queue {
            Some(EngineError::QueueFull(q.waiting.len()))
        } else {
            None
        };
        if let Some(e) = refused {
            metrics.reject(e.code());
            return Err(e);
        }
        q.waiting.push_back(Pending { request, tx, submitted: Instant::now(), faces });
        metrics.queue_depth.set(q.waiting.len() as i64);
        self.shared.wake.notify_one();
        Ok(stream)
    }

    /// The request's face budget, after checking it against the limits and the model.
    fn check(&self, request: &Request) -> Result<usize, EngineError> {
        let limit = self.face_limit();
        let faces = request.options.max_faces.unwrap_or(limit);
        if faces == 0 || faces > limit {
            return Err(EngineError::InvalidInput(format!(
                "max_faces must be between 1 and {limit}, got {faces}"
            )));
        }
        request
            .options
            .sampling
            .validate()
            .map_err(|e| EngineError::InvalidInput(e.to_string()))?;
        if let Some(beam) = request.options.face_beam
            && !(1..=MAX_FACE_BEAM).contains(&beam)
        {
            return Err(EngineError::InvalidInput(format!(
                "face_beam must be between 1 and {MAX_FACE_BEAM}, got {beam}"
            )));
        }
        let candidates = request.options.candidates.unwrap_or(1);
        if !(1..=MAX_CANDIDATES).contains(&candidates) {
            return Err(EngineError::InvalidInput(format!(
                "candidates must be between 1 and {MAX_CANDIDATES}, got {candidates}"
            )));
        }
        if candidates > 1 && matches!(request.conditioning, Conditioning::Image(_)) {
            return Err(EngineError::InvalidInput(
                "candidates are judged against input points: an image request takes 1".into(),
            ));
        }
        let fit_rounds = request.options.fit_rounds.unwrap_or(0);
        if fit_rounds > MAX_FIT_ROUNDS {
            return Err(EngineError::InvalidInput(format!(
                "fit_rounds must be at most {MAX_FIT_ROUNDS}, got {fit_rounds}"
            )));
        }
        if fit_rounds > 0 && matches!(request.conditioning, Conditioning::Image(_)) {
            return Err(EngineError::InvalidInput(
                "a mesh is fitted to input points: an image request has none".into(),
            ));
        }
        if let Some(n) = request.options.max_hole_edges
            && n > MAX_HOLE_EDGES
        {
            return Err(EngineError::InvalidInput(format!(
                "max_hole_edges must be at most {MAX_HOLE_EDGES}, got {n}"
            )));
        }
        if let Some(n) = request.options.hull_faces
            && n > limit
        {
            return Err(EngineError::InvalidInput(format!(
                "hull_faces must be at most {limit} (the face limit), got {n}"
            )));
        }
        let weld_radius = request.options.weld_radius.unwrap_or(0);
        if weld_radius > MAX_WELD_RADIUS {
            return Err(EngineError::InvalidInput(format!(
                "weld_radius must be at most {MAX_WELD_RADIUS}, got {weld_radius}"
            )));
        }
        if weld_radius > 0 && matches!(request.conditioning, Conditioning::Image(_)) {
            return Err(EngineError::InvalidInput(
                "welding ends a reconstruction's candidates: an image request takes 0".into(),
            ));
        }
        let cfg = &self.model_config;
        match &request.conditioning {
            Conditioning::Points(p) => {
                if !std::iter::once(&p.encoder).chain(&p.more_draws).all(|e| e.fits(cfg)) {
                    return Err(EngineError::InvalidInput(format!(
                        "prepared points do not match the model ({} points, {} queries)",
                        cfg.num_points, cfg.num_latents
                    )));
                }
                if p.reference.vertices.is_empty() {
                    return Err(EngineError::InvalidInput(
                        "prepared points have no reference points to judge candidates by".into(),
                    ));
                }
            }
            Conditioning::Image(prompt) => self.check_image(prompt)?,
        }
        // A budget larger than the whole batch's could never be admitted.
        Ok(faces.min(self.shared.config.max_batch_faces))
    }

    fn check_image(&self, prompt: &ImagePrompt) -> Result<(), EngineError> {
        let dit = self.diffusion_config.as_ref().ok_or_else(|| {
            EngineError::Unsupported(
                "this server has no image model: image requests are off".into(),
            )
        })?;
        let size = dit.image_encoder.image_size();
        if prompt.image.size() != size {
            return Err(EngineError::InvalidInput(format!(
                "the image must be prepared at {size} x {size} pixels, got {0} x {0}",
                prompt.image.size()
            )));
        }
        let max_steps = self.shared.config.max_diffusion_steps;
        if prompt.steps == 0 || prompt.steps > max_steps {
            return Err(EngineError::InvalidInput(format!(
                "steps must be between 1 and {max_steps}, got {}",
                prompt.steps
            )));
        }
        if !(0.0..=MAX_GUIDANCE).contains(&prompt.guidance) {
            return Err(EngineError::InvalidInput(format!(
                "guidance must be between 0 and {MAX_GUIDANCE}, got {}",
                prompt.guidance
            )));
        }
        Ok(())
    }

    pub fn status(&self) -> EngineStatus {
        let q = self.shared.lock();
        EngineStatus {
            waiting: q.waiting.len(),
            running: q.running,
            accepting: q.closing.is_none() && !q.stopped,
            alive: !q.stopped,
        }
    }

    /// Stops accepting requests; those already accepted may finish for `grace`, then fail.
    pub fn shutdown(&self, grace: Duration) {
        let mut q = self.shared.lock();
        let deadline = Instant::now() + grace;
        q.closing = Some(q.closing.map_or(deadline, |d| d.min(deadline)));
        self.shared.wake.notify_all();
    }

    /// Waits for the scheduler to stop (after [`Engine::shutdown`]). Blocking.
    pub fn join(&self) {
        let handle = self.thread.lock().ok().and_then(|mut t| t.take());
        if let Some(handle) = handle {
            let _ = handle.join();
        }
    }
}

#[cfg(test)]
mod tests;
