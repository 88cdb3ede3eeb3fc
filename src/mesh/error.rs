use std::path::PathBuf;

/// Everything that can go wrong reading, writing or checking a mesh.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    #[error("{path}: {error}")]
    Io {
        path: PathBuf,
        // In the message, not a source: a chain printer would repeat it.
        error: std::io::Error,
    },
    /// The bytes are not a valid file of the format (truncated, malformed, hostile).
    #[error("malformed {format} file: {message}")]
    Malformed { format: &'static str, message: String },
    /// A valid file that uses something we do not read (for example sparse accessors).
    #[error("unsupported {format} feature: {message}")]
    Unsupported { format: &'static str, message: String },
    /// The file would exceed a configured limit (vertices, faces, bytes).
    #[error("{what} exceeds the limit of {limit}")]
    TooLarge { what: &'static str, limit: u64 },
    /// The format could not be told from the name, content type or content.
    #[error("unknown mesh format: {0}")]
    UnknownFormat(String),
    /// A mesh that breaks an invariant (bad index, NaN, empty where geometry is required).
    #[error("invalid mesh: {0}")]
    Invalid(String),
}

impl MeshError {
    pub fn malformed(format: &'static str, message: impl Into<String>) -> Self {
        Self::Malformed { format, message: message.into() }
    }

    pub fn invalid(message: impl Into<String>) -> Self {
        Self::Invalid(message.into())
    }
}
