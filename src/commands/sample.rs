use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use meshstream::mesh::{Format, sample_surface, write_mesh_file};

use super::load_mesh;

#[derive(Args)]
pub struct SampleArgs {
    /// The mesh to sample (it needs faces).
    mesh: PathBuf,
    /// Number of points.
    #[arg(short = 'n', long, default_value_t = 8192)]
    count: usize,
    /// Where to write the points with their normals (PLY or OBJ keep normals).
    #[arg(short, long)]
    output: PathBuf,
    /// Output format, if not the output's extension.
    #[arg(long)]
    format: Option<Format>,
    /// Random seed: the same seed gives the same points.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

pub fn run(args: &SampleArgs) -> anyhow::Result<()> {
    let mesh = load_mesh(&args.mesh)?;
    let points = sample_surface(&mesh, args.count, args.seed)
        .with_context(|| format!("sampling {}", args.mesh.display()))?;
    write_mesh_file(&points, &args.output, args.format)
        .with_context(|| format!("writing {}", args.output.display()))?;
    eprintln!("wrote {} points to {}", points.vertices.len(), args.output.display());
    Ok(())
}
