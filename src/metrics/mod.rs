//! Evaluation metrics: Chamfer and Hausdorff distances between meshes, with one definition
//! everywhere (DESIGN.md, "Evaluation metrics"), the set-level summary, two predictions of one
//! set compared mesh by mesh, face-for-face agreement with a low-poly ground truth, how a
//! mesh is put together (boundary, non-manifold and misoriented edges, connected parts), how
//! much of it is seen from behind, and what an answer says of itself (its build and its
//! distance to its input).

mod distances;
mod error;
mod faces;
mod facing;
mod paired;
mod quality;
mod summary;
mod topology;

pub use distances::{Distances, MetricOptions, mesh_distances, point_set_distances};
pub use error::MetricsError;
pub use faces::{DEFAULT_FACE_TOLERANCE, FaceMatch, FaceSummary, face_match, summarize_faces};
pub use facing::back_faces_seen;
pub use paired::{PairedDifference, paired_chamfer};
pub use quality::MeshQuality;
pub use summary::{EvalRecord, EvalSummary, median, summarize};
pub use topology::{Topology, TopologySummary, summarize_topology, topology};
