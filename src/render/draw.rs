//! A mesh or point cloud through a camera into an image.

use image::RgbImage;

use super::camera::{NEAR_PLANE, View};
use super::options::{BACK_FACE_COLOR, DEFAULT_COLOR, WorldLight, shade};
use super::parts::{face_parts, part_color};
use super::raster::{Target, clip_near};
use super::{Coloring, RenderError, RenderOptions};
use crate::mesh::{Mesh, normalized, triangle_normal};

/// Renders `mesh` (in its own coordinates: normalize it first to frame it with the default
/// cameras) into an image of `options.width` x `options.height`.
///
/// Faces are shaded flat and from both sides (the normal facing the camera), since artist
/// meshes are not always consistently wound; [`Coloring::BackFaces`] shows where a face is
/// seen from behind. A mesh without faces is a point cloud: each point is a disc of
/// `options.point_radius` pixels, lit by its normal when the mesh has normals and as if it
/// faced the light when not. Faces that pass behind the camera are clipped at a near
/// plane; degenerate faces draw nothing; an empty mesh gives the background. The output
/// depends only on the inputs.
pub fn render(mesh: &Mesh, options: &RenderOptions) -> Result<RgbImage, RenderError> {
    options.validate()?;
    mesh.validate()?;
    let view = options.camera.view(options.width, options.height);
    let light = options.light.in_view(&view);
    let mut target = Target::new(options.width, options.height, options.background);
    if mesh.is_point_cloud() {
        let color = match options.coloring {
            Coloring::Uniform(c) => c,
            Coloring::Parts => part_color(0),
            Coloring::BackFaces => DEFAULT_COLOR,
        };
        draw_points(&mut target, mesh, &view, &light, color, options.point_radius);
    } else {
        draw_faces(&mut target, mesh, &view, &light, options.coloring);
    }
    Ok(target.into_image())
}

fn draw_faces(
    target: &mut Target,
    mesh: &Mesh,
    view: &View,
    light: &WorldLight,
    coloring: Coloring,
) {
    let camera_space: Vec<[f32; 3]> = mesh.vertices.iter().map(|&p| view.to_camera(p)).collect();
    let parts = match coloring {
        Coloring::Parts => face_parts(mesh),
        Coloring::Uniform(_) | Coloring::BackFaces => Vec::new(),
    };
    for (f, face) in mesh.faces.iter().enumerate() {
        let world = mesh.triangle(face);
        let front = triangle_normal(world);
        let Some(normal) = facing_camera(front, world[0], view.eye) else {
            continue;
        };
        let base = match coloring {
            Coloring::Uniform(c) => c,
            Coloring::Parts => part_color(parts.get(f).copied().unwrap_or(0)),
            Coloring::BackFaces if normal != front => BACK_FACE_COLOR,
            Coloring::BackFaces => DEFAULT_COLOR,
        };
        let color = shade(base, light.intensity(normal));
        // `mesh.validate()` checked every index; a bad one would still only skip the face.
        let [a, b, c] = face.map(|i| camera_space.get(i as usize).copied());
        let (Some(a), Some(b), Some(c)) = (a, b, c) else { continue };
        let (corners, n) = clip_near([a, b, c]);
        let screen = corners.map(|c| view.project(c));
        // The clipped polygon is convex: a fan of its corners covers it.
        for k in 1..n.saturating_sub(1) {
            target.fill_triangle([screen[0], screen[k], screen[k + 1]], color);
        }
    }
}

fn draw_points(
    target: &mut Target,
    mesh: &Mesh,
    view: &View,
    light: &WorldLight,
    color: [u8; 3],
    radius: f32,
) {
    for (i, &p) in mesh.vertices.iter().enumerate() {
        let c = view.to_camera(p);
        if c[2] < NEAR_PLANE {
            continue;
        }
        let normal = mesh.normals.as_ref().and_then(|n| n.get(i)).map(|&n| normalized(n));
        let intensity = match normal.and_then(|n| facing_camera(n, p, view.eye)) {
            Some(n) => light.intensity(n),
            None => light.full(),
        };
        target.fill_disc(view.project(c), radius, shade(color, intensity));
    }
}

/// The unit normal `n` of a surface at `p`, turned to face the camera at `eye`; `None` for a
/// zero normal (a degenerate face).
fn facing_camera(n: [f32; 3], p: [f32; 3], eye: [f32; 3]) -> Option<[f32; 3]> {
    if n == [0.0; 3] {
        return None;
    }
    let towards_eye = (0..3).map(|k| n[k] * (eye[k] - p[k])).sum::<f32>();
    Some(if towards_eye < 0.0 { n.map(|c| -c) } else { n })
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;
    use crate::mesh::primitives::{cuboid, uv_sphere};
    use crate::mesh::sample_surface;
    use crate::render::{Camera, Light, LightFrame};

    const BLACK: [u8; 3] = [0; 3];

    fn options(width: u32, height: u32, camera: Camera) -> RenderOptions {
        RenderOptions {
            width,
            height,
            camera,
            background: BLACK,
            coloring: Coloring::Uniform([255; 3]),
            ..RenderOptions::default()
        }
    }

    /// Foreground pixels (`x`, `y`, covered); with a black background and ambient light every
    /// surface pixel is brighter than the background.
    fn mask(img: &RgbImage) -> Vec<(u32, u32, bool)> {
        img.enumerate_pixels().map(|(x, y, p)| (x, y, p.0 != BLACK)).collect()
    }

    #[test]
    fn head_on_cube_is_the_analytic_square() {
        let (w, h, d, fov) = (120u32, 90u32, 4.0f32, 40.0f32);
        let cam = Camera { azimuth_deg: 0.0, elevation_deg: 0.0, distance: d, fov_y_deg: fov };
        let img = render(&cuboid([2.0; 3]), &options(w, h, cam)).unwrap();
        // The front face z = 1 is d - 1 in front of the camera; the sides are edge-on.
        let focal_px = h as f32 / 2.0 / (fov.to_radians() / 2.0).tan();
        let half = focal_px / (d - 1.0);
        let inside = |x: u32, y: u32, s: f32| {
            let (dx, dy) = (x as f32 + 0.5 - w as f32 / 2.0, y as f32 + 0.5 - h as f32 / 2.0);
            dx.abs() <= s && dy.abs() <= s
        };
        let mut covered = 0;
        for (x, y, fg) in mask(&img) {
            covered += fg as u32;
            if fg != inside(x, y, half) {
                assert!(inside(x, y, half + 1.0) && !inside(x, y, half - 1.0), "pixel {x},{y}");
            }
        }
        let area = (2.0 * half).powi(2);
        assert!((covered as f32 - area).abs() < 4.0 * 2.0 * half, "{covered} vs {area}");
    }

    /// Independent of the renderer's camera: a textbook look-at built from the eye position.
    fn project_look_at(cam: &Camera, w: u32, h: u32, p: [f32; 3]) -> [f32; 2] {
        let (az, el) = (cam.azimuth_deg.to_radians(), cam.elevation_deg.to_radians());
        let eye = [el.cos() * az.sin(), el.sin(), el.cos() * az.cos()].map(|c| c * cam.distance);
        let cross = |a: [f32; 3], b: [f32; 3]| {
            [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
        };
        let dot = |a: [f32; 3], b: [f32; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let forward = normalized(eye.map(|c| -c));
        let right = normalized(cross(forward, [0.0, 1.0, 0.0]));
        let up = cross(right, forward);
        let rel = [p[0] - eye[0], p[1] - eye[1], p[2] - eye[2]];
        let focal_px = h as f32 / 2.0 / (cam.fov_y_deg.to_radians() / 2.0).tan();
        let depth = dot(forward, rel);
        [
            w as f32 / 2.0 + focal_px * dot(right, rel) / depth,
            h as f32 / 2.0 - focal_px * dot(up, rel) / depth,
        ]
    }

    /// Convex hull (counter-clockwise in a y-up sense) by the monotone chain.
    fn convex_hull(mut pts: Vec<[f32; 2]>) -> Vec<[f32; 2]> {
        pts.sort_by(|a, b| a.partial_cmp(b).unwrap());
        let turn = |o: [f32; 2], a: [f32; 2], b: [f32; 2]| {
            (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
        };
        let mut hull: Vec<[f32; 2]> = Vec::new();
        for pass in [pts.clone(), pts.into_iter().rev().collect()] {
            let start = hull.len();
            for p in pass {
                while hull.len() >= start + 2
                    && turn(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0
                {
                    hull.pop();
                }
                hull.push(p);
            }
            hull.pop();
        }
        hull
    }

    /// Signed distance from `p` to the boundary of a convex polygon: positive inside.
    fn signed_distance(hull: &[[f32; 2]], p: [f32; 2]) -> f32 {
        (0..hull.len())
            .map(|i| {
                let (a, b) = (hull[i], hull[(i + 1) % hull.len()]);
                let (ex, ey) = (b[0] - a[0], b[1] - a[1]);
                ((ex * (p[1] - a[1]) - ey * (p[0] - a[0])) / (ex * ex + ey * ey).sqrt()).max(-1e9)
            })
            .fold(f32::INFINITY, f32::min)
    }

    #[test]
    fn oblique_cube_is_the_hull_of_its_projected_corners() {
        let (w, h) = (128u32, 112u32);
        let cam = Camera { azimuth_deg: 35.0, elevation_deg: 25.0, distance: 4.5, fov_y_deg: 45.0 };
        let cube = cuboid([2.0; 3]);
        let img = render(&cube, &options(w, h, cam)).unwrap();
        let hull =
            convex_hull(cube.vertices.iter().map(|&p| project_look_at(&cam, w, h, p)).collect());
        assert_eq!(hull.len(), 6, "a cube seen from a general direction has a hexagonal outline");
        let (mut both, mut either) = (0, 0);
        for (x, y, fg) in mask(&img) {
            let dist = signed_distance(&hull, [x as f32 + 0.5, y as f32 + 0.5]);
            let expected = dist >= 0.0;
            both += (fg && expected) as u32;
            either += (fg || expected) as u32;
            if fg != expected {
                assert!(dist.abs() <= 1.0, "pixel {x},{y} is {dist} from the outline");
            }
        }
        let iou = both as f32 / either as f32;
        assert!(iou > 0.98, "IoU {iou}");
    }

    #[test]
    fn faces_towards_the_light_are_brighter_and_unlit_faces_get_exactly_the_ambient_level() {
        let cam = Camera { azimuth_deg: 45.0, elevation_deg: 0.0, distance: 5.0, fov_y_deg: 40.0 };
        let base = [200, 160, 120];
        let light = |x: f32| Light {
            direction: [x, 0.0, 0.0],
            frame: LightFrame::World,
            ambient: 0.25,
            diffuse: 0.5,
        };
        let render_with = |l: Light| {
            let o = RenderOptions {
                light: l,
                coloring: Coloring::Uniform(base),
                ..options(64, 64, cam)
            };
            render(&cuboid([2.0; 3]), &o).unwrap()
        };
        // From azimuth 45 the +Z side is on the left of the image and the +X side on the right.
        let (left, right) = ((24, 32), (40, 32));
        let img = render_with(light(1.0));
        let px = |img: &RgbImage, (x, y): (u32, u32)| img.get_pixel(x, y).0;
        assert_eq!(px(&img, right), [150, 120, 90], "facing the light: ambient + diffuse");
        assert_eq!(px(&img, left), [50, 40, 30], "side-on to the light: ambient only");
        let away = render_with(light(-1.0));
        assert_eq!(px(&away, right), [50, 40, 30], "facing away: ambient only");
        assert!(px(&img, right).iter().zip(px(&away, right)).all(|(a, b)| *a > b));
    }

    #[test]
    fn winding_does_not_matter() {
        let mut flipped = cuboid([2.0; 3]);
        for f in &mut flipped.faces {
            f.swap(1, 2);
        }
        for coloring in [Coloring::Uniform([90, 200, 40]), Coloring::Parts] {
            let o = RenderOptions { coloring, ..RenderOptions::default() };
            assert_eq!(render(&cuboid([2.0; 3]), &o).unwrap(), render(&flipped, &o).unwrap());
        }
    }

    #[test]
    fn back_faces_show_red_only_where_a_face_is_seen_from_behind() {
        let light = Light { ambient: 1.0, diffuse: 0.0, ..Light::default() };
        let o = RenderOptions { coloring: Coloring::BackFaces, light, ..RenderOptions::default() };
        let colours = |mesh: &Mesh| {
            let img = render(mesh, &o).unwrap();
            let count = |c: [u8; 3]| img.pixels().filter(|p| p.0 == c).count();
            (count(DEFAULT_COLOR), count(BACK_FACE_COLOR))
        };
        let right = cuboid([2.0; 3]);
        let (front, back) = colours(&right);
        assert!(front > 0 && back == 0, "{front} {back}");
        let mut inside_out = right.clone();
        inside_out.faces.iter_mut().for_each(|f| f.swap(1, 2));
        assert_eq!(colours(&inside_out), (back, front));
    }

    #[test]
    fn parts_get_their_palette_colours() {
        let mut mesh = cuboid([1.0; 3]).translated([-1.0, 0.0, 0.0]);
        let right = cuboid([1.0; 3]).translated([1.0, 0.0, 0.0]);
        let offset = mesh.vertices.len() as u32;
        mesh.vertices.extend(&right.vertices);
        mesh.faces.extend(right.faces.iter().map(|f| f.map(|i| i + offset)));
        let cam = Camera { azimuth_deg: 0.0, elevation_deg: 0.0, distance: 5.0, fov_y_deg: 40.0 };
        let light = Light { ambient: 1.0, diffuse: 0.0, ..Light::default() };
        let o = RenderOptions { coloring: Coloring::Parts, light, ..options(64, 32, cam) };
        let img = render(&mesh, &o).unwrap();
        assert_eq!(img.get_pixel(22, 16).0, part_color(0));
        assert_eq!(img.get_pixel(42, 16).0, part_color(1));
    }

    #[test]
    fn a_camera_inside_a_box_sees_walls_everywhere() {
        for (az, el) in [(0.0, 0.0), (70.0, 30.0), (200.0, -89.0)] {
            let cam = Camera { azimuth_deg: az, elevation_deg: el, distance: 0.5, fov_y_deg: 90.0 };
            let img = render(&cuboid([2.0; 3]), &options(40, 30, cam)).unwrap();
            assert!(mask(&img).iter().all(|&(_, _, fg)| fg), "{az} {el}");
        }
    }

    #[test]
    fn a_floor_that_passes_behind_the_camera_is_clipped_not_mirrored() {
        let floor = Mesh::new(
            vec![
                [-10.0, -0.5, -10.0],
                [10.0, -0.5, -10.0],
                [10.0, -0.5, 10.0],
                [-10.0, -0.5, 10.0],
            ],
            vec![[0, 1, 2], [0, 2, 3]],
        );
        let cam = Camera { azimuth_deg: 0.0, elevation_deg: 0.0, distance: 4.0, fov_y_deg: 60.0 };
        let img = render(&floor, &options(32, 32, cam)).unwrap();
        let row = |y: u32| (0..32).filter(|&x| img.get_pixel(x, y).0 != BLACK).count();
        assert_eq!(row(31), 32, "the floor under the camera fills the bottom row");
        assert_eq!(row(0), 0, "nothing above the horizon");
        assert_eq!(row(14), 0, "the far edge is below the horizon");
    }

    #[test]
    fn point_clouds_are_discs_and_empty_or_degenerate_meshes_are_background() {
        let ball = sample_surface(&uv_sphere(0.8, 32, 16), 3000, 0).unwrap();
        let cam = Camera { azimuth_deg: 0.0, elevation_deg: 0.0, distance: 4.0, fov_y_deg: 40.0 };
        let o = options(64, 64, cam);
        let img = render(&ball, &o).unwrap();
        let covered = mask(&img).iter().filter(|m| m.2).count();
        // The sphere's outline has radius about focal * 0.8 / 4 = 19 px: a disc of ~1100 pixels.
        assert!((800..1400).contains(&covered), "{covered}");
        assert_eq!(img.get_pixel(0, 0).0, BLACK);
        let bare = Mesh { normals: None, ..ball.clone() };
        assert_eq!(mask(&render(&bare, &o).unwrap()), mask(&img), "normals change shading only");
        let background = |m: &Mesh| render(m, &o).unwrap().pixels().all(|p| p.0 == BLACK);
        assert!(background(&Mesh::default()));
        let flat =
            Mesh::new(vec![[0.0; 3], [0.5, 0.5, 0.5], [1.0, 1.0, 1.0]], vec![[0, 1, 2], [0, 0, 0]]);
        assert!(background(&flat));
    }

    #[test]
    fn invalid_inputs_are_typed_errors() {
        let o = RenderOptions::default();
        let bad_index = Mesh::new(vec![[0.0; 3]; 3], vec![[0, 1, 3]]);
        assert!(matches!(render(&bad_index, &o), Err(RenderError::Mesh(_))));
        let nan = Mesh::new(vec![[0.0, f32::NAN, 0.0]], vec![]);
        assert!(matches!(render(&nan, &o), Err(RenderError::Mesh(_))));
        let cube = cuboid([1.0; 3]);
        let empty = RenderOptions { width: 0, ..o.clone() };
        assert!(matches!(render(&cube, &empty), Err(RenderError::EmptyImage { .. })));
        let huge = RenderOptions { width: 1 << 20, height: 1 << 20, ..o.clone() };
        assert!(matches!(render(&cube, &huge), Err(RenderError::ImageTooLarge { .. })));
        let dark = RenderOptions { light: Light { direction: [0.0; 3], ..Light::default() }, ..o };
        assert!(matches!(render(&cube, &dark), Err(RenderError::InvalidLight(_))));
    }

    #[test]
    fn options_round_trip_through_json_and_missing_fields_take_defaults() {
        let o = RenderOptions {
            coloring: Coloring::Parts,
            light: Light { frame: LightFrame::World, ..Light::default() },
            ..RenderOptions::default()
        };
        let json = serde_json::to_string(&o).unwrap();
        assert_eq!(serde_json::from_str::<RenderOptions>(&json).unwrap(), o);
        let partial: RenderOptions =
            serde_json::from_str(r#"{"width": 64, "camera": {"azimuth_deg": 90}}"#).unwrap();
        assert_eq!(partial.width, 64);
        assert_eq!(partial.camera.azimuth_deg, 90.0);
        assert_eq!(partial.camera.distance, Camera::default().distance);
        assert!(serde_json::from_str::<RenderOptions>(r#"{"widht": 64}"#).is_err());
    }

    fn coordinate() -> impl Strategy<Value = f32> {
        prop_oneof![
            -2.0f32..2.0,
            -1e30f32..1e30,
            Just(0.0),
            Just(f32::MAX),
            Just(-f32::MIN_POSITIVE)
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]

        #[test]
        fn hostile_meshes_and_cameras_never_panic(
            vertices in prop::collection::vec(prop::array::uniform3(coordinate()), 0..12),
            raw_faces in prop::collection::vec(prop::array::uniform3(0u32..12), 0..12),
            azimuth in -1e4f32..1e4,
            elevation in -1e4f32..1e4,
            distance in prop_oneof![1e-4f32..0.5, 0.5f32..10.0, Just(1e30)],
            fov in 0.01f32..179.99,
            width in 0u32..40,
            height in 0u32..40,
            parts in any::<bool>(),
        ) {
            let n = vertices.len() as u32;
            let faces = raw_faces.into_iter().filter(|f| f.iter().all(|&i| i < n)).collect();
            let mesh = Mesh::new(vertices, faces);
            let camera = Camera { azimuth_deg: azimuth, elevation_deg: elevation, distance, fov_y_deg: fov };
            let coloring = if parts { Coloring::Parts } else { Coloring::Uniform([1, 2, 3]) };
            let o = RenderOptions { width, height, camera, coloring, ..RenderOptions::default() };
            match render(&mesh, &o) {
                Ok(img) => prop_assert_eq!(img.dimensions(), (width, height)),
                Err(RenderError::EmptyImage { .. }) => prop_assert!(width == 0 || height == 0),
                Err(e) => prop_assert!(false, "unexpected error {e}"),
            }
        }
    }
}
