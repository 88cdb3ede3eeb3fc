//! The stage before decoding for point requests: their encoder passes (the "prefill") run on
//! a thread of their own, a batch of admitted requests at a time, while the running sequences
//! go on stepping.
//!
//! Why: encoded on the scheduler's thread, a batch stopped every running sequence for as long
//! as it took. At 16 whole-mesh clients (four encoder passes a request, one per candidate)
//! that was 30% of the scheduler's time, while the cores were not all busy
//! (`docs/decisions.md`, "Serving").

use std::collections::VecDeque;
use std::sync::{Arc, mpsc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use candle_core::Tensor;
use rayon::prelude::*;

use super::EngineError;
use super::metrics::{Metrics, Stage};
use super::request::{Conditioning, EncoderPoints};
use super::scheduler::{Pending, Shared};
use super::stream::Event;
use crate::model::FaceModel;

/// A request whose latents are ready (or whose encoding failed): it joins the decode batch.
pub(super) struct Encoded {
    pub pending: Pending,
    /// (K, latent_dim).
    pub latents: Result<Tensor, EngineError>,
    pub queued: Duration,
    /// From its batch's submission to the encoder until its latents came back.
    pub prepare: Duration,
}

/// A batch for the encoder thread: its clouds in the order of its requests.
struct Job {
    id: u64,
    clouds: Vec<EncoderPoints>,
}

/// What the encoder thread sends back: (B, K, latent_dim) latents for job `id`.
struct Done {
    id: u64,
    latents: Result<Tensor, EngineError>,
}

/// A batch on the encoder thread; its requests stay here, so that they can be failed at once.
struct InFlight {
    id: u64,
    pendings: Vec<Pending>,
    submitted: Instant,
}

pub(super) struct EncodeStage {
    /// Closed on drop, which ends the thread.
    jobs: Option<mpsc::Sender<Job>>,
    done: mpsc::Receiver<Done>,
    /// Results taken from `done` and not yet handed out.
    finished: Vec<Done>,
    in_flight: VecDeque<InFlight>,
    next_id: u64,
    thread: Option<JoinHandle<()>>,
}

impl EncodeStage {
    /// Starts the encoder thread for `model`. When a batch is done it wakes the scheduler,
    /// under the queue's lock (see [`Self::has_results`]).
    pub fn start(model: FaceModel, shared: Arc<Shared>) -> Result<Self, EngineError> {
        let (jobs, job_rx) = mpsc::channel::<Job>();
        let (done_tx, done) = mpsc::channel();
        let thread = std::thread::Builder::new()
            .name("engine-encode".into())
            .spawn(move || {
                for job in job_rx {
                    let clouds: Vec<&EncoderPoints> = job.clouds.iter().collect();
                    let encode = || encode_batch(&model, &clouds);
                    // A panic fails this batch's requests, not the thread and every request
                    // after them.
                    let latents = shared.metrics.time(Stage::Encode, || {
                        std::panic::catch_unwind(std::panic::AssertUnwindSafe(encode))
                            .unwrap_or_else(|_| {
                                Err(EngineError::Model("the encoder failed on this batch".into()))
                            })
                    });
                    if done_tx.send(Done { id: job.id, latents }).is_err() {
                        return;
                    }
                    let _queue = shared.lock();
                    shared.wake.notify_all();
                }
            })
            .map_err(|e| EngineError::Model(format!("cannot start the encoder thread: {e}")))?;
        Ok(Self {
            jobs: Some(jobs),
            done,
            finished: Vec::new(),
            in_flight: VecDeque::new(),
            next_id: 0,
            thread: Some(thread),
        })
    }

    /// Requests being encoded.
    pub fn len(&self) -> usize {
        self.in_flight.iter().map(|b| b.pendings.len()).sum()
    }

    pub fn faces_reserved(&self) -> usize {
        self.in_flight.iter().flat_map(|b| &b.pendings).map(|p| p.faces).sum()
    }

    /// Sends point requests to the encoder thread as one batch.
    pub fn submit(&mut self, pendings: Vec<Pending>, now: Instant, metrics: &Metrics) {
        if pendings.is_empty() {
            return;
        }
        let clouds = pendings
            .iter()
            .filter_map(|p| match &p.request.conditioning {
                Conditioning::Points(points) => Some(points.encoder.clone()),
                Conditioning::Image(_) => None,
            })
            .collect::<Vec<_>>();
        if clouds.len() != pendings.len() {
            fail(pendings, &EngineError::Model("not a points request".into()), metrics);
            return;
        }
        let id = self.next_id;
        self.next_id += 1;
        let sent = self.jobs.as_ref().is_some_and(|jobs| jobs.send(Job { id, clouds }).is_ok());
        if !sent {
            fail(pendings, &EngineError::Model("the encoder thread has stopped".into()), metrics);
            return;
        }
        self.in_flight.push_back(InFlight { id, pendings, submitted: now });
    }

    /// Whether some batch has come back. The scheduler asks under the queue's lock before it
    /// waits: the encoder thread sends first and then notifies under that lock, so a batch
    /// that ends meanwhile always wakes it.
    pub fn has_results(&mut self) -> bool {
        self.finished.extend(self.done.try_iter());
        !self.finished.is_empty()
    }

    /// The requests of every batch that has come back, each with its own latents.
    pub fn take(&mut self, now: Instant) -> Vec<Encoded> {
        self.has_results();
        let mut out = Vec::new();
        for Done { id, latents } in std::mem::take(&mut self.finished) {
            // A batch failed meanwhile (shutdown) is no longer here.
            let Some(at) = self.in_flight.iter().position(|b| b.id == id) else { continue };
            let Some(batch) = self.in_flight.remove(at) else { continue };
            for (i, pending) in batch.pendings.into_iter().enumerate() {
                let latents = latents.as_ref().map_err(Clone::clone).and_then(|l| Ok(l.get(i)?));
                let queued = batch.submitted.saturating_duration_since(pending.submitted);
                out.push(Encoded { pending, latents, queued, prepare: now - batch.submitted });
            }
        }
        out
    }

    /// Fails every request being encoded; their batches' results are dropped when they come.
    pub fn fail_all(&mut self, error: EngineError, metrics: &Metrics) {
        for batch in self.in_flight.drain(..) {
            fail(batch.pendings, &error, metrics);
        }
    }
}

impl Drop for EncodeStage {
    fn drop(&mut self) {
        // Closing the channel ends the thread once its current batch is done.
        self.jobs = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

fn fail(pendings: Vec<Pending>, error: &EngineError, metrics: &Metrics) {
    for p in pendings {
        metrics.fail(error.code());
        let _ = p.tx.try_send(Event::Failed(error.clone()));
    }
}

/// Clouds one encoder pass takes on the CPU. Why one at a time: a pass over a whole mesh's 4
/// clouds took 1.66x as long as 4 passes of one, its intermediates (attention weights over
/// every point of every cloud) mapped and faulted in afresh (`docs/decisions.md`, "Where a
/// loaded server's time goes"). A GPU takes the batch whole.
const CPU_CLOUDS_PER_PASS: usize = 1;

/// Latent sets (B, K, latent_dim) of clouds that all have the model's point and query counts.
/// On the CPU each cloud gets a pass of its own (`CPU_CLOUDS_PER_PASS`), the passes in
/// parallel on rayon's pool (one thread per core): while one whole mesh's 4 clouds encode,
/// nothing else keeps the second core busy, and one whole-mesh client answered p50 in 538,
/// 515 and 526 ms against 575, 561 and 564 (`docs/decisions.md`, "Serving").
pub fn encode_batch(model: &FaceModel, clouds: &[&EncoderPoints]) -> Result<Tensor, EngineError> {
    let per_pass = if model.device().is_cpu() { CPU_CLOUDS_PER_PASS } else { clouds.len() };
    let latents = clouds
        .par_chunks(per_pass.max(1))
        .map(|pass| encode_pass(model, pass))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Tensor::cat(&latents, 0)?)
}

/// One encoder pass over `clouds`: (B, K, latent_dim).
pub fn encode_pass(model: &FaceModel, clouds: &[&EncoderPoints]) -> Result<Tensor, EngineError> {
    let device = model.device();
    let (b, m, k) = (clouds.len(), model.config().num_points, model.config().num_latents);
    let flat = |pick: fn(&EncoderPoints) -> &[[f32; 3]]| -> Vec<f32> {
        clouds.iter().flat_map(|c| pick(c).iter().flatten().copied()).collect()
    };
    let points = Tensor::from_vec(flat(|c| &c.points), (b, m, 3), device)?;
    let normals = Tensor::from_vec(flat(|c| &c.normals), (b, m, 3), device)?;
    let queries: Vec<u32> = clouds.iter().flat_map(|c| c.queries.iter().copied()).collect();
    let queries = Tensor::from_vec(queries, (b, k), device)?;
    Ok(model.encode(&points, &normals, &queries)?)
}

#[cfg(test)]
mod tests {
    use tokio::sync::mpsc as tokio_mpsc;

    use super::*;
    use crate::engine::request::{DecodeOptions, PreparedPoints, Request};
    use crate::engine::{EngineConfig, Metrics};
    use crate::mesh::UpAxis;
    use crate::mesh::primitives::uv_sphere;
    use crate::model::FaceConfig;
    use crate::model::testing::{max_abs_diff, random_model};

    fn shared() -> Arc<Shared> {
        Arc::new(Shared::new(EngineConfig::default(), Arc::new(Metrics::default())))
    }

    /// A points request for a sphere of radius `r`, and the receiver of its events.
    fn pending(model: &FaceModel, r: f32) -> (Pending, tokio_mpsc::Receiver<Event>) {
        let points =
            PreparedPoints::from_mesh(&uv_sphere(r, 6, 4), model.config(), 2048, 0, 1, UpAxis::Y)
                .unwrap();
        let (tx, rx) = tokio_mpsc::channel(4);
        let request = Request {
            id: format!("r{r}"),
            conditioning: Conditioning::Points(points),
            options: DecodeOptions::default(),
            deadline: None,
        };
        (Pending { request, tx, submitted: Instant::now(), faces: 10 }, rx)
    }

    fn alone(model: &FaceModel, p: &Pending) -> Tensor {
        let Conditioning::Points(points) = &p.request.conditioning else { unreachable!() };
        encode_batch(model, &[&points.encoder]).unwrap().get(0).unwrap()
    }

    /// Waits (a bounded while) until every submitted batch has come back.
    fn wait_for(stage: &mut EncodeStage, batches: usize) {
        let t0 = Instant::now();
        while stage.finished.len() < batches {
            assert!(t0.elapsed() < Duration::from_secs(30), "the encoder thread did not answer");
            stage.has_results();
            std::thread::sleep(Duration::from_millis(2));
        }
    }

    #[test]
    fn batches_come_back_with_each_requests_latents_as_encoded_alone() {
        let (_, model) = random_model(&FaceConfig::micro());
        let shared = shared();
        let mut stage = EncodeStage::start(model.clone(), Arc::clone(&shared)).unwrap();
        let (requests, _rx): (Vec<_>, Vec<_>) =
            [0.5, 0.8, 1.1].map(|r| pending(&model, r)).into_iter().unzip();
        let expected: Vec<Tensor> = requests.iter().map(|p| alone(&model, p)).collect();
        let mut requests = requests.into_iter();
        let metrics = &shared.metrics;
        stage.submit(requests.by_ref().take(2).collect(), Instant::now(), metrics);
        stage.submit(requests.collect(), Instant::now(), metrics);
        assert_eq!((stage.len(), stage.faces_reserved()), (3, 30));
        wait_for(&mut stage, 2);
        let encoded = stage.take(Instant::now());
        assert_eq!(stage.len(), 0);
        assert_eq!(encoded.len(), 3);
        for (e, expected) in encoded.iter().zip(&expected) {
            let latents = e.latents.as_ref().unwrap();
            assert!(max_abs_diff(latents, expected) < 1e-4, "{}", e.pending.request.id);
        }
        assert!(shared.metrics.work_seconds(Stage::Encode) > 0.0);
    }

    #[test]
    fn a_batch_the_encoder_cannot_take_fails_its_requests() {
        let (_, model) = random_model(&FaceConfig::micro());
        let shared = shared();
        let mut stage = EncodeStage::start(model.clone(), Arc::clone(&shared)).unwrap();
        let (mut request, _rx) = pending(&model, 0.5);
        if let Conditioning::Points(points) = &mut request.request.conditioning {
            points.encoder.points.truncate(5);
        }
        stage.submit(vec![request], Instant::now(), &shared.metrics);
        wait_for(&mut stage, 1);
        let encoded = stage.take(Instant::now());
        assert!(matches!(encoded.as_slice(), [Encoded { latents: Err(_), .. }]));
        // The thread goes on with the next batch.
        let (request, _rx) = pending(&model, 0.5);
        stage.submit(vec![request], Instant::now(), &shared.metrics);
        wait_for(&mut stage, 1);
        assert!(stage.take(Instant::now())[0].latents.is_ok());
    }

    #[test]
    fn failed_batches_are_answered_at_once_and_their_results_dropped() {
        let (_, model) = random_model(&FaceConfig::micro());
        let shared = shared();
        let mut stage = EncodeStage::start(model.clone(), Arc::clone(&shared)).unwrap();
        let (request, mut rx) = pending(&model, 0.5);
        stage.submit(vec![request], Instant::now(), &shared.metrics);
        stage.fail_all(EngineError::ShuttingDown, &shared.metrics);
        assert_eq!(stage.len(), 0);
        assert!(matches!(rx.try_recv(), Ok(Event::Failed(EngineError::ShuttingDown))));
        wait_for(&mut stage, 1);
        assert!(stage.take(Instant::now()).is_empty());
    }
}
