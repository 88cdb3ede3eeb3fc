//! How many threads candle's CPU kernels use. Two reasons to choose it here rather than leave
//! it to candle:
//! - Left unset, candle counts the cores again on every matmul, reading `/proc/cpuinfo` (3,104
//!   reads in a 20-face `bench decode`): one sequence decoded at 248 faces/s against 543 with
//!   `RAYON_NUM_THREADS` set.
//! - f32 matmuls split over `RAYON_NUM_THREADS` inside whatever rayon pool runs them, and
//!   quantized ones over one spinning pool of `CANDLE_NUM_THREADS` that serves one caller at a
//!   time. The engine already splits a batch into parts, one per decode thread
//!   (`engine::DecodePools`), so kernels splitting again inside a part only add hand-offs:
//!   with both at 2 instead of 1, q8_0 decoded about half the faces/s at batch 16 and 64
//!   (0.47x to 0.62x), though up to 1.24x at batch 4; f32 was the same within noise.
//!
//! Both default to 1 in `meshstream` (docs/decisions.md, "Serving"); rayon's global pool,
//! which fits candidates and runs the mesh tools, keeps one thread per core. A variable the
//! caller sets is left as it is.

use std::process::Command;
use std::sync::OnceLock;

/// The variables this process set itself, not its caller.
static DEFAULTED: OnceLock<Vec<&'static str>> = OnceLock::new();

/// Sets the variables the caller left unset to 1; the first thing `main` does.
pub fn one_per_kernel() -> anyhow::Result<()> {
    let mut defaulted = Vec::new();
    for name in ["CANDLE_NUM_THREADS", "RAYON_NUM_THREADS"] {
        if std::env::var_os(name).is_none() {
            // SAFETY: called before any other thread of this process exists.
            unsafe { std::env::set_var(name, "1") };
            defaulted.push(name);
        }
    }
    if defaulted.contains(&"RAYON_NUM_THREADS") {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        rayon::ThreadPoolBuilder::new()
            .num_threads(cores)
            .build_global()
            .map_err(|e| anyhow::anyhow!("cannot start the worker threads: {e}"))?;
    }
    let _ = DEFAULTED.set(defaulted);
    Ok(())
}

/// `command` (another `meshstream`) with the environment this one's caller gave it: without
/// the variables [`one_per_kernel`] set, so that the child defaults them as it would alone.
pub fn as_called(command: &mut Command) -> &mut Command {
    for name in DEFAULTED.get().into_iter().flatten() {
        command.env_remove(name);
    }
    command
}
