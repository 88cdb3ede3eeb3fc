//! `meshstream baseline` end to end: both methods on a small mesh, read back.

use std::path::Path;
use std::process::{Command, Output};

use meshstream::mesh::primitives::uv_sphere;
use meshstream::mesh::{ReadLimits, read_mesh_file, write_mesh_file};

fn meshstream(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_meshstream")).args(args).output().unwrap()
}

fn path(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn both_methods_write_a_mesh_within_budget_in_the_inputs_coordinates() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("ball.ply");
    // Far from the origin and large, so a result left in the normalized frame would show.
    let ball = uv_sphere(10.0, 32, 16).translated([100.0, -50.0, 0.0]);
    write_mesh_file(&ball, &src, None).unwrap();
    for (method, ext) in [("hull", "obj"), ("poisson", "glb")] {
        let out = dir.path().join(format!("{method}.{ext}"));
        let o = meshstream(&[
            "baseline",
            path(&src),
            "-o",
            path(&out),
            "--method",
            method,
            "--points",
            "1024",
            "--max-faces",
            "150",
        ]);
        assert!(o.status.success(), "{method}: {}", String::from_utf8_lossy(&o.stderr));
        let mesh = read_mesh_file(&out, &ReadLimits::default()).unwrap();
        assert!(
            !mesh.faces.is_empty() && mesh.faces.len() <= 150,
            "{method}: {}",
            mesh.faces.len()
        );
        let (lo, hi) = mesh.bounds().unwrap();
        for (k, centre) in [100.0f32, -50.0, 0.0].into_iter().enumerate() {
            assert!((lo[k] - (centre - 10.0)).abs() < 2.5, "{method}: {lo:?}");
            assert!((hi[k] - (centre + 10.0)).abs() < 2.5, "{method}: {hi:?}");
        }
    }
}

#[test]
fn flat_input_and_a_missing_model_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let flat = dir.path().join("flat.obj");
    std::fs::write(&flat, "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nv 0.5 0.2 0\n").unwrap();
    let out = dir.path().join("out.obj");
    let o = meshstream(&[
        "baseline",
        path(&flat),
        "-o",
        path(&out),
        "--method",
        "hull",
        "--points",
        "64",
        "--max-faces",
        "100",
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("coplanar"));
    let o = meshstream(&[
        "baseline",
        path(&flat),
        "-o",
        path(&out),
        "--method",
        "hull",
        "--model",
        path(&dir.path().join("no-model")),
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("the default --max-faces"));
}
