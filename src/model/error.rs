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

    /// A model folder with both weight layouts: which one is meant is anyone's guess.
    #[error(
        "checkpoint {dir}: holds both model.safetensors and model.safetensors.index.json; \
         remove one of the two layouts"
    )]
    MixedWeightLayouts { dir: PathBuf },

    #[error("checkpoint {path}: bad shard index: {message}")]
    BadShardIndex { path: PathBuf, message: String },

    #[error("checkpoint {path}: shard {shard} named by the index is missing")]
    MissingShard { path: PathBuf, shard: String },

    #[error("checkpoint {path}: tensor {name:?} is in both {first} and {second}")]
    DuplicateTensor { path: PathBuf, name: String, first: String, second: String },

    #[error("checkpoint {path}: the index puts tensor {name:?} in {shard}, which lacks it")]
    TensorNotInShard { path: PathBuf, name: String, shard: String },

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
