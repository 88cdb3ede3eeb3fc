//! Several views of one mesh around it, tiled into one image: a preview without a 3D viewer.

use image::RgbImage;
use image::imageops::replace;

use super::options::check_image_size;
use super::{Camera, RenderError, RenderOptions, render};
use crate::mesh::Mesh;

/// The most views one grid holds.
pub const MAX_GRID_VIEWS: u32 = 64;

/// `views` cameras like `camera` at evenly spaced azimuths, starting at its own.
pub fn orbit_cameras(camera: &Camera, views: u32) -> Vec<Camera> {
    let step = 360.0 / views.max(1) as f32;
    (0..views)
        .map(|i| Camera { azimuth_deg: camera.azimuth_deg + step * i as f32, ..*camera })
        .collect()
}

/// Renders `views` views of `options.width` x `options.height` at evenly spaced azimuths (see
/// [`orbit_cameras`]) and tiles them row by row, `ceil(sqrt(views))` to a row; tiles left over
/// in the last row are background.
pub fn render_grid(
    mesh: &Mesh,
    options: &RenderOptions,
    views: u32,
) -> Result<RgbImage, RenderError> {
    if !(1..=MAX_GRID_VIEWS).contains(&views) {
        return Err(RenderError::InvalidOption(format!(
            "a grid has 1 to {MAX_GRID_VIEWS} views, not {views}"
        )));
    }
    let columns = (1..=views).find(|c| c * c >= views).unwrap_or(views);
    let rows = views.div_ceil(columns);
    let (tile_w, tile_h) = (u64::from(options.width), u64::from(options.height));
    check_image_size(tile_w * u64::from(columns), tile_h * u64::from(rows))?;
    options.validate()?;
    let mut canvas = RgbImage::from_pixel(
        options.width * columns,
        options.height * rows,
        image::Rgb(options.background),
    );
    for (i, camera) in orbit_cameras(&options.camera, views).into_iter().enumerate() {
        let tile = render(mesh, &RenderOptions { camera, ..options.clone() })?;
        let (col, row) = (i as u64 % u64::from(columns), i as u64 / u64::from(columns));
        replace(&mut canvas, &tile, (col * tile_w) as i64, (row * tile_h) as i64);
    }
    Ok(canvas)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::cuboid;

    #[test]
    fn orbit_cameras_are_evenly_spaced_from_the_first() {
        let cam = Camera { azimuth_deg: 10.0, ..Camera::default() };
        let az: Vec<f32> = orbit_cameras(&cam, 4).iter().map(|c| c.azimuth_deg).collect();
        assert_eq!(az, [10.0, 100.0, 190.0, 280.0]);
    }

    #[test]
    fn four_views_make_a_two_by_two_grid_whose_tiles_are_the_single_renders() {
        let mesh = cuboid([1.0, 1.5, 0.5]);
        let options = RenderOptions { width: 32, height: 24, ..RenderOptions::default() };
        let grid = render_grid(&mesh, &options, 4).unwrap();
        assert_eq!(grid.dimensions(), (64, 48));
        for (i, camera) in orbit_cameras(&options.camera, 4).into_iter().enumerate() {
            let single = render(&mesh, &RenderOptions { camera, ..options.clone() }).unwrap();
            let (x, y) = ((i as u32 % 2) * 32, (i as u32 / 2) * 24);
            let tile = image::imageops::crop_imm(&grid, x, y, 32, 24).to_image();
            assert_eq!(tile, single, "view {i}");
        }
        // Three views: two columns, and the fourth tile is background.
        let grid = render_grid(&mesh, &options, 3).unwrap();
        assert_eq!(grid.dimensions(), (64, 48));
        let empty = image::imageops::crop_imm(&grid, 32, 24, 32, 24).to_image();
        assert!(empty.pixels().all(|p| p.0 == options.background));
    }

    #[test]
    fn bad_view_counts_and_oversized_grids_are_errors() {
        let mesh = cuboid([1.0; 3]);
        let options = RenderOptions::default();
        assert!(matches!(render_grid(&mesh, &options, 0), Err(RenderError::InvalidOption(_))));
        assert!(render_grid(&mesh, &options, MAX_GRID_VIEWS + 1).is_err());
        let huge = RenderOptions { width: 8192, height: 8192, ..options };
        assert!(matches!(render_grid(&mesh, &huge, 4), Err(RenderError::ImageTooLarge { .. })));
    }
}
