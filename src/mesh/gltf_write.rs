//! Binary glTF 2.0 (GLB) output: one buffer, one mesh with one primitive and its material,
//! one node, one scene. The JSON is built with `gltf-json`'s types and the container by
//! `gltf::binary::Glb`.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};

use gltf_json as json;
use json::validation::Checked::Valid;
use json::validation::USize64;

use super::{Mesh, MeshError};

/// The unit normal written for a vertex that has none (an isolated or degenerate one): glTF
/// requires every NORMAL to be unit length.
const FALLBACK_NORMAL: [f32; 3] = [0.0, 0.0, 1.0];

/// A surface's colour, linear RGBA: about the light grey `meshstream render` and the viewer
/// draw. Without a material a viewer takes glTF's default, which is fully metallic: black
/// wherever a face turns from the light, unless the viewer lights it with an environment map.
const SURFACE_COLOR: [f32; 4] = [0.6, 0.6, 0.65, 1.0];
const SURFACE_ROUGHNESS: f32 = 0.8;

pub(crate) fn write(mesh: &Mesh) -> Result<Vec<u8>, MeshError> {
    if mesh.vertices.is_empty() {
        return Err(MeshError::invalid("glTF accessors cannot be empty: the mesh has no vertices"));
    }
    // Point clouds keep the normals they have; surfaces always get some, as viewers expect.
    let normals = match (&mesh.normals, mesh.is_point_cloud()) {
        (Some(normals), _) => Some(normals.iter().map(|&n| unit(n)).collect::<Vec<_>>()),
        (None, false) => Some(mesh.vertex_normals().into_iter().map(unit).collect()),
        (None, true) => None,
    };

    let mut bin = Vec::new();
    let mut root = json::Root::default();
    let buffer = root.push(json::Buffer {
        byte_length: USize64(0),
        extensions: Default::default(),
        extras: Default::default(),
        name: None,
        uri: None,
    });
    let (lo, hi) = mesh.bounds().unwrap_or_default();
    let mut attributes = BTreeMap::new();
    let positions = push_vec3s(&mut root, &mut bin, buffer, &mesh.vertices, Some((lo, hi)));
    attributes.insert(Valid(json::mesh::Semantic::Positions), positions);
    if let Some(normals) = &normals {
        let normals = push_vec3s(&mut root, &mut bin, buffer, normals, None);
        attributes.insert(Valid(json::mesh::Semantic::Normals), normals);
    }
    let (indices, mode, material) = if mesh.is_point_cloud() {
        (None, json::mesh::Mode::Points, None)
    } else {
        let indices = push_indices(&mut root, &mut bin, buffer, &mesh.faces);
        let material = root.push(surface_material(seen_from_behind(mesh)));
        (Some(indices), json::mesh::Mode::Triangles, Some(material))
    };
    root.buffers[buffer.value()].byte_length = USize64::from(bin.len());

    let primitive = json::mesh::Primitive {
        attributes,
        extensions: Default::default(),
        extras: Default::default(),
        indices,
        material,
        mode: Valid(mode),
        targets: None,
    };
    let mesh_index = root.push(json::Mesh {
        extensions: Default::default(),
        extras: Default::default(),
        name: None,
        primitives: vec![primitive],
        weights: None,
    });
    let node = root.push(json::Node { mesh: Some(mesh_index), ..Default::default() });
    let scene = root.push(json::Scene {
        extensions: Default::default(),
        extras: Default::default(),
        name: None,
        nodes: vec![node],
    });
    root.scene = Some(scene);
    root.asset.generator = Some("meshstream".into());
    root.asset.version = "2.0".into();

    let json = json::serialize::to_vec(&root)
        .map_err(|e| MeshError::invalid(format!("cannot serialize glTF JSON: {e}")))?;
    // The GLB header stores the total length in 32 bits.
    if json.len() as u64 + bin.len() as u64 + 64 > u64::from(u32::MAX) {
        return Err(MeshError::invalid("the mesh is too large for a GLB file (4 GiB)"));
    }
    let glb = gltf::binary::Glb {
        // to_vec computes the length itself, with padding.
        header: gltf::binary::Header { magic: *b"glTF", version: 2, length: 0 },
        json: Cow::Owned(json),
        bin: Some(Cow::Owned(bin)),
    };
    glb.to_vec().map_err(|e| MeshError::invalid(format!("cannot write GLB: {e}")))
}

/// A plain matte material, drawn from both sides when `double_sided`.
fn surface_material(double_sided: bool) -> json::Material {
    json::Material {
        name: Some("surface".into()),
        double_sided,
        pbr_metallic_roughness: json::material::PbrMetallicRoughness {
            base_color_factor: json::material::PbrBaseColorFactor(SURFACE_COLOR),
            metallic_factor: json::material::StrengthFactor(0.0),
            roughness_factor: json::material::StrengthFactor(SURFACE_ROUGHNESS),
            ..Default::default()
        },
        ..Default::default()
    }
}

/// Whether some face of `mesh` can be seen from behind: unless the surface is closed and
/// wound alike (each edge, corners welded by position, run once each way by its two faces),
/// an open sheet, a fin or a face wound against its neighbours shows its back from some side.
/// glTF's default is to draw front sides only, which shows each such face as a hole; a
/// closed surface keeps that default, as its back sides face its inside.
fn seen_from_behind(mesh: &Mesh) -> bool {
    let mut runs: HashMap<(u32, u32), usize> = HashMap::new();
    for [a, b, c] in mesh.welded_faces() {
        for edge in [(a, b), (b, c), (c, a)] {
            *runs.entry(edge).or_default() += 1;
        }
    }
    runs.iter().any(|(&(p, q), &n)| n != 1 || runs.get(&(q, p)) != Some(&1))
}

fn unit(n: [f32; 3]) -> [f32; 3] {
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if len > 0.0 && len.is_finite() { n.map(|c| c / len) } else { FALLBACK_NORMAL }
}

/// Appends a buffer view (with `target`) over `bytes` to the binary chunk; views start on
/// 4-byte boundaries, as glTF requires for float and u32 data.
fn push_view(
    root: &mut json::Root,
    bin: &mut Vec<u8>,
    buffer: json::Index<json::Buffer>,
    bytes: &[u8],
    target: json::buffer::Target,
) -> json::Index<json::buffer::View> {
    let offset = bin.len();
    bin.extend_from_slice(bytes);
    bin.resize(bin.len().next_multiple_of(4), 0);
    root.push(json::buffer::View {
        buffer,
        byte_length: USize64::from(bytes.len()),
        byte_offset: Some(USize64::from(offset)),
        byte_stride: None,
        extensions: Default::default(),
        extras: Default::default(),
        name: None,
        target: Some(Valid(target)),
    })
}

fn push_vec3s(
    root: &mut json::Root,
    bin: &mut Vec<u8>,
    buffer: json::Index<json::Buffer>,
    values: &[[f32; 3]],
    bounds: Option<([f32; 3], [f32; 3])>,
) -> json::Index<json::Accessor> {
    let bytes: Vec<u8> = values.iter().flatten().flat_map(|c| c.to_le_bytes()).collect();
    let view = push_view(root, bin, buffer, &bytes, json::buffer::Target::ArrayBuffer);
    let (min, max) = bounds.map_or((None, None), |(lo, hi)| {
        (Some(json::Value::from(lo.to_vec())), Some(json::Value::from(hi.to_vec())))
    });
    push_accessor(
        root,
        view,
        values.len(),
        json::accessor::ComponentType::F32,
        json::accessor::Type::Vec3,
        min,
        max,
    )
}

fn push_indices(
    root: &mut json::Root,
    bin: &mut Vec<u8>,
    buffer: json::Index<json::Buffer>,
    faces: &[[u32; 3]],
) -> json::Index<json::Accessor> {
    let bytes: Vec<u8> = faces.iter().flatten().flat_map(|i| i.to_le_bytes()).collect();
    let view = push_view(root, bin, buffer, &bytes, json::buffer::Target::ElementArrayBuffer);
    push_accessor(
        root,
        view,
        3 * faces.len(),
        json::accessor::ComponentType::U32,
        json::accessor::Type::Scalar,
        None,
        None,
    )
}

fn push_accessor(
    root: &mut json::Root,
    view: json::Index<json::buffer::View>,
    count: usize,
    component: json::accessor::ComponentType,
    type_: json::accessor::Type,
    min: Option<json::Value>,
    max: Option<json::Value>,
) -> json::Index<json::Accessor> {
    root.push(json::Accessor {
        buffer_view: Some(view),
        byte_offset: None,
        count: USize64::from(count),
        component_type: Valid(json::accessor::GenericComponentType(component)),
        extensions: Default::default(),
        extras: Default::default(),
        type_: Valid(type_),
        min,
        max,
        name: None,
        normalized: false,
        sparse: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::cuboid;

    /// The material of the written file's one primitive, as a glTF reader sees it.
    fn material_of(mesh: &Mesh) -> Option<(bool, f32, f32)> {
        let glb = write(mesh).expect("a valid mesh is written");
        let document = gltf::Gltf::from_slice(&glb).expect("the file is read back").document;
        let primitive = document.meshes().next()?.primitives().next()?;
        let material = primitive.material();
        let pbr = material.pbr_metallic_roughness();
        material.index()?;
        Some((material.double_sided(), pbr.metallic_factor(), pbr.roughness_factor()))
    }

    #[test]
    fn a_closed_surface_wound_alike_is_drawn_from_the_front_only() {
        assert_eq!(material_of(&cuboid([1.0, 2.0, 3.0])), Some((false, 0.0, SURFACE_ROUGHNESS)));
        // Corners split along seams, as files split them for normals, are still one surface.
        let box_ = cuboid([1.0, 1.0, 1.0]);
        let split = Mesh::new(
            box_.faces.iter().flat_map(|f| box_.triangle(f)).collect(),
            (0..box_.faces.len() as u32).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect(),
        );
        assert_eq!(material_of(&split).map(|m| m.0), Some(false));
    }

    #[test]
    fn a_surface_seen_from_behind_somewhere_is_drawn_from_both_sides() {
        let mut open = cuboid([1.0, 1.0, 1.0]);
        open.faces.truncate(10);
        let mut turned = cuboid([1.0, 1.0, 1.0]);
        turned.faces[0].swap(1, 2);
        let mut finned = cuboid([1.0, 1.0, 1.0]);
        finned.vertices.push([0.0, 0.0, -2.0]);
        finned.faces.push([0, 1, 8]);
        for mesh in [open, turned, finned] {
            assert_eq!(material_of(&mesh).map(|m| m.0), Some(true), "{mesh:?}");
        }
    }

    #[test]
    fn a_point_cloud_has_no_material() {
        let cloud = Mesh::new(vec![[0.0; 3], [1.0, 0.0, 0.0]], Vec::new());
        assert_eq!(material_of(&cloud), None);
    }
}
