//! Prometheus metrics of the engine and of the interfaces in front of it, in one registry.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;

use crate::metrics::MeshQuality;

type ByReason = Family<Vec<(&'static str, &'static str)>, Counter>;
type Seconds = Family<Vec<(&'static str, &'static str)>, Counter<f64, AtomicU64>>;

/// A stage of the work requests take, as `meshstream_work_seconds_total` counts it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// An input's points for the encoder (sampling, farthest point sampling), one draw per
    /// candidate, and the reference points.
    Prepare,
    /// The encoder, on the batch of requests starting together.
    Encode,
    /// Stepping the running sequences by one face.
    Decode,
    /// Diffusion steps of image requests.
    Diffuse,
    /// Ending a request: welding a reconstruction's candidates, fitting their corners to the
    /// input, judging them; measuring the answer's build and distance to its input.
    End,
}

impl Stage {
    pub const ALL: [Stage; 5] =
        [Stage::Prepare, Stage::Encode, Stage::Decode, Stage::Diffuse, Stage::End];

    pub fn name(self) -> &'static str {
        match self {
            Stage::Prepare => "prepare",
            Stage::Encode => "encode",
            Stage::Decode => "decode",
            Stage::Diffuse => "diffuse",
            Stage::End => "end",
        }
    }
}

pub struct Metrics {
    registry: Registry,
    pub queue_depth: Gauge,
    pub running_sequences: Gauge,
    pub faces_generated: Counter,
    pub time_to_first_face: Histogram,
    pub time_between_faces: Histogram,
    pub request_duration: Histogram,
    /// Observed through [`Self::observe_step`].
    batch_size: Histogram,
    /// Decode steps and the sequences they stepped, for [`Self::decode_steps`] (the histogram
    /// keeps its sum and count to itself).
    steps: AtomicU64,
    rows_stepped: AtomicU64,
    pub diffusion_steps: Counter,
    pub diffusion_batch_size: Histogram,
    /// Image requests sampled again, their mesh having come out empty (`engine::resample`).
    pub image_resamples: Counter,
    /// What the answers say of themselves ([`MeshQuality`]), through [`Self::observe_answer`]:
    /// a model or a setting that makes worse meshes shows here before users say so.
    answer_parts: Histogram,
    answer_boundary_share: Histogram,
    answer_input_chamfer: Histogram,
    rejections: ByReason,
    failures: ByReason,
    finished: ByReason,
    work: Seconds,
}

impl Default for Metrics {
    fn default() -> Self {
        let mut registry = Registry::with_prefix("meshstream");
        let m = Self {
            queue_depth: Gauge::default(),
            running_sequences: Gauge::default(),
            faces_generated: Counter::default(),
            time_to_first_face: Histogram::new(exponential_buckets(0.005, 2.0, 14)),
            time_between_faces: Histogram::new(exponential_buckets(0.0002, 2.0, 14)),
            request_duration: Histogram::new(exponential_buckets(0.01, 2.0, 14)),
            batch_size: Histogram::new(exponential_buckets(1.0, 2.0, 9)),
            steps: AtomicU64::new(0),
            rows_stepped: AtomicU64::new(0),
            diffusion_steps: Counter::default(),
            diffusion_batch_size: Histogram::new(exponential_buckets(1.0, 2.0, 9)),
            image_resamples: Counter::default(),
            answer_parts: Histogram::new(exponential_buckets(1.0, 2.0, 9)),
            answer_boundary_share: Histogram::new([
                0.0, 0.02, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.7, 0.9, 1.0,
            ]),
            answer_input_chamfer: Histogram::new(exponential_buckets(0.005, 2.0, 10)),
            rejections: ByReason::default(),
            failures: ByReason::default(),
            finished: ByReason::default(),
            work: Seconds::default(),
            registry: Registry::default(),
        };
        registry.register("queue_depth", "Requests waiting to start", m.queue_depth.clone());
        registry.register(
            "running_sequences",
            "Sequences being decoded",
            m.running_sequences.clone(),
        );
        registry.register("faces_generated", "Faces decoded", m.faces_generated.clone());
        registry.register(
            "time_to_first_face_seconds",
            "From a request's admission to the queue to its first face",
            m.time_to_first_face.clone(),
        );
        registry.register(
            "time_between_faces_seconds",
            "Between consecutive faces of one request",
            m.time_between_faces.clone(),
        );
        registry.register(
            "request_duration_seconds",
            "From admission to the queue to the last event",
            m.request_duration.clone(),
        );
        registry.register(
            "batch_size",
            "Sequences stepped together in one decode iteration",
            m.batch_size.clone(),
        );
        registry.register(
            "diffusion_steps",
            "Euler steps taken by the diffusion batch (one per iteration with image requests)",
            m.diffusion_steps.clone(),
        );
        registry.register(
            "diffusion_batch_size",
            "Image requests stepped together in one diffusion step",
            m.diffusion_batch_size.clone(),
        );
        registry.register(
            "image_resamples",
            "Image requests sampled again from the next seed, their mesh having come out empty",
            m.image_resamples.clone(),
        );
        registry.register(
            "answer_parts",
            "Connected parts of each answer with faces",
            m.answer_parts.clone(),
        );
        registry.register(
            "answer_boundary_share",
            "Share of each answer's edges that one face uses (holes, open borders)",
            m.answer_boundary_share.clone(),
        );
        registry.register(
            "answer_input_chamfer",
            "Chamfer distance between each points request's answer and its input points, the \
             input's longest side spanning 2",
            m.answer_input_chamfer.clone(),
        );
        registry.register(
            "requests_rejected",
            "Requests refused before they started, by reason",
            m.rejections.clone(),
        );
        registry.register(
            "requests_failed",
            "Requests that started and then failed, by reason",
            m.failures.clone(),
        );
        registry.register(
            "requests_finished",
            "Requests that completed, by why decoding stopped",
            m.finished.clone(),
        );
        registry.register(
            "work_seconds",
            "Seconds spent in each stage of request work, by stage; decode and diffuse run \
             on up to --decode-threads cores at once, the others on one core per task (an \
             encoder batch, a request's points, a candidate's ending)",
            m.work.clone(),
        );
        // Every stage is exported from the start, at 0 until it has run.
        for stage in Stage::ALL {
            let _ = m.work.get_or_create(&vec![("stage", stage.name())]);
        }
        Self { registry, ..m }
    }
}

impl Metrics {
    pub fn reject(&self, reason: &'static str) {
        self.rejections.get_or_create(&vec![("reason", reason)]).inc();
    }

    pub fn fail(&self, reason: &'static str) {
        self.failures.get_or_create(&vec![("reason", reason)]).inc();
    }

    pub fn finish(&self, reason: &'static str) {
        self.finished.get_or_create(&vec![("reason", reason)]).inc();
    }

    /// Counts `took` as work of `stage`.
    pub fn add_work(&self, stage: Stage, took: Duration) {
        self.work.get_or_create(&vec![("stage", stage.name())]).inc_by(took.as_secs_f64());
    }

    /// Runs `work` and counts its time as work of `stage`.
    pub fn time<T>(&self, stage: Stage, work: impl FnOnce() -> T) -> T {
        let started = std::time::Instant::now();
        let out = work();
        self.add_work(stage, started.elapsed());
        out
    }

    /// Counts what an answer says of itself; an answer without faces has nothing to say.
    pub fn observe_answer(&self, quality: &MeshQuality) {
        if quality.edges == 0 {
            return;
        }
        self.answer_parts.observe(quality.parts as f64);
        self.answer_boundary_share.observe(quality.boundary_edges as f64 / quality.edges as f64);
        if let Some(cd) = quality.input_chamfer {
            self.answer_input_chamfer.observe(cd);
        }
    }

    /// Counts a decode step of `rows` sequences.
    pub fn observe_step(&self, rows: usize) {
        self.batch_size.observe(rows as f64);
        self.steps.fetch_add(1, Ordering::Relaxed);
        self.rows_stepped.fetch_add(rows as u64, Ordering::Relaxed);
    }

    /// Decode steps so far and the sequences they stepped in all.
    pub fn decode_steps(&self) -> (u64, u64) {
        (self.steps.load(Ordering::Relaxed), self.rows_stepped.load(Ordering::Relaxed))
    }

    /// Seconds of work counted for `stage` so far.
    pub fn work_seconds(&self, stage: Stage) -> f64 {
        self.work.get_or_create(&vec![("stage", stage.name())]).get()
    }

    /// The Prometheus text exposition format.
    pub fn render(&self) -> String {
        let mut out = String::new();
        // Writing into a String cannot fail.
        let _ = encode(&mut out, &self.registry);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metrics_render_in_the_text_format_with_labels() {
        let m = Metrics::default();
        m.reject("queue_full");
        m.observe_step(4);
        m.observe_step(3);
        assert_eq!(m.decode_steps(), (2, 7));
        m.faces_generated.inc_by(7);
        m.add_work(Stage::Decode, Duration::from_millis(250));
        m.time(Stage::Decode, || ());
        assert!((0.25..0.3).contains(&m.work_seconds(Stage::Decode)));
        assert_eq!(m.work_seconds(Stage::End), 0.0);
        let text = m.render();
        assert!(text.contains("meshstream_work_seconds_total{stage=\"decode\"} 0.25"));
        assert!(text.contains("meshstream_requests_rejected_total{reason=\"queue_full\"} 1"));
        assert!(text.contains("meshstream_faces_generated_total 7"));
        assert!(text.contains("meshstream_batch_size_count 2"));
        // Answers: an empty one says nothing, an image's no distance.
        let answer = |edges, input_chamfer| MeshQuality {
            edges,
            boundary_edges: edges / 4,
            non_manifold_edges: 0,
            parts: 3,
            watertight: false,
            input_chamfer,
        };
        m.observe_answer(&answer(0, None));
        m.observe_answer(&answer(40, Some(0.03)));
        m.observe_answer(&answer(40, None));
        let text = m.render();
        assert!(text.contains("meshstream_answer_parts_count 2"), "{text}");
        assert!(text.contains("meshstream_answer_boundary_share_bucket{le=\"0.3\"} 2"), "{text}");
        assert!(text.contains("meshstream_answer_input_chamfer_count 1"), "{text}");
        assert!(text.ends_with("# EOF\n"));
    }
}
