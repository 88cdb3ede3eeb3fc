use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use indicatif::ProgressBar;
use meshstream::diffusion::{Framing, ImageOptions, decode_image, images_to_tensor};
use meshstream::engine::EngineConfig;
use meshstream::mesh::Normalization;
use meshstream::model::{checkpoint, parse_device};
use meshstream::server::ImageServeConfig;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::decode::{DecodeArgs, decode, progress, write_decoded};
use super::{image_model_dir, load_image_model};

#[derive(Args)]
pub struct GenerateArgs {
    /// A PNG, JPEG or WebP image of one object (transparent pixels are put on white).
    image: PathBuf,
    #[command(flatten)]
    decode: DecodeArgs,
    /// Model folder (config.json + model.safetensors).
    #[arg(long, env = "MESHSTREAM_MODEL", default_value = "models/default")]
    model: PathBuf,
    /// Image model folder; default: the model folder's `dit/`.
    #[arg(long, env = "MESHSTREAM_IMAGE_MODEL")]
    image_model: Option<PathBuf>,
    /// DINOv2 weights (safetensors), for an image model configured with a DINOv2 encoder.
    #[arg(long, env = "MESHSTREAM_IMAGE_ENCODER")]
    image_encoder: Option<PathBuf>,
    /// Euler steps of the diffusion sampler.
    #[arg(long, default_value_t = ImageServeConfig::default().steps)]
    steps: usize,
    /// Classifier-free guidance: 0 ignores the image, 1 is plain conditional sampling.
    #[arg(long, default_value_t = ImageServeConfig::default().guidance)]
    guidance: f32,
    /// object: the object found, centred and scaled as in the image model's training renders,
    /// its backdrop painted white; centre_crop: the largest centred square, as given.
    #[arg(long, default_value_t = ImageServeConfig::default().framing)]
    framing: Framing,
    /// Seed of the diffusion noise, and of the decoding when it samples.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Samples to take: one whose mesh comes out empty is drawn again from the next seed, up
    /// to this many in all.
    #[arg(long, default_value_t = EngineConfig::default().image_attempts as u64, value_parser = clap::value_parser!(u64).range(1..))]
    attempts: u64,
    /// cpu or cuda:N (with --features cuda).
    #[arg(long, default_value = "cpu")]
    device: String,
}

/// Image -> latents (diffusion, step by step) -> faces, written in the model's frame.
pub fn run(args: &GenerateArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.steps > 0, "--steps must be at least 1");
    let device = parse_device(&args.device)?;
    let model = checkpoint::load(&args.model, &device)
        .with_context(|| format!("loading the model in {}", args.model.display()))?;
    let dir = image_model_dir(&args.model, args.image_model.as_deref()).with_context(|| {
        format!("{} has no image model (dit/); pass --image-model", args.model.display())
    })?;
    let diffusion = load_image_model(&dir, &args.model, args.image_encoder.as_deref(), &device)?;
    let size = u32::try_from(diffusion.config().image_encoder.image_size())?;
    let bytes =
        std::fs::read(&args.image).with_context(|| format!("reading {}", args.image.display()))?;
    let image =
        decode_image(&bytes, &ImageOptions { framing: args.framing, ..ImageOptions::new(size) })
            .with_context(|| format!("decoding {}", args.image.display()))?;
    let start = Instant::now();
    let images = images_to_tensor(&[image], &device)?;
    // As the server does: a sample whose mesh comes out empty is drawn again from the next
    // seed (`EngineConfig::image_attempts`).
    let mut attempt = 0;
    let decoded = loop {
        let mut rng = ChaCha8Rng::seed_from_u64(args.seed.wrapping_add(attempt));
        let mut run = diffusion.start(&images, vec![args.guidance], args.steps, &mut rng)?;
        let bar = progress(
            ProgressBar::new(args.steps as u64),
            "diffusion {bar:30} step {pos}/{len} ({per_sec}) {elapsed}",
        );
        while !run.is_done() {
            diffusion.step(&mut run)?;
            bar.inc(1);
        }
        bar.finish_and_clear();
        let latents = diffusion.latents(&run)?;
        let decoded = decode(&model, &[latents], &args.decode, None, args.seed)?;
        attempt += 1;
        if !decoded.0.faces.is_empty() || attempt >= args.attempts {
            break decoded;
        }
        eprintln!("no faces from seed {}: sampling again", args.seed.wrapping_add(attempt - 1));
    };
    write_decoded(decoded, &args.decode, Normalization::identity(), None, start)
}
