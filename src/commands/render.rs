use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;
use image::ImageFormat;
use meshstream::mesh::{Normalization, UpAxis};
use meshstream::render::{Camera, Coloring, Light, LightFrame, RenderOptions, render_grid};

use super::load_mesh;

#[derive(Args)]
pub struct RenderArgs {
    /// The mesh (or point cloud) to draw. It is normalized first, so any input frames well.
    mesh: PathBuf,
    /// The image to write: .png, .jpg/.jpeg or .webp (lossless).
    #[arg(short, long)]
    output: PathBuf,
    /// Number of views at evenly spaced azimuths, tiled in a grid (ceil(sqrt(N)) per row).
    #[arg(long, default_value_t = 4)]
    views: u32,
    /// Size of each view: W (square) or WxH.
    #[arg(long, default_value = "256", value_parser = parse_size)]
    size: (u32, u32),
    /// Azimuth of the first view in degrees (0 = front, looking down -Z; 90 = from +X).
    #[arg(long, default_value_t = Camera::default().azimuth_deg, allow_negative_numbers = true)]
    azimuth: f32,
    /// Elevation in degrees (positive = from above).
    #[arg(long, default_value_t = Camera::default().elevation_deg, allow_negative_numbers = true)]
    elevation: f32,
    /// Camera distance from the centre, in the normalized frame ([-1, 1]^3). Default: just
    /// far enough for the whole mesh to fit every view.
    #[arg(long)]
    distance: Option<f32>,
    /// Vertical field of view in degrees.
    #[arg(long, default_value_t = Camera::default().fov_y_deg)]
    fov: f32,
    /// Direction towards the light as x,y,z, in camera coordinates (x right, y up, z towards
    /// the viewer) unless --world-light.
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    light: Option<[f32; 3]>,
    /// The light direction is in the mesh's (normalized) coordinates instead of the camera's.
    #[arg(long)]
    world_light: bool,
    /// A flat colour per part (connected component of faces sharing vertices).
    #[arg(long, conflicts_with = "back_faces")]
    color_parts: bool,
    /// Faces seen from behind in red: what a viewer drawing front sides only (glTF's
    /// default) leaves out.
    #[arg(long)]
    back_faces: bool,
    /// The mesh's up axis (y, z, x, or one of them negated), drawn up: `--up z` stands a mesh
    /// from Blender, CAD or `reconstruct --up z` upright.
    #[arg(long, default_value = "y")]
    up: UpAxis,
}

pub fn run(args: &RenderArgs) -> anyhow::Result<()> {
    let format = image_format(&args.output)?;
    let mesh = load_mesh(&args.mesh)?;
    let mesh = Normalization::fit(&mesh.vertices)
        .with_context(|| format!("normalizing {}", args.mesh.display()))?
        .with_up(args.up)
        .apply_mesh(&mesh);
    let (width, height) = args.size;
    let distance = args.distance.unwrap_or_else(|| {
        // Every vertex within this radius of the centre is in every view of the orbit.
        let radius = mesh
            .vertices
            .iter()
            .map(|p| p.iter().map(|c| c * c).sum::<f32>())
            .fold(0.0, f32::max)
            .sqrt();
        Camera::distance_to_frame(radius, args.fov, width as f32 / height as f32)
    });
    let defaults = Light::default();
    let options = RenderOptions {
        width,
        height,
        camera: Camera {
            azimuth_deg: args.azimuth,
            elevation_deg: args.elevation,
            distance,
            fov_y_deg: args.fov,
        },
        light: Light {
            direction: args.light.unwrap_or(defaults.direction),
            frame: if args.world_light { LightFrame::World } else { LightFrame::Camera },
            ..defaults
        },
        coloring: match (args.color_parts, args.back_faces) {
            (true, _) => Coloring::Parts,
            (_, true) => Coloring::BackFaces,
            _ => Coloring::default(),
        },
        ..RenderOptions::default()
    };
    let image = render_grid(&mesh, &options, args.views)?;
    image
        .save_with_format(&args.output, format)
        .with_context(|| format!("writing {}", args.output.display()))?;
    eprintln!(
        "wrote {} ({}x{}, {} view{})",
        args.output.display(),
        image.width(),
        image.height(),
        args.views,
        if args.views == 1 { "" } else { "s" }
    );
    Ok(())
}

/// The image format named by the output's extension: one of those the crate is built with.
fn image_format(path: &Path) -> anyhow::Result<ImageFormat> {
    match ImageFormat::from_path(path) {
        Ok(f @ (ImageFormat::Png | ImageFormat::Jpeg | ImageFormat::WebP)) => Ok(f),
        _ => anyhow::bail!("{}: the output must end in .png, .jpg, .jpeg or .webp", path.display()),
    }
}

/// "256" (square) or "320x240".
fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let side =
        |v: &str| v.trim().parse::<u32>().map_err(|e| format!("{v:?} is not a pixel count: {e}"));
    match s.split_once(['x', 'X']) {
        Some((w, h)) => Ok((side(w)?, side(h)?)),
        None => side(s).map(|w| (w, w)),
    }
}

/// "x,y,z".
fn parse_vec3(s: &str) -> Result<[f32; 3], String> {
    let parts: Vec<&str> = s.split(',').collect();
    let [x, y, z] = parts.as_slice() else {
        return Err(format!("{s:?}: expected three numbers x,y,z"));
    };
    let num = |v: &str| v.trim().parse::<f32>().map_err(|e| format!("{v:?}: {e}"));
    Ok([num(x)?, num(y)?, num(z)?])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_and_vectors_parse() {
        assert_eq!(parse_size("256"), Ok((256, 256)));
        assert_eq!(parse_size("320x240"), Ok((320, 240)));
        assert!(parse_size("320x").is_err());
        assert!(parse_size("-3").is_err());
        assert_eq!(parse_vec3("1, -2,0.5"), Ok([1.0, -2.0, 0.5]));
        assert!(parse_vec3("1,2").is_err());
        assert!(parse_vec3("1,2,z").is_err());
    }

    #[test]
    fn only_built_image_formats_are_accepted() {
        assert_eq!(image_format(Path::new("a.PNG")).unwrap(), ImageFormat::Png);
        assert_eq!(image_format(Path::new("a.jpeg")).unwrap(), ImageFormat::Jpeg);
        assert_eq!(image_format(Path::new("a.webp")).unwrap(), ImageFormat::WebP);
        assert!(image_format(Path::new("a.tiff")).is_err());
        assert!(image_format(Path::new("a")).is_err());
    }
}
