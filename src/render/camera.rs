//! The orbit camera: always looks at the origin, +Y up, placed by azimuth and elevation.

use serde::{Deserialize, Serialize};

use super::RenderError;
use crate::mesh::transform::{Mat3, mat_vec};

/// A perspective camera on a sphere around the origin, looking at the origin with +Y up.
///
/// Azimuth 0 and elevation 0 put the camera on the +Z axis looking down -Z (the front view of a
/// Y-up mesh); azimuth turns it counter-clockwise seen from above (90 degrees is on +X), and
/// positive elevation raises it above the XZ plane. Angles are in degrees.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Camera {
    pub azimuth_deg: f32,
    pub elevation_deg: f32,
    /// Distance from the origin, in the mesh's units (the normalized frame: [-1, 1]^3).
    pub distance: f32,
    /// Vertical field of view; the horizontal one follows from the image's aspect ratio.
    pub fov_y_deg: f32,
}

/// Points nearer to the camera than this (along its axis) are clipped, so that faces passing
/// through or behind the camera are cut rather than projected through infinity.
pub(super) const NEAR_PLANE: f32 = 1e-3;

impl Default for Camera {
    /// A three-quarter view from slightly above that frames the whole normalized cube.
    fn default() -> Self {
        let fov_y_deg = 40.0;
        let distance = Self::distance_to_frame(3f32.sqrt(), fov_y_deg, 1.0);
        Self { azimuth_deg: 30.0, elevation_deg: 20.0, distance, fov_y_deg }
    }
}

impl Camera {
    /// The distance at which a sphere of `radius` around the origin just fits the view, for an
    /// image `aspect` (width / height) wide: the narrower of the two fields of view decides.
    pub fn distance_to_frame(radius: f32, fov_y_deg: f32, aspect: f32) -> f32 {
        let half_y = (fov_y_deg.to_radians() / 2.0).tan();
        let half = half_y.min(half_y * aspect).atan();
        radius / half.sin()
    }

    pub fn validate(&self) -> Result<(), RenderError> {
        let bad = |what: String| Err(RenderError::InvalidCamera(what));
        if !self.azimuth_deg.is_finite() || !self.elevation_deg.is_finite() {
            return bad(format!(
                "angles must be finite (azimuth {}, elevation {})",
                self.azimuth_deg, self.elevation_deg
            ));
        }
        // The field of view first: a distance derived from a bad one is bad for that reason.
        if !(self.fov_y_deg > 0.0 && self.fov_y_deg < 180.0) {
            return bad(format!(
                "field of view must be in (0, 180) degrees, not {}",
                self.fov_y_deg
            ));
        }
        if !(self.distance.is_finite() && self.distance > 0.0) {
            return bad(format!("distance must be positive and finite, not {}", self.distance));
        }
        Ok(())
    }

    /// Where the camera is, in world coordinates.
    pub fn eye(&self) -> [f32; 3] {
        let back = self.axes()[2];
        back.map(|c| c * self.distance)
    }

    /// The camera's right, up and backward unit axes (rows), in world coordinates. They have a
    /// closed form in the angles, so looking straight down (elevation 90) needs no special case.
    fn axes(&self) -> Mat3 {
        let (sa, ca) = self.azimuth_deg.to_radians().sin_cos();
        let (se, ce) = self.elevation_deg.to_radians().sin_cos();
        let right = [ca, 0.0, -sa];
        let back = [ce * sa, se, ce * ca];
        // up = back x right
        let up = [-se * sa, ce, -se * ca];
        [right, up, back]
    }

    /// The view for an image of `width` x `height` pixels.
    pub(super) fn view(&self, width: u32, height: u32) -> View {
        let axes = self.axes();
        View {
            axes,
            eye: self.eye(),
            focal_px: height as f32 / 2.0 / (self.fov_y_deg.to_radians() / 2.0).tan(),
            center: [width as f32 / 2.0, height as f32 / 2.0],
        }
    }
}

/// A camera set up for one image size: world -> camera space -> pixels.
pub(super) struct View {
    /// Rows: right, up, back.
    pub axes: Mat3,
    pub eye: [f32; 3],
    /// Focal length in pixels (square pixels: the same for x and y).
    pub focal_px: f32,
    /// The image centre, where the optical axis meets the image.
    pub center: [f32; 2],
}

impl View {
    /// Camera-space coordinates `(x right, y up, depth)`, depth measured along the viewing
    /// direction (positive in front of the camera).
    pub fn to_camera(&self, p: [f32; 3]) -> [f32; 3] {
        let rel = [p[0] - self.eye[0], p[1] - self.eye[1], p[2] - self.eye[2]];
        let [x, y, z] = mat_vec(&self.axes, rel);
        [x, y, -z]
    }

    /// Pixel coordinates (x right, y down, pixel centres at half-integers) and inverse depth of
    /// a camera-space point in front of the near plane.
    pub fn project(&self, [x, y, depth]: [f32; 3]) -> [f32; 3] {
        let inv = 1.0 / depth;
        [self.center[0] + self.focal_px * x * inv, self.center[1] - self.focal_px * y * inv, inv]
    }

    /// A camera-space direction in world coordinates.
    pub fn direction_to_world(&self, d: [f32; 3]) -> [f32; 3] {
        let [r, u, b] = self.axes;
        std::array::from_fn(|k| d[0] * r[k] + d[1] * u[k] + d[2] * b[k])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
        a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    }

    #[test]
    fn axes_are_orthonormal_and_the_camera_looks_at_the_origin() {
        for (az, el) in [(0.0, 0.0), (37.0, 21.0), (-120.0, -80.0), (10.0, 90.0)] {
            let cam = Camera { azimuth_deg: az, elevation_deg: el, ..Camera::default() };
            let [r, u, b] = cam.axes();
            for (p, q, want) in [(r, r, 1.0), (u, u, 1.0), (b, b, 1.0), (r, u, 0.0), (u, b, 0.0)] {
                assert!((dot(p, q) - want).abs() < 1e-6, "{az} {el}");
            }
            // Right-handed: right x up = back.
            let c =
                [r[1] * u[2] - r[2] * u[1], r[2] * u[0] - r[0] * u[2], r[0] * u[1] - r[1] * u[0]];
            assert!(dot(c, b) > 0.999_999);
            let view = cam.view(100, 80);
            let origin = view.to_camera([0.0; 3]);
            assert!(origin[0].abs() < 1e-5 && origin[1].abs() < 1e-5);
            assert!((origin[2] - cam.distance).abs() < 1e-5);
            assert_eq!(&view.project(origin)[..2], &[50.0, 40.0]);
        }
    }

    #[test]
    fn front_view_sees_x_right_and_y_up() {
        let cam = Camera { azimuth_deg: 0.0, elevation_deg: 0.0, distance: 3.0, fov_y_deg: 90.0 };
        let view = cam.view(200, 200);
        // fov 90 at 200 px: focal length 100 px; a point 1 to the right at depth 2 lands 50 px right.
        let p = view.project(view.to_camera([1.0, 1.0, 1.0]));
        assert!((p[0] - 150.0).abs() < 1e-3 && (p[1] - 50.0).abs() < 1e-3, "{p:?}");
        let side = Camera { azimuth_deg: 90.0, ..cam }.eye();
        assert!((side[0] - 3.0).abs() < 1e-6 && side[2].abs() < 1e-6);
    }

    #[test]
    fn framing_distance_fits_the_sphere_in_the_narrower_field() {
        let d = Camera::distance_to_frame(1.0, 90.0, 1.0);
        assert!((d - 2f32.sqrt()).abs() < 1e-6);
        assert!(Camera::distance_to_frame(1.0, 90.0, 0.5) > d);
        assert_eq!(Camera::distance_to_frame(1.0, 90.0, 2.0), d);
    }

    #[test]
    fn bad_cameras_are_typed_errors() {
        let ok = Camera::default();
        assert!(ok.validate().is_ok());
        for bad in [
            Camera { distance: 0.0, ..ok },
            Camera { distance: f32::INFINITY, ..ok },
            Camera { fov_y_deg: 180.0, ..ok },
            Camera { fov_y_deg: f32::NAN, ..ok },
            Camera { azimuth_deg: f32::NAN, ..ok },
        ] {
            assert!(matches!(bad.validate(), Err(RenderError::InvalidCamera(_))), "{bad:?}");
        }
    }
}
