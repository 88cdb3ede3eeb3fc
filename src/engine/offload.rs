//! CPU work that ends a request (fitting and judging candidates, measuring the answer) runs on
//! rayon's pool, one thread per core, off the async runtime: however many requests end
//! together, their work queues there rather than each taking a thread of its own from the
//! decoding or blocking the runtime's workers.

use std::sync::Arc;

use super::EngineError;
use super::metrics::{Metrics, Stage};

/// Runs `work` on rayon's pool and waits for it; its time counts as [`Stage::End`].
pub(super) async fn off_runtime<T: Send + 'static>(
    metrics: &Arc<Metrics>,
    work: impl FnOnce() -> T + Send + 'static,
) -> Result<T, EngineError> {
    let (tx, rx) = tokio::sync::oneshot::channel();
    let metrics = Arc::clone(metrics);
    rayon::spawn(move || {
        let _ = tx.send(metrics.time(Stage::End, work));
    });
    rx.await.map_err(|_| EngineError::Model("ending the request failed".into()))
}
