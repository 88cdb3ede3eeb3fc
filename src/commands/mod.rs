//! Subcommands of the `meshstream` binary.

pub mod bench_decode;
