//! `Connection: close` on HTTP/1 answers given before the request's body was read to its end:
//! refusals without a key, bad query parameters, 413, 408, a server without an image model.
//!
//! Hyper drains a small unread body when it can, and otherwise closes the connection after the
//! answer; which of the two happens depends on whether the body's bytes had arrived yet. When
//! it closes an answer that did not say so, a client that pooled the connection sends its next
//! request into a closed socket and gets an error instead of an answer (RFC 9112 9.6 asks a
//! server that closes to say `close`). Saying it on every such answer makes the outcome the same
//! every time: the client opens a new connection.

use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::task::{Context, Poll};

use axum::body::{Body, Bytes, HttpBody};
use axum::extract::Request;
use axum::http::{HeaderValue, Version, header};
use axum::middleware::Next;
use axum::response::Response;
use http_body::{Frame, SizeHint};

/// The middleware: marks the answer `Connection: close` when the request announced a body
/// and the body was not read to its end. HTTP/2 streams are left alone (the header has no
/// meaning there and a connection outlives any one stream).
pub async fn close_if_body_unread(request: Request, next: Next) -> Response {
    if !announces_body(&request) || request.version() > Version::HTTP_11 {
        return next.run(request).await;
    }
    let finished = Arc::new(AtomicBool::new(false));
    let seen = finished.clone();
    let request = request.map(|body| Body::new(Watched { body, finished: seen }));
    let mut response = next.run(request).await;
    if !finished.load(Ordering::Acquire) {
        response.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
    }
    response
}

/// Whether an HTTP/1 request carries a body: a non-zero `Content-Length`, or any
/// `Transfer-Encoding` (RFC 9112 6.1).
fn announces_body(request: &Request) -> bool {
    let headers = request.headers();
    headers.contains_key(header::TRANSFER_ENCODING)
        || headers
            .get(header::CONTENT_LENGTH)
            .is_some_and(|v| v.to_str().ok().and_then(|s| s.parse::<u64>().ok()) != Some(0))
}

/// A body that records whether it was read to its end.
struct Watched {
    body: Body,
    finished: Arc<AtomicBool>,
}

impl HttpBody for Watched {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        let polled = Pin::new(&mut self.body).poll_frame(cx);
        if matches!(polled, Poll::Ready(None)) || self.body.is_end_stream() {
            self.finished.store(true, Ordering::Release);
        }
        polled
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.body.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use axum::Router;
    use axum::routing::post;
    use http_body_util::BodyExt;
    use tower::ServiceExt;

    use super::*;

    async fn read_all(body: Body) -> &'static str {
        body.collect().await.map(|_| "read").unwrap_or("failed")
    }

    async fn answer_unread() -> &'static str {
        "unread"
    }

    async fn connection_header(route: &str, body: &'static str, length: Option<&str>) -> bool {
        let app = Router::new()
            .route("/read", post(read_all))
            .route("/unread", post(answer_unread))
            .layer(axum::middleware::from_fn(close_if_body_unread));
        let mut request = axum::http::Request::post(route);
        if let Some(length) = length {
            request = request.header(header::CONTENT_LENGTH, length);
        }
        let response = app.oneshot(request.body(Body::from(body)).unwrap()).await.unwrap();
        response.headers().get(header::CONNECTION).is_some_and(|v| v == "close")
    }

    #[tokio::test]
    async fn only_an_answer_that_left_a_body_unread_closes_the_connection() {
        assert!(connection_header("/unread", "a body", Some("6")).await);
        assert!(!connection_header("/read", "a body", Some("6")).await);
        // No body announced: nothing is left on the connection.
        assert!(!connection_header("/unread", "", Some("0")).await);
        assert!(!connection_header("/unread", "", None).await);
    }
}
