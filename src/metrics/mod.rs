//! Evaluation metrics: Chamfer and Hausdorff distances between meshes, with one definition
//! everywhere (DESIGN.md, "Evaluation metrics"), and the set-level summary.

mod distances;
mod error;
mod summary;

pub use distances::{Distances, MetricOptions, mesh_distances, point_set_distances};
pub use error::MetricsError;
pub use summary::{EvalRecord, EvalSummary, summarize};
