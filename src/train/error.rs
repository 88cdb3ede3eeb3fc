use std::path::{Path, PathBuf};

use crate::mesh::MeshError;
use crate::model::ModelError;
use crate::tokenize::TokenizeError;

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error(transparent)]
    Mesh(#[from] MeshError),
    #[error(transparent)]
    Tokenize(#[from] TokenizeError),
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error(transparent)]
    Tensor(#[from] candle_core::Error),
    #[error("{path}: {error}")]
    Io {
        path: PathBuf,
        // In the message, not a source: a chain printer would repeat it.
        error: std::io::Error,
    },
    #[error("{path}: bad manifest: {message}")]
    Manifest { path: PathBuf, message: String },
    #[error("{path}: {message}")]
    Weights { path: PathBuf, message: String },
    #[error("JSON: {0}")]
    Json(String),
    #[error("the batch thread stopped")]
    DataStopped,
    #[error("{0}")]
    Config(String),
}

impl TrainError {
    /// For `map_err`: an I/O error on `path`.
    pub(crate) fn io(path: &Path) -> impl FnOnce(std::io::Error) -> TrainError + '_ {
        move |error| TrainError::Io { path: path.to_path_buf(), error }
    }
}
