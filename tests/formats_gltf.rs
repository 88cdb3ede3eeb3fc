//! glTF reading on hand-built files: node hierarchies, non-indexed, strip and fan primitives,
//! points, external buffers, quantized and meshopt-compressed data, unsupported extensions and
//! hostile files; files made small for the web by the tools people use (`tests/data/web-gltf`);
//! and what our GLB writer produces, checked by parsing it back with the `gltf` crate.

use std::borrow::Cow;

use meshstream::mesh::{
    Format, Mesh, MeshError, ReadLimits, read_mesh, read_mesh_file, write_mesh,
};
use serde_json::{Value, json};

/// Builds the binary buffer, buffer views and accessors of a test file.
#[derive(Default)]
struct Bin {
    bytes: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Bin {
    fn view(&mut self, data: &[u8]) -> usize {
        let offset = self.bytes.len();
        self.bytes.extend_from_slice(data);
        self.bytes.resize(self.bytes.len().next_multiple_of(4), 0);
        self.views.push(json!({"buffer": 0, "byteOffset": offset, "byteLength": data.len()}));
        self.views.len() - 1
    }

    fn accessor(&mut self, accessor: Value) -> usize {
        self.accessors.push(accessor);
        self.accessors.len() - 1
    }

    fn vec3s(&mut self, values: &[[f32; 3]]) -> usize {
        let data: Vec<u8> = values.iter().flatten().flat_map(|c| c.to_le_bytes()).collect();
        let view = self.view(&data);
        self.accessor(json!({"bufferView": view, "componentType": 5126, "type": "VEC3", "count": values.len()}))
    }

    fn indices(&mut self, values: &[u16]) -> usize {
        let data: Vec<u8> = values.iter().flat_map(|c| c.to_le_bytes()).collect();
        let view = self.view(&data);
        self.accessor(json!({"bufferView": view, "componentType": 5123, "type": "SCALAR", "count": values.len()}))
    }

    /// The document: `doc` plus asset, buffers, views and accessors.
    fn document(&self, mut doc: Value) -> Value {
        doc["asset"] = json!({"version": "2.0"});
        doc["buffers"] = json!([{"byteLength": self.bytes.len()}]);
        doc["bufferViews"] = Value::Array(self.views.clone());
        doc["accessors"] = Value::Array(self.accessors.clone());
        doc
    }

    fn glb(&self, doc: Value) -> Vec<u8> {
        glb_of(&serde_json::to_vec(&self.document(doc)).unwrap(), &self.bytes)
    }
}

fn glb_of(json: &[u8], bin: &[u8]) -> Vec<u8> {
    gltf::binary::Glb {
        header: gltf::binary::Header { magic: *b"glTF", version: 2, length: 0 },
        json: Cow::Borrowed(json),
        bin: Some(Cow::Borrowed(bin)),
    }
    .to_vec()
    .unwrap()
}

fn read(bytes: &[u8]) -> Result<Mesh, MeshError> {
    read_mesh(bytes, Format::Gltf, &ReadLimits::default())
}

fn assert_close(actual: &[[f32; 3]], expected: &[[f32; 3]]) {
    assert_eq!(actual.len(), expected.len(), "{actual:?} vs {expected:?}");
    for (a, e) in actual.iter().zip(expected) {
        assert!(a.iter().zip(e).all(|(a, e)| (a - e).abs() < 1e-5), "{actual:?} vs {expected:?}");
    }
}

const TRIANGLE: [[f32; 3]; 3] = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];

#[test]
fn node_transforms_are_applied_down_the_hierarchy() {
    let mut bin = Bin::default();
    let positions = bin.vec3s(&TRIANGLE);
    let normals = bin.vec3s(&[[0.0, 0.0, 1.0]; 3]);
    let indices = bin.indices(&[0, 1, 2]);
    let half = std::f32::consts::FRAC_1_SQRT_2;
    let doc = json!({
        "scene": 1,
        "scenes": [{"nodes": [2]}, {"nodes": [0, 2]}],
        "nodes": [
            {"translation": [10.0, 0.0, 0.0], "children": [1]},
            // A quarter turn about z and a uniform scale of 2.
            {"rotation": [0.0, 0.0, half, half], "scale": [2.0, 2.0, 2.0], "mesh": 0},
            // A mirror (x -> -x) moved up by 5, as a matrix.
            {"matrix": [-1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 5.0, 1.0], "mesh": 0}
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": positions, "NORMAL": normals}, "indices": indices}]}]
    });
    let mesh = read(&bin.glb(doc)).unwrap();
    assert_close(
        &mesh.vertices,
        &[
            [10.0, 0.0, 0.0],
            [10.0, 2.0, 0.0],
            [8.0, 0.0, 0.0],
            [0.0, 0.0, 5.0],
            [-1.0, 0.0, 5.0],
            [0.0, 1.0, 5.0],
        ],
    );
    // The mirrored copy has its winding turned back, so both face +z like their normals.
    assert_eq!(mesh.faces, vec![[0, 1, 2], [3, 5, 4]]);
    assert_close(mesh.normals.as_ref().unwrap(), &[[0.0, 0.0, 1.0]; 6]);
    for n in mesh.face_normals() {
        assert_close(&[n], &[[0.0, 0.0, 1.0]]);
    }
}

#[test]
fn non_indexed_strips_and_fans_without_a_scene() {
    let mut bin = Bin::default();
    let triangle = bin.vec3s(&TRIANGLE);
    let quad = bin.vec3s(&[[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [1.0, 1.0, 1.0]]);
    let doc = json!({
        "meshes": [{"primitives": [
            {"attributes": {"POSITION": triangle}},
            {"attributes": {"POSITION": quad}, "mode": 5},
            {"attributes": {"POSITION": quad}, "mode": 6},
            {"attributes": {"POSITION": triangle}, "mode": 1}
        ]}]
    });
    let mesh = read(&bin.glb(doc)).unwrap();
    assert_eq!(mesh.vertices.len(), 3 + 4 + 4, "the line primitive adds nothing");
    assert_eq!(mesh.faces, vec![[0, 1, 2], [3, 4, 5], [4, 6, 5], [8, 9, 7], [9, 10, 7]]);
    assert!(mesh.normals.is_none(), "no primitive has normals");
}

#[test]
fn points_only_is_a_point_cloud() {
    let mut bin = Bin::default();
    let points = bin.vec3s(&TRIANGLE);
    let normals = bin.vec3s(&[[0.0, 0.0, 2.0]; 3]);
    let doc = json!({
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "translation": [0.0, 0.0, 1.0]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": points, "NORMAL": normals}, "mode": 0}]}]
    });
    let mesh = read(&bin.glb(doc)).unwrap();
    assert!(mesh.is_point_cloud());
    assert_close(&mesh.vertices, &[[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]]);
    assert_close(mesh.normals.as_ref().unwrap(), &[[0.0, 0.0, 1.0]; 3]);
}

fn triangle_doc(bin: &mut Bin) -> Value {
    let positions = bin.vec3s(&TRIANGLE);
    json!({"meshes": [{"primitives": [{"attributes": {"POSITION": positions}}]}]})
}

#[test]
fn geometry_extensions_are_read_or_refused_by_name() {
    // Required, but the data is plain: read as it is.
    for ext in ["KHR_draco_mesh_compression", "KHR_mesh_quantization", "EXT_meshopt_compression"] {
        let mut bin = Bin::default();
        let mut doc = triangle_doc(&mut bin);
        doc["extensionsUsed"] = json!([ext]);
        doc["extensionsRequired"] = json!([ext]);
        assert_eq!(read(&bin.glb(doc)).unwrap().faces, vec![[0, 1, 2]], "{ext}");
    }
    for ext in ["EXT_mesh_gpu_instancing", "KHR_mesh_something_new"] {
        let mut bin = Bin::default();
        let mut doc = triangle_doc(&mut bin);
        doc["extensionsRequired"] = json!([ext]);
        let err = read(&bin.glb(doc)).unwrap_err();
        assert!(matches!(err, MeshError::Unsupported { .. }), "{ext}: {err}");
        assert!(err.to_string().contains(ext), "{err}");
    }
    // An accessor without data, and no extension to give it any.
    let bin = Bin::default();
    let doc = json!({
        "extensionsUsed": ["KHR_draco_mesh_compression"],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}]
    });
    let mut doc = bin.document(doc);
    doc["accessors"] = json!([{"componentType": 5126, "type": "VEC3", "count": 3, "min": [0, 0, 0], "max": [1, 1, 0]}]);
    let err = read(&glb_of(&serde_json::to_vec(&doc).unwrap(), &[0; 4])).unwrap_err();
    assert!(matches!(err, MeshError::Unsupported { .. }), "{err}");
    // A material extension does not touch geometry.
    let mut bin = Bin::default();
    let mut doc = triangle_doc(&mut bin);
    doc["extensionsUsed"] = json!(["KHR_materials_clearcoat"]);
    doc["extensionsRequired"] = json!(["KHR_materials_clearcoat"]);
    assert_eq!(read(&bin.glb(doc)).unwrap().faces, vec![[0, 1, 2]]);
}

#[test]
fn quantized_positions_and_normals_are_read_as_the_specification_maps_them() {
    // KHR_mesh_quantization: normalized shorts (padded to 8 bytes a vertex) scaled back by
    // the node, plain unsigned bytes, and normalized signed bytes for normals.
    let mut bin = Bin::default();
    let shorts: [[i16; 4]; 3] = [[0, 0, 0, 0], [32767, 0, 0, 0], [0, -32767, 0, 0]];
    let view = bin.view(&shorts.iter().flatten().flat_map(|c| c.to_le_bytes()).collect::<Vec<_>>());
    bin.views[view]["byteStride"] = json!(8);
    let normalized = bin.accessor(json!({"bufferView": view, "componentType": 5122, "normalized": true, "type": "VEC3", "count": 3}));
    let view = bin.view(&[0, 0, 0, 0, 2, 0, 0, 0, 0, 0, 3, 0]);
    bin.views[view]["byteStride"] = json!(4);
    let bytes = bin
        .accessor(json!({"bufferView": view, "componentType": 5121, "type": "VEC3", "count": 3}));
    let view = bin.view(&[0, 0, 127, 0, 0, 0, 127, 0, 0, 0, 0x81, 0]);
    bin.views[view]["byteStride"] = json!(4);
    let normals = bin.accessor(json!({"bufferView": view, "componentType": 5120, "normalized": true, "type": "VEC3", "count": 3}));
    let doc = json!({
        "extensionsUsed": ["KHR_mesh_quantization"],
        "extensionsRequired": ["KHR_mesh_quantization"],
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [{"mesh": 0, "scale": [2.0, 2.0, 2.0]}, {"mesh": 1}],
        "meshes": [
            {"primitives": [{"attributes": {"POSITION": normalized, "NORMAL": normals}}]},
            {"primitives": [{"attributes": {"POSITION": bytes, "NORMAL": normals}}]}
        ]
    });
    let mesh = read(&bin.glb(doc)).unwrap();
    assert_close(
        &mesh.vertices,
        &[
            [0.0, 0.0, 0.0],
            [2.0, 0.0, 0.0],
            [0.0, -2.0, 0.0],
            [0.0, 0.0, 0.0],
            [2.0, 0.0, 0.0],
            [0.0, 0.0, 3.0],
        ],
    );
    let n = mesh.normals.as_ref().unwrap();
    assert_close(n, &[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]].repeat(2));
    assert_eq!(mesh.faces, vec![[0, 1, 2], [3, 4, 5]]);
}

/// A triangle whose positions (floats, optionally through the exponential filter) and indices
/// are meshopt-compressed into buffer 0, with buffer 1 the fallback without data; `ext` names
/// the extension, and `mutate` damages the document before it is written.
fn meshopt_triangle(ext: &str, exponential: bool, mutate: impl Fn(&mut Value)) -> Vec<u8> {
    let words: Vec<[u32; 3]> = if exponential {
        meshopt::encoding::encode_filter_exp(
            &TRIANGLE,
            24,
            meshopt::encoding::EncodeExpMode::Separate,
        )
    } else {
        TRIANGLE.iter().map(|p| p.map(f32::to_bits)).collect()
    };
    let vertices = meshopt::encoding::encode_vertex_buffer(&words).unwrap();
    let indices = meshopt::encoding::encode_index_buffer(&[0, 1, 2], 3).unwrap();
    let mut bin = vertices.clone();
    bin.resize(bin.len().next_multiple_of(4), 0);
    let index_offset = bin.len();
    bin.extend_from_slice(&indices);
    bin.resize(bin.len().next_multiple_of(4), 0);
    let filter = if exponential { "EXPONENTIAL" } else { "NONE" };
    let mut doc = json!({
        "asset": {"version": "2.0"},
        "extensionsUsed": [ext],
        "extensionsRequired": [ext],
        "buffers": [{"byteLength": bin.len()}, {"byteLength": 48, "extensions": {ext: {"fallback": true}}}],
        "bufferViews": [
            {"buffer": 1, "byteOffset": 0, "byteLength": 36, "byteStride": 12, "extensions": {ext: {
                "buffer": 0, "byteOffset": 0, "byteLength": vertices.len(), "byteStride": 12,
                "count": 3, "mode": "ATTRIBUTES", "filter": filter}}},
            {"buffer": 1, "byteOffset": 36, "byteLength": 12, "extensions": {ext: {
                "buffer": 0, "byteOffset": index_offset, "byteLength": indices.len(),
                "byteStride": 4, "count": 3, "mode": "TRIANGLES"}}}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "type": "VEC3", "count": 3},
            {"bufferView": 1, "componentType": 5125, "type": "SCALAR", "count": 3}
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}]
    });
    mutate(&mut doc);
    glb_of(&serde_json::to_vec(&doc).unwrap(), &bin)
}

#[test]
fn meshopt_compressed_views_decode_under_either_extension_name() {
    for ext in ["EXT_meshopt_compression", "KHR_meshopt_compression"] {
        for exponential in [false, true] {
            let mesh = read(&meshopt_triangle(ext, exponential, |_| {})).unwrap();
            assert_close(&mesh.vertices, &TRIANGLE);
            assert_eq!(mesh.faces, vec![[0, 1, 2]], "{ext}");
        }
    }
    // (what, buffer view, field of its compression, value)
    let damages = [
        ("compressed range past its buffer", 0, "byteOffset", json!(4000)),
        ("compressed range cut short", 0, "byteLength", json!(5)),
        ("more vertices than the view holds", 0, "count", json!(1u64 << 40)),
        ("a stride that is not a multiple of 4", 0, "byteStride", json!(6)),
        ("a filter for another stride", 0, "filter", json!("QUATERNION")),
        ("an unknown mode", 0, "mode", json!("SPLATS")),
        ("triangles that are not whole", 1, "count", json!(2)),
        ("compressed data in the fallback buffer", 0, "buffer", json!(1)),
        ("a fallback view read as it is", 0, "", Value::Null),
    ];
    for (what, view, field, value) in damages {
        let bytes = meshopt_triangle("EXT_meshopt_compression", false, |d| {
            let extensions = &mut d["bufferViews"][view]["extensions"];
            match field {
                "" => *extensions = json!({}),
                _ => extensions["EXT_meshopt_compression"][field] = value.clone(),
            }
        });
        match read(&bytes) {
            Err(MeshError::Malformed { .. } | MeshError::Unsupported { .. }) => {}
            other => panic!("{what}: {other:?}"),
        }
    }
}

/// The files in `tests/data/web-gltf`, made from `pine-tree.glb` by glTF-Transform and
/// gltfpack (`make.sh` there).
const WEB_FILES: [&str; 4] = [
    "pine-tree-quantized.glb",
    "pine-tree-meshopt.glb",
    "pine-tree-gltfpack.glb",
    "pine-tree-draco.glb",
];

fn web_file(name: &str) -> Vec<u8> {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/web-gltf").join(name);
    std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn files_made_small_for_the_web_read_as_their_source() {
    let source = read(&web_file("pine-tree.glb")).unwrap();
    let source_normals = source.normals.as_ref().unwrap();
    let nearest = |p: [f32; 3]| {
        let d = |i: usize| (0..3).map(|k| (source.vertices[i][k] - p[k]).powi(2)).sum::<f32>();
        let i = (0..source.vertices.len()).min_by(|&a, &b| d(a).total_cmp(&d(b))).unwrap();
        (i, d(i).sqrt())
    };
    let canonical = |t: [u32; 3]| {
        let r = (0..3).min_by_key(|&k| t[k]).unwrap();
        [t[r], t[(r + 1) % 3], t[(r + 2) % 3]]
    };
    let mut source_faces: Vec<_> = source.faces.iter().map(|&t| canonical(t)).collect();
    source_faces.sort();
    for name in WEB_FILES {
        let mesh = read(&web_file(name)).unwrap();
        assert_eq!(mesh.vertices.len(), source.vertices.len(), "{name}");
        let normals = mesh.normals.as_ref().unwrap_or_else(|| panic!("{name}: no normals"));
        // Each vertex within quantization error (14 bits over a 2-unit tree) of its source.
        let mut map = Vec::new();
        for (p, n) in mesh.vertices.iter().zip(normals) {
            let (i, distance) = nearest(*p);
            assert!(distance < 1e-3, "{name}: a vertex {distance} from its source");
            let cos: f32 = (0..3).map(|k| n[k] * source_normals[i][k]).sum();
            assert!(cos > 0.99, "{name}: a normal turned ({cos})");
            map.push(i as u32);
        }
        let mut faces: Vec<_> =
            mesh.faces.iter().map(|t| canonical(t.map(|v| map[v as usize]))).collect();
        faces.sort();
        assert_eq!(faces, source_faces, "{name}: the faces and their winding");
    }
}

#[test]
fn damaged_web_files_fail_cleanly_or_read() {
    // Every byte of each file flipped in turn, and the file cut at every length: the reader
    // returns, with a mesh or an error, and never panics or hangs.
    for name in WEB_FILES {
        let good = web_file(name);
        for at in 0..good.len() {
            let mut bytes = good.clone();
            bytes[at] ^= 0xa5;
            let _ = read(&bytes);
            let _ = read(&good[..at]);
        }
    }
}

#[test]
fn draco_streams_stop_at_the_reader_s_limits() {
    let bytes = web_file("pine-tree-draco.glb");
    let limits = ReadLimits { max_faces: 50, ..ReadLimits::default() };
    let err = read_mesh(&bytes, Format::Gltf, &limits).unwrap_err();
    assert!(matches!(err, MeshError::TooLarge { what: "face count", limit: 50 }), "{err}");
    let limits = ReadLimits { max_vertices: 20, ..ReadLimits::default() };
    let err = read_mesh(&bytes, Format::Gltf, &limits).unwrap_err();
    assert!(matches!(err, MeshError::TooLarge { what: "vertex count", .. }), "{err}");
}

#[test]
fn external_buffers_resolve_next_to_the_file_only() {
    let mut bin = Bin::default();
    let doc = triangle_doc(&mut bin);
    let mut doc = bin.document(doc);
    doc["buffers"][0]["uri"] = json!("tri%20data.bin");
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("tri data.bin"), &bin.bytes).unwrap();
    let path = dir.path().join("tri.gltf");
    std::fs::write(&path, serde_json::to_vec(&doc).unwrap()).unwrap();
    let mesh = read_mesh_file(&path, &ReadLimits::default()).unwrap();
    assert_eq!(
        (mesh.vertices.as_slice(), mesh.faces.as_slice()),
        (&TRIANGLE[..], &[[0, 1, 2]][..])
    );
    let json_bytes = std::fs::read(&path).unwrap();
    assert!(matches!(read(&json_bytes), Err(MeshError::Unsupported { .. })));
    let small = ReadLimits { max_bytes: json_bytes.len() as u64 + 10, ..ReadLimits::default() };
    assert!(matches!(read_mesh_file(&path, &small), Err(MeshError::TooLarge { .. })));
    for uri in ["/etc/passwd", "file:///etc/passwd", "../x.bin"] {
        doc["buffers"][0]["uri"] = json!(uri);
        std::fs::write(&path, serde_json::to_vec(&doc).unwrap()).unwrap();
        assert!(read_mesh_file(&path, &ReadLimits::default()).is_err(), "{uri}");
    }
}

#[test]
fn hostile_files_give_typed_errors() {
    let mut bin = Bin::default();
    let doc = triangle_doc(&mut bin);
    let good = bin.document(doc);
    let mutations: &[fn(&mut Value)] = &[
        |d| d["accessors"][0]["count"] = json!(1u64 << 40),
        |d| d["accessors"][0]["count"] = json!(0),
        |d| d["accessors"][0]["byteOffset"] = json!(8),
        |d| d["bufferViews"][0]["byteStride"] = json!(4),
        |d| d["bufferViews"][0]["byteLength"] = json!(1000),
        |d| d["accessors"][0]["componentType"] = json!(5125),
        |d| d["buffers"][0]["byteLength"] = json!(1u64 << 40),
        |d| {
            d["scenes"] = json!([{"nodes": [0]}]);
            d["nodes"] = json!([{"children": [1]}, {"children": [0], "mesh": 0}]);
        },
        |d| {
            d["meshes"][0]["primitives"][0]["indices"] = json!(1);
            let indices = json!({"bufferView": 0, "byteOffset": 12, "componentType": 5125, "type": "SCALAR", "count": 3});
            d["accessors"].as_array_mut().unwrap().push(indices);
        },
    ];
    for (i, mutate) in mutations.iter().enumerate() {
        let mut doc = good.clone();
        mutate(&mut doc);
        let bytes = glb_of(&serde_json::to_vec(&doc).unwrap(), &bin.bytes);
        match read(&bytes) {
            Err(
                MeshError::Malformed { .. }
                | MeshError::Unsupported { .. }
                | MeshError::TooLarge { .. },
            ) => {}
            other => panic!("mutation {i}: {other:?}"),
        }
    }
    // Index 1e9 into three vertices, through a u32 index accessor.
    let mut bin = Bin::default();
    let positions = bin.vec3s(&TRIANGLE);
    let view = bin
        .view(&[0u32, 1, 1_000_000_000].iter().flat_map(|i| i.to_le_bytes()).collect::<Vec<_>>());
    let indices = bin
        .accessor(json!({"bufferView": view, "componentType": 5125, "type": "SCALAR", "count": 3}));
    let doc = json!({"meshes": [{"primitives": [{"attributes": {"POSITION": positions}, "indices": indices}]}]});
    assert!(matches!(read(&bin.glb(doc)), Err(MeshError::Malformed { .. })));
    // GLB headers that lie about their length.
    for length in [0u32, 11, 12, u32::MAX] {
        let mut bytes = glb_of(b"{}", &[]);
        bytes[8..12].copy_from_slice(&length.to_le_bytes());
        assert!(matches!(read(&bytes), Err(MeshError::Malformed { .. })), "length {length}");
    }
}

#[test]
fn written_glb_parses_back_with_the_gltf_crate() {
    let mesh = Mesh::new(
        vec![[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, -1.0]],
        vec![[0, 1, 2], [0, 2, 3]],
    );
    let bytes = write_mesh(&mesh, Format::Gltf).unwrap();
    assert_eq!(bytes.len() % 4, 0);
    let (doc, buffers, _) = gltf::import_slice(&bytes).unwrap();
    assert_eq!(doc.as_json().asset.version, "2.0");
    assert_eq!(doc.as_json().asset.generator.as_deref(), Some("meshstream"));
    assert_eq!(doc.buffers().len(), 1);
    let primitive = doc.meshes().next().unwrap().primitives().next().unwrap();
    assert_eq!(primitive.mode(), gltf::mesh::Mode::Triangles);
    let position = primitive.get(&gltf::Semantic::Positions).unwrap();
    assert_eq!(position.min(), Some(json!([0.0, 0.0, -1.0])));
    assert_eq!(position.max(), Some(json!([2.0, 3.0, 0.0])));
    let reader = primitive.reader(|b| Some(&buffers[b.index()]));
    assert_eq!(reader.read_positions().unwrap().collect::<Vec<_>>(), mesh.vertices);
    let normals: Vec<_> = reader.read_normals().unwrap().collect();
    assert_close(&normals, &mesh.vertex_normals());
    assert_eq!(primitive.indices().unwrap().data_type(), gltf::accessor::DataType::U32);
    let indices: Vec<u32> = reader.read_indices().unwrap().into_u32().collect();
    assert_eq!(indices, vec![0, 1, 2, 0, 2, 3]);

    let cloud = Mesh::new(mesh.vertices.clone(), vec![]);
    let bytes = write_mesh(&cloud, Format::Gltf).unwrap();
    let (doc, _, _) = gltf::import_slice(&bytes).unwrap();
    let primitive = doc.meshes().next().unwrap().primitives().next().unwrap();
    assert_eq!(primitive.mode(), gltf::mesh::Mode::Points);
    assert!(primitive.indices().is_none());
    assert!(primitive.get(&gltf::Semantic::Normals).is_none());
    assert_eq!(read(&bytes).unwrap(), cloud);
    assert!(matches!(write_mesh(&Mesh::default(), Format::Gltf), Err(MeshError::Invalid(_))));
}

#[test]
fn without_a_default_scene_all_scenes_are_read_each_node_once() {
    let mut bin = Bin::default();
    let doc = triangle_doc(&mut bin);
    let mut doc = bin.document(doc);
    doc["scenes"] = json!([{"nodes": [0]}, {"nodes": [1, 0]}]);
    doc["nodes"] = json!([{"mesh": 0}, {"mesh": 0, "translation": [0.0, 0.0, 1.0]}]);
    let mesh = read(&glb_of(&serde_json::to_vec(&doc).unwrap(), &bin.bytes)).unwrap();
    assert_eq!(mesh.faces, vec![[0, 1, 2], [3, 4, 5]]);
    assert_close(&mesh.vertices[3..], &TRIANGLE.map(|[x, y, _]| [x, y, 1.0]));
}

#[test]
fn a_mesh_placed_many_times_stops_at_the_limits() {
    let mut bin = Bin::default();
    let doc = triangle_doc(&mut bin);
    let mut doc = bin.document(doc);
    let primitive = doc["meshes"][0]["primitives"][0].clone();
    doc["meshes"][0]["primitives"] = Value::Array(vec![primitive; 2000]);
    doc["nodes"] = Value::Array(vec![json!({"mesh": 0}); 20_000]);
    doc["scenes"] = json!([{"nodes": (0..20_000).collect::<Vec<_>>()}]);
    let bytes = glb_of(&serde_json::to_vec(&doc).unwrap(), &bin.bytes);
    let limits = ReadLimits { max_bytes: 1 << 24, max_vertices: 30_000, max_faces: 10_000 };
    let start = std::time::Instant::now();
    let result = read_mesh(&bytes, Format::Gltf, &limits);
    assert!(matches!(result, Err(MeshError::TooLarge { .. })), "{result:?}");
    assert!(start.elapsed() < std::time::Duration::from_secs(2), "{:?}", start.elapsed());
}

#[test]
fn json_made_of_tiny_objects_is_refused_before_parsing() {
    let nodes = vec!["{}"; 1_100_000].join(",");
    let text = format!(r#"{{"asset":{{"version":"2.0"}},"nodes":[{nodes}]}}"#);
    assert!(matches!(read(text.as_bytes()), Err(MeshError::TooLarge { .. })));
    let bytes = glb_of(text.as_bytes(), &[]);
    assert!(matches!(read(&bytes), Err(MeshError::TooLarge { .. })));
}
