//! The `meshstream` command: inspect, convert, sample and evaluate meshes, reconstruct them,
//! generate them from images, and serve the models over HTTP and gRPC.

mod commands;
mod kernel_threads;

use clap::{Parser, Subcommand};

/// meshstream turns point clouds and dense meshes into clean, artist-style triangle meshes
/// with the FACE method (one face, one token).
///
/// Mesh files can be OBJ, PLY (ASCII or binary), STL (ASCII or binary) and glTF 2.0 (.glb or
/// .gltf); a PLY or OBJ with vertices only is a point cloud.
#[derive(Parser)]
#[command(name = "meshstream", version, about, long_about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Vertices, faces and the FACE sequence lengths of meshes (files or folders).
    Stats(commands::stats::StatsArgs),
    /// Convert a mesh between formats, optionally snapping it to the quantization grid.
    Convert(commands::convert::ConvertArgs),
    /// Sample points with normals uniformly by area on a mesh's surface.
    Sample(commands::sample::SampleArgs),
    /// Reconstruct a clean mesh from a point cloud or a dense mesh with a FACE model.
    Reconstruct(commands::reconstruct::ReconstructArgs),
    /// Write a model's linear layers quantized (q8_0 or q4k) to a GGUF model folder.
    Quantize(commands::quantize::QuantizeArgs),
    /// Generate a mesh from an image: diffusion to the shape's latents, then the face decoder.
    Generate(commands::generate::GenerateArgs),
    /// Serve HTTP and gRPC on one engine (continuous batching, faces streamed as decoded).
    Serve(commands::serve::ServeArgs),
    /// A training-free baseline (convex hull or Poisson) from the same input and face budget.
    Baseline(commands::baseline::BaselineArgs),
    /// Chamfer and Hausdorff distances of predicted meshes against ground truth.
    Eval(commands::eval::EvalArgs),
    /// Draw a mesh or point cloud to an image (PNG, JPEG, WebP): a grid of views around it.
    Render(commands::render::RenderArgs),
    /// Exit 0 when a running server answers its readiness check, else 1 (a container's HEALTHCHECK).
    Healthcheck(commands::healthcheck::HealthcheckArgs),
    /// Benchmarks that print a table (run them in a release build).
    #[command(subcommand)]
    Bench(commands::bench::BenchCommand),
}

fn main() -> anyhow::Result<()> {
    kernel_threads::one_per_kernel()?;
    meshstream::engine::map_large_blocks();
    match Cli::parse().command {
        Command::Stats(args) => commands::stats::run(&args),
        Command::Convert(args) => commands::convert::run(&args),
        Command::Sample(args) => commands::sample::run(&args),
        Command::Eval(args) => commands::eval::run(&args),
        Command::Reconstruct(args) => commands::reconstruct::run(&args),
        Command::Quantize(args) => commands::quantize::run(&args),
        Command::Generate(args) => commands::generate::run(&args),
        Command::Serve(args) => commands::serve::run(&args),
        Command::Render(args) => commands::render::run(&args),
        Command::Baseline(args) => commands::baseline::run(&args),
        Command::Healthcheck(args) => commands::healthcheck::run(&args),
        Command::Bench(cmd) => commands::bench::run(&cmd),
    }
}
