//! The gRPC interface (tonic): `meshstream.v1.MeshGenerator/Reconstruct` and
//! `GenerateFromImage`, plus the standard health service and server reflection (so `grpcurl`
//! works without the proto file).

use std::collections::VecDeque;
use std::pin::Pin;
use std::time::{Duration, Instant};

use futures_util::{Stream, stream};
use tonic::{Request, Response, Status};

use crate::engine::{
    Conditioning, DecodeOptions, Engine, Event, RequestStream, StreamedFace, Summary,
};
use crate::mesh::Format;

use super::error::ApiError;
use super::image_input::{GenerateOptions, ImageDefaults, ImageUpload};
use super::input::{InputLimits, ReconstructOptions, parse_file, point_cloud};
use super::proto::mesh_generator_server::MeshGenerator;
use super::proto::{
    Face, FaceChunk, GenerateRequest, MeshQuality, Progress, ReconstructRequest,
    ReconstructResponse, Stats, reconstruct_request, reconstruct_response,
};
use super::{no_image_model, prepare};

/// Faces sent in one message at most, when several are waiting.
const MAX_FACES_PER_MESSAGE: usize = 64;

pub struct GrpcService {
    pub engine: Engine,
    pub limits: InputLimits,
    /// `None` when the engine has no image model.
    pub image: Option<ImageDefaults>,
    pub request_timeout: Duration,
}

impl From<ApiError> for Status {
    fn from(e: ApiError) -> Self {
        let message = format!("{}: {}", e.code, e.message);
        match e.status.as_u16() {
            // The server gave up on the client (a stalled stream reader, a body too slow).
            408 => Status::cancelled(message),
            429 => Status::resource_exhausted(message),
            501 => Status::unimplemented(message),
            503 => Status::unavailable(message),
            504 => Status::deadline_exceeded(message),
            400..=499 => Status::invalid_argument(message),
            _ => Status::internal(message),
        }
    }
}

type ResponseStream = Pin<Box<dyn Stream<Item = Result<ReconstructResponse, Status>> + Send>>;

#[tonic::async_trait]
impl MeshGenerator for GrpcService {
    type ReconstructStream = ResponseStream;
    type GenerateFromImageStream = ResponseStream;

    async fn reconstruct(
        &self,
        request: Request<ReconstructRequest>,
    ) -> Result<Response<ResponseStream>, Status> {
        let id = request_id(&request);
        let started = self.start(&id, request.into_inner()).await;
        self.answer(id, started)
    }

    async fn generate_from_image(
        &self,
        request: Request<GenerateRequest>,
    ) -> Result<Response<ResponseStream>, Status> {
        let id = request_id(&request);
        let started = self.start_image(&id, request.into_inner()).await;
        self.answer(id, started)
    }
}

/// The caller's `x-request-id`, if it is usable, or a new one.
fn request_id<T>(request: &Request<T>) -> String {
    request
        .metadata()
        .get("x-request-id")
        .and_then(|v| v.to_str().ok())
        .filter(|v| !v.is_empty() && v.len() <= 128)
        .map_or_else(|| uuid::Uuid::new_v4().to_string(), str::to_string)
}

impl GrpcService {
    /// The response stream of a started request, or its refusal as a status.
    fn answer(
        &self,
        id: String,
        started: Result<RequestStream, ApiError>,
    ) -> Result<Response<ResponseStream>, Status> {
        let stream = started.inspect_err(|e| {
            // The engine counts its own refusals; these are the ones before it.
            if !matches!(e.status.as_u16(), 429 | 503) {
                self.engine.metrics().reject(e.code);
            }
            tracing::info!(request_id = %id, code = e.code, "refused: {}", e.message);
        })?;
        let mut response = Response::new(Box::pin(responses(stream, id.clone())) as ResponseStream);
        if let Ok(v) = id.parse() {
            response.metadata_mut().insert("x-request-id", v);
        }
        Ok(response)
    }

    async fn start_image(
        &self,
        id: &str,
        request: GenerateRequest,
    ) -> Result<RequestStream, ApiError> {
        let defaults = self.image.clone().ok_or_else(no_image_model)?;
        let o = request.options.unwrap_or_default();
        let upload = ImageUpload {
            image: request.image.into(),
            options: GenerateOptions {
                max_faces: o.max_faces.map(|n| n as usize),
                steps: o.steps.map(|n| n as usize),
                guidance: o.guidance,
                seed: o.seed,
                temperature: o.temperature,
                top_k: o.top_k.map(|k| k as usize),
                top_p: o.top_p,
                face_beam: o.face_beam.map(|n| n as usize),
                format: None,
                framing: o.framing,
            },
        };
        let parsed = tokio::task::spawn_blocking(move || upload.parse(&defaults))
            .await
            .map_err(|e| ApiError::internal(format!("request preparation stopped: {e}")))??;
        self.submit(id, Conditioning::Image(parsed.prompt), parsed.decode)
    }

    fn submit(
        &self,
        id: &str,
        conditioning: Conditioning,
        options: DecodeOptions,
    ) -> Result<RequestStream, ApiError> {
        let request = crate::engine::Request {
            id: id.to_string(),
            conditioning,
            options,
            deadline: Some(Instant::now() + self.request_timeout),
        };
        Ok(self.engine.submit(request)?)
    }

    async fn start(
        &self,
        id: &str,
        request: ReconstructRequest,
    ) -> Result<RequestStream, ApiError> {
        let options = request.options.unwrap_or_default();
        let options = ReconstructOptions {
            max_faces: options.max_faces.map(|n| n as usize),
            temperature: options.temperature,
            top_k: options.top_k.map(|k| k as usize),
            top_p: options.top_p,
            face_beam: options.face_beam.map(|n| n as usize),
            candidates: options.candidates.map(|n| n as usize),
            fit_rounds: options.fit_rounds.map(|n| n as usize),
            // Past u16 is past the limit too: saturate, and let the check refuse it.
            weld_radius: options.weld_radius.map(|n| u16::try_from(n).unwrap_or(u16::MAX)),
            max_hole_edges: options.max_hole_edges.map(|n| n as usize),
            hull_faces: options.hull_faces.map(|n| n as usize),
            seed: options.seed,
            format: None,
            up: options.up,
            drafts: options.drafts,
        };
        let (limits, engine) = (self.limits, self.engine.clone());
        let (parsed, prepared) = tokio::task::spawn_blocking(move || {
            let mesh = match request.input {
                Some(reconstruct_request::Input::Points(p)) => {
                    point_cloud(&p.positions, &p.normals, &limits)?
                }
                Some(reconstruct_request::Input::File(f)) => {
                    let format = match f.format.as_str() {
                        "" => None,
                        name => Some(name.parse::<Format>().map_err(|_| {
                            ApiError::invalid(format!("format {name:?}: use ply, obj, stl or glb"))
                        })?),
                    };
                    parse_file(&f.data, format, &limits)?
                }
                None => return Err(ApiError::invalid("give points or a file")),
            };
            let parsed = options.checked(mesh)?;
            let draws = parsed.decode.candidates.unwrap_or(1);
            let prepared = prepare(&engine, &parsed.input, &limits, parsed.seed, draws, parsed.up)?;
            Ok((parsed, prepared))
        })
        .await
        .map_err(|e| ApiError::internal(format!("request preparation stopped: {e}")))??;
        self.submit(id, prepared, parsed.decode)
    }
}

/// The request's events as messages: the faces that are waiting, in one message, then the
/// stats. Dropping it (the client went away) cancels the request.
fn responses(
    stream: RequestStream,
    id: String,
) -> impl Stream<Item = Result<ReconstructResponse, Status>> {
    let state = (Some(stream), VecDeque::new());
    stream::unfold(state, move |(mut stream, mut ready)| {
        let id = id.clone();
        async move {
            loop {
                if let Some(message) = ready.pop_front() {
                    return Some((message, (stream, ready)));
                }
                let events = stream.as_mut()?.next_many(MAX_FACES_PER_MESSAGE).await;
                if events.is_empty() {
                    return None;
                }
                let (mut faces, mut drafts) = (Vec::new(), Vec::new());
                let mut progress = None;
                let mut last = None;
                let face = |f: StreamedFace| Face {
                    index: f.index as u32,
                    vertices: f.vertices.iter().flatten().copied().collect(),
                };
                for event in events {
                    match event {
                        // Only the latest matters to a client that is behind.
                        Event::Progress { step, steps } => {
                            progress = Some(Progress { step: step as u32, steps: steps as u32 });
                        }
                        Event::Face(f) => faces.push(face(f)),
                        // Every draft comes before the answer's first face.
                        Event::Draft(f) => drafts.push(face(f)),
                        Event::Finished(summary) => last = Some(Ok(done(&id, &summary))),
                        Event::Failed(e) => last = Some(Err(Status::from(ApiError::from(e)))),
                    }
                }
                if let Some(p) = progress {
                    let event = reconstruct_response::Event::Progress(p);
                    ready.push_back(Ok(ReconstructResponse { event: Some(event) }));
                }
                if !drafts.is_empty() {
                    let event = reconstruct_response::Event::Drafts(FaceChunk { faces: drafts });
                    ready.push_back(Ok(ReconstructResponse { event: Some(event) }));
                }
                if !faces.is_empty() {
                    let event = reconstruct_response::Event::Faces(FaceChunk { faces });
                    ready.push_back(Ok(ReconstructResponse { event: Some(event) }));
                }
                if let Some(last) = last {
                    ready.push_back(last);
                    stream = None;
                }
            }
        }
    })
}

fn done(id: &str, s: &Summary) -> ReconstructResponse {
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    let stats = Stats {
        request_id: id.to_string(),
        faces: s.faces as u32,
        finish_reason: s.finish.name().to_string(),
        queued_ms: ms(s.queued),
        encode_ms: ms(s.prepare),
        decode_ms: ms(s.decode),
        time_to_first_face_ms: s.time_to_first_face.map(ms),
        total_ms: ms(s.total),
        quality: s.quality.map(|q| MeshQuality {
            edges: saturating_u32(q.edges),
            boundary_edges: saturating_u32(q.boundary_edges),
            non_manifold_edges: saturating_u32(q.non_manifold_edges),
            parts: saturating_u32(q.parts),
            watertight: q.watertight,
            input_chamfer: q.input_chamfer,
        }),
    };
    ReconstructResponse { event: Some(reconstruct_response::Event::Done(stats)) }
}

fn saturating_u32(n: usize) -> u32 {
    u32::try_from(n).unwrap_or(u32::MAX)
}
