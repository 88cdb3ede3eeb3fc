//! The images the DiT learns from: renders of a normalized mesh with a random orbit camera and a
//! random world-fixed light (paper, section 3.4: "random lighting conditions and camera
//! poses"), stored as u8 RGB and turned into the encoder's (B, 3, S, S) input in [0, 1].

use candle_core::{DType, Device, Tensor};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::diffusion::ImageOptions;
use crate::mesh::Mesh;
use crate::render::{Camera, Light, LightFrame, RenderError, RenderOptions, render};

/// How training views are drawn. Saved with the latent cache, so a changed setting rebuilds it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ViewConfig {
    /// Side of the square image: the DiT image encoder's input size.
    pub size: u32,
    /// Camera elevation is drawn uniformly from this range (degrees): from slightly below the
    /// horizon to well above it, the range of ordinary product shots.
    pub min_elevation_deg: f32,
    pub max_elevation_deg: f32,
    pub fov_y_deg: f32,
    /// Ambient light is drawn from this range; diffuse light fills the rest up to 1.
    pub min_ambient: f32,
    pub max_ambient: f32,
    /// What uncovered pixels show: the colour the inference path composites alpha onto, so
    /// training and user images agree on the background.
    pub background: [u8; 3],
}

impl ViewConfig {
    pub fn new(size: u32) -> Self {
        Self {
            size,
            min_elevation_deg: -10.0,
            max_elevation_deg: 45.0,
            fov_y_deg: Camera::default().fov_y_deg,
            min_ambient: 0.2,
            max_ambient: 0.45,
            background: ImageOptions::new(size).background,
        }
    }

    /// A camera at a distance that frames the whole normalized cube (its bounding sphere), so
    /// no view crops the mesh.
    fn camera(&self, azimuth_deg: f32, elevation_deg: f32) -> Camera {
        let distance = Camera::distance_to_frame(3f32.sqrt(), self.fov_y_deg, 1.0);
        Camera { azimuth_deg, elevation_deg, distance, fov_y_deg: self.fov_y_deg }
    }

    fn options(&self, camera: Camera, light: Light) -> RenderOptions {
        RenderOptions {
            width: self.size,
            height: self.size,
            camera,
            light,
            background: self.background,
            ..RenderOptions::default()
        }
    }

    /// A random view: azimuth uniform, elevation in the configured range, a light from a
    /// random direction of the upper hemisphere with random ambient/diffuse balance.
    pub fn random(&self, rng: &mut impl Rng) -> RenderOptions {
        let azimuth = rng.random_range(0.0..360.0);
        let (lo, hi) = (self.min_elevation_deg, self.max_elevation_deg.max(self.min_elevation_deg));
        let elevation = if hi > lo { rng.random_range(lo..hi) } else { lo };
        let mut direction: [f32; 3] = std::array::from_fn(|_| StandardNormal.sample(rng));
        // Light from above (+Y is up in the normalized frame), never exactly from the side.
        direction[1] = direction[1].abs() + 0.2;
        let (alo, ahi) = (self.min_ambient, self.max_ambient.max(self.min_ambient));
        let ambient = if ahi > alo { rng.random_range(alo..ahi) } else { alo };
        let light = Light { direction, frame: LightFrame::World, ambient, diffuse: 1.0 - ambient };
        self.options(self.camera(azimuth, elevation), light)
    }

    /// The fixed evaluation view: the project's default three-quarter view and light.
    pub fn fixed(&self) -> RenderOptions {
        let default = Camera::default();
        self.options(self.camera(default.azimuth_deg, default.elevation_deg), Light::default())
    }
}

/// `size` x `size` x 3 bytes, row-major RGB.
pub fn render_rgb(mesh: &Mesh, options: &RenderOptions) -> Result<Vec<u8>, RenderError> {
    Ok(render(mesh, options)?.into_raw())
}

/// Stacked row-major RGB images (each `size * size * 3` bytes) as the encoder's input:
/// (B, 3, size, size) f32 in [0, 1].
pub fn images_tensor(
    images: &[&[u8]],
    size: usize,
    device: &Device,
) -> candle_core::Result<Tensor> {
    let data: Vec<u8> = images.iter().flat_map(|img| img.iter().copied()).collect();
    Tensor::from_vec(data, (images.len(), size, size, 3), device)?
        .to_dtype(DType::F32)?
        .affine(1.0 / 255.0, 0.0)?
        .permute((0, 3, 1, 2))?
        .contiguous()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diffusion::framing::TRAINING_FILL;
    use crate::mesh::primitives::{cuboid, frustum, torus};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn random_views_vary_frame_the_mesh_and_keep_the_background() {
        let cfg = ViewConfig::new(32);
        let (mesh, _) = cuboid([1.0, 2.0, 0.5]).normalized().unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let a = cfg.random(&mut rng);
        let b = cfg.random(&mut rng);
        assert_ne!(a, b);
        for opts in [a, b, cfg.fixed()] {
            let el = opts.camera.elevation_deg;
            assert!((cfg.min_elevation_deg..=cfg.max_elevation_deg).contains(&el) || el == 20.0);
            let img = render_rgb(&mesh, &opts).unwrap();
            assert_eq!(img.len(), 32 * 32 * 3);
            // The corners are background, the centre is the mesh.
            assert_eq!(&img[..3], &cfg.background);
            let centre = (16 * 32 + 16) * 3;
            assert_ne!(&img[centre..centre + 3], &cfg.background);
        }
    }

    /// Pictures are framed into [`TRAINING_FILL`], the middle of the shares of the frame objects
    /// span as the training camera renders them: a change of the camera must move it too.
    #[test]
    fn the_training_camera_frames_objects_as_the_framing_assumes() {
        let cfg = ViewConfig::new(128);
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut fills = Vec::new();
        for i in 0..24 {
            let size = [0.3 + 0.1 * (i % 7) as f32, 0.4 + 0.08 * (i % 5) as f32, 1.0];
            let shape = match i % 3 {
                0 => cuboid(size),
                1 => frustum(size[0], size[1], 1.0, 12),
                _ => torus(1.0, size[0] * 0.5, 16, 8),
            };
            let (mesh, _) = shape.normalized().unwrap();
            let img = render_rgb(&mesh, &cfg.random(&mut rng)).unwrap();
            // The longer side of the box of the covered pixels, as a share of the side.
            let covered: Vec<(usize, usize)> = (0..128 * 128)
                .filter(|i| img[3 * i..3 * i + 3] != cfg.background)
                .map(|i| (i % 128, i / 128))
                .collect();
            let extent = |axis: fn(&(usize, usize)) -> usize| {
                let (lo, hi) = covered
                    .iter()
                    .map(axis)
                    .fold((usize::MAX, 0), |(lo, hi), v| (lo.min(v), hi.max(v)));
                hi + 1 - lo
            };
            fills.push(extent(|p| p.0).max(extent(|p| p.1)) as f32 / 128.0);
        }
        fills.sort_by(f32::total_cmp);
        let median = fills[fills.len() / 2];
        assert!(TRAINING_FILL.contains(&median), "median fill {median}: {fills:?}");
    }

    #[test]
    fn images_become_channel_major_unit_floats() {
        let mut img = vec![0u8; 2 * 2 * 3];
        img[3] = 255; // pixel (0, 1), red channel
        let t = images_tensor(&[&img, &img], 2, &Device::Cpu).unwrap();
        assert_eq!(t.dims(), &[2, 3, 2, 2]);
        let red = t.get(1).unwrap().get(0).unwrap().to_vec2::<f32>().unwrap();
        assert_eq!(red, vec![vec![0.0, 1.0], vec![0.0, 0.0]]);
    }
}
