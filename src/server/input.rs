//! Request bodies to a mesh or point cloud and decoding options: a JSON body of points, or a
//! raw upload of a point cloud or mesh in any supported format.

use axum::http::HeaderMap;
use axum::http::header::CONTENT_TYPE;
use serde::Deserialize;
use utoipa::{IntoParams, ToSchema};

use crate::candidates::{MAX_CANDIDATES, MAX_WELD_RADIUS};
use crate::engine::DecodeOptions;
use crate::mesh::{Format, MAX_FIT_ROUNDS, MAX_HOLE_EDGES, Mesh, ReadLimits, UpAxis, read_mesh};
use crate::model::{DEFAULT_TEMPERATURE, MAX_FACE_BEAM, SamplingParams};

use super::error::ApiError;

/// Decoding options: fields of the JSON body, or query parameters of a raw upload.
#[derive(Debug, Clone, Default, Deserialize, ToSchema, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct ReconstructOptions {
    /// Face budget (default and maximum: the server's limit, see `/v1/info`).
    #[param(minimum = 1)]
    pub max_faces: Option<usize>,
    /// Sampling temperature (default 0: greedy decoding with the face beam).
    #[param(minimum = 0)]
    pub temperature: Option<f32>,
    #[param(minimum = 1)]
    pub top_k: Option<usize>,
    #[param(exclusive_minimum = 0, maximum = 1)]
    pub top_p: Option<f32>,
    /// Partial faces kept while greedy decoding picks each face's coordinates (default 4,
    /// at most 32); 1 picks coordinate by coordinate.
    #[param(minimum = 1, maximum = 32)]
    pub face_beam: Option<usize>,
    /// Decode this many meshes, each from its own draw of the input points (all greedy for a
    /// greedy request; otherwise the first as asked, one greedy and the rest sampled), and keep
    /// the one that ends closest to the input points, fitted when it is (at most 16). Default: the server's setting (4 unless
    /// configured, see `/v1/info`) for a whole mesh, 1 for a stream. With more than 1, every
    /// face arrives at the end.
    #[param(minimum = 1, maximum = 16)]
    pub candidates: Option<usize>,
    /// Rounds of moving each candidate's corners to fit the input points (the same faces,
    /// flat polygons split again for the moved corners; at most 200), after which the winner
    /// drops the faces that lie on other faces and the connected parts the points do not
    /// need; 0 keeps them as decoded. Default: the server's setting for a whole mesh (see
    /// `/v1/info`), 0 for a stream. Above 0, every face arrives at the end.
    #[param(maximum = 200)]
    pub fit_rounds: Option<usize>,
    /// Merge the corners of each candidate that lie within this many grid cells of each other
    /// on every axis, and split its faces at corners this close to their open edges, before
    /// fitting (at most 4): closes the cracks between faces that should share a corner or an
    /// edge; 0 keeps them as decoded. Default: the server's setting for a whole mesh
    /// (1 unless configured, see `/v1/info`), 0 for a stream. Above 0, every face arrives at
    /// the end.
    #[param(maximum = 4)]
    pub weld_radius: Option<u16>,
    /// Close the fitted mesh's loops of at most this many open edges (at most 32) with new
    /// faces, where the input points cover them: the cracks and missing faces of an otherwise
    /// closed surface; an opening the points show (a cup's rim) stays open. Below 3 leaves
    /// every hole. Default 8 (see `/v1/info`); only a fitted mesh (`fit_rounds` above 0).
    #[param(maximum = 32)]
    pub max_hole_edges: Option<usize>,
    /// A fitted answer may be the convex hull of the input points with at most this many
    /// faces (and `max_faces`), chosen where it ends at least 10% closer to the points than
    /// every decoded candidate (finish reason `convex_hull`); 0 never. Default: the server's
    /// setting (100 unless configured, see `/v1/info`); only a fitted mesh (`fit_rounds`
    /// above 0).
    pub hull_faces: Option<usize>,
    /// Seed of the point sampling and of the decoding when it samples.
    #[param(schema_with = seed_schema)]
    pub seed: Option<u64>,
    /// glb (default), obj, ply or stl.
    #[param(value_type = Option<MeshFormat>)]
    pub format: Option<String>,
    /// The input's up axis: y (default, glTF's), z (Blender, CAD, most scans and 3D
    /// printing), x, or one of them negated (-y: upside down). The model's training shapes
    /// mostly stand on +y; the input is turned onto it and the mesh comes back turned as sent.
    #[param(schema_with = up_schema)]
    pub up: Option<String>,
    /// Streams only: while an answer whose faces come at the end is made (more than one
    /// candidate, welded or fitted), send the first candidate's faces as `draft` events as
    /// they are decoded, then the answer's as `face` events (default false). Drafts are not
    /// part of the answer; a client that reads slowly may miss some, never the answer's faces.
    pub drafts: Option<bool>,
}

/// `POST /reconstruct` with `Content-Type: application/json`.
///
/// The fields of [`ReconstructOptions`] are repeated rather than `#[serde(flatten)]`ed: serde
/// does not support `deny_unknown_fields` with `flatten`, and a misspelt option must be an
/// error, not a silent default.
#[derive(Debug, Clone, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PointsBody {
    /// [[x, y, z], ...] in any units and frame: the mesh comes back in the same.
    #[schema(value_type = Vec<Point>)]
    pub points: Vec<[f32; 3]>,
    /// One per point; estimated from the points when absent.
    #[schema(value_type = Option<Vec<Point>>)]
    pub normals: Option<Vec<[f32; 3]>>,
    #[schema(minimum = 1)]
    pub max_faces: Option<usize>,
    #[schema(minimum = 0)]
    pub temperature: Option<f32>,
    #[schema(minimum = 1)]
    pub top_k: Option<usize>,
    #[schema(exclusive_minimum = 0, maximum = 1)]
    pub top_p: Option<f32>,
    #[schema(minimum = 1, maximum = 32)]
    pub face_beam: Option<usize>,
    #[schema(minimum = 1, maximum = 16)]
    pub candidates: Option<usize>,
    #[schema(maximum = 200)]
    pub fit_rounds: Option<usize>,
    #[schema(maximum = 4)]
    pub weld_radius: Option<u16>,
    #[schema(maximum = 32)]
    pub max_hole_edges: Option<usize>,
    pub hull_faces: Option<usize>,
    #[schema(schema_with = seed_schema)]
    pub seed: Option<u64>,
    #[schema(value_type = Option<MeshFormat>)]
    pub format: Option<String>,
    #[schema(schema_with = up_schema)]
    pub up: Option<String>,
    pub drafts: Option<bool>,
}

/// A seed: any u64 (utoipa's int64 would stop at i64::MAX).
pub(super) fn seed_schema() -> utoipa::openapi::Object {
    utoipa::openapi::ObjectBuilder::new()
        .schema_type(utoipa::openapi::Type::Integer)
        .minimum(Some(0))
        .maximum(Some(u64::MAX))
        .build()
}

/// The `up` option: an axis by name.
fn up_schema() -> utoipa::openapi::Object {
    utoipa::openapi::ObjectBuilder::new()
        .schema_type(utoipa::openapi::Type::String)
        .enum_values(Some(UpAxis::NAMES))
        .build()
}

/// The mesh formats of an answer: the schema of the `format` option.
#[derive(ToSchema)]
#[schema(rename_all = "lowercase")]
#[allow(dead_code)] // a schema only
pub enum MeshFormat {
    Glb,
    Obj,
    Ply,
    Stl,
}

/// Three coordinates: the schema of `[f32; 3]`, which utoipa gives no length.
#[derive(ToSchema)]
#[schema(min_items = 3, max_items = 3)]
#[allow(dead_code)] // a schema only
pub struct Point(Vec<f32>);

/// What a request asks for, parsed and checked.
#[derive(Debug, Clone)]
pub struct ParsedRequest {
    pub input: Mesh,
    pub decode: DecodeOptions,
    pub seed: u64,
    pub format: Format,
    /// The input's up axis.
    pub up: UpAxis,
}

#[derive(Debug, Clone, Copy)]
pub struct InputLimits {
    pub max_points: usize,
    /// The most input points a reconstruction's candidates are judged and fitted against
    /// (the encoder takes the model's `num_points` of them).
    pub reference_points: usize,
    pub read: ReadLimits,
}

impl ReconstructOptions {
    pub fn checked(self, input: Mesh) -> Result<ParsedRequest, ApiError> {
        let format = output_format(self.format.as_deref())?;
        let seed = self.seed.unwrap_or(0);
        let mut decode = decode_options(
            self.max_faces,
            self.temperature,
            self.top_k,
            self.top_p,
            self.face_beam,
            seed,
        )?;
        if let Some(n) = self.candidates
            && !(1..=MAX_CANDIDATES).contains(&n)
        {
            return Err(ApiError::invalid(format!(
                "candidates {n} must be between 1 and {MAX_CANDIDATES}"
            )));
        }
        decode.candidates = self.candidates;
        if let Some(n) = self.fit_rounds
            && n > MAX_FIT_ROUNDS
        {
            return Err(ApiError::invalid(format!(
                "fit_rounds {n} must be at most {MAX_FIT_ROUNDS}"
            )));
        }
        decode.fit_rounds = self.fit_rounds;
        if let Some(n) = self.weld_radius
            && n > MAX_WELD_RADIUS
        {
            return Err(ApiError::invalid(format!(
                "weld_radius {n} must be at most {MAX_WELD_RADIUS}"
            )));
        }
        decode.weld_radius = self.weld_radius;
        if let Some(n) = self.max_hole_edges
            && n > MAX_HOLE_EDGES
        {
            return Err(ApiError::invalid(format!(
                "max_hole_edges {n} must be at most {MAX_HOLE_EDGES}"
            )));
        }
        decode.max_hole_edges = self.max_hole_edges;
        decode.hull_faces = self.hull_faces;
        decode.drafts = self.drafts.unwrap_or(false);
        let up = self.up.as_deref().map(str::parse).transpose().map_err(ApiError::invalid)?;
        Ok(ParsedRequest { input, decode, seed, format, up: up.unwrap_or_default() })
    }
}

/// The mesh format asked for: GLB when none is.
pub fn output_format(name: Option<&str>) -> Result<Format, ApiError> {
    match name {
        None => Ok(Format::Gltf),
        Some(name) => name
            .parse::<Format>()
            .map_err(|_| ApiError::invalid(format!("format {name:?}: use glb, obj, ply or stl"))),
    }
}

/// Decoding options from a request's fields, checked; at [`DEFAULT_TEMPERATURE`] (greedy) unless
/// a temperature is given.
pub fn decode_options(
    max_faces: Option<usize>,
    temperature: Option<f32>,
    top_k: Option<usize>,
    top_p: Option<f32>,
    face_beam: Option<usize>,
    seed: u64,
) -> Result<DecodeOptions, ApiError> {
    let sampling = SamplingParams {
        temperature: temperature.unwrap_or(DEFAULT_TEMPERATURE),
        top_k,
        top_p,
        seed,
    };
    sampling.validate().map_err(|e| ApiError::invalid(e.to_string()))?;
    if let Some(beam) = face_beam
        && !(1..=MAX_FACE_BEAM).contains(&beam)
    {
        return Err(ApiError::invalid(format!(
            "face_beam {beam} must be between 1 and {MAX_FACE_BEAM}"
        )));
    }
    Ok(DecodeOptions { max_faces, sampling, face_beam, ..DecodeOptions::default() })
}

/// The request's media type, lower case, without parameters ("" when absent).
pub(super) fn media_type(headers: &HeaderMap) -> String {
    let content_type = headers.get(CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("");
    content_type.split(';').next().unwrap_or_default().trim().to_ascii_lowercase()
}

/// Parses a body by its Content-Type: JSON points, or a mesh file (by type, or sniffed when
/// the type is generic or missing). CPU work for large uploads: call it off the runtime.
pub fn parse_body(
    headers: &HeaderMap,
    query: ReconstructOptions,
    body: &[u8],
    limits: &InputLimits,
) -> Result<ParsedRequest, ApiError> {
    let content_type = headers.get(CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("");
    let essence = media_type(headers);
    if essence == "application/json" {
        return parse_json(body, limits);
    }
    let format = match Format::from_content_type(&essence) {
        Some(f) => Some(f),
        None if matches!(essence.as_str(), "" | "application/octet-stream") => None,
        None => {
            return Err(unsupported(format!(
                "Content-Type {content_type:?}: send application/json, a mesh type \
                 (model/gltf-binary, model/obj, model/stl, application/ply) or \
                 application/octet-stream"
            )));
        }
    };
    query.checked(parse_file(body, format, limits)?)
}

/// A point cloud or mesh file in `format`, or in the format its bytes show.
pub fn parse_file(
    body: &[u8],
    format: Option<Format>,
    limits: &InputLimits,
) -> Result<Mesh, ApiError> {
    if body.is_empty() {
        return Err(ApiError::invalid("the body is empty: send points or a mesh"));
    }
    let format = format
        .or_else(|| Format::sniff(body))
        .ok_or_else(|| unsupported("the body is not a PLY, OBJ, STL or glTF file"))?;
    let mesh = read_mesh(body, format, &limits.read)?;
    check_points(&mesh, limits)?;
    Ok(mesh)
}

pub(super) fn unsupported(message: impl Into<String>) -> ApiError {
    ApiError::new(axum::http::StatusCode::BAD_REQUEST, "unsupported_format", message)
}

/// A point cloud from flat (x, y, z) triples, with optional normals.
pub fn point_cloud(
    positions: &[f32],
    normals: &[f32],
    limits: &InputLimits,
) -> Result<Mesh, ApiError> {
    if !positions.len().is_multiple_of(3) || !normals.len().is_multiple_of(3) {
        return Err(ApiError::invalid("positions and normals come in (x, y, z) triples"));
    }
    let triples =
        |v: &[f32]| -> Vec<[f32; 3]> { v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect() };
    let normals = (!normals.is_empty()).then(|| triples(normals));
    points_mesh(triples(positions), normals, limits)
}

fn points_mesh(
    points: Vec<[f32; 3]>,
    normals: Option<Vec<[f32; 3]>>,
    limits: &InputLimits,
) -> Result<Mesh, ApiError> {
    if let Some(normals) = &normals
        && normals.len() != points.len()
    {
        return Err(ApiError::invalid(format!(
            "{} normals for {} points: give one per point, or none",
            normals.len(),
            points.len()
        )));
    }
    let mesh = Mesh { vertices: points, faces: Vec::new(), normals };
    check_points(&mesh, limits)?;
    Ok(mesh)
}

fn parse_json(body: &[u8], limits: &InputLimits) -> Result<ParsedRequest, ApiError> {
    let b: PointsBody = serde_json::from_slice(body).map_err(|e| {
        if e.is_data() {
            ApiError::invalid(format!("the JSON body does not fit the schema: {e}"))
        } else {
            ApiError::malformed(format!("the body is not JSON: {e}"))
        }
    })?;
    let mesh = points_mesh(b.points, b.normals, limits)?;
    let options = ReconstructOptions {
        max_faces: b.max_faces,
        temperature: b.temperature,
        top_k: b.top_k,
        top_p: b.top_p,
        face_beam: b.face_beam,
        candidates: b.candidates,
        fit_rounds: b.fit_rounds,
        weld_radius: b.weld_radius,
        max_hole_edges: b.max_hole_edges,
        hull_faces: b.hull_faces,
        seed: b.seed,
        format: b.format,
        up: b.up,
        drafts: b.drafts,
    };
    options.checked(mesh)
}

fn check_points(mesh: &Mesh, limits: &InputLimits) -> Result<(), ApiError> {
    let n = mesh.vertices.len();
    if n == 0 {
        return Err(ApiError::invalid("nothing to reconstruct: the input has no points"));
    }
    if mesh.faces.is_empty() && n < 3 {
        return Err(ApiError::invalid(format!("a point cloud needs at least 3 points, got {n}")));
    }
    if n > limits.max_points {
        return Err(ApiError::invalid(format!(
            "{n} points: this server accepts at most {}",
            limits.max_points
        )));
    }
    mesh.validate()?;
    if let Some(normals) = &mesh.normals
        && normals.iter().flatten().any(|c| !c.is_finite())
    {
        return Err(ApiError::invalid("a normal has a non-finite coordinate"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    fn limits() -> InputLimits {
        InputLimits { max_points: 100, reference_points: 100, read: ReadLimits::default() }
    }

    fn json(body: &str) -> Result<ParsedRequest, ApiError> {
        let mut h = HeaderMap::new();
        h.insert(CONTENT_TYPE, HeaderValue::from_static("application/json"));
        parse_body(&h, ReconstructOptions::default(), body.as_bytes(), &limits())
    }

    #[test]
    fn json_points_with_options_parse() {
        let r = json(r#"{"points": [[0,0,0],[1,0,0],[0,1,0]], "max_faces": 10, "format": "obj"}"#)
            .unwrap();
        assert_eq!(r.input.vertices.len(), 3);
        assert_eq!(r.decode.max_faces, Some(10));
        assert_eq!(r.format, Format::Obj);
    }

    #[test]
    fn requests_decode_greedily_unless_they_ask_to_sample() {
        let points = r#""points": [[0,0,0],[1,0,0],[0,1,0]]"#;
        let temperature = |extra: &str| json(&format!("{{{points}{extra}}}")).unwrap();
        let default = temperature("").decode.sampling.temperature;
        assert_eq!(default, DEFAULT_TEMPERATURE);
        assert_eq!(default, 0.0);
        assert_eq!(temperature(r#", "temperature": 1.2"#).decode.sampling.temperature, 1.2);
        assert_eq!(temperature(r#", "temperature": 0.4"#).decode.sampling.temperature, 0.4);
    }

    #[test]
    fn bad_json_bodies_get_their_codes() {
        let code = |b: &str| json(b).map(|_| ()).unwrap_err();
        assert_eq!(code("{not json").status.as_u16(), 400);
        assert_eq!(code(r#"{"points": []}"#).code, "invalid_input");
        assert_eq!(code(r#"{"points": [[0,0]]}"#).status.as_u16(), 422);
        assert_eq!(code(r#"{"points": [[0,0,0],[1,0,0],[0,1,0]], "max_face": 3}"#).status, 422);
        let huge = r#"{"points": [[1e39,0,0],[1,0,0],[0,1,0]]}"#;
        assert_eq!(code(huge).status.as_u16(), 422);
        let normals = r#"{"points": [[0,0,0],[1,0,0],[0,1,0]], "normals": [[0,0,1]]}"#;
        assert!(code(normals).message.contains("1 normals for 3 points"));
        let format = r#"{"points": [[0,0,0],[1,0,0],[0,1,0]], "format": "fbx"}"#;
        assert!(code(format).message.contains("fbx"));
        let temp = r#"{"points": [[0,0,0],[1,0,0],[0,1,0]], "temperature": -1}"#;
        assert_eq!(code(temp).status.as_u16(), 422);
        let many: Vec<String> = (0..101).map(|i| format!("[{i},0,0]")).collect();
        let many = format!(r#"{{"points": [{}]}}"#, many.join(","));
        assert!(code(&many).message.contains("at most 100"));
    }

    #[test]
    fn raw_uploads_go_by_content_type_or_sniffing() {
        let obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";
        let parse = |ct: Option<&'static str>, body: &[u8]| {
            let mut h = HeaderMap::new();
            if let Some(ct) = ct {
                h.insert(CONTENT_TYPE, HeaderValue::from_static(ct));
            }
            parse_body(&h, ReconstructOptions::default(), body, &limits())
        };
        assert_eq!(parse(Some("model/obj"), obj).unwrap().input.faces.len(), 1);
        assert_eq!(parse(None, obj).unwrap().input.faces.len(), 1);
        assert_eq!(parse(Some("image/png"), obj).unwrap_err().code, "unsupported_format");
        assert_eq!(parse(None, b"\x00\x01garbage").unwrap_err().code, "unsupported_format");
        assert_eq!(parse(Some("model/obj"), b"").unwrap_err().code, "invalid_input");
        assert_eq!(
            parse(Some("application/ply"), b"ply\nformat nonsense\n").unwrap_err().status,
            400
        );
    }
}
