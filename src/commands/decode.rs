//! What `reconstruct` and `generate` share: the decoding flags, and latents to a mesh file
//! with a progress spinner.

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use candle_core::Tensor;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use meshstream::candidates::{Ending, best_of, candidate_options};
use meshstream::mesh::{Format, Mesh, Normalization, write_mesh_file};
use meshstream::metrics::MeshQuality;
use meshstream::model::{
    DEFAULT_FACE_BEAM, DEFAULT_TEMPERATURE, FaceModel, FinishReason, GenerateOptions,
    SamplingParams, generate,
};
use meshstream::tokenize::{Quantizer, detokenize};

#[derive(Args)]
pub struct DecodeArgs {
    /// Where to write the mesh.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Output format, if not the output's extension.
    #[arg(long)]
    pub format: Option<Format>,
    /// Face budget (at most the model's limit).
    #[arg(long)]
    pub max_faces: Option<usize>,
    /// Sampling temperature; 0 decodes greedily (the paper's default), with the face beam.
    #[arg(long, default_value_t = DEFAULT_TEMPERATURE)]
    pub temperature: f32,
    #[arg(long)]
    pub top_k: Option<usize>,
    #[arg(long)]
    pub top_p: Option<f32>,
    /// Greedy decoding keeps this many partial faces while it picks each face's coordinates,
    /// and takes the most likely whole face; 1 picks coordinate by coordinate.
    #[arg(long, default_value_t = DEFAULT_FACE_BEAM)]
    pub face_beam: usize,
}

/// A spinner or bar on stderr with `template`, left plain if the template does not parse.
pub fn progress(bar: ProgressBar, template: &str) -> ProgressBar {
    if let Ok(style) = ProgressStyle::with_template(template) {
        bar.set_style(style);
    }
    bar
}

/// What a reconstruction decodes from besides its latents: its input points (normalized
/// frame, with normals), how many candidate meshes to decode and judge against them, and how
/// to end them (welded, fitted to the points).
pub struct FromPoints<'a> {
    pub cloud: &'a Mesh,
    pub candidates: usize,
    pub ending: Ending,
}

/// Decodes `latents` (each (K, latent_dim)) into faces, in the model's frame; `seed` drives
/// sampling when the temperature is not 0. A reconstruction has a set of latents per draw of
/// its input points, candidate `i` decoding from the `i`-th (cycling), and keeps the candidate
/// that ends closest to its points; a generation decodes the first. The mesh may be empty.
pub fn decode(
    model: &FaceModel,
    latents: &[Tensor],
    args: &DecodeArgs,
    from_points: Option<FromPoints>,
    seed: u64,
) -> anyhow::Result<(Mesh, FinishReason)> {
    let cfg = model.config();
    let options = GenerateOptions {
        sampling: SamplingParams {
            temperature: args.temperature,
            top_k: args.top_k,
            top_p: args.top_p,
            seed,
        },
        max_faces: args.max_faces.unwrap_or(cfg.max_faces),
        face_beam: args.face_beam,
        ..GenerateOptions::default()
    };
    let q = Quantizer::new(u16::try_from(cfg.quant_levels).context("quantization levels")?)?;
    let bar =
        progress(ProgressBar::new_spinner(), "{spinner} {pos} faces decoded ({per_sec}) {elapsed}");
    let decoded = match from_points {
        Some(p) => {
            let options = candidate_options(&options, p.candidates);
            let (best, mesh) =
                best_of(model, latents, options, p.cloud, &p.ending, q, || bar.inc(1))?;
            (mesh, best.map_or(FinishReason::ConvexHull, |best| best.finish))
        }
        None => {
            let latents = latents.first().context("nothing to decode from")?;
            let (faces, reason) = generate(model, latents, options, |_| {
                bar.inc(1);
                ControlFlow::Continue(())
            })?;
            (detokenize(&faces, q), reason)
        }
    };
    bar.finish_and_clear();
    Ok(decoded)
}

/// Writes a decoded mesh (not empty, normalized frame) in the caller's frame, `normalization`
/// inverted, and reports what it wrote: its size, the time from `start`, and its
/// [`MeshQuality`] against the `input` points it was made from.
pub fn write_decoded(
    (mesh, reason): (Mesh, FinishReason),
    args: &DecodeArgs,
    normalization: Normalization,
    input: Option<&[[f32; 3]]>,
    start: Instant,
) -> anyhow::Result<()> {
    anyhow::ensure!(!mesh.faces.is_empty(), "the model produced no faces ({reason:?})");
    let seconds = start.elapsed().as_secs_f64();
    let quality = MeshQuality::measure(&mesh, input);
    // A reconstruction's ending drops faces but keeps their vertices in order.
    let mesh = normalization.invert_mesh(&mesh.without_unused_vertices());
    write(&mesh, &args.output, args.format)?;
    eprintln!(
        "wrote {}: {} faces, {} vertices in {seconds:.1} s (finish reason {}); {quality}",
        args.output.display(),
        mesh.faces.len(),
        mesh.vertices.len(),
        reason.name(),
    );
    Ok(())
}

fn write(mesh: &Mesh, path: &Path, format: Option<Format>) -> anyhow::Result<()> {
    write_mesh_file(mesh, path, format).with_context(|| format!("writing {}", path.display()))
}
