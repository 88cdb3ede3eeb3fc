use crate::mesh::MeshError;

/// Everything that can go wrong rendering a mesh: bad options or a mesh that breaks its
/// invariants. Rendering itself cannot fail on a valid mesh.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("image size {width}x{height}: both sides must be at least 1 pixel")]
    EmptyImage { width: u32, height: u32 },
    #[error("image size {width}x{height} exceeds the limit of {limit} pixels")]
    ImageTooLarge { width: u64, height: u64, limit: u64 },
    #[error("invalid camera: {0}")]
    InvalidCamera(String),
    #[error("invalid light: {0}")]
    InvalidLight(String),
    /// Any other option out of its range (point radius, number of views).
    #[error("invalid render option: {0}")]
    InvalidOption(String),
    #[error(transparent)]
    Mesh(#[from] MeshError),
}
