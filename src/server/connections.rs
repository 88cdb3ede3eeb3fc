//! HTTP connections served by hyper directly rather than through `axum::serve`, which does not
//! let a caller set hyper's header read timeout: a client that sends its headers too slowly
//! (slowloris) is disconnected instead of holding a connection and a task for ever.

use std::future::Future;
use std::time::Duration;

use axum::Router;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::conn::auto;
use hyper_util::service::TowerToHyperService;
use tokio::net::TcpListener;
use tokio::sync::watch;

/// How long a client may take to send what a request is made of.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadTimeouts {
    /// From the connection's first byte (or the end of the previous request) to the end of
    /// the request's headers; an idle keep-alive connection is closed after it too.
    pub header: Duration,
    /// For a request's whole body; past it the request is answered 408 `body_timeout`.
    pub body: Duration,
}

impl Default for ReadTimeouts {
    fn default() -> Self {
        Self { header: Duration::from_secs(30), body: Duration::from_secs(60) }
    }
}

/// Serves `router` on `listener` until `closing` resolves, then stops accepting, lets every
/// connection finish the request it is in (idle ones close at once) and returns when all have.
pub async fn serve_http(
    listener: TcpListener,
    router: Router,
    timeouts: ReadTimeouts,
    closing: impl Future<Output = ()>,
) {
    let mut builder = auto::Builder::new(TokioExecutor::new());
    builder.http1().timer(TokioTimer::new()).header_read_timeout(timeouts.header);
    // Each connection holds a receiver: a message asks them to finish, and the sender's
    // `closed` tells when the last one has.
    let (finish_tx, finish_rx) = watch::channel(());
    tokio::pin!(closing);
    loop {
        let stream = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => stream,
                Err(e) => {
                    // Out of file descriptors and the like: back off rather than spin.
                    tracing::warn!("accepting a connection failed: {e}");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            () = &mut closing => break,
        };
        let builder = builder.clone();
        let service = TowerToHyperService::new(router.clone());
        let mut finish = finish_rx.clone();
        tokio::spawn(async move {
            // hyper reads the first bytes to tell HTTP/1 from HTTP/2 before its header timer
            // starts: a client that connects and sends nothing is closed here, and at once
            // when the server is closing (it is as idle as a connection can be).
            let mut first = [0u8; 1];
            tokio::select! {
                peeked = tokio::time::timeout(timeouts.header, stream.peek(&mut first)) => {
                    if !matches!(peeked, Ok(Ok(n)) if n > 0) {
                        return;
                    }
                }
                _ = finish.changed() => return,
            }
            let connection = builder.serve_connection_with_upgrades(TokioIo::new(stream), service);
            tokio::pin!(connection);
            tokio::select! {
                _ = connection.as_mut() => return,
                _ = finish.changed() => connection.as_mut().graceful_shutdown(),
            }
            let _ = connection.await;
        });
    }
    drop(listener);
    drop(finish_rx);
    let _ = finish_tx.send(());
    finish_tx.closed().await;
}
