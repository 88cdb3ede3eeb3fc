//! The one error type of the model: every fallible call in `crate::model` returns it.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error("tensor error: {0}")]
    Candle(#[from] candle_core::Error),

    /// A caller passed a tensor or value whose shape does not fit the model.
    #[error("bad input: {0}")]
    BadInput(String),

    #[error("invalid model config: {0}")]
    InvalidConfig(String),

    #[error("sequence too long: position {position} exceeds the model's limit of {limit}")]
    SequenceTooLong { position: usize, limit: usize },

    #[error("unknown device {0:?}: expected cpu or cuda:N")]
    UnknownDevice(String),

    #[error("device {0:?} needs CUDA, but meshstream was built without the `cuda` feature")]
    CudaNotCompiled(String),

    #[error("checkpoint {path}: {error}")]
    Io {
        path: PathBuf,
        // In the message, not a source: a chain printer would repeat it.
        error: std::io::Error,
    },

    #[error("checkpoint {path}: {message}")]
    BadCheckpoint { path: PathBuf, message: String },

    #[error("checkpoint {path}: tensor {name:?} is missing")]
    MissingTensor { path: PathBuf, name: String },

    #[error(
        "checkpoint {path}: tensor {name:?} has shape {found:?}, but the config expects {expected:?}"
    )]
    ShapeMismatch { path: PathBuf, name: String, expected: Vec<usize>, found: Vec<usize> },

    #[error("checkpoint {path}: unexpected tensor(s) not used by the config: {names:?}")]
    UnexpectedTensors { path: PathBuf, names: Vec<String> },

    #[error(
        "the image model in {image_model} generates the latents of another encoder than the face \
         model's in {face_model} (encoder fingerprints {expected} and {found}): train an image \
         model for this face model with `meshstream-train dit --ae {face_model}`"
    )]
    ForeignEncoder { image_model: PathBuf, face_model: PathBuf, expected: String, found: String },
}

impl ModelError {
    pub(crate) fn bad_input(msg: impl Into<String>) -> Self {
        Self::BadInput(msg.into())
    }
}
