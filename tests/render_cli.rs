//! `meshstream render` end to end: a mesh file in, an image file out, decoded back.

use std::path::Path;
use std::process::{Command, Output};

use meshstream::mesh::primitives::{cuboid, uv_sphere};
use meshstream::mesh::{sample_surface, write_mesh_file};

fn meshstream(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_meshstream")).args(args).output().unwrap()
}

fn path(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn render_ok(args: &[&str]) {
    let out = meshstream(args);
    assert!(out.status.success(), "{args:?}: {}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn render_writes_a_grid_that_decodes_to_the_right_size() {
    let dir = tempfile::tempdir().unwrap();
    // Far from the origin and large: normalization frames it anyway.
    let mesh = dir.path().join("box.obj");
    write_mesh_file(&cuboid([30.0, 10.0, 20.0]).translated([100.0, 5.0, 0.0]), &mesh, None)
        .unwrap();
    let png = dir.path().join("preview.png");
    render_ok(&["render", path(&mesh), "-o", path(&png), "--size", "64x48", "--color-parts"]);
    let img = image::open(&png).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (128, 96), "4 views of 64x48 in a 2x2 grid");
    // The box is in every tile, and the tiles' corners are background.
    let white = image::Rgb([255u8, 255, 255]);
    for (x, y) in [(0, 0), (64, 0), (0, 48), (64, 48)] {
        assert_eq!(*img.get_pixel(x, y), white);
        assert_ne!(*img.get_pixel(x + 32, y + 24), white, "tile at {x},{y}");
    }
}

#[test]
fn render_takes_camera_and_light_options_and_other_formats() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = dir.path().join("ball.ply");
    write_mesh_file(&uv_sphere(1.0, 24, 12), &mesh, None).unwrap();
    for ext in ["jpg", "webp"] {
        let out = dir.path().join(format!("view.{ext}"));
        render_ok(&[
            "render",
            path(&mesh),
            "-o",
            path(&out),
            "--views",
            "1",
            "--size",
            "40",
            "--azimuth",
            "-30",
            "--elevation",
            "-10",
            "--distance",
            "3",
            "--fov",
            "50",
            "--light",
            "-1,1,0.5",
            "--world-light",
        ]);
        assert_eq!(image::open(&out).unwrap().to_rgb8().dimensions(), (40, 40), "{ext}");
    }
}

#[test]
fn render_draws_point_clouds_and_rejects_bad_requests() {
    let dir = tempfile::tempdir().unwrap();
    let cloud = dir.path().join("points.ply");
    write_mesh_file(&sample_surface(&uv_sphere(1.0, 24, 12), 500, 0).unwrap(), &cloud, None)
        .unwrap();
    let png = dir.path().join("points.png");
    render_ok(&["render", path(&cloud), "-o", path(&png), "--views", "2", "--size", "32"]);
    assert_eq!(image::open(&png).unwrap().to_rgb8().dimensions(), (64, 32));

    let fails_with = |args: &[&str], message: &str| {
        let out = meshstream(args);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && stderr.contains(message), "{args:?}: {stderr}");
    };
    let tiff = dir.path().join("out.tiff");
    fails_with(&["render", path(&cloud), "-o", path(&tiff)], ".png");
    fails_with(&["render", path(&cloud), "-o", path(&png), "--size", "0x10"], "at least 1 pixel");
    fails_with(&["render", path(&cloud), "-o", path(&png), "--views", "0"], "views");
    fails_with(&["render", path(&cloud), "-o", path(&png), "--fov", "200"], "field of view");
}

#[test]
fn a_z_up_mesh_drawn_with_up_z_looks_as_its_y_up_twin() {
    let dir = tempfile::tempdir().unwrap();
    let standing = dir.path().join("standing.obj");
    let lying = dir.path().join("lying.obj");
    write_mesh_file(&cuboid([1.0, 4.0, 2.0]), &standing, None).unwrap();
    write_mesh_file(&cuboid([1.0, 2.0, 4.0]), &lying, None).unwrap();
    let [a, b, c] = ["standing.png", "lying.png", "lying-as-is.png"].map(|n| dir.path().join(n));
    let small = ["--views", "2", "--size", "48"];
    render_ok(&[&["render", path(&standing), "-o", path(&a)][..], &small].concat());
    render_ok(&[&["render", path(&lying), "-o", path(&b), "--up", "z"][..], &small].concat());
    render_ok(&[&["render", path(&lying), "-o", path(&c)][..], &small].concat());
    let pixels = |p: &Path| image::open(p).unwrap().to_rgb8().into_raw();
    assert_eq!(pixels(&a), pixels(&b));
    assert_ne!(pixels(&a), pixels(&c));
}

#[test]
fn back_faces_shows_an_inside_out_box_red_and_a_right_one_not() {
    let dir = tempfile::tempdir().unwrap();
    let right = cuboid([1.0, 2.0, 1.5]);
    let mut inside_out = right.clone();
    inside_out.faces.iter_mut().for_each(|f| f.swap(1, 2));
    let red_pixels = |mesh: &meshstream::mesh::Mesh, name: &str| {
        let (file, png) =
            (dir.path().join(format!("{name}.ply")), dir.path().join(format!("{name}.png")));
        write_mesh_file(mesh, &file, None).unwrap();
        render_ok(&["render", path(&file), "-o", path(&png), "--size", "48", "--back-faces"]);
        let img = image::open(&png).unwrap().to_rgb8();
        img.pixels().filter(|p| i32::from(p.0[0]) > i32::from(p.0[1]) + 60).count()
    };
    assert_eq!(red_pixels(&right, "right"), 0);
    assert!(red_pixels(&inside_out, "inside-out") > 1000);
    let both = meshstream(&["render", "x.ply", "-o", "x.png", "--back-faces", "--color-parts"]);
    assert!(
        !both.status.success() && String::from_utf8_lossy(&both.stderr).contains("cannot be used")
    );
}
