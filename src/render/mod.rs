//! A small software rasterizer: previews of meshes for users without a 3D viewer, and the
//! views that image-conditioned training renders of each mesh.
//!
//! Conventions: meshes in the normalized frame ([-1, 1]^3, +Y up; see DESIGN.md), an orbit
//! [`Camera`] looking at the origin, flat two-sided Lambert shading with ambient light,
//! z-buffered, deterministic. One render runs on one thread: callers that need many views
//! render them in parallel.

mod camera;
mod draw;
mod error;
mod grid;
mod options;
mod parts;
mod raster;

pub use camera::Camera;
pub use draw::render;
pub use error::RenderError;
pub use grid::{MAX_GRID_VIEWS, orbit_cameras, render_grid};
pub use options::{Coloring, Light, LightFrame, MAX_PIXELS, RenderOptions};
pub use parts::{face_parts, part_color};
