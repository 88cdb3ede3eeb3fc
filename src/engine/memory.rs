//! Handing freed memory back to the operating system when the engine goes idle.
//!
//! glibc's malloc keeps what a burst of requests freed (KV caches, decoded meshes, bodies) in
//! its arenas, so a server's resident memory stays at the burst's peak long after it: a
//! 10,000-request soak ended 35% above its warm level, and rounds of 1,500 requests against
//! one server levelled off at the peak (185, 208, 204, 211 MiB) instead of growing, which is
//! retention, not a leak. `malloc_trim` returns the free pages of every arena.
//!
//! It does not return the free top of the arenas of threads other than `main`, and glibc
//! moves large blocks there: each mapped block freed raises its mmap threshold to that block's
//! size (up to 32 MiB), so after loading a model, blocks of many MiB (encoder activations,
//! batches of logits) come from the decode and fitting threads' arenas and stay resident.
//! [`map_large_blocks`] fixes the threshold instead.

use std::time::Duration;

/// How long the engine must have nothing to do before freed memory is handed back: long
/// enough that a steady stream of requests never pays for it.
pub const TRIM_AFTER_IDLE: Duration = Duration::from_secs(1);

/// Blocks from this size up get a mapping of their own, handed back to the system when freed.
pub const MAP_FROM_BYTES: usize = 1 << 20;

/// Fixes glibc's mmap threshold at `MAP_FROM_BYTES` unless the caller chose one
/// (`MALLOC_MMAP_THRESHOLD_`, or `GLIBC_TUNABLES`), so that large blocks never settle in a
/// thread's arena. The first thing a server should do, before it loads a model. Measured with
/// a CI-sized `bench soak` (160 requests, 8 clients), three runs each: resident memory at
/// the start 108-109 MiB against 143-151, at the end 110-111 against 146-163, decoding as
/// fast within noise (`bench decode --model models/default`). A no-op off glibc.
pub fn map_large_blocks() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let chosen = std::env::var_os("MALLOC_MMAP_THRESHOLD_").is_some()
            || std::env::var("GLIBC_TUNABLES").is_ok_and(|t| t.contains("mmap_threshold"));
        if chosen {
            return;
        }
        // SAFETY: mallopt only sets glibc's own tunables, under its lock; 1 MiB is within the
        // range it accepts (up to 32 MiB on 64-bit).
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, MAP_FROM_BYTES as libc::c_int);
        }
    }
}

/// Returns the allocator's free memory to the operating system (glibc; a no-op elsewhere).
pub fn release_free_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: malloc_trim only walks glibc's own heap under its locks; any pad is valid.
        unsafe {
            libc::malloc_trim(0);
        }
    }
}
