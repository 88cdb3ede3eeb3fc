//! Our GLB output checked by Khronos's glTF-Validator, when it is installed: set
//! `MESHSTREAM_GLTF_VALIDATOR` to the `gltf-validator` npm module's directory (installed with
//! `npm install gltf-validator`), or to a script of your own taking GLB paths as arguments.

use std::path::{Path, PathBuf};
use std::process::Command;

use meshstream::mesh::{Format, Mesh, ReadLimits, read_mesh_file, write_mesh};

/// The meshes whose GLB is validated: a closed surface (computed normals), a surface with its
/// own normals, an unused vertex and a degenerate face, an open surface (a material drawn from
/// both sides), and point clouds with and without normals.
fn cases() -> Vec<(&'static str, Mesh)> {
    let tetra = Mesh::new(
        vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
    );
    let mut with_normals = tetra.clone();
    with_normals.normals =
        Some(vec![[0.0, 0.0, 2.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]);
    let mut odd = tetra.clone();
    odd.vertices.push([5.0, 5.0, 5.0]);
    odd.faces.push([0, 0, 1]);
    let open = Mesh::new(tetra.vertices.clone(), tetra.faces[..3].to_vec());
    let cloud = Mesh::new(tetra.vertices.clone(), vec![]);
    let mut cloud_with_normals = cloud.clone();
    cloud_with_normals.normals = Some(tetra.vertex_normals());
    let mut cases = vec![
        ("tetra", tetra),
        ("tetra-normals", with_normals),
        ("tetra-unused-degenerate", odd),
        ("tetra-open", open),
        ("cloud", cloud),
        ("cloud-normals", cloud_with_normals),
    ];
    // A real model too, when the shared data is there.
    let spot = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data/famous-dev/common-3d-test-models__spot.ply");
    if let Ok(mesh) = read_mesh_file(&spot, &ReadLimits::default()) {
        cases.push(("spot", mesh));
    }
    cases
}

#[test]
fn written_glb_passes_the_khronos_validator() {
    let Some(validator) = std::env::var_os("MESHSTREAM_GLTF_VALIDATOR").map(PathBuf::from) else {
        println!(
            "SKIPPED: set MESHSTREAM_GLTF_VALIDATOR to the gltf-validator npm module directory"
        );
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let files: Vec<PathBuf> = cases()
        .into_iter()
        .map(|(name, mesh)| {
            let path = dir.path().join(format!("{name}.glb"));
            std::fs::write(&path, write_mesh(&mesh, Format::Gltf).unwrap()).unwrap();
            path
        })
        .collect();
    let script = if validator.extension().is_some_and(|e| e == "js" || e == "mjs") {
        validator.clone()
    } else {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/formats_gltf_validator.js")
    };
    let output = Command::new("node")
        .arg(&script)
        .args(&files)
        .env("MESHSTREAM_GLTF_VALIDATOR", &validator)
        .output()
        .expect("node runs");
    let stdout = String::from_utf8_lossy(&output.stdout);
    println!("{stdout}{}", String::from_utf8_lossy(&output.stderr));
    assert!(output.status.success(), "the validator found errors or warnings:\n{stdout}");
    assert_eq!(stdout.lines().count(), files.len());
    assert!(stdout.lines().all(|l| l.contains(r#""numErrors":0,"numWarnings":0"#)));
}
