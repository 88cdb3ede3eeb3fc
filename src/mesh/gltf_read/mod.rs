//! glTF 2.0 (`.gltf` JSON and `.glb`) through the `gltf` crate: every triangle primitive of
//! the default scene (or of all scenes when none is the default), node transforms applied.
//! A file whose only geometry is POINTS primitives is read as a point cloud.
//!
//! Files made small for the web are read too: integer positions and normals
//! (`KHR_mesh_quantization`), buffer views compressed by meshoptimizer
//! (`EXT_meshopt_compression`, [`meshopt`]) and Draco-compressed primitives
//! (`KHR_draco_mesh_compression`, [`draco`]).
//!
//! Accessor data is read here rather than through `gltf::mesh::Reader`, because that reader
//! trusts the file (mismatched strides or counts panic inside it); every range is checked first.

mod draco;
mod meshopt;

use std::collections::HashMap;
use std::path::Path;

use gltf::accessor::{Accessor, DataType, Dimensions};
use gltf::buffer::Source;
use gltf::mesh::Mode;
use gltf::{Document, Primitive, Semantic};

use super::assemble::Assembler;
use super::{Mesh, MeshError, ReadLimits};

const FORMAT: &str = "glTF";

/// Required extensions that change how geometry is stored, and that this reader decodes.
const GEOMETRY_EXTENSIONS: [&str; 4] =
    ["KHR_mesh_quantization", draco::EXTENSION, meshopt::EXTENSIONS[0], meshopt::EXTENSIONS[1]];

fn malformed(message: impl Into<String>) -> MeshError {
    MeshError::malformed(FORMAT, message)
}

fn unsupported(message: impl Into<String>) -> MeshError {
    MeshError::Unsupported { format: FORMAT, message: message.into() }
}

/// Column-major 4x4 matrix (`m[column][row]`), as glTF stores them; f64 so that deep
/// hierarchies do not accumulate rounding.
type Mat4 = [[f64; 4]; 4];

const IDENTITY: Mat4 =
    [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];

/// Reads glTF or GLB bytes; `base` is the directory external buffers are resolved against
/// (`None`: external buffers are refused).
pub(crate) fn read(
    bytes: &[u8],
    base: Option<&Path>,
    limits: &ReadLimits,
) -> Result<Mesh, MeshError> {
    let (document, blob) = parse(bytes)?;
    let buffers = load_buffers(&document, blob, base, limits, bytes.len() as u64)?;
    let instances = instances(&document)?;

    // Which primitives to read is decided over the meshes placed in the scene, each once
    // (a mesh may be placed many times). Lines carry no surface, and points beside a surface
    // are not part of it: surfaces are read when there are any, else points.
    let mut placed = vec![false; document.meshes().len()];
    for instance in &instances {
        if let Some(p) = placed.get_mut(instance.mesh.index()) {
            *p = true;
        }
    }
    let primitives = || {
        document
            .meshes()
            .filter(|m| placed.get(m.index()) == Some(&true))
            .flat_map(|m| m.primitives())
    };
    let wanted: fn(Mode) -> bool = if primitives().any(|p| is_surface(p.mode())) {
        is_surface
    } else if primitives().any(|p| p.mode() == Mode::Points) {
        |mode| mode == Mode::Points
    } else if primitives().next().is_none() {
        |_| false
    } else {
        return Err(unsupported("the only primitives are lines, which have no surface"));
    };
    let with_normals =
        primitives().filter(|p| wanted(p.mode())).all(|p| p.get(&Semantic::Normals).is_some());

    let mut asm = Assembler::new(FORMAT, limits);
    let mut normals = Vec::new();
    let ctx = Context::new(&document, &buffers, primitives().filter(|p| wanted(p.mode())), limits)?;
    for instance in &instances {
        for primitive in instance.mesh.primitives().filter(|p| wanted(p.mode())) {
            let normals = with_normals.then_some(&mut normals);
            ctx.read_primitive(&primitive, &instance.world, &mut asm, normals)?;
        }
    }
    asm.finish((with_normals && !normals.is_empty()).then_some(normals))
}

fn is_surface(mode: Mode) -> bool {
    matches!(mode, Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan)
}

/// The most JSON objects and arrays a glTF file may have. Parsed, each takes up to ~250 bytes
/// for as little as 3 bytes of text (`{},`), so without this bound a file within the byte
/// limit could take ~80 times its size in memory; with it, the JSON costs at most ~250 MB.
/// Real files have a few objects per node, mesh and accessor: far fewer than a million.
const MAX_JSON_CONTAINERS: u64 = 1 << 20;

/// The JSON text of a glTF file: the whole file, or a GLB's JSON chunk.
fn json_text(bytes: &[u8]) -> Result<&[u8], MeshError> {
    if !bytes.starts_with(b"glTF") {
        return Ok(bytes);
    }
    let word = |at: usize| {
        let b = bytes.get(at..at + 4)?;
        Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
    };
    // Checked here because the crate subtracts the header size from the declared length
    // without checking it.
    if word(8).is_none_or(|n| n < 12) {
        return Err(malformed("truncated GLB header"));
    }
    let json = word(12).and_then(|len| bytes.get(20..20usize.checked_add(len)?));
    json.ok_or_else(|| malformed("truncated GLB JSON chunk"))
}

/// The document, validated, and the GLB binary chunk if any.
fn parse(bytes: &[u8]) -> Result<(Document, Option<Vec<u8>>), MeshError> {
    let json = json_text(bytes)?;
    let containers = json.iter().filter(|&&b| b == b'{' || b == b'[').count() as u64;
    if containers > MAX_JSON_CONTAINERS {
        let what = "glTF JSON objects and arrays";
        return Err(MeshError::TooLarge { what, limit: MAX_JSON_CONTAINERS });
    }
    let gltf =
        gltf::Gltf::from_slice_without_validation(bytes).map_err(|e| malformed(e.to_string()))?;
    let mut root = gltf.document.into_json();
    // The crate refuses every required extension it does not implement; most (materials,
    // textures, lights) do not touch geometry, and those that do are decoded here or refused
    // by name.
    let read_here = |e: &String| appearance_only(e) || GEOMETRY_EXTENSIONS.contains(&e.as_str());
    if let Some(ext) = root.extensions_required.iter().find(|e| !read_here(e)) {
        return Err(unsupported(format!("required extension {ext}")));
    }
    root.extensions_required.clear();
    validate(&root)?;
    Ok((Document::from_json_without_validation(root), gltf.blob))
}

/// The crate's validation (every index refers to something that exists, which the document
/// accessors rely on), less two checks whose absence we handle: POSITION `min`/`max`, which
/// many exporters omit and we never use, and an accessor without a buffer view, which is how
/// Draco-compressed primitives look and is reported when the accessor is read.
fn validate(root: &gltf_json::Root) -> Result<(), MeshError> {
    use gltf_json::validation::{Error, Validate};
    // The crate's own check of POSITION indexes the accessors without a bounds check.
    let positions = root.meshes.iter().flat_map(|m| &m.primitives).filter_map(|p| {
        p.attributes.get(&gltf_json::validation::Checked::Valid(Semantic::Positions))
    });
    if let Some(bad) = positions.map(|i| i.value()).find(|&i| i >= root.accessors.len()) {
        return Err(malformed(format!("POSITION refers to accessor {bad}, which does not exist")));
    }
    let mut problems = Vec::new();
    root.validate(root, gltf_json::Path::new, &mut |path, error| {
        let path = path();
        let tolerated = matches!(error, Error::Missing)
            && ["[\"POSITION\"].min", "[\"POSITION\"].max", "].bufferView"]
                .iter()
                .any(|end| path.as_str().ends_with(end));
        if !tolerated {
            problems.push(format!("{path}: {error}"));
        }
    });
    if problems.is_empty() {
        Ok(())
    } else {
        Err(malformed(format!("invalid glTF: {}", problems.join("; "))))
    }
}

fn appearance_only(extension: &str) -> bool {
    ["KHR_materials_", "KHR_texture_", "EXT_texture_", "MSFT_texture_"]
        .iter()
        .any(|prefix| extension.starts_with(prefix))
        || extension == "KHR_lights_punctual"
}

fn load_buffers(
    document: &Document,
    mut blob: Option<Vec<u8>>,
    base: Option<&Path>,
    limits: &ReadLimits,
    input_bytes: u64,
) -> Result<Vec<Option<Vec<u8>>>, MeshError> {
    // Declared lengths include those of meshopt fallback buffers, which bound what their
    // compressed views decode into.
    let declared = document.buffers().map(|b| b.length() as u64).fold(0u64, u64::saturating_add);
    limits.check_bytes(declared)?;
    let mut total = input_bytes;
    let mut buffers = Vec::new();
    for buffer in document.buffers() {
        if meshopt::is_fallback(&buffer) {
            buffers.push(None);
            continue;
        }
        let data = match buffer.source() {
            Source::Bin => {
                blob.take().ok_or_else(|| malformed("a buffer refers to a missing BIN chunk"))?
            }
            Source::Uri(uri) if uri.starts_with("data:") => {
                // Decoded from the input itself, so bounded by its size.
                gltf::buffer::Data::from_source(buffer.source(), None)
                    .map_err(|e| malformed(e.to_string()))?
                    .0
            }
            Source::Uri(uri) => {
                let base = base.ok_or_else(|| {
                    unsupported(format!(
                        "external buffer {uri:?}: read the .gltf file from disk, or use .glb"
                    ))
                })?;
                let data = read_external(uri, base, limits, total)?;
                total += data.len() as u64;
                data
            }
        };
        if data.len() < buffer.length() {
            return Err(malformed(format!(
                "buffer {} declares {} bytes but has {}",
                buffer.index(),
                buffer.length(),
                data.len()
            )));
        }
        buffers.push(Some(data));
    }
    Ok(buffers)
}

/// An external buffer file, resolved relative to the `.gltf` file and size-checked first.
fn read_external(
    uri: &str,
    base: &Path,
    limits: &ReadLimits,
    so_far: u64,
) -> Result<Vec<u8>, MeshError> {
    let decoded =
        urlencoding::decode(uri).map_err(|_| malformed(format!("bad buffer URI {uri:?}")))?;
    let relative = Path::new(decoded.as_ref());
    if decoded.contains(':') || relative.is_absolute() {
        return Err(unsupported(format!("buffer URI {uri:?}: only relative paths are read")));
    }
    let path = base.join(relative);
    let io = |error| MeshError::Io { path: path.clone(), error };
    let size = std::fs::metadata(&path).map_err(io)?.len();
    limits.check_bytes(so_far.saturating_add(size))?;
    std::fs::read(&path).map_err(io)
}

/// A mesh placed in the scene by a node.
struct Instance<'a> {
    mesh: gltf::Mesh<'a>,
    world: Mat4,
}

/// Every mesh the scene places, with its node's world transform: the default scene, else the
/// union of all scenes. A node hierarchy is a forest, so each node is reached once per scene;
/// a node reached twice in one scene (a cycle or a shared child) is refused, since it would
/// loop forever or multiply geometry without bound. A node another scene already placed is
/// not placed again (its world transform is the same in every scene), so the work stays
/// linear in the number of nodes.
fn instances(document: &Document) -> Result<Vec<Instance<'_>>, MeshError> {
    let scenes: Vec<_> = match document.default_scene() {
        Some(scene) => vec![scene],
        None => document.scenes().collect(),
    };
    if scenes.is_empty() {
        // No scene at all: every mesh as it is.
        return Ok(document.meshes().map(|mesh| Instance { mesh, world: IDENTITY }).collect());
    }
    let mut instances = Vec::new();
    // 0: not reached yet; otherwise 1 + the number of the scene that reached the node.
    let mut reached_in = vec![0usize; document.nodes().len()];
    for (number, scene) in scenes.into_iter().enumerate() {
        let stamp = number + 1;
        let mut stack: Vec<_> = scene.nodes().map(|n| (n, IDENTITY)).collect();
        stack.reverse();
        while let Some((node, parent)) = stack.pop() {
            let reached = reached_in.get_mut(node.index()).ok_or_else(|| malformed("bad node"))?;
            match *reached {
                0 => *reached = stamp,
                s if s == stamp => {
                    let i = node.index();
                    return Err(malformed(format!("node {i} is reached twice in a scene")));
                }
                _ => continue,
            }
            let local = node.transform().matrix().map(|column| column.map(f64::from));
            let world = mul(&parent, &local);
            if let Some(mesh) = node.mesh() {
                instances.push(Instance { mesh, world });
            }
            let children: Vec<_> = node.children().collect();
            stack.extend(children.into_iter().rev().map(|child| (child, world)));
        }
    }
    Ok(instances)
}

fn mul(a: &Mat4, b: &Mat4) -> Mat4 {
    let mut m = [[0.0; 4]; 4];
    for (c, column) in m.iter_mut().enumerate() {
        for (r, value) in column.iter_mut().enumerate() {
            *value = (0..4).map(|k| a[k][r] * b[c][k]).sum();
        }
    }
    m
}

fn transform_point(m: &Mat4, p: [f32; 3]) -> [f32; 3] {
    let p = p.map(f64::from);
    std::array::from_fn(|r| (m[0][r] * p[0] + m[1][r] * p[1] + m[2][r] * p[2] + m[3][r]) as f32)
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// The matrix that maps normals: the inverse transpose of the linear part, up to a positive
/// factor (the cofactor matrix, whose columns are cross products of the linear part's, times
/// the sign of the determinant), which the normalization after it removes.
/// Returns the columns and the determinant's sign (negative: the transform mirrors).
fn normal_matrix(m: &Mat4) -> ([[f64; 3]; 3], f64) {
    let a: [[f64; 3]; 3] = std::array::from_fn(|c| [m[c][0], m[c][1], m[c][2]]);
    let cof = [cross(a[1], a[2]), cross(a[2], a[0]), cross(a[0], a[1])];
    let det: f64 = (0..3).map(|k| a[0][k] * cof[0][k]).sum();
    let sign = if det < 0.0 { -1.0 } else { 1.0 };
    (cof.map(|col| col.map(|x| x * sign)), sign)
}

fn transform_normal(cof: &[[f64; 3]; 3], n: [f32; 3]) -> [f32; 3] {
    let n = n.map(f64::from);
    let v: [f64; 3] =
        std::array::from_fn(|r| cof[0][r] * n[0] + cof[1][r] * n[1] + cof[2][r] * n[2]);
    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if len > 0.0 && len.is_finite() { v.map(|x| (x / len) as f32) } else { [0.0; 3] }
}

/// An accessor's bytes, checked to hold all its elements.
struct Strided<'b> {
    data: &'b [u8],
    stride: usize,
    size: usize,
    count: usize,
    data_type: DataType,
    normalized: bool,
}

impl<'b> Strided<'b> {
    fn element(&self, i: usize) -> Result<&'b [u8], MeshError> {
        let start = i * self.stride;
        self.data
            .get(start..start + self.size)
            .ok_or_else(|| malformed("accessor element out of range"))
    }

    /// Element `i` of a VEC3 accessor of floats or of (normalized) 8- or 16-bit integers.
    fn vec3(&self, i: usize) -> Result<[f32; 3], MeshError> {
        let element = self.element(i)?;
        let width = self.size / 3;
        let mut v = [0.0; 3];
        for (value, bytes) in v.iter_mut().zip(element.chunks_exact(width)) {
            *value = scalar(bytes, self.data_type, self.normalized)
                .ok_or_else(|| malformed("bad vec3 element"))?;
        }
        Ok(v)
    }

    fn index(&self, i: usize) -> Result<u32, MeshError> {
        Ok(match *self.element(i)? {
            [a] => u32::from(a),
            [a, b] => u32::from(u16::from_le_bytes([a, b])),
            [a, b, c, d] => u32::from_le_bytes([a, b, c, d]),
            _ => return Err(malformed("bad index size")),
        })
    }
}

/// One component's value: a float, or an integer, which a normalized accessor maps to [0, 1]
/// (unsigned) or [-1, 1] (signed) as the glTF specification says.
fn scalar(bytes: &[u8], data_type: DataType, normalized: bool) -> Option<f32> {
    let (value, max) = match (data_type, bytes) {
        (DataType::F32, &[a, b, c, d]) => return Some(f32::from_le_bytes([a, b, c, d])),
        (DataType::I8, &[a]) => (f32::from(a as i8), 127.0),
        (DataType::U8, &[a]) => (f32::from(a), 255.0),
        (DataType::I16, &[a, b]) => (f32::from(i16::from_le_bytes([a, b])), 32767.0),
        (DataType::U16, &[a, b]) => (f32::from(u16::from_le_bytes([a, b])), 65535.0),
        _ => return None,
    };
    Some(if normalized { (value / max).max(-1.0) } else { value })
}

/// What a primitive is made of, read from its accessors or decoded from Draco.
struct Geometry {
    positions: Vec<[f32; 3]>,
    normals: Option<Vec<[f32; 3]>>,
    /// `None`: the vertices in order.
    indices: Option<Vec<u32>>,
}

struct Context<'b> {
    document: &'b Document,
    buffers: &'b [Option<Vec<u8>>],
    /// The decoded bytes of the buffer views that are meshopt-compressed, by index.
    decoded: HashMap<usize, Vec<u8>>,
    limits: &'b ReadLimits,
}

impl<'b> Context<'b> {
    /// For reading `primitives`: the compressed buffer views they use are decoded here.
    fn new(
        document: &'b Document,
        buffers: &'b [Option<Vec<u8>>],
        primitives: impl Iterator<Item = Primitive<'b>>,
        limits: &'b ReadLimits,
    ) -> Result<Self, MeshError> {
        let mut views = Vec::new();
        for primitive in primitives {
            if let Some(ext) = primitive.extension_value(draco::EXTENSION) {
                views.push(view_at(document, draco::buffer_view(ext)?)?);
                continue;
            }
            let accessors = [Semantic::Positions, Semantic::Normals]
                .iter()
                .filter_map(|semantic| primitive.get(semantic))
                .chain(primitive.indices());
            views.extend(accessors.filter_map(|accessor| accessor.view()));
        }
        let decoded = meshopt::decode_views(views, buffers)?;
        Ok(Self { document, buffers, decoded, limits })
    }

    /// A buffer view's bytes: decoded when it is compressed, else its range of its buffer.
    fn view_bytes(&self, view: &gltf::buffer::View) -> Result<&[u8], MeshError> {
        if let Some(decoded) = self.decoded.get(&view.index()) {
            return Ok(decoded);
        }
        let buffer = match self.buffers.get(view.buffer().index()) {
            Some(Some(buffer)) => buffer,
            Some(None) => {
                return Err(malformed(format!(
                    "buffer view {} is not compressed, and its buffer is a fallback without data",
                    view.index()
                )));
            }
            None => return Err(malformed("bad buffer index")),
        };
        view.offset()
            .checked_add(view.length())
            .and_then(|end| buffer.get(view.offset()..end))
            .ok_or_else(|| malformed(format!("buffer view {} runs past its buffer", view.index())))
    }

    fn accessor(&self, accessor: &Accessor, semantic: &str) -> Result<Strided<'_>, MeshError> {
        let i = accessor.index();
        if accessor.sparse().is_some() {
            return Err(unsupported(format!("sparse accessor {i} ({semantic})")));
        }
        let Some(view) = accessor.view() else {
            return Err(unsupported(format!("{semantic} accessor {i} has no buffer view")));
        };
        let size = accessor.size();
        let stride = view.stride().unwrap_or(size);
        let count = accessor.count();
        let view_bytes = self.view_bytes(&view)?;
        if count == 0 {
            return Err(malformed(format!(
                "accessor {i} ({semantic}) is empty; glTF requires count >= 1"
            )));
        }
        let needed = (count - 1).checked_mul(stride).and_then(|b| b.checked_add(size));
        let data = needed
            .filter(|_| stride >= size && size > 0)
            .and_then(|needed| {
                view_bytes.get(accessor.offset()..accessor.offset().checked_add(needed)?)
            })
            .ok_or_else(|| {
                malformed(format!("accessor {i} ({semantic}) runs past its buffer view"))
            })?;
        let (data_type, normalized) = (accessor.data_type(), accessor.normalized());
        Ok(Strided { data, stride, size, count, data_type, normalized })
    }

    /// A VEC3 accessor of floats, or of 8- or 16-bit integers (`KHR_mesh_quantization`).
    fn vec3_accessor(&self, accessor: &Accessor, semantic: &str) -> Result<Strided<'_>, MeshError> {
        let quantized = matches!(
            accessor.data_type(),
            DataType::I8 | DataType::U8 | DataType::I16 | DataType::U16
        );
        if accessor.dimensions() != Dimensions::Vec3
            || !(accessor.data_type() == DataType::F32 || quantized)
        {
            return Err(unsupported(format!(
                "{semantic} stored as {:?} {:?}, not VEC3 of floats or 8- or 16-bit integers",
                accessor.dimensions(),
                accessor.data_type()
            )));
        }
        self.accessor(accessor, semantic)
    }

    /// A primitive's positions, normals when `with_normals` and indices, from its accessors.
    fn accessor_geometry(
        &self,
        primitive: &Primitive,
        with_normals: bool,
    ) -> Result<Geometry, MeshError> {
        let Some(positions) = primitive.get(&Semantic::Positions) else {
            return Err(malformed(format!("primitive {} has no POSITION", primitive.index())));
        };
        let positions = self.vec3_accessor(&positions, "POSITION")?;
        let n = positions.count;
        self.limits.check_vertices(n as u64)?;
        let read_all = |source: &Strided| -> Result<Vec<[f32; 3]>, MeshError> {
            (0..source.count).map(|i| source.vec3(i)).collect()
        };
        let normals = if with_normals {
            let accessor =
                primitive.get(&Semantic::Normals).ok_or_else(|| malformed("NORMAL vanished"))?;
            let source = self.vec3_accessor(&accessor, "NORMAL")?;
            if source.count != n {
                return Err(malformed(format!("{} normals for {n} positions", source.count)));
            }
            Some(read_all(&source)?)
        } else {
            None
        };
        let indices = match primitive.indices() {
            Some(accessor) => {
                if accessor.dimensions() != Dimensions::Scalar
                    || !matches!(accessor.data_type(), DataType::U8 | DataType::U16 | DataType::U32)
                {
                    return Err(malformed("indices must be unsigned integer scalars"));
                }
                let source = self.accessor(&accessor, "indices")?;
                Some((0..source.count).map(|i| source.index(i)).collect::<Result<_, _>>()?)
            }
            None => None,
        };
        Ok(Geometry { positions: read_all(&positions)?, normals, indices })
    }

    fn read_primitive(
        &self,
        primitive: &Primitive,
        world: &Mat4,
        asm: &mut Assembler,
        normals: Option<&mut Vec<[f32; 3]>>,
    ) -> Result<(), MeshError> {
        let with_normals = normals.is_some();
        let (geometry, mode) = match primitive.extension_value(draco::EXTENSION) {
            Some(ext) => {
                let view = view_at(self.document, draco::buffer_view(ext)?)?;
                let geometry =
                    draco::decode(self.view_bytes(&view)?, ext, with_normals, self.limits)?;
                // Draco decodes strips and fans into a list.
                let mode =
                    if primitive.mode() == Mode::Points { Mode::Points } else { Mode::Triangles };
                (geometry, mode)
            }
            None => (self.accessor_geometry(primitive, with_normals)?, primitive.mode()),
        };
        let n = geometry.positions.len();
        asm.check_limits(n as u64, 0)?;
        let base = asm.vertices.len();
        if u32::try_from(base + n).is_err() {
            return Err(malformed("more vertices than 32-bit indices can address"));
        }
        let base = base as u32;
        asm.reserve(n as u64, 0)?;
        for p in geometry.positions {
            asm.push_vertex(transform_point(world, p))?;
        }
        let (normal_matrix, winding) = normal_matrix(world);
        if let (Some(normals), Some(source)) = (normals, geometry.normals) {
            normals.extend(source.into_iter().map(|n| transform_normal(&normal_matrix, n)));
        }
        if mode == Mode::Points {
            return Ok(());
        }
        let indices = geometry.indices.unwrap_or_else(|| (0..n as u32).collect());
        if let Some(bad) = indices.iter().find(|&&index| index as usize >= n) {
            return Err(malformed(format!("index {bad} with {n} vertices")));
        }
        let triangles = triangles(mode, &indices)?;
        asm.check_limits(0, triangles.len() as u64)?;
        for [a, b, c] in triangles {
            // A mirroring transform turns the winding; swapping two corners restores it.
            let t = if winding < 0.0 { [a, c, b] } else { [a, b, c] };
            asm.push_triangle(t.map(|i| base + i))?;
        }
        Ok(())
    }
}

/// Buffer view `index`, named by an extension (the document's own indices are validated).
fn view_at(document: &Document, index: usize) -> Result<gltf::buffer::View<'_>, MeshError> {
    document
        .views()
        .nth(index)
        .ok_or_else(|| malformed(format!("buffer view {index} does not exist")))
}

/// The triangles of a triangle list, strip or fan, as the glTF specification defines them.
fn triangles(mode: Mode, indices: &[u32]) -> Result<Vec<[u32; 3]>, MeshError> {
    let v = indices;
    let strip_or_fan = v.len().saturating_sub(2);
    Ok(match mode {
        Mode::Triangles => {
            if !v.len().is_multiple_of(3) {
                return Err(malformed(format!("{} indices do not make whole triangles", v.len())));
            }
            v.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect()
        }
        Mode::TriangleStrip => {
            (0..strip_or_fan)
                .map(|i| {
                    if i % 2 == 0 { [v[i], v[i + 1], v[i + 2]] } else { [v[i], v[i + 2], v[i + 1]] }
                })
                .collect()
        }
        Mode::TriangleFan => (0..strip_or_fan).map(|i| [v[i + 1], v[i + 2], v[0]]).collect(),
        _ => Vec::new(),
    })
}
