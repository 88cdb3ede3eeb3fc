//! One module per subcommand of `meshstream`.

pub mod baseline;
pub mod bench;
pub mod bench_decode;
pub mod bench_diffusion;
mod bench_requests;
pub mod bench_serve;
pub mod bench_soak;
pub mod convert;
pub mod decode;
pub mod eval;
pub mod generate;
pub mod healthcheck;
pub mod quantize;
pub mod reconstruct;
pub mod render;
pub mod sample;
pub mod serve;
pub mod stats;

use std::path::Path;

use anyhow::Context;
use candle_core::Device;
use meshstream::candidates::MAX_CANDIDATES;
use meshstream::diffusion::{DiffusionModel, checkpoint as dit_checkpoint};
use meshstream::mesh::{Mesh, Normalization, ReadLimits, UpAxis, read_mesh_file};
use meshstream::model::quantize::load_quantized;
use meshstream::model::{FaceModel, Quantize, QuantizeReport};

/// Writes one line of results to stdout. A reader that has gone away (`meshstream eval | head`)
/// is not an error, as for other Unix tools: the rest of the output has nowhere to go.
/// (`println!` would panic.)
pub fn out(line: impl std::fmt::Display) -> anyhow::Result<()> {
    use std::io::Write;
    match writeln!(std::io::stdout().lock(), "{line}") {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e).context("writing to stdout"),
        _ => Ok(()),
    }
}

/// Loads the face model in `dir` with its linear layers in `quantize` (a folder with a
/// quantized model file loads as it was written); the report says which layers stayed f32.
pub fn load_face_model(
    dir: &Path,
    device: &Device,
    quantize: Quantize,
) -> anyhow::Result<(FaceModel, QuantizeReport)> {
    load_quantized(dir, device, quantize)
        .with_context(|| format!("loading the model in {}", dir.display()))
}

/// Reads a mesh with the default limits, naming the file in the error.
pub fn load_mesh(path: &Path) -> anyhow::Result<Mesh> {
    read_mesh_file(path, &ReadLimits::default())
        .with_context(|| format!("reading {}", path.display()))
}

/// An input file in its normalized frame, and the normalization that puts a result back in
/// the file's coordinates. `reconstruct` and `baseline` draw their points from it alike (see
/// [`meshstream::mesh::input_clouds`]), so that the model and the baselines see the same.
pub fn normalized_input(path: &Path, up: UpAxis) -> anyhow::Result<(Mesh, Normalization)> {
    let input = load_mesh(path)?;
    let normalization =
        Normalization::fit(&input.vertices).context("normalizing the input")?.with_up(up);
    Ok((normalization.apply_mesh(&input), normalization))
}

/// Where a model folder keeps its image model (the diffusion transformer), if it has one.
pub const IMAGE_MODEL_SUBDIR: &str = "dit";

/// The image model to load: `explicit` if given (it must exist), else the `dit/` folder of
/// the face model's folder when there is one.
pub fn image_model_dir(model: &Path, explicit: Option<&Path>) -> Option<std::path::PathBuf> {
    match explicit {
        Some(dir) => Some(dir.to_path_buf()),
        None => {
            let dir = model.join(IMAGE_MODEL_SUBDIR);
            dir.join("config.json").is_file().then_some(dir)
        }
    }
}

/// Loads the image model in `dir` to run beside the face model in `face_model`, which must
/// have the encoder it was trained for; `dinov2` is the frozen backbone's weights for a DINOv2
/// config.
pub fn load_image_model(
    dir: &Path,
    face_model: &Path,
    dinov2: Option<&Path>,
    device: &Device,
) -> anyhow::Result<DiffusionModel> {
    let model = dit_checkpoint::load(dir, device, dinov2)
        .with_context(|| format!("loading the image model in {}", dir.display()))?;
    dit_checkpoint::check_encoder(model.config(), dir, face_model)?;
    Ok(model)
}

/// The parser of a `--candidates` flag: 1 to `MAX_CANDIDATES`.
pub fn candidate_count() -> clap::builder::RangedU64ValueParser<usize> {
    clap::builder::RangedU64ValueParser::new().range(1..=MAX_CANDIDATES as u64)
}

/// The most points a command draws from its input: a million is 64 times a reconstruction's
/// default reference, and the Poisson baseline's time and memory grow with the count.
pub const MAX_INPUT_POINTS: usize = 1 << 20;

/// The parser of a flag that counts input points: 1 to [`MAX_INPUT_POINTS`].
pub fn point_count() -> clap::builder::RangedU64ValueParser<usize> {
    clap::builder::RangedU64ValueParser::new().range(1..=MAX_INPUT_POINTS as u64)
}

/// A table printed as Markdown, so figures paste straight into notes and model cards.
pub fn table() -> comfy_table::Table {
    let mut table = comfy_table::Table::new();
    table.load_style(comfy_table::presets::ASCII_MARKDOWN);
    table
}

/// A file's name without its folder, for tables.
pub fn display_name(path: &Path) -> String {
    path.file_name()
        .map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned())
}
