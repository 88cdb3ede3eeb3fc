//! `meshstream bench diffusion`: the image model's cost. One Euler step at batch 1 and 8 (with
//! and without classifier-free guidance, which doubles the passes), then whole image requests
//! through the engine (diffusion, hand-over, face decoding), 1 and 8 at once.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use candle_core::{DType, Device};
use clap::Args;
use meshstream::diffusion::{
    DiffusionModel, DitConfig, ImageOptions, PreparedImage, decode_image, images_to_tensor,
};
use meshstream::engine::{
    Conditioning, DecodeOptions, Engine, EngineConfig, ImagePrompt, Metrics, Request,
};
use meshstream::model::{checkpoint, parse_device};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use meshstream::server::ImageServeConfig;

use super::out;

use super::{image_model_dir, load_image_model};

#[derive(Args)]
pub struct DiffusionBenchArgs {
    /// Model folder; its `dit/` is the image model (random `tiny` weights when it has none:
    /// the cost does not depend on the weights).
    #[arg(long, default_value = "models/default")]
    model: PathBuf,
    #[arg(long, default_value = "cpu")]
    device: String,
    /// Batch sizes, one row each.
    #[arg(long, value_delimiter = ',', default_values_t = [1, 8])]
    batch: Vec<usize>,
    /// Euler steps of each image request.
    #[arg(long, default_value_t = ImageServeConfig::default().steps)]
    steps: usize,
    /// Guidance scale of the image requests.
    #[arg(long, default_value_t = ImageServeConfig::default().guidance)]
    guidance: f32,
    /// Face budget of each image request.
    #[arg(long, default_value_t = 200)]
    max_faces: usize,
    /// Minimum time spent on each step measurement, in seconds.
    #[arg(long, default_value_t = 3.0)]
    seconds: f64,
}

pub fn run(args: &DiffusionBenchArgs) -> anyhow::Result<()> {
    let device = parse_device(&args.device)?;
    let face = checkpoint::load(&args.model, &device)
        .with_context(|| format!("loading the model in {}", args.model.display()))?;
    let (diffusion, weights) = match image_model_dir(&args.model, None) {
        Some(dir) => {
            (load_image_model(&dir, &args.model, None, &device)?, dir.display().to_string())
        }
        None => (random_tiny(&device)?, "random tiny weights".to_string()),
    };
    let cfg = diffusion.config().clone();
    eprintln!(
        "image model: {weights}, {:.2}M parameters; {} threads",
        cfg.parameter_count() as f64 / 1e6,
        rayon::current_num_threads()
    );
    let image = test_image(cfg.image_encoder.image_size())?;

    let mut steps = super::table();
    steps.set_header(["batch", "guidance", "time per step", "per image per step", "vs batch 1"]);
    for guidance in [1.0f32, args.guidance] {
        let mut single = None;
        for &b in &args.batch {
            let t = time_step(&diffusion, &image, b, guidance, args.seconds, &device)?;
            let per_image = t / b as u32;
            let base = *single.get_or_insert(per_image);
            steps.add_row([
                b.to_string(),
                format!("{guidance}"),
                ms(t),
                ms(per_image),
                format!("{:.2}x", base.as_secs_f64() / per_image.as_secs_f64()),
            ]);
        }
    }
    out(format_args!("One Euler step (guidance 1 runs the conditional pass only):\n{steps}\n"))?;

    let mut requests = super::table();
    requests.set_header([
        "requests at once",
        "wall time",
        "latency mean",
        "diffusion mean",
        "first face mean",
        "faces",
        "requests/s",
    ]);
    let engine = Engine::start(
        face,
        Some(diffusion),
        EngineConfig::default(),
        Arc::new(Metrics::default()),
    )?;
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    for &b in &args.batch {
        let row = runtime.block_on(image_requests(&engine, &image, b, args))?;
        requests.add_row(row);
    }
    engine.shutdown(Duration::from_secs(1));
    engine.join();
    out(format_args!(
        "Image requests through the engine ({} steps, guidance {}, at most {} faces, greedy):\n{requests}",
        args.steps, args.guidance, args.max_faces
    ))?;
    Ok(())
}

fn ms(d: Duration) -> String {
    format!("{:.1} ms", d.as_secs_f64() * 1e3)
}

fn random_tiny(device: &Device) -> anyhow::Result<DiffusionModel> {
    let varmap = candle_nn::VarMap::new();
    let vb = candle_nn::VarBuilder::from_varmap(&varmap, DType::F32, device);
    Ok(DiffusionModel::new(&DitConfig::tiny(), vb, None)?)
}

/// A synthetic picture: a shaded disc on white, at the model's input size.
fn test_image(size: usize) -> anyhow::Result<PreparedImage> {
    let side = u32::try_from(size)?;
    let img = image::RgbImage::from_fn(side * 4, side * 4, |x, y| {
        let (dx, dy) = (x as f32 / (side * 2) as f32 - 1.0, y as f32 / (side * 2) as f32 - 1.0);
        let shade = (200.0 * (1.0 - dx * dx - dy * dy).max(0.0)) as u8;
        if dx * dx + dy * dy < 0.5 {
            image::Rgb([shade, shade / 2, 80])
        } else {
            image::Rgb([255; 3])
        }
    });
    let mut png = std::io::Cursor::new(Vec::new());
    img.write_to(&mut png, image::ImageFormat::Png)?;
    Ok(decode_image(png.get_ref(), &ImageOptions::new(side))?)
}

/// Mean time of one Euler step for a batch of `b` images, run inside a thread pool as the
/// engine runs it (calls from outside a pool pay rayon's cross-thread hand-off on every op).
fn time_step(
    model: &DiffusionModel,
    image: &PreparedImage,
    b: usize,
    guidance: f32,
    seconds: f64,
    device: &Device,
) -> anyhow::Result<Duration> {
    let pool = rayon::ThreadPoolBuilder::new().build()?;
    pool.install(|| {
        let images = images_to_tensor(&vec![image.clone(); b], device)?;
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        // Enough steps that a run never finishes while timing.
        let mut run = model.start(&images, vec![guidance; b], 1 << 20, &mut rng)?;
        model.step(&mut run)?; // warm-up
        let start = Instant::now();
        let mut n = 0u32;
        while n == 0 || start.elapsed().as_secs_f64() < seconds {
            model.step(&mut run)?;
            n += 1;
        }
        Ok(start.elapsed() / n)
    })
}

/// `b` image requests submitted at once; one table row.
async fn image_requests(
    engine: &Engine,
    image: &PreparedImage,
    b: usize,
    args: &DiffusionBenchArgs,
) -> anyhow::Result<[String; 7]> {
    let start = Instant::now();
    let streams = (0..b)
        .map(|i| {
            engine.submit(Request {
                id: format!("bench-{i}"),
                conditioning: Conditioning::Image(ImagePrompt {
                    image: image.clone(),
                    steps: args.steps,
                    guidance: args.guidance,
                    seed: i as u64,
                }),
                options: DecodeOptions { max_faces: Some(args.max_faces), ..Default::default() },
                deadline: None,
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    let handles: Vec<_> = streams.into_iter().map(|s| tokio::spawn(s.collect())).collect();
    let mut summaries = Vec::new();
    for h in handles {
        summaries.push(h.await??.summary);
    }
    let wall = start.elapsed();
    let mean = |f: &dyn Fn(&meshstream::engine::Summary) -> Duration| {
        summaries.iter().map(f).sum::<Duration>() / b as u32
    };
    let faces: usize = summaries.iter().map(|s| s.faces).sum();
    Ok([
        b.to_string(),
        ms(wall),
        ms(mean(&|s| s.total)),
        ms(mean(&|s| s.prepare)),
        ms(mean(&|s| s.time_to_first_face.unwrap_or_default())),
        faces.to_string(),
        format!("{:.2}", b as f64 / wall.as_secs_f64()),
    ])
}
