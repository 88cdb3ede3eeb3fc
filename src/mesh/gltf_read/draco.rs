//! Primitives compressed with `KHR_draco_mesh_compression` (Blender's and glTF-Transform's
//! Draco option), decoded by `draco-core`, a Rust port of Google's decoder: the primitive's
//! accessors then only describe the data, which comes from the Draco stream in a buffer view.

use std::collections::HashMap;

use draco_core::{DecodeLimits, DecoderBuffer, ErrorKind, MeshDecoder, PointAttribute};
use serde::Deserialize;

use super::{Geometry, malformed};
use crate::mesh::{MeshError, ReadLimits};

pub(super) const EXTENSION: &str = "KHR_draco_mesh_compression";

/// What the extension says of a primitive.
#[derive(Debug, Deserialize)]
#[serde(rename_all = "camelCase")]
struct Compressed {
    buffer_view: usize,
    /// Each glTF attribute's unique id in the Draco stream.
    attributes: HashMap<String, u32>,
}

fn parse(ext: &serde_json::Value) -> Result<Compressed, MeshError> {
    Compressed::deserialize(ext).map_err(|e| malformed(format!("{EXTENSION}: {e}")))
}

/// The buffer view that holds a compressed primitive's Draco stream.
pub(super) fn buffer_view(ext: &serde_json::Value) -> Result<usize, MeshError> {
    Ok(parse(ext)?.buffer_view)
}

/// The primitive's geometry from its Draco stream `bytes`, with normals when `with_normals`.
/// The reader's limits bound the decoder's output before it allocates.
pub(super) fn decode(
    bytes: &[u8],
    ext: &serde_json::Value,
    with_normals: bool,
    limits: &ReadLimits,
) -> Result<Geometry, MeshError> {
    let compressed = parse(ext)?;
    let ceilings = DecodeLimits::default()
        .with_max_points(limits.max_vertices as u64)
        .with_max_faces(limits.max_faces as u64)
        .with_max_decoded_bytes(limits.max_bytes);
    let mut buffer = DecoderBuffer::new(bytes).with_limits(ceilings);
    let mut mesh = draco_core::Mesh::new();
    MeshDecoder::new().decode(&mut buffer, &mut mesh).map_err(|e| {
        if e.kind() == ErrorKind::LimitExceeded {
            too_large(e.message(), limits)
        } else {
            malformed(format!("Draco stream: {e}"))
        }
    })?;
    let n = mesh.num_points();
    let vec3s = |semantic: &str| -> Result<Vec<[f32; 3]>, MeshError> {
        let attribute = attribute(&mesh, &compressed, semantic)?;
        let flat = attribute.read_f32s(n, 3);
        Ok(flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
    };
    let positions = vec3s("POSITION")?;
    let normals = if with_normals { Some(vec3s("NORMAL")?) } else { None };
    let indices = mesh.faces().iter().flat_map(|face| face.map(|p| p.0)).collect();
    Ok(Geometry { positions, normals, indices: Some(indices) })
}

/// The Draco attribute that holds `semantic`, checked to have 3 components a point.
fn attribute<'m>(
    mesh: &'m draco_core::Mesh,
    compressed: &Compressed,
    semantic: &str,
) -> Result<&'m PointAttribute, MeshError> {
    let id = compressed.attributes.get(semantic).ok_or_else(|| {
        malformed(format!("the Draco-compressed primitive has no {semantic} in its stream"))
    })?;
    let attribute = mesh.attribute_by_unique_id(*id).ok_or_else(|| {
        malformed(format!("{semantic} is Draco attribute {id}, which the stream does not have"))
    })?;
    if attribute.num_components() != 3 {
        return Err(malformed(format!(
            "Draco attribute {id} ({semantic}) has {} components, not 3",
            attribute.num_components()
        )));
    }
    Ok(attribute)
}

/// The reader's limit that the decoder's `message` says the stream would exceed.
fn too_large(message: &str, limits: &ReadLimits) -> MeshError {
    // The decoder names what it counted ("points", "faces", "decoded attribute bytes").
    let (what, limit) = if message.contains("faces") {
        ("face count", limits.max_faces as u64)
    } else if message.contains("points") {
        ("vertex count", limits.max_vertices as u64)
    } else {
        ("input bytes", limits.max_bytes)
    };
    MeshError::TooLarge { what, limit }
}
