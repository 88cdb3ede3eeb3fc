use std::time::Duration;

use thiserror::Error;

use crate::mesh::MeshError;
use crate::model::ModelError;

/// Why a request was refused or did not complete. Cloneable, so that one failed batch can
/// tell each of its requests.
#[derive(Debug, Clone, Error, PartialEq)]
pub enum EngineError {
    #[error("{0}")]
    InvalidInput(String),
    #[error("the queue is full ({0} requests waiting); retry later")]
    QueueFull(usize),
    #[error("the server is shutting down")]
    ShuttingDown,
    #[error("the request waited {0:.1?} in the queue without being started")]
    QueueTimeout(Duration),
    #[error("the request's deadline passed after {0} faces")]
    DeadlineExceeded(usize),
    #[error("the client read nothing for {0:.1?}: its stream was cancelled")]
    StreamIdle(Duration),
    #[error("the model failed: {0}")]
    Model(String),
    #[error("the engine stopped")]
    Stopped,
    /// The request needs a model this engine was started without.
    #[error("{0}")]
    Unsupported(String),
}

impl EngineError {
    /// A stable, machine-readable name: the error code of the APIs and the label of the
    /// rejection and failure metrics.
    pub fn code(&self) -> &'static str {
        match self {
            Self::InvalidInput(_) => "invalid_input",
            Self::QueueFull(_) => "queue_full",
            Self::ShuttingDown => "shutting_down",
            Self::QueueTimeout(_) => "queue_timeout",
            Self::DeadlineExceeded(_) => "deadline_exceeded",
            Self::StreamIdle(_) => "stream_idle",
            Self::Model(_) => "model_error",
            Self::Stopped => "engine_stopped",
            Self::Unsupported(_) => "unsupported",
        }
    }
}

impl From<MeshError> for EngineError {
    fn from(e: MeshError) -> Self {
        Self::InvalidInput(e.to_string())
    }
}

impl From<ModelError> for EngineError {
    fn from(e: ModelError) -> Self {
        Self::Model(e.to_string())
    }
}

impl From<candle_core::Error> for EngineError {
    fn from(e: candle_core::Error) -> Self {
        Self::Model(e.to_string())
    }
}
