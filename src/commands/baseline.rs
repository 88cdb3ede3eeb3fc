use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::{Args, ValueEnum};
use meshstream::baseline::{Method, PoissonOptions, baseline_mesh};
use meshstream::mesh::{Format, write_mesh_file};
use meshstream::model::checkpoint;

use super::input_points;

/// Most input points accepted: a million is 100x what the models take, and the Poisson solver's
/// time and memory grow with the count.
const MAX_POINTS: usize = 1 << 20;

#[derive(Clone, Copy, ValueEnum)]
enum MethodName {
    /// Convex hull of the points.
    Hull,
    /// Screened Poisson reconstruction (normals given or estimated), then simplification.
    Poisson,
}

#[derive(Args)]
pub struct BaselineArgs {
    /// The same inputs as `reconstruct`: a point cloud (normals used when present, estimated
    /// when not) or a mesh (its surface is sampled).
    input: PathBuf,
    /// Where to write the mesh, in the input's own coordinates.
    #[arg(short, long)]
    output: PathBuf,
    /// Output format, if not the output's extension.
    #[arg(long)]
    format: Option<Format>,
    #[arg(long, value_enum)]
    method: MethodName,
    /// Model folder whose config.json gives the default --points and --max-faces, so that the
    /// baseline sees the model's input and spends its face budget (not needed when both flags
    /// are given).
    #[arg(long, env = "MESHSTREAM_MODEL", default_value = "models/default")]
    model: PathBuf,
    /// Input points drawn from the input [default: the model's num_points].
    #[arg(long)]
    points: Option<usize>,
    /// Face budget: the result is simplified to at most this many faces [default: the
    /// model's max_faces].
    #[arg(long)]
    max_faces: Option<usize>,
    /// Seed of the point sampling (the same default as `reconstruct`, so both see the same
    /// points).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Poisson: octree depth (cells across the shape = 2^depth).
    #[arg(long, default_value_t = PoissonOptions::default().depth)]
    depth: usize,
    /// Poisson: depth where point density is estimated (at most --depth).
    #[arg(long, default_value_t = PoissonOptions::default().density_depth)]
    density_depth: usize,
    /// Poisson: weight of point positions against normals (0 = unscreened).
    #[arg(long, default_value_t = PoissonOptions::default().screening)]
    screening: f64,
    /// Poisson: conjugate-gradient iterations per level.
    #[arg(long, default_value_t = PoissonOptions::default().solver_iterations)]
    solver_iterations: usize,
}

pub fn run(args: &BaselineArgs) -> anyhow::Result<()> {
    let (points, max_faces) = budgets(args)?;
    anyhow::ensure!(points <= MAX_POINTS, "--points {points} is over the limit of {MAX_POINTS}");
    let (cloud, normalization) = input_points(&args.input, points, args.seed)?;
    let method = match args.method {
        MethodName::Hull => Method::Hull,
        MethodName::Poisson => Method::Poisson(PoissonOptions {
            depth: args.depth,
            density_depth: args.density_depth,
            screening: args.screening,
            solver_iterations: args.solver_iterations,
        }),
    };
    let start = Instant::now();
    let mesh = baseline_mesh(&cloud, &method, max_faces)
        .with_context(|| format!("building the baseline for {}", args.input.display()))?;
    let mesh = normalization.invert_mesh(&mesh);
    write_mesh_file(&mesh, &args.output, args.format)
        .with_context(|| format!("writing {}", args.output.display()))?;
    eprintln!(
        "wrote {}: {} faces, {} vertices in {:.2} s",
        args.output.display(),
        mesh.faces.len(),
        mesh.vertices.len(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

/// (input points, face budget): the flags, or the model's config where a flag is absent.
fn budgets(args: &BaselineArgs) -> anyhow::Result<(usize, usize)> {
    if let (Some(points), Some(max_faces)) = (args.points, args.max_faces) {
        return Ok((points, max_faces));
    }
    let cfg = checkpoint::load_config(&args.model).with_context(|| {
        format!(
            "reading the model config in {} for the default --points and --max-faces \
             (give both flags to run without a model)",
            args.model.display()
        )
    })?;
    Ok((args.points.unwrap_or(cfg.num_points), args.max_faces.unwrap_or(cfg.max_faces)))
}
