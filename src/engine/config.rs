use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::EngineError;

/// The scheduler's knobs. The defaults suit the `tiny` model on a 2-core machine.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EngineConfig {
    /// Sequences decoded together, one face each per iteration. The default, 64, lets 16
    /// whole-mesh requests (4 candidates each) decode at once: on 2 cores their rows stepped
    /// together gave 9-12% more faces/s than 16 rows did (`docs/decisions.md`, "Serving"), for
    /// at most 64 decoder caches (about 4 MiB each at the shipped model's 400 faces).
    pub max_running: usize,
    /// Requests waiting to start; one more is refused (HTTP 429).
    pub max_queue: usize,
    /// Face budget of one request (also capped by the model's own limit).
    pub max_faces_per_request: usize,
    /// Sum of the face budgets of the running sequences: bounds the decoder caches' memory.
    pub max_batch_faces: usize,
    /// Requests sent to the encoder (as one batch) in one iteration: a smaller batch comes
    /// back sooner.
    pub max_encodes_per_iteration: usize,
    /// A request waiting this long is refused rather than started.
    #[serde(with = "secs")]
    pub queue_timeout: Duration,
    /// A waiting request older than this is no longer overtaken by smaller ones that fit.
    #[serde(with = "secs")]
    pub aging: Duration,
    /// Events buffered for a client that reads slower than the model writes; a sequence
    /// whose buffer is full waits (it is not stepped) until the client catches up.
    pub stream_buffer: usize,
    /// A sequence whose client has not made room in its buffer for this long is cancelled,
    /// so that a reader that stalls cannot hold its slot and face budget for ever.
    #[serde(with = "secs")]
    pub stream_idle_timeout: Duration,
    /// Threads that step parts of the running batch in parallel (0: one per core).
    pub decode_threads: usize,
    /// Euler steps an image request may ask for: each costs one or two forward passes of
    /// the diffusion model over its batch.
    pub max_diffusion_steps: usize,
    /// Samples an image request may take: one whose mesh comes out empty is sampled again
    /// from the next seed, up to this many times in all (1: never).
    pub image_attempts: usize,
    /// A fitted reconstruction of several candidates or one judges the convex hull of its input
    /// points beside them, with at most this many faces (and its face budget): the answer is the
    /// hull when it ends at least 10% closer to the points (0: never;
    /// [`crate::candidates::hull_candidate`]).
    pub hull_faces: usize,
}

impl Default for EngineConfig {
    fn default() -> Self {
        Self {
            max_running: 64,
            max_queue: 64,
            max_faces_per_request: 4096,
            max_batch_faces: 16 * 4096,
            max_encodes_per_iteration: 4,
            queue_timeout: Duration::from_secs(30),
            aging: Duration::from_secs(2),
            stream_buffer: 256,
            stream_idle_timeout: Duration::from_secs(30),
            decode_threads: 0,
            max_diffusion_steps: 250,
            image_attempts: 3,
            hull_faces: crate::candidates::DEFAULT_HULL_FACES,
        }
    }
}

impl EngineConfig {
    pub fn validate(&self) -> Result<(), EngineError> {
        let positive = [
            ("max_running", self.max_running),
            ("max_queue", self.max_queue),
            ("max_faces_per_request", self.max_faces_per_request),
            ("max_batch_faces", self.max_batch_faces),
            ("max_encodes_per_iteration", self.max_encodes_per_iteration),
            ("max_diffusion_steps", self.max_diffusion_steps),
            ("image_attempts", self.image_attempts),
        ];
        if let Some((name, _)) = positive.iter().find(|(_, v)| *v == 0) {
            return Err(EngineError::InvalidInput(format!("{name} must be at least 1")));
        }
        if self.stream_buffer < 2 {
            // One face plus the final event must always fit.
            return Err(EngineError::InvalidInput("stream_buffer must be at least 2".into()));
        }
        Ok(())
    }

    pub fn threads(&self) -> usize {
        match self.decode_threads {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
            n => n,
        }
    }
}

mod secs {
    use std::time::Duration;

    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(d: &Duration, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_f64(d.as_secs_f64())
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Duration, D::Error> {
        let secs = f64::deserialize(d)?;
        Duration::try_from_secs_f64(secs).map_err(serde::de::Error::custom)
    }
}
