//! `meshstream-train`: train FACE autoencoders and image-to-latent diffusion models, export
//! their weights, plot their curves.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, bail};
use candle_core::{DType, Device};
use clap::{Args, Parser, Subcommand, ValueEnum};
use meshstream::diffusion::{DitConfig, ImageEncoderConfig, LatentStats};
use meshstream::mesh::{ReadLimits, expand_mesh_paths, read_mesh_file, write_mesh_file};
use meshstream::model::{CoordinateNll, EncoderTraining, FaceConfig, parse_device};
use meshstream::tokenize::{DEFAULT_LEVELS, Quantizer};
use meshstream::train::augment::{AugmentConfig, Rotation};
use meshstream::train::batch::{BatchConfig, CurriculumStage, SampleConfig};
use meshstream::train::bench::{StepPhases, bench_train_step};
use meshstream::train::bench_ops::bench_ops;
use meshstream::train::checkpoint::{RunDir, average_dir, export, parse_shard_size};
use meshstream::train::dataset::{UpAxes, UpRule, load_folder};
use meshstream::train::device_check::check_device;
use meshstream::train::dit::DitTrainConfig;
use meshstream::train::dit::cache::{AutoencoderId, CacheSpec};
use meshstream::train::dit::evaluate::DitEvalOptions;
use meshstream::train::dit::trainer::DitTrainer;
use meshstream::train::dit::views::ViewConfig;
use meshstream::train::evaluate::{
    EvalSet, GreedyScore, HELD_OUT_PROCEDURAL_SEED, coordinate_nll_per_mesh, greedy_scores,
    loss_per_mesh,
};
use meshstream::train::log::read_log;
use meshstream::train::optim::OptimConfig;
use meshstream::train::plot::plot_curves;
use meshstream::train::procedural::{ProceduralShapes, ShapeKind};
use meshstream::train::run_loop::{self, Plan, SessionLimits, Steps};
use meshstream::train::trainer::{TrainConfig, Trainer, stop_flag_on_ctrl_c};

/// Train FACE models on your meshes (and on procedural low-poly shapes), export the weights
/// that `meshstream` serves, and plot training curves.
#[derive(Parser)]
#[command(name = "meshstream-train", version, about, long_about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Train the point-cloud autoencoder (encoder + autoregressive face decoder).
    Ae(Box<AeArgs>),
    /// Train the image-to-latent diffusion model (DiT) against a frozen autoencoder.
    Dit(Box<DitArgs>),
    /// Write just what inference needs (config.json + model.safetensors, or its shards) from a
    /// run or checkpoint.
    Export {
        /// A run folder (its best weights, else its checkpoint's weight average, else the
        /// checkpoint itself), or a checkpoint or model folder.
        from: PathBuf,
        /// The model folder to write, e.g. models/mine.
        #[arg(short, long)]
        output: PathBuf,
        #[arg(long, value_enum, default_value_t = WeightType::F16)]
        dtype: WeightType,
        /// Tensor data per weights file (bytes, or with a unit: KB, MB, KiB, MiB, ...): larger
        /// weights are written as model-0000I-of-0000N.safetensors shards plus
        /// model.safetensors.index.json. The default keeps each file under 16 MiB.
        #[arg(long, default_value = "15MiB", value_parser = parse_shard_size)]
        max_shard_size: u64,
    },
    /// Write procedural low-poly shapes as PLY files, e.g. the held-aside evaluation set
    /// (the default seed), to score models and baselines on shapes never trained on.
    Shapes {
        /// Folder to write NNN-Kind.ply into.
        #[arg(short, long)]
        output: PathBuf,
        #[arg(short = 'n', long, default_value_t = 100)]
        count: usize,
        /// The default is the trainers' held-aside seed, which no training stream uses.
        #[arg(long, default_value_t = HELD_OUT_PROCEDURAL_SEED)]
        seed: u64,
        /// Only the simple one-part primitives (box, prism, pyramid, wedge, frustum, cone).
        #[arg(long)]
        primitives: bool,
        /// Most faces per shape.
        #[arg(long, default_value_t = 400)]
        max_faces: usize,
        /// The quantization grid the shapes' flat polygons are split for: the model's
        /// `quant_levels`, so that its rebuilds can match them face for face.
        #[arg(long, default_value_t = DEFAULT_LEVELS)]
        levels: u16,
    },
    /// The teacher-forced loss of a model on meshes, mesh by mesh (nats per face, end of mesh
    /// included, as in training): which shapes it has learned, whatever decoding does.
    Loss(LossArgs),
    /// Where a training step's time goes: the step taken apart into phases (upload, encoder,
    /// decoder, head, loss, backward, update), each waited out on the device, at each batch
    /// size; a table, or JSON lines.
    Bench {
        /// A model folder (or a run folder: its best weights): the architecture timed.
        #[arg(long, default_value = "models/default")]
        model: PathBuf,
        /// cpu or cuda:N (with --features cuda).
        #[arg(long, default_value = "cpu")]
        device: String,
        /// Face positions per step, one row each.
        #[arg(long, value_delimiter = ',', default_values_t = [1200, 4800])]
        positions: Vec<usize>,
        /// Timed steps per row (after one untimed).
        #[arg(long, default_value_t = 3)]
        steps: usize,
        #[arg(long, default_value_t = 0.25)]
        max_padding: f64,
        /// A mesh folder (a manifest's train split) drawn half the time beside procedural
        /// shapes; without it, procedural shapes only.
        #[arg(long)]
        data: Option<PathBuf>,
        /// On CUDA, f32 matrix products on TF32 tensor cores.
        #[arg(long)]
        tf32: bool,
        /// Also time a pass's building blocks one by one (matmul, linear, MLP, layer norm,
        /// softmax, attention), forward and backward, at the shapes of one pass of each row.
        #[arg(long)]
        ops: bool,
        #[arg(long)]
        json: bool,
    },
    /// Check that a device computes what the CPU does: a model's loss and gradient norm on
    /// the same batch of held-aside procedural shapes, on both. Fails (exit status 1) beyond
    /// the tolerance: run it before a GPU build trains anything.
    CheckDevice {
        /// A model folder (or a run folder: its best weights).
        #[arg(long, default_value = "models/default")]
        model: PathBuf,
        /// The device to check against the CPU: cuda:N (with --features cuda), or cpu.
        #[arg(long, default_value = "cuda:0")]
        device: String,
        #[arg(long, default_value_t = 8)]
        meshes: usize,
        /// Largest relative difference allowed in the loss and in the gradient norm.
        #[arg(long, default_value_t = 1e-3)]
        tolerance: f64,
        /// On CUDA, let f32 matrix products run on TF32 tensor cores (inputs rounded to a 10-bit
        /// mantissa, f32 accumulation; weights and optimizer state stay f32). No effect on the CPU.
        #[arg(long)]
        tf32: bool,
        /// One JSON object instead of the lines.
        #[arg(long)]
        json: bool,
    },
    /// Draw the loss and evaluation curves of a run's log.jsonl into a PNG.
    Plot {
        log: PathBuf,
        #[arg(short, long)]
        output: PathBuf,
    },
}

#[derive(Clone, Copy, ValueEnum)]
enum WeightType {
    F16,
    F32,
}

/// The training meshes, for `ae` and `dit`.
#[derive(Args, Debug, Clone)]
struct DataArgs {
    /// Folder of meshes; with a manifest.csv its split column picks the rows. Without it the
    /// run trains on procedural shapes only.
    #[arg(long)]
    data: Option<PathBuf>,
    #[arg(long, default_value = "train")]
    split: String,
    #[arg(long, default_value = "dev")]
    eval_split: String,
    /// The folder's files whose source puts another axis than y up, by name prefix, as
    /// PREFIX=AXIS (repeatable): they are stood on y when loaded, as training turns meshes
    /// about y only. The low-poly set's Kenney kits stand on z: `--up-axis kenney-road=z`,
    /// and so on (docs/decisions.md, "The caller says which axis is up").
    #[arg(long = "up-axis", value_name = "PREFIX=AXIS")]
    up_axes: Vec<UpRule>,
}

#[derive(Args)]
struct AeArgs {
    /// Run folder: train.json, checkpoint/, best/, log.jsonl.
    #[arg(long)]
    out: PathBuf,
    /// Continue the run in --out exactly from its last checkpoint (its train.json is used;
    /// only --steps may change).
    #[arg(long)]
    resume: bool,
    /// Start from the weights of an exported model with the same configuration. They are
    /// evaluated before the first step, and stay the run's best until a step beats them.
    #[arg(long, conflicts_with = "resume")]
    init: Option<PathBuf>,
    /// Keep the encoder of --init as it is and train the decoder and head only: the latent
    /// space stays the one an image model (the model folder's dit/) was trained on, and a
    /// step skips the encoder's backward pass.
    #[arg(long, requires = "init")]
    freeze_encoder: bool,
    /// The encoder's learning rate as a share of the schedule's, in (0, 1]: below 1 a
    /// fine-tune moves the latent space less than the decoder (an image model trained on it
    /// still needs retraining once it moves at all).
    #[arg(long, default_value_t = 1.0, value_parser = parse_rate_share, conflicts_with = "freeze_encoder")]
    encoder_lr_scale: f64,
    /// Keep an exponential moving average of the weights with this decay (e.g. 0.995, about
    /// the last 200 steps): evaluations, best/ and exports use it; the checkpoint keeps it in
    /// checkpoint/average/ beside the raw weights that training continues from.
    #[arg(long)]
    weight_average: Option<f64>,
    /// Model preset: tiny, base or large (with --init, the one its weights have the layers of).
    #[arg(long, default_value = "tiny")]
    preset: String,
    /// Override the preset's face limit (with --init, the weights').
    #[arg(long)]
    max_faces: Option<usize>,
    /// Draw the encoder's points as the farthest apart of this many times as many, so that
    /// they spread evenly (1: drawn independently, the presets' choice; with --init, the
    /// weights' own). Saved in the model's config, so that inference draws them the same way.
    #[arg(long)]
    point_oversampling: Option<usize>,
    #[command(flatten)]
    data: DataArgs,
    /// Length of the run: the learning-rate schedule spans this many steps.
    #[arg(long, default_value_t = 10_000)]
    steps: u64,
    #[command(flatten)]
    session: SessionArgs,
    #[arg(long, default_value_t = 1e-3)]
    lr: f64,
    #[command(flatten)]
    plan: PlanArgs,
    #[arg(long, default_value_t = 200)]
    warmup: u64,
    #[arg(long, default_value_t = 0.1)]
    weight_decay: f64,
    /// Batches whose gradients are summed into one step.
    #[arg(long, default_value_t = 1)]
    accumulate: usize,
    /// Face positions per batch.
    #[arg(long, default_value_t = 1200)]
    batch_faces: usize,
    /// Padding allowed per forward pass, as a fraction of its real face positions: a batch
    /// runs as groups of similar lengths.
    #[arg(long, default_value_t = 0.25)]
    max_padding: f64,
    /// Fraction of samples drawn from the procedural shape generator.
    #[arg(long, default_value_t = 0.5)]
    procedural_ratio: f32,
    /// How often procedural kinds are drawn relative to the others, as KIND=WEIGHT pairs,
    /// e.g. "box=3,prism=3" (a kind not listed has weight 1; 0 leaves it out).
    #[arg(long, value_parser = parse_kind_weight, value_delimiter = ',')]
    procedural_weights: Vec<(ShapeKind, u32)>,
    /// Curriculum as STEP:MAX_FACES pairs, e.g. "0:100,3000:400".
    #[arg(long, default_value = "0:100,3000:400")]
    curriculum: String,
    #[arg(long, value_enum, default_value_t = Rotation::Upright)]
    rotation: Rotation,
    /// With --rotation upright: the share of samples turned by any angle; the rest turn by a
    /// quarter turn, which keeps axis-aligned faces (most of an artist's) axis-aligned.
    #[arg(long, default_value_t = 0.25, value_parser = parse_share)]
    any_angle_share: f32,
    #[arg(long, default_value_t = 0.5, value_parser = parse_share)]
    flip_probability: f32,
    #[arg(long, default_value_t = 0.25)]
    scale_jitter: f32,
    /// The share of samples whose encoder points come as a scan's do: moved by noise (see
    /// --scan-noise) and with normals estimated from them, as a request without normals has.
    #[arg(long, default_value_t = 0.0, value_parser = parse_share)]
    scanned_share: f32,
    /// The largest standard deviation of a scanned sample's noise, as a share of its longest
    /// side (each draws its own from 0 to this).
    #[arg(long, default_value_t = 0.0, value_parser = parse_share)]
    scan_noise: f32,
    #[arg(long, default_value_t = 16)]
    eval_meshes: usize,
    #[arg(long, default_value_t = 16)]
    eval_procedural: usize,
    #[arg(long, default_value_t = 50_000)]
    eval_samples: usize,
    /// Seed of the initial weights and of the batches: the same seed draws the same.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// cpu or cuda:N (with --features cuda).
    #[arg(long, default_value = "cpu")]
    device: String,
    /// On CUDA, let f32 matrix products run on TF32 tensor cores (inputs rounded to a 10-bit
    /// mantissa, f32 accumulation; weights and optimizer state stay f32). No effect on the CPU.
    #[arg(long)]
    tf32: bool,
    /// No progress bar (logs only), e.g. under CI.
    #[arg(long)]
    no_progress: bool,
}

/// Where this session ends short of the schedule (continue later with --resume).
#[derive(Args)]
struct SessionArgs {
    /// End this session at this step (checkpointed). The schedule still spans --steps.
    #[arg(long)]
    stop_at: Option<u64>,
    /// End this session within this many seconds of wall time, its final evaluation and
    /// checkpoint included (e.g. a rented GPU's slot). The schedule still spans --steps.
    #[arg(long, value_parser = parse_seconds)]
    time_budget: Option<Duration>,
}

impl SessionArgs {
    fn limits(&self) -> SessionLimits {
        SessionLimits { stop_at: self.stop_at, time_budget: self.time_budget }
    }
}

fn parse_seconds(text: &str) -> Result<Duration, String> {
    match text.parse::<f64>() {
        Ok(s) if s > 0.0 && s.is_finite() => Ok(Duration::from_secs_f64(s)),
        _ => Err(format!("{text:?} is not a positive number of seconds")),
    }
}

/// The schedule's end, clipping and cadence, the same for both trainers (the length, warm-up
/// and peak learning rate have per-trainer defaults).
#[derive(Args)]
struct PlanArgs {
    /// The cosine schedule ends at lr x this.
    #[arg(long, default_value_t = 0.1)]
    min_lr_ratio: f64,
    #[arg(long, default_value_t = 1.0)]
    grad_clip: f64,
    #[arg(long, default_value_t = 250)]
    checkpoint_every: u64,
    #[arg(long, default_value_t = 1000)]
    eval_every: u64,
}

impl PlanArgs {
    fn plan(&self, steps: u64, warmup_steps: u64, lr: f64) -> Plan {
        Plan {
            steps,
            warmup_steps,
            lr,
            min_lr_ratio: self.min_lr_ratio,
            grad_clip: self.grad_clip,
            checkpoint_every: self.checkpoint_every,
            eval_every: self.eval_every,
        }
    }
}

#[derive(Args)]
struct DitArgs {
    /// Run folder: train.json, latent-cache/, checkpoint/, best/, log.jsonl.
    #[arg(long)]
    out: PathBuf,
    /// The frozen autoencoder (a model folder such as models/default).
    #[arg(long, required_unless_present = "resume")]
    ae: Option<PathBuf>,
    /// Continue the run in --out exactly from its last checkpoint (its train.json is used;
    /// only --steps may change).
    #[arg(long)]
    resume: bool,
    /// Start from the weights of an exported diffusion model with the same architecture. They
    /// are evaluated before the first step, and stay the run's best until a step beats them.
    #[arg(long, conflicts_with = "resume")]
    init: Option<PathBuf>,
    /// Diffusion preset: tiny or base (K and the latent width always follow the autoencoder).
    #[arg(long, default_value = "tiny")]
    preset: String,
    /// Override the preset's width (DiT and patch encoder; MLPs are 4x).
    #[arg(long)]
    width: Option<usize>,
    /// Override the preset's number of DiT blocks.
    #[arg(long)]
    layers: Option<usize>,
    #[command(flatten)]
    data: DataArgs,
    /// Procedural shapes added to the training meshes.
    #[arg(long, default_value_t = 256)]
    procedural: usize,
    /// Augmented copies of each training mesh in the latent cache.
    #[arg(long, default_value_t = 4)]
    augmentations: usize,
    /// Rendered views of each augmented copy.
    #[arg(long, default_value_t = 4)]
    views: usize,
    /// Augmentation rotation. None by default: the camera's random azimuth already turns the
    /// mesh about the vertical axis (y, the renderer's up).
    #[arg(long, value_enum, default_value_t = Rotation::None)]
    rotation: Rotation,
    /// With --rotation upright: the share of samples turned by any angle, the rest by a
    /// quarter turn.
    #[arg(long, default_value_t = 0.25, value_parser = parse_share)]
    any_angle_share: f32,
    /// Mirroring probability per axis (a y flip shows the mesh upside down).
    #[arg(long, default_value_t = 0.0, value_parser = parse_share)]
    flip_probability: f32,
    #[arg(long, default_value_t = 0.25)]
    scale_jitter: f32,
    /// Length of the run: the learning-rate schedule spans this many steps.
    #[arg(long, default_value_t = 20_000)]
    steps: u64,
    #[command(flatten)]
    session: SessionArgs,
    /// (latent, view) pairs per step.
    #[arg(long, default_value_t = 32)]
    batch: usize,
    #[arg(long, default_value_t = 3e-4)]
    lr: f64,
    #[command(flatten)]
    plan: PlanArgs,
    #[arg(long, default_value_t = 500)]
    warmup: u64,
    /// The paper trains the DiT without weight decay.
    #[arg(long, default_value_t = 0.0)]
    weight_decay: f64,
    /// AdamW for every parameter instead of Muon for the block matrices (the paper's choice).
    #[arg(long)]
    adamw: bool,
    /// Held-aside meshes of --eval-split (the first, by name).
    #[arg(long, default_value_t = 8)]
    eval_meshes: usize,
    /// Held-aside procedural shapes.
    #[arg(long, default_value_t = 4)]
    eval_procedural: usize,
    /// Euler steps when sampling for evaluation.
    #[arg(long, default_value_t = 25)]
    eval_steps: usize,
    /// Classifier-free guidance scale when sampling for evaluation.
    #[arg(long, default_value_t = 3.0)]
    guidance: f32,
    /// Face budget of the evaluation's greedy decoding (default: the autoencoder's limit).
    #[arg(long)]
    eval_max_faces: Option<usize>,
    #[arg(long, default_value_t = 20_000)]
    eval_samples: usize,
    /// Seed of the initial weights, the batches and the flow-matching noise: the same seed
    /// draws the same.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// cpu or cuda:N (with --features cuda).
    #[arg(long, default_value = "cpu")]
    device: String,
    /// No progress bars (logs only), e.g. under CI.
    #[arg(long)]
    no_progress: bool,
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Ae(args) => train_ae(&args),
        Command::Dit(args) => train_dit(&args),
        Command::Export { from, output, dtype, max_shard_size } => {
            let from = model_folder(&from);
            let dtype = match dtype {
                WeightType::F16 => DType::F16,
                WeightType::F32 => DType::F32,
            };
            export(&from, &output, dtype, max_shard_size)
                .with_context(|| format!("exporting {}", from.display()))?;
            eprintln!("exported {} to {}", from.display(), output.display());
            Ok(())
        }
        Command::Shapes { output, count, seed, primitives, max_faces, levels } => {
            let grid = Quantizer::new(levels).context("--levels")?;
            let kinds: &[ShapeKind] = if primitives { &ShapeKind::PRIMITIVES } else { &[] };
            std::fs::create_dir_all(&output)
                .with_context(|| format!("creating {}", output.display()))?;
            for (i, (kind, mesh)) in ProceduralShapes::of_kinds(seed, max_faces, kinds)
                .on_grid(grid)
                .take(count)
                .enumerate()
            {
                let path = output.join(format!("{i:03}-{kind:?}.ply"));
                write_mesh_file(&mesh, &path, None)
                    .with_context(|| format!("writing {}", path.display()))?;
            }
            eprintln!("wrote {count} shapes (seed {seed}) to {}", output.display());
            Ok(())
        }
        Command::Loss(args) => loss_command(&args),
        Command::Bench { model, device, positions, steps, max_padding, data, tf32, ops, json } => {
            candle_core::cuda::set_gemm_reduced_precision_f32(tf32);
            let rows = BenchRows { positions: &positions, steps, max_padding, ops, json };
            bench_command(&model_folder(&model), &device, &rows, data)
        }
        Command::CheckDevice { model, device, meshes, tolerance, tf32, json } => {
            candle_core::cuda::set_gemm_reduced_precision_f32(tf32);
            let folder = model_folder(&model);
            let checked = parse_device(&device)?;
            let report =
                check_device(&folder, meshes, &candle_core::Device::Cpu, &checked, tolerance)
                    .with_context(|| format!("checking {device} with {}", folder.display()))?;
            if json {
                println!("{}", serde_json::to_string(&report)?);
            } else {
                for r in [&report.reference, &report.checked] {
                    println!(
                        "{}: loss {:.6}, gradient norm {:.6}, one step {:.1} ms; decoded greedily in {:.0} ms, CD {}",
                        r.device,
                        r.loss,
                        r.grad_norm,
                        r.step_ms,
                        r.decode_ms,
                        r.decoded_chamfer.map_or_else(|| "-".into(), |c| format!("{c:.4}"))
                    );
                }
                println!(
                    "{} meshes, {} face positions: relative difference loss {:.2e}, gradient norm {:.2e} (tolerance {:.0e})",
                    report.meshes,
                    report.positions,
                    report.loss_rel_diff,
                    report.grad_rel_diff,
                    report.tolerance
                );
            }
            if !report.passed() {
                bail!("{device} does not compute what the CPU does (beyond {tolerance:e})");
            }
            Ok(())
        }
        Command::Plot { log, output } => {
            let records = read_log(&log).with_context(|| format!("reading {}", log.display()))?;
            plot_curves(&records, &output)?;
            eprintln!("wrote {}", output.display());
            Ok(())
        }
    }
}

#[derive(Args)]
struct LossArgs {
    /// A model folder (or a run folder: its best weights).
    #[arg(long)]
    model: PathBuf,
    /// Meshes, or folders of them; each is scored as it is, in its own pose.
    #[arg(required = true)]
    meshes: Vec<PathBuf>,
    /// Seed of the points sampled on each mesh's surface.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// One JSON object instead of the table.
    #[arg(long)]
    json: bool,
    /// Also split each mesh's loss by coordinate: the mean over its faces of each of the 9
    /// values (z, y, x of each corner, in token order) and the end of mesh, in nats.
    #[arg(long)]
    per_coordinate: bool,
    /// Also decode each mesh greedily from the same points and score the decode: whether a
    /// wrong greedy mesh is one the model prefers to the truth (fewer nats in all) or one that
    /// decoding settled for.
    #[arg(long)]
    greedy: bool,
}

#[derive(serde::Serialize)]
struct MeshLoss {
    name: String,
    faces: usize,
    loss: f64,
    #[serde(flatten, skip_serializing_if = "Option::is_none")]
    by_coordinate: Option<CoordinateNll>,
    #[serde(skip_serializing_if = "Option::is_none")]
    greedy: Option<GreedyScore>,
}

impl MeshLoss {
    /// Whether greedy decoding made something else, which the model prefers to the truth.
    fn prefers_greedy(&self) -> Option<bool> {
        let g = self.greedy?;
        Some(!g.same && g.nll() < self.loss * (self.faces + 1) as f64)
    }
}

/// `meshstream-train loss`: meshes that cannot be read or tokenized are reported and counted.
fn loss_command(args: &LossArgs) -> anyhow::Result<()> {
    let folder = model_folder(&args.model);
    let model = meshstream::model::checkpoint::load(&folder, &candle_core::Device::Cpu)
        .with_context(|| format!("loading {}", folder.display()))?;
    let cfg = model.config().clone();
    let mut meshes = Vec::new();
    let mut unreadable = Vec::new();
    for path in expand_mesh_paths(&args.meshes)? {
        let name = path
            .file_stem()
            .map_or_else(|| path.display().to_string(), |s| s.to_string_lossy().into());
        match read_mesh_file(&path, &ReadLimits::default()) {
            Ok(mesh) => meshes.push((name, mesh)),
            Err(e) => unreadable.push(format!("{}: {e}", path.display())),
        }
    }
    let sample = SampleConfig::for_model(&cfg, AugmentConfig::OFF)?;
    let (set, left_out) = EvalSet::of_meshes(&meshes, &sample, cfg.max_faces, args.seed);
    // The split gives the loss too, so a mesh is run through the model once either way.
    let (losses, by_coordinate): (Vec<f64>, Vec<Option<CoordinateNll>>) = if args.per_coordinate {
        let split = coordinate_nll_per_mesh(&model, &set)?;
        let losses = (split.iter().zip(&set.items))
            .map(|(c, (_, s))| f64::from(c.per_position(s.faces.len())))
            .collect();
        (losses, split.into_iter().map(Some).collect())
    } else {
        (loss_per_mesh(&model, &set)?, vec![None; set.items.len()])
    };
    let greedy: Vec<Option<GreedyScore>> = if args.greedy {
        greedy_scores(&model, &set)?.into_iter().map(Some).collect()
    } else {
        vec![None; set.items.len()]
    };
    let rows: Vec<MeshLoss> = set
        .items
        .iter()
        .zip(losses)
        .zip(by_coordinate)
        .zip(greedy)
        .map(|((((_, s), loss), by_coordinate), greedy)| MeshLoss {
            name: s.name.clone(),
            faces: s.faces.len(),
            loss,
            by_coordinate,
            greedy,
        })
        .collect();
    let positions: usize = rows.iter().map(|r| r.faces + 1).sum();
    let per_position =
        rows.iter().map(|r| r.loss * (r.faces + 1) as f64).sum::<f64>() / positions.max(1) as f64;
    let mean = rows.iter().map(|r| r.loss).sum::<f64>() / rows.len().max(1) as f64;
    if args.json {
        let report = serde_json::json!({
            "meshes": rows,
            "loss_mean": mean,
            "loss_per_face": per_position,
            "left_out": left_out.iter().map(|(name, why)| format!("{name}: {why}")).collect::<Vec<_>>(),
            "unreadable": unreadable,
        });
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        let mut header = vec!["mesh", "faces", "loss (nats per face)"];
        if args.per_coordinate {
            header.extend(["z0", "y0", "x0", "z1", "y1", "x1", "z2", "y2", "x2", "end"]);
        }
        if args.greedy {
            header.extend(["greedy faces", "greedy loss", "greedy made", "more likely"]);
        }
        println!("| {} |\n|{}", header.join(" | "), "---|".repeat(header.len()));
        for r in &rows {
            let split = r.by_coordinate.as_ref().map_or_else(String::new, |c| {
                let values = c.coordinates.iter().chain([&c.end]);
                values.map(|v| format!(" {v:.3} |")).collect()
            });
            let greedy = r.greedy.map_or_else(String::new, |g| {
                let (made, likelier) = if g.same {
                    ("the truth", "-")
                } else if r.prefers_greedy() == Some(true) {
                    ("another mesh", "greedy's")
                } else {
                    ("another mesh", "the truth")
                };
                format!(" {} | {:.3} | {made} | {likelier} |", g.faces, g.loss)
            });
            println!("| {} | {} | {:.3} |{split}{greedy}", r.name, r.faces, r.loss);
        }
        println!("{} meshes: mean {mean:.3}, per face over all {per_position:.3}", rows.len());
        if args.greedy {
            let same = rows.iter().filter(|r| r.greedy.is_some_and(|g| g.same)).count();
            let preferred = rows.iter().filter(|r| r.prefers_greedy() == Some(true)).count();
            println!(
                "greedy decoding made the truth {same} times; of the {} other meshes it made, \
                 the model prefers {preferred} to the truth (fewer nats in all)",
                rows.len() - same
            );
        }
    }
    for (name, why) in &left_out {
        eprintln!("left out {name}: {why}");
    }
    for line in &unreadable {
        eprintln!("unreadable: {line}");
    }
    Ok(())
}

/// What `meshstream-train bench` times: steps of each number of positions, and with `ops`
/// the blocks of one of their passes.
struct BenchRows<'a> {
    positions: &'a [usize],
    steps: usize,
    max_padding: f64,
    ops: bool,
    json: bool,
}

/// `meshstream-train bench`: one row per batch size, then with `--ops` one per block and size.
fn bench_command(
    model: &Path,
    device: &str,
    rows: &BenchRows,
    data: Option<PathBuf>,
) -> anyhow::Result<()> {
    let device = parse_device(device)?;
    let cfg = meshstream::model::checkpoint::load_config(model)
        .with_context(|| format!("reading {}", model.display()))?;
    let folder = match data {
        Some(dir) => {
            let q = Quantizer::new(u16::try_from(cfg.quant_levels).context("quant_levels")?)?;
            let folder = load_folder(&dir, Some("train"), cfg.max_faces, q, &UpAxes::default())
                .with_context(|| format!("loading {}", dir.display()))?;
            Some(std::sync::Arc::new(folder))
        }
        None => None,
    };
    let mut table = comfy_table::Table::new();
    let mut header = vec!["positions".to_string(), "passes".into(), "faces/s".into()];
    header.extend(StepPhases::PHASES.iter().map(|p| format!("{p} ms")));
    table.set_header(header);
    let mut pass_rows = Vec::new();
    for &n in rows.positions {
        let phases =
            bench_train_step(model, folder.clone(), n, rows.steps, rows.max_padding, &device)
                .with_context(|| format!("timing steps of {n} positions"))?;
        pass_rows.push((phases.positions as f64 / phases.passes.max(1.0)).round() as usize);
        if rows.json {
            println!("{}", serde_json::to_string(&phases)?);
            continue;
        }
        let mut row = vec![
            phases.positions.to_string(),
            format!("{:.1}", phases.passes),
            format!("{:.0}", phases.faces_per_s),
        ];
        row.extend(phases.times().iter().map(|t| format!("{:.1}", t * 1e3)));
        table.add_row(row);
    }
    if !rows.json {
        println!("{table}");
        println!(
            "{device:?}, {}: ms per step by phase, each waited out on the device",
            model.display()
        );
    }
    if rows.ops {
        bench_ops_command(&cfg, &pass_rows, rows, &device)?;
    }
    Ok(())
}

/// `meshstream-train bench --ops`: each block at the shapes of a pass of each of `pass_rows`.
fn bench_ops_command(
    cfg: &FaceConfig,
    pass_rows: &[usize],
    rows: &BenchRows,
    device: &Device,
) -> anyhow::Result<()> {
    let mut table = comfy_table::Table::new();
    table.set_header([
        "pass rows",
        "block",
        "input",
        "forward ms",
        "backward ms",
        "backward / forward",
        "matmul TFLOP/s",
    ]);
    for &n in pass_rows {
        let times = bench_ops(cfg, n, rows.steps, device)
            .with_context(|| format!("timing the blocks of a pass of {n} positions"))?;
        for t in times {
            if rows.json {
                let mut line = serde_json::to_value(&t)?;
                line["pass_rows"] = n.into();
                println!("{line}");
                continue;
            }
            table.add_row([
                n.to_string(),
                t.op.to_string(),
                t.shape.clone(),
                format!("{:.2}", t.forward_s * 1e3),
                format!("{:.2}", t.backward_s * 1e3),
                format!("{:.1}", t.backward_s / t.forward_s.max(f64::EPSILON)),
                t.matmul_tflops().map_or_else(String::new, |f| format!("{f:.2}")),
            ]);
        }
    }
    if !rows.json {
        println!("{table}");
        println!(
            "{device:?}: ms per block, forward and backward from its output's sum, each waited \
             out on the device; matmul TFLOP/s counts the block's matrix products only"
        );
    }
    Ok(())
}

/// A run folder stands for its best weights (or its latest checkpoint before any evaluation).
fn model_folder(from: &Path) -> PathBuf {
    let run = RunDir(from.to_path_buf());
    if run.best().is_dir() {
        run.best()
    } else if average_dir(&run.checkpoint()).is_dir() {
        average_dir(&run.checkpoint())
    } else if run.checkpoint().is_dir() {
        run.checkpoint()
    } else {
        from.to_path_buf()
    }
}

fn train_ae(args: &AeArgs) -> anyhow::Result<()> {
    let device = parse_device(&args.device)?;
    candle_core::cuda::set_gemm_reduced_precision_f32(args.tf32);
    let mut trainer = if args.resume {
        Trainer::resume(args.out.clone(), device, Some(args.steps))
            .with_context(|| format!("resuming {}", args.out.display()))?
    } else {
        refuse_to_overwrite(&args.out)?;
        Trainer::create(config_from_args(args)?, args.out.clone(), args.init.as_deref(), device)?
    };
    print_setup(&trainer.data_summary(), trainer.parameter_counts());
    let from_init = args.init.is_some();
    let progress = !args.no_progress;
    run_session(&mut trainer, &args.out, args.steps, args.session.limits(), from_init, progress)
}

fn train_dit(args: &DitArgs) -> anyhow::Result<()> {
    let device = parse_device(&args.device)?;
    let progress = !args.no_progress;
    let mut trainer = if args.resume {
        DitTrainer::resume(args.out.clone(), device, Some(args.steps))
            .with_context(|| format!("resuming {}", args.out.display()))?
    } else {
        refuse_to_overwrite(&args.out)?;
        let cfg = dit_config_from_args(args)?;
        DitTrainer::create(cfg, args.out.clone(), args.init.as_deref(), device, progress)?
    };
    print_setup(&trainer.data_summary(), trainer.parameter_counts());
    let from_init = args.init.is_some();
    run_session(&mut trainer, &args.out, args.steps, args.session.limits(), from_init, progress)
}

/// A new run may not start in a folder that already holds one.
fn refuse_to_overwrite(out: &Path) -> anyhow::Result<()> {
    if RunDir(out.to_path_buf()).checkpoint().exists() {
        bail!("{} already holds a run: pass --resume, or choose another --out", out.display());
    }
    Ok(())
}

fn print_setup(data_summary: &str, parameter_counts: HashMap<&'static str, usize>) {
    eprintln!("{data_summary}");
    let mut counts: Vec<_> = parameter_counts.into_iter().collect();
    counts.sort();
    eprintln!("parameters by optimizer: {counts:?}");
}

/// Trains until `steps`, one of `limits` or Ctrl-C (printing each evaluation), then says how
/// the session ended. A run from `--init` evaluates those weights first.
fn run_session<T: Steps>(
    trainer: &mut T,
    out: &Path,
    steps: u64,
    limits: SessionLimits,
    evaluate_first: bool,
    progress: bool,
) -> anyhow::Result<()> {
    let stop = stop_flag_on_ctrl_c();
    let summary = run_loop::run(trainer, &stop, limits, evaluate_first, progress)?;
    let state = &summary.state;
    eprintln!(
        "{} at step {} after {:.0} s of training; checkpoint in {}",
        if summary.out_of_time {
            "out of time"
        } else if summary.interrupted || state.step < steps {
            "stopped"
        } else {
            "finished"
        },
        state.step,
        state.elapsed_s,
        RunDir(out.to_path_buf()).checkpoint().display()
    );
    Ok(())
}

fn dit_config_from_args(args: &DitArgs) -> anyhow::Result<DitTrainConfig> {
    let ae_dir = args.ae.clone().context("--ae is required for a new run")?;
    let autoencoder = AutoencoderId::of(&ae_dir)
        .with_context(|| format!("reading the autoencoder {}", ae_dir.display()))?;
    let mut model = DitConfig::preset(&args.preset)?;
    if let ImageEncoderConfig::Dinov2(_) = model.image_encoder {
        // Checked before the latent cache is built, which would otherwise be wasted.
        bail!(
            "preset {:?} uses a frozen DINOv2 encoder, which `dit` training does not load yet; \
             use a patch-encoder preset (tiny)",
            args.preset
        );
    }
    model.num_latents = autoencoder.config.num_latents;
    model.latent_dim = autoencoder.config.latent_dim;
    model.latent_stats = LatentStats::identity(model.latent_dim);
    if let Some(width) = args.width {
        model.width = width;
        model.mlp_hidden = 4 * width;
        if let ImageEncoderConfig::Patch(p) = &mut model.image_encoder {
            p.width = width;
            p.mlp_hidden = 4 * width;
        }
    }
    if let Some(layers) = args.layers {
        model.layers = layers;
    }
    model.validate()?;
    let view = ViewConfig::new(
        u32::try_from(model.image_encoder.image_size()).context("image size too large")?,
    );
    let max_faces = args.eval_max_faces.unwrap_or(autoencoder.config.max_faces);
    Ok(DitTrainConfig {
        cache: CacheSpec {
            data: args.data.data.clone(),
            split: args.data.split.clone(),
            up_axes: UpAxes(args.data.up_axes.clone()),
            procedural: args.procedural,
            augmentations: args.augmentations,
            views: args.views,
            augment: AugmentConfig {
                rotation: args.rotation,
                flip_probability: args.flip_probability,
                scale_jitter: args.scale_jitter,
                any_angle_share: args.any_angle_share,
                // The image model learns the latents of the meshes' own surfaces.
                scanned_share: 0.0,
                scan_noise: 0.0,
            },
            view,
            seed: args.seed,
            autoencoder,
        },
        model,
        autoencoder: ae_dir,
        eval_split: args.data.eval_split.clone(),
        eval_folder_meshes: args.eval_meshes,
        eval_procedural: args.eval_procedural,
        eval: DitEvalOptions {
            steps: args.eval_steps,
            guidance: args.guidance,
            seed: args.seed,
            max_faces,
            metric_samples: args.eval_samples,
        },
        batch: args.batch,
        optim: OptimConfig { weight_decay: args.weight_decay, ..OptimConfig::default() },
        muon: !args.adamw,
        plan: args.plan.plan(args.steps, args.warmup, args.lr),
        seed: args.seed,
    })
}

/// The model to train: the preset's configuration, or with --init the weights' own (the
/// preset's layers, with their face limit and point drawing), changed by --max-faces and
/// --point-oversampling.
///
/// Why the weights' own: a fine-tuning that fell back to the preset's independent points would
/// save them in the exported config, and the shipped weights decode the dev split further from
/// the shape so (greedy CD 0.282 against 0.256; `docs/decisions.md`, "Training on a GPU").
fn model_config(args: &AeArgs) -> anyhow::Result<FaceConfig> {
    let preset = FaceConfig::preset(&args.preset)?;
    let mut model = match &args.init {
        None => preset,
        Some(init) => {
            let own = meshstream::model::checkpoint::load_config(init)
                .with_context(|| format!("reading the configuration of {}", init.display()))?;
            let layers = FaceConfig { max_faces: own.max_faces, ..preset };
            if !layers.same_weights(&own) {
                bail!(
                    "{} holds other layers than the {:?} preset: pass its --preset",
                    init.display(),
                    args.preset
                );
            }
            own
        }
    };
    if let Some(max_faces) = args.max_faces {
        model.max_faces = max_faces;
        model.validate()?;
    }
    if let Some(oversampling) = args.point_oversampling {
        model.point_oversampling = oversampling;
        model.validate()?;
    }
    Ok(model)
}

fn config_from_args(args: &AeArgs) -> anyhow::Result<TrainConfig> {
    let model = model_config(args)?;
    let augment = AugmentConfig {
        rotation: args.rotation,
        flip_probability: args.flip_probability,
        scale_jitter: args.scale_jitter,
        any_angle_share: args.any_angle_share,
        scanned_share: args.scanned_share,
        scan_noise: args.scan_noise,
    };
    Ok(TrainConfig {
        data: args.data.data.clone(),
        train_split: args.data.split.clone(),
        up_axes: UpAxes(args.data.up_axes.clone()),
        eval_split: args.data.eval_split.clone(),
        batch: BatchConfig {
            sample: SampleConfig::for_model(&model, augment)?,
            faces_per_batch: args.batch_faces,
            procedural_ratio: args.procedural_ratio,
            procedural_weights: procedural_weights(&args.procedural_weights)?,
            curriculum: parse_curriculum(&args.curriculum)?,
            max_faces: model.max_faces,
            seed: args.seed,
            max_padding: args.max_padding,
        },
        optim: OptimConfig { weight_decay: args.weight_decay, ..OptimConfig::default() },
        plan: args.plan.plan(args.steps, args.warmup, args.lr),
        accumulate: args.accumulate,
        eval_folder_meshes: args.eval_meshes,
        eval_procedural: args.eval_procedural,
        eval_metric_samples: args.eval_samples,
        encoder: if args.freeze_encoder {
            EncoderTraining::Frozen
        } else {
            EncoderTraining::Trained
        },
        encoder_lr_scale: args.encoder_lr_scale,
        weight_average: args.weight_average,
        model,
    })
}

/// A probability or share: a number in [0, 1].
fn parse_share(text: &str) -> anyhow::Result<f32> {
    let value: f32 = text.trim().parse().with_context(|| format!("{text:?} is not a number"))?;
    if !(0.0..=1.0).contains(&value) {
        bail!("{value} is not between 0 and 1");
    }
    Ok(value)
}

/// A share of a learning rate: a number in (0, 1].
fn parse_rate_share(text: &str) -> anyhow::Result<f64> {
    let value: f64 = text.trim().parse().with_context(|| format!("{text:?} is not a number"))?;
    if !(value > 0.0 && value <= 1.0) {
        bail!("{value} is not in (0, 1]");
    }
    Ok(value)
}

/// The weights as a map, checked now rather than when the first batch is drawn.
fn procedural_weights(pairs: &[(ShapeKind, u32)]) -> anyhow::Result<BTreeMap<ShapeKind, u32>> {
    let weights = pairs.iter().copied().collect();
    ProceduralShapes::weighted(0, 1, &weights).context("--procedural-weights")?;
    Ok(weights)
}

fn parse_kind_weight(pair: &str) -> Result<(ShapeKind, u32), String> {
    let (kind, weight) =
        pair.split_once('=').ok_or_else(|| format!("'{pair}' is not KIND=WEIGHT"))?;
    let kind = ShapeKind::from_str(kind.trim(), true).map_err(|_| {
        let kinds: Vec<String> = ShapeKind::ALL
            .iter()
            .filter_map(|k| k.to_possible_value().map(|v| v.get_name().to_string()))
            .collect();
        format!("unknown shape kind '{kind}' (kinds: {})", kinds.join(", "))
    })?;
    let weight = weight.trim().parse().map_err(|_| format!("weight in '{pair}' is not a count"))?;
    Ok((kind, weight))
}

fn parse_curriculum(text: &str) -> anyhow::Result<Vec<CurriculumStage>> {
    let mut stages = text
        .split(',')
        .filter(|s| !s.trim().is_empty())
        .map(|pair| {
            let (step, faces) = pair
                .split_once(':')
                .with_context(|| format!("curriculum stage '{pair}' is not STEP:MAX_FACES"))?;
            Ok(CurriculumStage {
                from_step: step.trim().parse().with_context(|| format!("step in '{pair}'"))?,
                max_faces: faces
                    .trim()
                    .parse()
                    .with_context(|| format!("face count in '{pair}'"))?,
            })
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    stages.sort_by_key(|s| s.from_step);
    Ok(stages)
}
