//! One error shape for every interface: `{"error": {"code", "message"}}` over HTTP, a status
//! with the same message over gRPC.

use std::time::Duration;

use axum::Json;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use utoipa::ToSchema;

use crate::engine::EngineError;
use crate::mesh::MeshError;

#[derive(Debug, Clone, PartialEq)]
pub struct ApiError {
    pub status: StatusCode,
    pub code: &'static str,
    pub message: String,
    /// For 429 and 503: when to try again.
    pub retry_after: Option<Duration>,
}

#[derive(Serialize, ToSchema)]
pub struct ErrorBody {
    pub error: ErrorDetail,
}

#[derive(Serialize, ToSchema)]
pub struct ErrorDetail {
    /// Stable and machine-readable: invalid_input, malformed_body, unsupported_format,
    /// too_large, body_timeout, queue_full, queue_timeout, shutting_down, deadline_exceeded,
    /// stream_idle, model_error...
    pub code: String,
    pub message: String,
}

impl ApiError {
    pub fn new(status: StatusCode, code: &'static str, message: impl Into<String>) -> Self {
        Self { status, code, message: message.into(), retry_after: None }
    }

    /// Well-formed but unacceptable values (NaN, empty, over a limit, bad options).
    pub fn invalid(message: impl Into<String>) -> Self {
        Self::new(StatusCode::UNPROCESSABLE_ENTITY, "invalid_input", message)
    }

    /// A body that cannot be parsed at all.
    pub fn malformed(message: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, "malformed_body", message)
    }

    pub fn body(&self) -> ErrorBody {
        ErrorBody { error: ErrorDetail { code: self.code.into(), message: self.message.clone() } }
    }

    pub fn internal(message: impl Into<String>) -> Self {
        Self::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", message)
    }
}

impl From<EngineError> for ApiError {
    fn from(e: EngineError) -> Self {
        let status = match &e {
            EngineError::InvalidInput(_) => StatusCode::UNPROCESSABLE_ENTITY,
            EngineError::QueueFull(_) => StatusCode::TOO_MANY_REQUESTS,
            EngineError::ShuttingDown | EngineError::QueueTimeout(_) | EngineError::Stopped => {
                StatusCode::SERVICE_UNAVAILABLE
            }
            EngineError::DeadlineExceeded(_) => StatusCode::GATEWAY_TIMEOUT,
            EngineError::StreamIdle(_) => StatusCode::REQUEST_TIMEOUT,
            EngineError::Model(_) => StatusCode::INTERNAL_SERVER_ERROR,
            EngineError::Unsupported(_) => StatusCode::NOT_IMPLEMENTED,
        };
        let retry_after = matches!(status, StatusCode::TOO_MANY_REQUESTS)
            .then_some(Duration::from_secs(1))
            .or(matches!(e, EngineError::QueueTimeout(_)).then_some(Duration::from_secs(5)));
        Self { status, code: e.code(), message: e.to_string(), retry_after }
    }
}

impl From<MeshError> for ApiError {
    fn from(e: MeshError) -> Self {
        match e {
            MeshError::UnknownFormat(_) => {
                Self::new(StatusCode::BAD_REQUEST, "unsupported_format", e.to_string())
            }
            MeshError::TooLarge { .. } => {
                Self::new(StatusCode::PAYLOAD_TOO_LARGE, "too_large", e.to_string())
            }
            MeshError::Invalid(_) => Self::invalid(e.to_string()),
            MeshError::Unsupported { .. } => {
                Self::new(StatusCode::UNPROCESSABLE_ENTITY, "unsupported_feature", e.to_string())
            }
            _ => Self::malformed(e.to_string()),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut response = (self.status, Json(self.body())).into_response();
        if let Some(after) = self.retry_after {
            let secs = after.as_secs().max(1).to_string();
            if let Ok(v) = HeaderValue::from_str(&secs) {
                response.headers_mut().insert(header::RETRY_AFTER, v);
            }
        }
        response
    }
}
