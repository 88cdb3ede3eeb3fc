//! The JSON of streamed events, shared by the SSE and NDJSON streams.

use serde::Serialize;
use utoipa::ToSchema;

use crate::engine::{StreamedFace, Summary};
use crate::metrics::MeshQuality;

use super::error::ErrorBody;

/// The diffusion stage of an image request: `step` of `steps` Euler steps done.
#[derive(Serialize, ToSchema)]
pub struct ProgressEvent {
    pub step: usize,
    pub steps: usize,
}

#[derive(Serialize, ToSchema)]
pub struct FaceEvent {
    pub index: usize,
    /// The three corners in the request's coordinates, in the face's winding.
    pub vertices: [[f32; 3]; 3],
}

#[derive(Serialize, ToSchema)]
pub struct DoneEvent {
    pub request_id: String,
    pub faces: usize,
    /// end_of_mesh, max_faces, dead_end or cancelled; convex_hull when a fitted answer is the
    /// convex hull of the input points, which ended at least 10% closer to them than every decoded
    /// candidate.
    pub finish_reason: &'static str,
    pub queued_ms: f64,
    /// The stage before decoding: the point encoder, or diffusion from the image.
    pub encode_ms: f64,
    pub decode_ms: f64,
    pub time_to_first_face_ms: Option<f64>,
    /// Until the last face was ready.
    pub total_ms: f64,
    /// How the mesh is built and how far it lies from the input points: absent only when it
    /// could not be measured.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub quality: Option<MeshQuality>,
}

/// One NDJSON line.
#[derive(Serialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Line {
    Progress(ProgressEvent),
    Face(FaceEvent),
    /// A face of the first candidate as it is decoded (the `drafts` option), not of the answer.
    Draft(FaceEvent),
    Done(DoneEvent),
    Error(ErrorBody),
}

impl From<&StreamedFace> for FaceEvent {
    fn from(f: &StreamedFace) -> Self {
        Self { index: f.index, vertices: f.vertices }
    }
}

impl DoneEvent {
    pub fn new(request_id: &str, s: &Summary) -> Self {
        let ms = |d: std::time::Duration| d.as_secs_f64() * 1e3;
        Self {
            request_id: request_id.to_string(),
            faces: s.faces,
            finish_reason: s.finish.name(),
            queued_ms: ms(s.queued),
            encode_ms: ms(s.prepare),
            decode_ms: ms(s.decode),
            time_to_first_face_ms: s.time_to_first_face.map(ms),
            total_ms: ms(s.total),
            quality: s.quality,
        }
    }
}
