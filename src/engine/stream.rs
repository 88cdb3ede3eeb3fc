//! What a client receives: faces as they are decoded, in its own coordinates, then a summary.

use std::time::Duration;

use tokio::sync::mpsc;

use crate::mesh::Mesh;
use crate::model::FinishReason;
use crate::tokenize::FaceToken;

use super::EngineError;

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
    pub total: Duration,
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
}

impl RequestStream {
    pub(super) fn new(id: String, events: mpsc::Receiver<Event>) -> Self {
        Self { id, events }
    }

    /// The next event; `None` after the last one (or if the engine went away).
    pub async fn next(&mut self) -> Option<Event> {
        self.events.recv().await
    }

    /// Up to `max` events that are ready now, waiting only for the first: lets a slow reader
    /// take several faces at once.
    pub async fn next_many(&mut self, max: usize) -> Vec<Event> {
        let mut out = Vec::new();
        self.events.recv_many(&mut out, max.max(1)).await;
        out
    }

    /// Waits for the whole request. The mesh is made of the faces' corners as they came,
    /// which are the tokens' unless the mesh was fitted to its points.
    pub async fn collect(mut self) -> Result<Completed, EngineError> {
        let (mut tokens, mut corners) = (Vec::new(), Vec::new());
        while let Some(event) = self.next().await {
            match event {
                Event::Progress { .. } => {}
                Event::Face(face) => {
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
