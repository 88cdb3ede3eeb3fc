//! Training-free baselines the FACE model is compared against, on the same input points and
//! face budget: the convex hull of the points, and screened Poisson reconstruction simplified
//! to the budget with meshoptimizer.

mod error;
mod hull;
mod points;
mod poisson;
mod simplify;

pub use error::BaselineError;
pub use hull::convex_hull;
pub use poisson::{MAX_POISSON_DEPTH, PoissonOptions, poisson_surface};
pub use simplify::{simplify_to_budget, simplify_within};

use crate::mesh::Mesh;

/// Which baseline to build.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Method {
    Hull,
    Poisson(PoissonOptions),
}

/// The baseline's mesh for a cloud of points (with normals for Poisson, as
/// [`crate::mesh::reference_points`] gives them), with at most `max_faces` faces. The hull is
/// held to the same budget as Poisson and the model, so that every row of a comparison has
/// the same number of faces to spend.
pub fn baseline_mesh(
    cloud: &Mesh,
    method: &Method,
    max_faces: usize,
) -> Result<Mesh, BaselineError> {
    let surface = match method {
        Method::Hull => convex_hull(&cloud.vertices)?,
        Method::Poisson(opts) => poisson_surface(cloud, opts)?,
    };
    simplify_to_budget(&surface, max_faces)
}

/// Runs a third-party solver, turning a panic inside it into an error message: both geometry
/// crates assert internally on inputs they find degenerate, and a bad input must not take the
/// process down.
fn catch_solver_panic<T>(solve: impl FnOnce() -> T) -> Result<T, String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(solve)).map_err(|payload| {
        payload
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "the solver panicked".into())
    })
}
