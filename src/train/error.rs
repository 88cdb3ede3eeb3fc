use std::path::PathBuf;

use crate::mesh::MeshError;
use crate::tokenize::TokenizeError;

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error(transparent)]
    Mesh(#[from] MeshError),
    #[error(transparent)]
    Tokenize(#[from] TokenizeError),
    #[error("{path}: bad manifest: {message}")]
    Manifest { path: PathBuf, message: String },
}
