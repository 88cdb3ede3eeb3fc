//! What a render looks like: image size, camera, light, colours. Serde-ready, so training
//! configs can store the views they render.

use serde::{Deserialize, Serialize};

use super::camera::View;
use super::{Camera, RenderError};
use crate::mesh::normalized;

/// The largest image (or grid of images) rendered: 64 megapixels, about 450 MB of colour and
/// depth buffers. Larger requests are errors rather than out-of-memory aborts.
pub const MAX_PIXELS: u64 = 1 << 26;

/// Everything a render needs besides the mesh.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RenderOptions {
    pub width: u32,
    pub height: u32,
    pub camera: Camera,
    pub light: Light,
    pub coloring: Coloring,
    /// Colour of pixels no surface covers (sRGB).
    pub background: [u8; 3],
    /// Radius in pixels of the disc drawn for each point of a point cloud.
    pub point_radius: f32,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            width: 256,
            height: 256,
            camera: Camera::default(),
            light: Light::default(),
            coloring: Coloring::default(),
            background: [255, 255, 255],
            point_radius: 1.5,
        }
    }
}

impl RenderOptions {
    pub fn validate(&self) -> Result<(), RenderError> {
        check_image_size(self.width.into(), self.height.into())?;
        self.camera.validate()?;
        self.light.validate()?;
        if !(self.point_radius.is_finite() && self.point_radius >= 0.0) {
            return Err(RenderError::InvalidOption(format!(
                "point radius must be finite and non-negative, not {}",
                self.point_radius
            )));
        }
        Ok(())
    }
}

/// Checks an image size against [`MAX_PIXELS`] (u64, so that a grid's total cannot overflow).
pub(super) fn check_image_size(width: u64, height: u64) -> Result<(), RenderError> {
    if width == 0 || height == 0 {
        // Sizes that reach here as u64 come from u32 fields or products of them.
        let side = |v: u64| u32::try_from(v).unwrap_or(u32::MAX);
        return Err(RenderError::EmptyImage { width: side(width), height: side(height) });
    }
    if width.saturating_mul(height) > MAX_PIXELS {
        return Err(RenderError::ImageTooLarge { width, height, limit: MAX_PIXELS });
    }
    Ok(())
}

/// One directional light plus ambient light: a surface with unit normal `n` gets
/// `ambient + diffuse * max(0, n . direction)` times its colour, clamped to white. Surfaces are
/// lit from both sides: the normal used is the one facing the camera.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Light {
    /// Direction from the surface towards the light (any length but zero).
    pub direction: [f32; 3],
    /// Whether `direction` is fixed to the camera or to the mesh.
    pub frame: LightFrame,
    pub ambient: f32,
    pub diffuse: f32,
}

/// The frame a light's direction is given in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum LightFrame {
    /// x right, y up, z towards the viewer: the light moves with the camera, so every view of
    /// an orbit is lit alike (previews).
    #[default]
    Camera,
    /// World coordinates: the light stays put while the camera moves (training views with
    /// random lighting).
    World,
}

impl Default for Light {
    /// A key light from the upper left, in front of the mesh.
    fn default() -> Self {
        Self { direction: [-0.4, 0.6, 1.0], frame: LightFrame::Camera, ambient: 0.3, diffuse: 0.7 }
    }
}

impl Light {
    pub fn validate(&self) -> Result<(), RenderError> {
        let len2: f32 = self.direction.iter().map(|c| c * c).sum();
        if !(len2.is_finite() && len2 > 0.0) {
            return Err(RenderError::InvalidLight(format!(
                "direction must be finite and non-zero, not {:?}",
                self.direction
            )));
        }
        for (name, v) in [("ambient", self.ambient), ("diffuse", self.diffuse)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(RenderError::InvalidLight(format!(
                    "{name} must be finite and non-negative, not {v}"
                )));
            }
        }
        Ok(())
    }

    /// The light set up for one view: its unit direction in world coordinates.
    pub(super) fn in_view(&self, view: &View) -> WorldLight {
        let d = match self.frame {
            LightFrame::Camera => view.direction_to_world(self.direction),
            LightFrame::World => self.direction,
        };
        WorldLight { direction: normalized(d), ambient: self.ambient, diffuse: self.diffuse }
    }
}

/// A validated light in world coordinates.
pub(super) struct WorldLight {
    direction: [f32; 3],
    ambient: f32,
    diffuse: f32,
}

impl WorldLight {
    /// Brightness factor of a surface with unit normal `n`.
    pub fn intensity(&self, n: [f32; 3]) -> f32 {
        let d = self.direction;
        self.ambient + self.diffuse * (n[0] * d[0] + n[1] * d[1] + n[2] * d[2]).max(0.0)
    }

    /// Brightness of a surface that faces the light: for points without normals.
    pub fn full(&self) -> f32 {
        self.ambient + self.diffuse
    }
}

/// `color` scaled by a brightness factor, clamped to white, rounded to the nearest level.
pub(super) fn shade(color: [u8; 3], intensity: f32) -> [u8; 3] {
    // `as u8` saturates; the clamp keeps the intent explicit.
    color.map(|c| (c as f32 * intensity).round().clamp(0.0, 255.0) as u8)
}

/// How surfaces are coloured before lighting.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Coloring {
    /// One base colour (sRGB) for the whole mesh.
    Uniform([u8; 3]),
    /// A flat colour per part (connected component of faces that share vertices), from a
    /// fixed palette in the order the parts' first faces appear; point clouds use the
    /// palette's first colour.
    Parts,
    /// The default colour where a face is seen from its front, red where from behind: what
    /// a viewer that draws front sides only (glTF's default) would leave out.
    BackFaces,
}

/// The colour [`Coloring::BackFaces`] gives a face seen from behind.
pub const BACK_FACE_COLOR: [u8; 3] = [220, 40, 40];

/// The base colour a mesh is drawn in unless asked otherwise (sRGB).
pub const DEFAULT_COLOR: [u8; 3] = [200, 200, 210];

impl Default for Coloring {
    fn default() -> Self {
        Self::Uniform(DEFAULT_COLOR)
    }
}
