use std::ops::ControlFlow;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use meshstream::mesh::{Format, write_mesh_file};
use meshstream::model::{GenerateOptions, SamplingParams, checkpoint, generate, parse_device};
use meshstream::tokenize::{Quantizer, detokenize};

use super::input_points;

#[derive(Args)]
pub struct ReconstructArgs {
    /// A point cloud (PLY/OBJ with vertices only; normals used when present, estimated when
    /// not) or a mesh (its surface is sampled).
    input: PathBuf,
    /// Where to write the mesh, in the input's own coordinates.
    #[arg(short, long)]
    output: PathBuf,
    /// Output format, if not the output's extension.
    #[arg(long)]
    format: Option<Format>,
    /// Model folder (config.json + model.safetensors).
    #[arg(long, env = "MESHSTREAM_MODEL", default_value = "models/default")]
    model: PathBuf,
    /// Face budget (at most the model's limit).
    #[arg(long)]
    max_faces: Option<usize>,
    /// 0 decodes greedily (the paper's default).
    #[arg(long, default_value_t = 0.0)]
    temperature: f32,
    #[arg(long)]
    top_k: Option<usize>,
    #[arg(long)]
    top_p: Option<f32>,
    /// Seed of the point sampling and of the decoding when it samples.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// cpu or cuda:N (with --features cuda).
    #[arg(long, default_value = "cpu")]
    device: String,
}

pub fn run(args: &ReconstructArgs) -> anyhow::Result<()> {
    let device = parse_device(&args.device)?;
    let model = checkpoint::load(&args.model, &device)
        .with_context(|| format!("loading the model in {}", args.model.display()))?;
    let cfg = model.config().clone();
    let (cloud, normalization) = input_points(&args.input, cfg.num_points, args.seed)?;
    let start = Instant::now();
    let latents = model.encode_point_cloud(&cloud)?;
    let options = GenerateOptions {
        sampling: SamplingParams {
            temperature: args.temperature,
            top_k: args.top_k,
            top_p: args.top_p,
            seed: args.seed,
        },
        max_faces: args.max_faces.unwrap_or(cfg.max_faces),
        ..GenerateOptions::default()
    };
    let bar = ProgressBar::new_spinner();
    if let Ok(style) =
        ProgressStyle::with_template("{spinner} {pos} faces decoded ({per_sec}) {elapsed}")
    {
        bar.set_style(style);
    }
    let (faces, reason) = generate(&model, &latents, options, |_| {
        bar.inc(1);
        ControlFlow::Continue(())
    })?;
    bar.finish_and_clear();
    let q = Quantizer::new(u16::try_from(cfg.quant_levels).context("quantization levels")?)?;
    let mesh = normalization.invert_mesh(&detokenize(&faces, q));
    anyhow::ensure!(!mesh.faces.is_empty(), "the model produced no faces ({reason:?})");
    write_mesh_file(&mesh, &args.output, args.format)
        .with_context(|| format!("writing {}", args.output.display()))?;
    eprintln!(
        "wrote {}: {} faces, {} vertices in {:.1} s (stopped by {reason:?})",
        args.output.display(),
        mesh.faces.len(),
        mesh.vertices.len(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}
