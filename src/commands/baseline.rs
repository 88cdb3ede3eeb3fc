use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::{Args, ValueEnum};
use meshstream::baseline::{Method, PoissonOptions, baseline_mesh};
use meshstream::mesh::{Format, REFERENCE_POINTS, UpAxis, reference_points, write_mesh_file};
use meshstream::model::checkpoint;

use super::{normalized_input, point_count};

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
    /// Model folder whose config.json gives the default --max-faces, so that the baseline
    /// spends the model's face budget (not needed when the flag is given).
    #[arg(long, env = "MESHSTREAM_MODEL", default_value = "models/default")]
    model: PathBuf,
    /// The most points drawn from the input: by default the points `reconstruct` judges and
    /// fits its mesh against (its --reference-points), so that both see the same input.
    #[arg(long, default_value_t = REFERENCE_POINTS, value_parser = point_count())]
    points: usize,
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
    let max_faces = face_budget(args)?;
    let (input, normalization) = normalized_input(&args.input, UpAxis::Y)?;
    let cloud =
        reference_points(&input, args.points, args.seed).context("preparing the input points")?;
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

/// The face budget: the flag, or the model's when it is absent.
fn face_budget(args: &BaselineArgs) -> anyhow::Result<usize> {
    if let Some(max_faces) = args.max_faces {
        return Ok(max_faces);
    }
    let cfg = checkpoint::load_config(&args.model).with_context(|| {
        format!(
            "reading the model config in {} for the default --max-faces \
             (give the flag to run without a model)",
            args.model.display()
        )
    })?;
    Ok(cfg.max_faces)
}
