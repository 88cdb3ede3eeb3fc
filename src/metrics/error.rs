use crate::mesh::MeshError;

/// Why two meshes could not be compared. Each is a failure the caller counts, never a number.
#[derive(Debug, thiserror::Error)]
pub enum MetricsError {
    /// The prediction has no faces: nothing was generated (or only points).
    #[error("the prediction has no faces")]
    EmptyPrediction,
    /// The prediction has faces but no usable surface: bad indices, non-finite coordinates,
    /// zero total area, or coordinates that overflow in the ground truth's frame.
    #[error("invalid prediction: {0}")]
    InvalidPrediction(#[source] MeshError),
    /// The ground truth cannot define the frame or be sampled.
    #[error("invalid ground truth: {0}")]
    InvalidGroundTruth(#[source] MeshError),
    #[error("the number of surface samples must be positive")]
    NoSamples,
    /// Faces can only be matched against a ground truth that has faces, not a point cloud.
    #[error("the ground truth has no faces to match")]
    NoGroundTruthFaces,
    #[error("the face tolerance must be finite and not negative, not {0}")]
    InvalidTolerance(f32),
}
