//! Property tests of the mesh formats: writing then reading gives the same geometry, and no
//! input (random bytes, damaged valid files, hostile headers) makes a reader panic, allocate
//! without bound or return a mesh that breaks its invariants or the limits.

use std::time::{Duration, Instant};

use meshstream::mesh::{Format, Mesh, MeshError, ReadLimits, read_mesh, write_mesh};
use proptest::prelude::*;

fn coordinate() -> impl Strategy<Value = f32> {
    prop_oneof![-1000.0f32..1000.0, Just(0.0), Just(-0.0), Just(1e-30), Just(3.4e37)]
}

fn point() -> impl Strategy<Value = [f32; 3]> {
    [coordinate(), coordinate(), coordinate()]
}

/// Meshes with 1 to 40 vertices, up to 60 faces (none: a point cloud), maybe normals.
fn mesh() -> impl Strategy<Value = Mesh> {
    (1usize..40)
        .prop_flat_map(|n| {
            let face = [0..n as u32, 0..n as u32, 0..n as u32];
            (
                prop::collection::vec(point(), n),
                prop::collection::vec(face, 0..60),
                prop::option::of(prop::collection::vec(point(), n)),
            )
        })
        .prop_map(|(vertices, faces, normals)| Mesh { vertices, faces, normals })
}

/// 256 cases per property (a few seconds in all), or `PROPTEST_CASES` for a longer hunt.
fn cases() -> u32 {
    std::env::var("PROPTEST_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(256)
}

fn read(bytes: &[u8], format: Format) -> Result<Mesh, MeshError> {
    read_mesh(bytes, format, &ReadLimits::default())
}

fn unit(n: [f32; 3]) -> Option<[f32; 3]> {
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    (len > 0.0 && len.is_finite()).then(|| n.map(|c| c / len))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(cases()))]

    #[test]
    fn obj_and_ply_round_trip_exactly(mesh in mesh()) {
        for format in [Format::Obj, Format::Ply] {
            let back = read(&write_mesh(&mesh, format).unwrap(), format).unwrap();
            prop_assert_eq!(&back, &mesh, "{}", format);
        }
    }

    #[test]
    fn stl_round_trips_every_triangle_welded(mesh in mesh()) {
        if mesh.is_point_cloud() {
            prop_assert!(matches!(write_mesh(&mesh, Format::Stl), Err(MeshError::Invalid(_))));
            return Ok(());
        }
        let back = read(&write_mesh(&mesh, Format::Stl).unwrap(), Format::Stl).unwrap();
        prop_assert_eq!(back.faces.len(), mesh.faces.len());
        for (a, b) in mesh.faces.iter().zip(&back.faces) {
            prop_assert_eq!(mesh.triangle(a), back.triangle(b));
        }
        // Welded: no two vertices share a position.
        let mut keys: Vec<[u32; 3]> = back.vertices.iter().map(|v| v.map(|c| (c + 0.0).to_bits())).collect();
        keys.sort_unstable();
        keys.dedup();
        prop_assert_eq!(keys.len(), back.vertices.len());
    }

    #[test]
    fn glb_round_trips_positions_faces_and_unit_normals(mesh in mesh()) {
        let back = read(&write_mesh(&mesh, Format::Gltf).unwrap(), Format::Gltf).unwrap();
        prop_assert_eq!(&back.vertices, &mesh.vertices);
        prop_assert_eq!(&back.faces, &mesh.faces);
        match (&mesh.normals, &back.normals) {
            (Some(ours), Some(theirs)) => {
                for (n, m) in ours.iter().zip(theirs) {
                    let expected = unit(*n).unwrap_or([0.0, 0.0, 1.0]);
                    prop_assert!(expected.iter().zip(m).all(|(a, b)| (a - b).abs() < 1e-5), "{:?} {:?}", n, m);
                }
            }
            (None, Some(_)) => prop_assert!(!mesh.is_point_cloud(), "computed normals for a surface only"),
            (None, None) => prop_assert!(mesh.is_point_cloud()),
            (Some(_), None) => prop_assert!(false, "normals lost"),
        }
    }
}

/// Limits small enough that damaged files hit them, to check that results respect them.
const TIGHT: ReadLimits = ReadLimits { max_bytes: 1 << 16, max_vertices: 100, max_faces: 150 };

/// Reads with tight limits; whatever comes back must be a valid mesh within them.
fn check_robust(bytes: &[u8], format: Format) -> Result<(), TestCaseError> {
    let start = Instant::now();
    let result = read_mesh(bytes, format, &TIGHT);
    prop_assert!(start.elapsed() < Duration::from_secs(2), "{format}: took {:?}", start.elapsed());
    if let Ok(mesh) = result {
        prop_assert!(mesh.validate().is_ok());
        prop_assert!(mesh.vertices.len() <= TIGHT.max_vertices);
        prop_assert!(mesh.faces.len() <= TIGHT.max_faces);
    }
    Ok(())
}

/// ASCII renderings, which the writers do not produce, so that their parsers get damaged input too.
fn ascii_ply(mesh: &Mesh) -> Vec<u8> {
    let mut s = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.vertices.len(),
        mesh.faces.len()
    );
    for [x, y, z] in &mesh.vertices {
        s += &format!("{x} {y} {z}\n");
    }
    for [a, b, c] in &mesh.faces {
        s += &format!("3 {a} {b} {c}\n");
    }
    s.into_bytes()
}

fn ascii_stl(mesh: &Mesh) -> Vec<u8> {
    let mut s = String::from("solid test\n");
    for f in &mesh.faces {
        s += "facet normal 0 0 0\nouter loop\n";
        for [x, y, z] in mesh.triangle(f) {
            s += &format!("vertex {x} {y} {z}\n");
        }
        s += "endloop\nendfacet\n";
    }
    s += "endsolid test\n";
    s.into_bytes()
}

/// A valid file of each kind we read, from a mesh.
fn valid_files(mesh: &Mesh) -> Vec<(Format, Vec<u8>)> {
    let mut files: Vec<(Format, Vec<u8>)> = Format::ALL
        .into_iter()
        .filter_map(|f| write_mesh(mesh, f).ok().map(|bytes| (f, bytes)))
        .collect();
    files.push((Format::Ply, ascii_ply(mesh)));
    files.push((Format::Stl, ascii_stl(mesh)));
    files
}

#[derive(Debug, Clone)]
enum Damage {
    Truncate(prop::sample::Index),
    Overwrite(prop::sample::Index, Vec<u8>),
    Insert(prop::sample::Index, Vec<u8>),
    /// A digit changed in a text file: counts and indices that lie.
    Digit(prop::sample::Index, u8),
}

fn damage() -> impl Strategy<Value = Damage> {
    let index = any::<prop::sample::Index>();
    let bytes = prop::collection::vec(any::<u8>(), 1..8);
    prop_oneof![
        index.clone().prop_map(Damage::Truncate),
        (index.clone(), bytes.clone()).prop_map(|(i, b)| Damage::Overwrite(i, b)),
        (index.clone(), bytes).prop_map(|(i, b)| Damage::Insert(i, b)),
        (index, b'0'..=b'9').prop_map(|(i, d)| Damage::Digit(i, d)),
    ]
}

fn apply(bytes: &mut Vec<u8>, damage: &Damage) {
    if bytes.is_empty() {
        return;
    }
    match damage {
        Damage::Truncate(i) => bytes.truncate(i.index(bytes.len())),
        Damage::Overwrite(i, b) => {
            let at = i.index(bytes.len());
            for (k, &byte) in b.iter().enumerate() {
                if let Some(slot) = bytes.get_mut(at + k) {
                    *slot = byte;
                }
            }
        }
        Damage::Insert(i, b) => {
            let at = i.index(bytes.len());
            bytes.splice(at..at, b.iter().copied());
        }
        Damage::Digit(i, d) => {
            let digits: Vec<usize> =
                (0..bytes.len()).filter(|&k| bytes[k].is_ascii_digit()).collect();
            if !digits.is_empty() {
                bytes[digits[i.index(digits.len())]] = *d;
            }
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(cases()))]

    #[test]
    fn arbitrary_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..2048)) {
        for format in Format::ALL {
            check_robust(&bytes, format)?;
        }
        // Arbitrary bytes behind each format's magic, to get past the first check.
        for magic in [&b"ply\nformat binary_little_endian 1.0\n"[..], b"solid x\n", b"glTF\x02\0\0\0"] {
            let mut prefixed = magic.to_vec();
            prefixed.extend_from_slice(&bytes);
            for format in Format::ALL {
                check_robust(&prefixed, format)?;
            }
        }
    }

    #[test]
    fn damaged_valid_files_never_panic(mesh in mesh(), damages in prop::collection::vec(damage(), 1..4)) {
        for (format, mut bytes) in valid_files(&mesh) {
            for d in &damages {
                apply(&mut bytes, d);
            }
            check_robust(&bytes, format)?;
            if let Some(sniffed) = Format::sniff(&bytes) {
                check_robust(&bytes, sniffed)?;
            }
        }
    }
}

/// Headers that claim billions of elements in a few bytes fail at once, even with no limits
/// (an allocation of the claimed size would abort the test process).
#[test]
fn hostile_headers_fail_fast_even_without_limits() {
    let unlimited =
        ReadLimits { max_bytes: u64::MAX, max_vertices: usize::MAX, max_faces: usize::MAX };
    let mut stl = vec![b' '; 84];
    stl[80..84].copy_from_slice(&u32::MAX.to_le_bytes());
    stl.extend_from_slice(&[0; 50]);
    let hostile: Vec<(Format, Vec<u8>)> = vec![
        (Format::Stl, stl),
        (
            Format::Ply,
            b"ply\nformat binary_big_endian 1.0\nelement vertex 4294967295\nproperty float x\n\
              property float y\nproperty float z\nend_header\n\0\0\0\0"
                .to_vec(),
        ),
        (
            Format::Ply,
            b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\nproperty float y\n\
              property float z\nelement face 2147483648\nproperty list uchar int vertex_indices\nend_header\n\x03"
                .to_vec(),
        ),
        (
            Format::Ply,
            b"ply\nformat ascii 1.0\nelement junk 18446744073709551615\nproperty list uint int a\nend_header\n9\n"
                .to_vec(),
        ),
        (
            Format::Gltf,
            br#"{"asset":{"version":"2.0"},"buffers":[{"byteLength":4294967295,"uri":"data:application/octet-stream;base64,AAAA"}]}"#
                .to_vec(),
        ),
    ];
    for (format, bytes) in hostile {
        for limits in [&unlimited, &ReadLimits::default()] {
            let start = Instant::now();
            let result = read_mesh(&bytes, format, limits);
            assert!(result.is_err(), "{format}: {result:?}");
            // Refused from the header, before allocating what it promises: well under a
            // second even on a busy test machine.
            assert!(start.elapsed() < Duration::from_secs(2), "{format}: {:?}", start.elapsed());
        }
    }
}
