use crate::mesh::MeshError;

use super::{MAX_LEVELS, MIN_LEVELS};

/// Everything that can go wrong turning meshes into face tokens and back.
#[derive(Debug, thiserror::Error)]
pub enum TokenizeError {
    #[error("{levels} quantization levels: supported are {MIN_LEVELS}..={MAX_LEVELS}")]
    InvalidLevels { levels: u16 },
    /// A per-coordinate sequence must hold 9 tokens per face.
    #[error(
        "a per-coordinate sequence of {len} tokens is not a whole number of faces (9 per face)"
    )]
    PerCoordinateLength { len: usize },
    #[error(transparent)]
    Mesh(#[from] MeshError),
}
