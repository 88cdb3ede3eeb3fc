//! What a client receives: faces as they are decoded, in its own coordinates, then a summary
//! with what the answer says of itself (its build, its distance to the input).

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::mpsc;

use crate::mesh::{Mesh, Normalization};
use crate::metrics::MeshQuality;
use crate::model::FinishReason;
use crate::tokenize::FaceToken;

use super::EngineError;
use super::metrics::Metrics;
use super::offload::off_runtime;

#[derive(Debug, Clone, PartialEq)]
pub struct StreamedFace {
    /// 0 for the first face of the request.
    pub index: usize,
    pub token: FaceToken,
    /// The three corners in the caller's coordinates, in the face's winding.
    pub vertices: [[f32; 3]; 3],
}

#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    pub faces: usize,
    pub finish: FinishReason,
    /// Waiting in the queue, the stage before decoding (the point encoder, or diffusion from
    /// the image), and decoding.
    pub queued: Duration,
    pub prepare: Duration,
    pub decode: Duration,
    pub time_to_first_face: Option<Duration>,
    /// Until the last face was ready: the answer is measured after.
    pub total: Duration,
    /// The answer's build and distance to its input, measured as the request's stream hands
    /// it over ([`RequestStream`]); `None` inside the engine (a candidate, an attempt) and when
    /// it could not be measured.
    pub quality: Option<MeshQuality>,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// An image request's diffusion stage: `step` of `steps` Euler steps done. Sent when the
    /// client has room for it; a slow client may miss some, never the faces.
    Progress {
        step: usize,
        steps: usize,
    },
    Face(StreamedFace),
    /// A face of a whole answer's first candidate as it is decoded ([`super::DecodeOptions`]
    /// `drafts`), before the answer's own faces: not part of the answer. Sent when the client
    /// has room for it; a slow client may miss some, never the answer's faces.
    Draft(StreamedFace),
    /// The last event of a request that completed.
    Finished(Summary),
    /// The last event of a request that did not.
    Failed(EngineError),
}

/// A finished request: the mesh in the caller's coordinates (vertices welded as in
/// [`crate::tokenize::detokenize`]) and how it went.
#[derive(Debug, Clone)]
pub struct Completed {
    pub mesh: Mesh,
    pub tokens: Vec<FaceToken>,
    pub summary: Summary,
}

/// The receiving end of one request. Dropping it cancels the request: the engine sees the
/// closed channel before its next step.
#[derive(Debug)]
pub struct RequestStream {
    pub id: String,
    events: mpsc::Receiver<Event>,
    /// Set on the stream a client gets ([`RequestStream::measured`]), not on the engine's own.
    answer: Option<Answer>,
}

/// The faces a client has been handed so far, to measure the answer by when it ends.
struct Answer {
    corners: Vec<[[f32; 3]; 3]>,
    /// A points request's input points (normalized frame) and the normalization that takes
    /// the faces back to that frame.
    input: Option<(Arc<Mesh>, Normalization)>,
    metrics: Arc<Metrics>,
}

impl RequestStream {
    pub(super) fn new(id: String, events: mpsc::Receiver<Event>) -> Self {
        Self { id, events, answer: None }
    }

    /// This stream's summary carries the answer's [`MeshQuality`], measured against `input`
    /// (a points request's reference points and normalization) when there is one.
    pub(super) fn measured(
        mut self,
        input: Option<(Arc<Mesh>, Normalization)>,
        metrics: Arc<Metrics>,
    ) -> Self {
        self.answer = Some(Answer { corners: Vec::new(), input, metrics });
        self
    }

    /// The next event; `None` after the last one (or if the engine went away).
    pub async fn next(&mut self) -> Option<Event> {
        let mut event = self.events.recv().await?;
        self.observe(std::slice::from_mut(&mut event)).await;
        Some(event)
    }

    /// Up to `max` events that are ready now, waiting only for the first: lets a slow reader
    /// take several faces at once.
    pub async fn next_many(&mut self, max: usize) -> Vec<Event> {
        let mut out = Vec::new();
        self.events.recv_many(&mut out, max.max(1)).await;
        self.observe(&mut out).await;
        out
    }

    /// Keeps the faces handed over and measures the answer into its summary at the end.
    async fn observe(&mut self, events: &mut [Event]) {
        let Some(answer) = &mut self.answer else { return };
        for event in events {
            match event {
                Event::Face(face) => answer.corners.push(face.vertices),
                Event::Finished(summary) => summary.quality = answer.measure().await,
                Event::Progress { .. } | Event::Draft(_) | Event::Failed(_) => {}
            }
        }
    }

    /// Waits for the whole request. The mesh is made of the faces' corners as they came,
    /// which are the tokens' unless the mesh was fitted to its points.
    pub async fn collect(self) -> Result<Completed, EngineError> {
        self.collect_watching(|_| {}).await
    }

    /// [`Self::collect`], handing each face to `watch` as it comes.
    pub(super) async fn collect_watching(
        mut self,
        mut watch: impl FnMut(&StreamedFace),
    ) -> Result<Completed, EngineError> {
        let (mut tokens, mut corners) = (Vec::new(), Vec::new());
        while let Some(event) = self.next().await {
            match event {
                Event::Progress { .. } | Event::Draft(_) => {}
                Event::Face(face) => {
                    watch(&face);
                    tokens.push(face.token);
                    corners.push(face.vertices);
                }
                Event::Finished(summary) => {
                    let mesh = Mesh::from_triangles(corners);
                    return Ok(Completed { mesh, tokens, summary });
                }
                Event::Failed(e) => return Err(e),
            }
        }
        Err(EngineError::Stopped)
    }
}

impl std::fmt::Debug for Answer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Answer")
            .field("faces", &self.corners.len())
            .field("input_points", &self.input.as_ref().map(|(p, _)| p.vertices.len()))
            .finish_non_exhaustive()
    }
}

impl Answer {
    /// The faces handed over, measured off the async runtime; `None` if that failed.
    async fn measure(&mut self) -> Option<MeshQuality> {
        let corners = std::mem::take(&mut self.corners);
        let input = self.input.clone();
        let work = move || {
            // Back in the frame of the input points, where there are some.
            let frame = |p| input.as_ref().map_or(p, |(_, n)| n.apply(p));
            let mesh = Mesh::from_triangles(corners.iter().map(|c| c.map(frame)));
            MeshQuality::measure(&mesh, input.as_ref().map(|(points, _)| &points.vertices[..]))
        };
        let quality = off_runtime(&self.metrics, work).await.ok()?;
        self.metrics.observe_answer(&quality);
        Some(quality)
    }
}
