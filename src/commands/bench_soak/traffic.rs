//! One soak client's requests: what kinds there are, how each is sent and read to its end,
//! and what came of it. A request refused with 429 (RESOURCE_EXHAUSTED) is sent again after
//! its `Retry-After`.

use std::time::{Duration, Instant};

use futures_util::StreamExt;
use meshstream::mesh::{Format, ReadLimits, read_mesh};
use meshstream::server::proto::mesh_generator_client::MeshGeneratorClient;
use meshstream::server::proto::{Options, PointCloud, ReconstructRequest, reconstruct_request};
use meshstream::server::proto::{ReconstructResponse, reconstruct_response};
use rand::Rng;
use reqwest::StatusCode;
use reqwest::header::{ACCEPT, CONTENT_TYPE, RETRY_AFTER};
use serde_json::{Value, json};
use tonic::transport::Channel;

/// What a request is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// `POST /reconstruct` answered with a GLB.
    HttpMesh,
    /// `POST /reconstruct` answered with NDJSON events; `leave`: the client goes away after
    /// its first face.
    HttpStream {
        leave: bool,
    },
    /// `MeshGenerator/Reconstruct`.
    GrpcStream {
        leave: bool,
    },
    Garbage(Garbage),
}

/// Requests the server must refuse, each in its own way.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Garbage {
    /// JSON that is not JSON.
    BadJson,
    /// Points JSON sent as `text/plain`.
    WrongContentType,
    /// Points JSON cut off halfway.
    Truncated,
    /// One byte over the server's body limit.
    Oversized,
    /// A gRPC request with no points.
    NoPoints,
}

impl Kind {
    pub fn name(self) -> &'static str {
        match self {
            Self::HttpMesh => "HTTP whole mesh",
            Self::HttpStream { .. } => "HTTP stream",
            Self::GrpcStream { .. } => "gRPC stream",
            Self::Garbage(_) => "garbage",
        }
    }
}

/// The shares of each kind of request.
#[derive(Debug, Clone, Copy)]
pub struct Mix {
    pub garbage: f64,
    /// Of the requests that are not garbage.
    pub grpc: f64,
    /// Of the HTTP requests that are not garbage.
    pub http_stream: f64,
    /// Of the streams.
    pub leave: f64,
}

impl Mix {
    pub fn pick(&self, rng: &mut impl Rng, grpc: bool) -> Kind {
        if rng.random_bool(self.garbage) {
            let all = [
                Garbage::BadJson,
                Garbage::WrongContentType,
                Garbage::Truncated,
                Garbage::Oversized,
                Garbage::NoPoints,
            ];
            let pick = all[rng.random_range(0..if grpc { all.len() } else { all.len() - 1 })];
            return Kind::Garbage(pick);
        }
        let leave = rng.random_bool(self.leave);
        if grpc && rng.random_bool(self.grpc) {
            Kind::GrpcStream { leave }
        } else if rng.random_bool(self.http_stream) {
            Kind::HttpStream { leave }
        } else {
            Kind::HttpMesh
        }
    }
}

/// What came of a request.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// A whole answer: `latency` from sending the request that was admitted to its last byte.
    Completed { latency: Duration, first_face: Option<Duration> },
    /// An error answer: an HTTP status, a gRPC status or a stream's error event.
    Refused(String),
    /// The client went away after the first face, as planned.
    Left,
    /// A garbage request that was answered as if it were valid.
    Accepted(String),
    /// No complete answer and no error.
    Lost(String),
}

#[derive(Debug)]
pub struct Record {
    pub kind: Kind,
    pub outcome: Outcome,
    /// The time each 429 (RESOURCE_EXHAUSTED) answer took.
    pub busy: Vec<Duration>,
}

/// What every client sends, made once.
pub struct Traffic {
    pub http: reqwest::Client,
    pub base_url: String,
    pub grpc_url: Option<String>,
    /// The points JSON, without options.
    pub points: Value,
    pub grpc_points: PointCloud,
    pub max_faces: u32,
    pub candidates: u32,
    pub fit_rounds: u32,
    /// The server's body limit, for the oversized garbage.
    pub max_body_bytes: usize,
    pub max_retries: u32,
    /// A request with no complete answer after this long counts as lost.
    pub timeout: Duration,
}

enum Attempt {
    /// 429: try again after this long.
    Busy(Duration),
    Done(Outcome),
}

/// One client: a gRPC connection of its own (made when first needed), HTTP from the pool.
pub struct Client<'a> {
    traffic: &'a Traffic,
    grpc: Option<MeshGeneratorClient<Channel>>,
}

impl<'a> Client<'a> {
    pub fn new(traffic: &'a Traffic) -> Self {
        Self { traffic, grpc: None }
    }

    /// Sends the request until it is not refused with 429, at most `max_retries` times more.
    pub async fn send(&mut self, kind: Kind, seed: u64) -> Record {
        let mut busy = Vec::new();
        for _ in 0..=self.traffic.max_retries {
            let t0 = Instant::now();
            let attempt = tokio::time::timeout(self.traffic.timeout, self.attempt(kind, seed))
                .await
                .unwrap_or_else(|_| {
                    let secs = self.traffic.timeout.as_secs_f64();
                    Attempt::Done(Outcome::Lost(format!("no complete answer within {secs} s")))
                });
            match attempt {
                Attempt::Busy(after) => {
                    busy.push(t0.elapsed());
                    tokio::time::sleep(after).await;
                }
                Attempt::Done(outcome) => return Record { kind, outcome, busy },
            }
        }
        let outcome = Outcome::Refused(format!("queue_full {} times", busy.len()));
        Record { kind, outcome, busy }
    }

    async fn attempt(&mut self, kind: Kind, seed: u64) -> Attempt {
        match kind {
            Kind::GrpcStream { leave } => self.grpc(self.grpc_request(seed), leave, false).await,
            Kind::Garbage(Garbage::NoPoints) => {
                let request = ReconstructRequest {
                    input: Some(reconstruct_request::Input::Points(PointCloud::default())),
                    options: None,
                };
                self.grpc(request, false, true).await
            }
            _ => self.http(kind, seed).await,
        }
    }

    fn options(&self, seed: u64) -> Value {
        json!({"max_faces": self.traffic.max_faces, "seed": seed})
    }

    fn points_json(&self, extra: Value) -> Vec<u8> {
        let mut body = self.traffic.points.clone();
        if let (Some(b), Some(e)) = (body.as_object_mut(), extra.as_object()) {
            b.extend(e.clone());
        }
        serde_json::to_vec(&body).unwrap_or_default()
    }

    async fn http(&self, kind: Kind, seed: u64) -> Attempt {
        let json_type = "application/json";
        let (content_type, body) = match kind {
            Kind::HttpMesh => {
                let mut options = self.options(seed);
                options["candidates"] = self.traffic.candidates.into();
                options["fit_rounds"] = self.traffic.fit_rounds.into();
                (json_type, self.points_json(options))
            }
            Kind::Garbage(Garbage::BadJson) => (json_type, b"{\"points\": [[0, 0,, 1]".to_vec()),
            Kind::Garbage(Garbage::WrongContentType) => {
                ("text/plain", self.points_json(self.options(seed)))
            }
            Kind::Garbage(Garbage::Truncated) => {
                let mut body = self.points_json(self.options(seed));
                body.truncate(body.len() / 2);
                (json_type, body)
            }
            Kind::Garbage(Garbage::Oversized) => {
                (json_type, vec![b' '; self.traffic.max_body_bytes + 1])
            }
            _ => (json_type, self.points_json(self.options(seed))),
        };
        let streaming = matches!(kind, Kind::HttpStream { .. });
        let accept = if streaming { "application/x-ndjson" } else { "*/*" };
        let url = format!("{}/reconstruct", self.traffic.base_url);
        let t0 = Instant::now();
        let sent = self
            .traffic
            .http
            .post(url)
            .header(CONTENT_TYPE, content_type)
            .header(ACCEPT, accept)
            .body(body)
            .send()
            .await;
        let response = match sent {
            Ok(r) => r,
            Err(e) => return Attempt::Done(Outcome::Lost(format!("no answer: {e}"))),
        };
        let status = response.status();
        if status == StatusCode::TOO_MANY_REQUESTS {
            let after = response
                .headers()
                .get(RETRY_AFTER)
                .and_then(|v| v.to_str().ok()?.parse::<u64>().ok())
                .map_or(Duration::from_secs(1), Duration::from_secs);
            return Attempt::Busy(after);
        }
        if !status.is_success() {
            let body: Value = response.json().await.unwrap_or(Value::Null);
            let code = body["error"]["code"].as_str().unwrap_or("(no error body)");
            return Attempt::Done(Outcome::Refused(format!("HTTP {} {code}", status.as_u16())));
        }
        if matches!(kind, Kind::Garbage(_)) {
            return Attempt::Done(Outcome::Accepted(format!("HTTP {status}")));
        }
        let outcome = match kind {
            Kind::HttpStream { leave } => read_ndjson(response, t0, leave).await,
            _ => read_glb(response, t0).await,
        };
        Attempt::Done(outcome)
    }

    fn grpc_request(&self, seed: u64) -> ReconstructRequest {
        ReconstructRequest {
            input: Some(reconstruct_request::Input::Points(self.traffic.grpc_points.clone())),
            options: Some(Options {
                max_faces: Some(self.traffic.max_faces),
                seed: Some(seed),
                ..Options::default()
            }),
        }
    }

    async fn grpc(&mut self, request: ReconstructRequest, leave: bool, garbage: bool) -> Attempt {
        let client = match self.grpc_client().await {
            Ok(c) => c,
            Err(e) => return Attempt::Done(Outcome::Lost(format!("no gRPC connection: {e}"))),
        };
        let t0 = Instant::now();
        let mut stream = match client.reconstruct(request).await {
            Ok(r) => r.into_inner(),
            Err(status) if status.code() == tonic::Code::ResourceExhausted => {
                return Attempt::Busy(Duration::from_secs(1));
            }
            Err(status) => return Attempt::Done(grpc_error(&status)),
        };
        if garbage {
            return Attempt::Done(Outcome::Accepted("gRPC OK".into()));
        }
        let (mut faces, mut first_face) = (0usize, None);
        loop {
            let message: Option<ReconstructResponse> = match stream.message().await {
                Ok(m) => m,
                Err(status) => return Attempt::Done(grpc_error(&status)),
            };
            let Some(event) = message.and_then(|m| m.event) else {
                return Attempt::Done(Outcome::Lost("the stream ended without its stats".into()));
            };
            match event {
                reconstruct_response::Event::Faces(chunk) => {
                    faces += chunk.faces.len();
                    first_face.get_or_insert_with(|| t0.elapsed());
                    if leave {
                        return Attempt::Done(Outcome::Left);
                    }
                }
                reconstruct_response::Event::Done(stats) => {
                    return Attempt::Done(counted(stats.faces as usize, faces, t0, first_face));
                }
                reconstruct_response::Event::Progress(_)
                | reconstruct_response::Event::Drafts(_) => {}
            }
        }
    }

    async fn grpc_client(&mut self) -> Result<&mut MeshGeneratorClient<Channel>, String> {
        let Some(url) = &self.traffic.grpc_url else {
            return Err("this run has no gRPC endpoint".into());
        };
        if self.grpc.is_none() {
            let client = MeshGeneratorClient::connect(url.clone()).await;
            self.grpc = Some(client.map_err(|e| e.to_string())?);
        }
        self.grpc.as_mut().ok_or_else(|| "no gRPC client".into())
    }
}

/// A gRPC status from the server is an error answer; one the transport made up (the
/// connection broke: `Unknown`, or a message without the server's `code: ` prefix) is not.
fn grpc_error(status: &tonic::Status) -> Outcome {
    let from_server = status.message().split_once(": ").is_some_and(|(code, _)| {
        !code.is_empty() && code.bytes().all(|b| b.is_ascii_lowercase() || b == b'_')
    });
    if from_server && status.code() != tonic::Code::Unknown {
        let code = status.message().split(':').next().unwrap_or_default();
        Outcome::Refused(format!("gRPC {:?} {code}", status.code()))
    } else {
        Outcome::Lost(format!("gRPC {:?}: {}", status.code(), status.message()))
    }
}

/// Complete when the stream's own count of faces is the number that came.
fn counted(said: usize, came: usize, t0: Instant, first_face: Option<Duration>) -> Outcome {
    if said == came {
        Outcome::Completed { latency: t0.elapsed(), first_face }
    } else {
        Outcome::Lost(format!("the stream said {said} faces and sent {came}"))
    }
}

async fn read_glb(response: reqwest::Response, t0: Instant) -> Outcome {
    let said: Option<usize> =
        response.headers().get("x-meshstream-faces").and_then(|v| v.to_str().ok()?.parse().ok());
    let bytes = match response.bytes().await {
        Ok(b) => b,
        Err(e) => return Outcome::Lost(format!("the mesh broke off: {e}")),
    };
    let latency = t0.elapsed();
    match read_mesh(&bytes, Format::Gltf, &ReadLimits::default()) {
        Ok(mesh) if Some(mesh.faces.len()) == said => {
            Outcome::Completed { latency, first_face: None }
        }
        Ok(mesh) => Outcome::Lost(format!("a mesh of {} faces, said {said:?}", mesh.faces.len())),
        Err(e) => Outcome::Lost(format!("the mesh does not parse: {e}")),
    }
}

async fn read_ndjson(response: reqwest::Response, t0: Instant, leave: bool) -> Outcome {
    let mut chunks = response.bytes_stream();
    let (mut buffer, mut faces, mut first_face) = (Vec::new(), 0usize, None);
    while let Some(chunk) = chunks.next().await {
        match chunk {
            Ok(chunk) => buffer.extend_from_slice(&chunk),
            Err(e) => return Outcome::Lost(format!("the stream broke off: {e}")),
        }
        while let Some(end) = buffer.iter().position(|&b| b == b'\n') {
            let line: Vec<u8> = buffer.drain(..=end).collect();
            let event: Value = match serde_json::from_slice(&line) {
                Ok(v) => v,
                Err(e) => return Outcome::Lost(format!("a line that is not JSON: {e}")),
            };
            match event["type"].as_str() {
                Some("face") => {
                    faces += 1;
                    first_face.get_or_insert_with(|| t0.elapsed());
                    if leave {
                        return Outcome::Left;
                    }
                }
                Some("done") => {
                    let said = event["faces"].as_u64().unwrap_or(u64::MAX) as usize;
                    return counted(said, faces, t0, first_face);
                }
                Some("error") => {
                    let code = event["error"]["code"].as_str().unwrap_or("-");
                    return Outcome::Refused(format!("stream error {code}"));
                }
                _ => {}
            }
        }
    }
    Outcome::Lost("the stream ended without its last event".into())
}
