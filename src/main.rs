// Temporary entry point so `meshstream bench decode` can be run while the lead wires the real
// command line.
mod commands;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "meshstream")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Benchmarks.
    #[command(subcommand)]
    Bench(Bench),
}

#[derive(Subcommand)]
enum Bench {
    /// Decoding speed of the FACE model against the per-coordinate baseline.
    Decode(commands::bench_decode::DecodeBenchArgs),
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Bench(Bench::Decode(args)) => commands::bench_decode::run(&args),
    }
}
