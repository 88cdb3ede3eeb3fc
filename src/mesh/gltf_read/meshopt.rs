//! Buffer views compressed with `EXT_meshopt_compression` (or its Khronos successor
//! `KHR_meshopt_compression`), as gltfpack and glTF-Transform write them for the web: the view's
//! bytes are decoded by meshoptimizer's own decoders (the `meshopt` crate) from the compressed
//! range the extension names, and the view's own buffer is then only a fallback, often without
//! any data.

use std::collections::HashMap;

use serde::Deserialize;

use super::{malformed, unsupported};
use crate::mesh::MeshError;

/// The extension's names: the vendor one and the ratified one share the bitstream.
pub(super) const EXTENSIONS: [&str; 2] = ["EXT_meshopt_compression", "KHR_meshopt_compression"];

/// The largest vertex a compressed ATTRIBUTES view may hold, as the extension defines it.
const MAX_ATTRIBUTE_STRIDE: usize = 256;

/// What the extension says of a buffer view.
#[derive(Debug, Deserialize)]
#[serde(rename_all = "camelCase")]
struct Compressed {
    buffer: usize,
    #[serde(default)]
    byte_offset: usize,
    byte_length: usize,
    byte_stride: usize,
    count: usize,
    mode: Mode,
    #[serde(default)]
    filter: Filter,
}

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
enum Mode {
    Attributes,
    Triangles,
    Indices,
}

#[derive(Debug, Clone, Copy, Default, Deserialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
enum Filter {
    #[default]
    None,
    Octahedral,
    Quaternion,
    Exponential,
    Color,
}

/// The extension's object on `view`, if any.
fn extension<'a>(view: &'a gltf::buffer::View) -> Option<&'a serde_json::Value> {
    EXTENSIONS.iter().find_map(|name| view.extension_value(name))
}

/// Whether `buffer` is only a fallback for compressed views: it need not have any data.
pub(super) fn is_fallback(buffer: &gltf::Buffer) -> bool {
    EXTENSIONS
        .iter()
        .filter_map(|name| buffer.extension_value(name))
        .any(|ext| ext.get("fallback").and_then(serde_json::Value::as_bool) == Some(true))
}

/// The decoded bytes of each compressed view among `views` (by index), read from `buffers`.
/// A decoded view holds at most its declared length, which its buffer's declared length
/// bounds, and that the reader's byte limit checked: a small compressed range cannot decode
/// into more memory than the file declares.
pub(super) fn decode_views<'a>(
    views: impl IntoIterator<Item = gltf::buffer::View<'a>>,
    buffers: &[Option<Vec<u8>>],
) -> Result<HashMap<usize, Vec<u8>>, MeshError> {
    let mut decoded = HashMap::new();
    for view in views {
        if decoded.contains_key(&view.index()) {
            continue;
        }
        if let Some(ext) = extension(&view) {
            decoded.insert(view.index(), decode_view(&view, ext, buffers)?);
        }
    }
    Ok(decoded)
}

fn decode_view(
    view: &gltf::buffer::View,
    ext: &serde_json::Value,
    buffers: &[Option<Vec<u8>>],
) -> Result<Vec<u8>, MeshError> {
    let i = view.index();
    let c = Compressed::deserialize(ext)
        .map_err(|e| malformed(format!("buffer view {i}: meshopt compression: {e}")))?;
    let size = c.count.checked_mul(c.byte_stride).filter(|&size| size <= view.length());
    if size.is_none()
        || view.offset().checked_add(view.length()).is_none_or(|end| end > view.buffer().length())
    {
        return Err(malformed(format!(
            "buffer view {i}: {} elements of {} bytes do not fit its {} bytes in its buffer",
            c.count,
            c.byte_stride,
            view.length()
        )));
    }
    let source = buffers
        .get(c.buffer)
        .and_then(Option::as_deref)
        .and_then(|b| b.get(c.byte_offset..c.byte_offset.checked_add(c.byte_length)?))
        .ok_or_else(|| {
            malformed(format!(
                "buffer view {i}: its compressed range is not in buffer {}",
                c.buffer
            ))
        })?;
    let failed = |e: meshopt::Error| malformed(format!("buffer view {i}: meshopt decoding: {e}"));
    match (c.mode, c.byte_stride) {
        (Mode::Attributes, stride)
            if stride % 4 == 0 && (4..=MAX_ATTRIBUTE_STRIDE).contains(&stride) =>
        {
            let mut words = vertex_buffer(source, c.count, stride).map_err(failed)?;
            apply(c.filter, stride, &mut words).ok_or_else(|| {
                unsupported(format!("buffer view {i}: filter {:?} with stride {stride}", c.filter))
            })?;
            Ok(words.iter().flat_map(|w| w.to_le_bytes()).collect())
        }
        (Mode::Triangles | Mode::Indices, stride @ (2 | 4)) => {
            if matches!(c.mode, Mode::Triangles) && c.count % 3 != 0 {
                return Err(malformed(format!(
                    "buffer view {i}: {} indices are not whole triangles",
                    c.count
                )));
            }
            let decoded: Vec<u32> = match (c.mode, stride) {
                (Mode::Triangles, 2) => widen(meshopt::decode_index_buffer::<u16>(source, c.count)),
                (Mode::Indices, 2) => widen(meshopt::decode_index_sequence::<u16>(source, c.count)),
                (Mode::Triangles, _) => meshopt::decode_index_buffer::<u32>(source, c.count),
                _ => meshopt::decode_index_sequence::<u32>(source, c.count),
            }
            .map_err(failed)?;
            Ok(if stride == 2 {
                decoded.iter().flat_map(|&x| (x as u16).to_le_bytes()).collect()
            } else {
                decoded.iter().flat_map(|x| x.to_le_bytes()).collect()
            })
        }
        (mode, stride) => Err(malformed(format!(
            "buffer view {i}: meshopt mode {mode:?} with a stride of {stride} bytes"
        ))),
    }
}

fn widen(decoded: meshopt::Result<Vec<u16>>) -> meshopt::Result<Vec<u32>> {
    decoded.map(|v| v.into_iter().map(u32::from).collect())
}

/// `count` vertices of `stride` bytes (a multiple of 4), as little-endian words.
fn vertex_buffer(source: &[u8], count: usize, stride: usize) -> meshopt::Result<Vec<u32>> {
    let mut words = vec![0u32; count * stride / 4];
    // SAFETY: `words` holds `count * stride` bytes, which is what the decoder writes; the
    // source pointer and length describe one slice. The crate's typed wrapper fixes the stride
    // at compile time, and the stride here comes from the file. meshoptimizer's decoder is
    // made for untrusted input: it checks the source's bounds and fails with a code.
    let code = unsafe {
        meshopt::ffi::meshopt_decodeVertexBuffer(
            words.as_mut_ptr().cast(),
            count,
            stride,
            source.as_ptr(),
            source.len(),
        )
    };
    if code == 0 { Ok(words) } else { Err(meshopt::Error::Native(code)) }
}

/// The view's filter applied in place; `None` when the filter does not take this stride.
fn apply(filter: Filter, stride: usize, words: &mut [u32]) -> Option<()> {
    match (filter, stride) {
        (Filter::None, _) => {}
        (Filter::Octahedral, 4) => {
            meshopt::decode_filter_oct::<i8>(bytemuck::cast_slice_mut(words))
        }
        (Filter::Octahedral, 8) => {
            meshopt::decode_filter_oct::<i16>(bytemuck::cast_slice_mut(words))
        }
        (Filter::Quaternion, 8) => meshopt::decode_filter_quat(bytemuck::cast_slice_mut(words)),
        // Each 32-bit value decodes on its own, so the words need not be grouped by vertex.
        (Filter::Exponential, _) => {
            meshopt::decode_filter_exp::<1>(bytemuck::cast_slice_mut(words))
        }
        (Filter::Color, 4) => meshopt::decode_filter_color::<u8>(bytemuck::cast_slice_mut(words)),
        (Filter::Color, 8) => meshopt::decode_filter_color::<u16>(bytemuck::cast_slice_mut(words)),
        _ => return None,
    }
    Some(())
}
