//! `meshstream-train`: train FACE autoencoders, export their weights, plot their curves.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use candle_core::DType;
use clap::{Args, Parser, Subcommand, ValueEnum};
use meshstream::model::{FaceConfig, parse_device};
use meshstream::train::augment::{AugmentConfig, Rotation};
use meshstream::train::batch::{BatchConfig, CurriculumStage, SampleConfig};
use meshstream::train::checkpoint::{RunDir, export};
use meshstream::train::log::read_log;
use meshstream::train::optim::OptimConfig;
use meshstream::train::plot::plot_curves;
use meshstream::train::trainer::{TrainConfig, Trainer, eval_line, stop_flag_on_ctrl_c};

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
    /// Write just what inference needs (config.json + model.safetensors) from a run or checkpoint.
    Export {
        /// A run folder (its best weights are exported), or a checkpoint or model folder.
        from: PathBuf,
        /// The model folder to write, e.g. models/mine.
        #[arg(short, long)]
        output: PathBuf,
        #[arg(long, value_enum, default_value_t = WeightType::F16)]
        dtype: WeightType,
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

#[derive(Args)]
struct AeArgs {
    /// Run folder: train.json, checkpoint/, best/, log.jsonl.
    #[arg(long)]
    out: PathBuf,
    /// Continue the run in --out exactly from its last checkpoint (its train.json is used;
    /// only --steps may change).
    #[arg(long)]
    resume: bool,
    /// Start from the weights of an exported model with the same configuration.
    #[arg(long, conflicts_with = "resume")]
    init: Option<PathBuf>,
    /// Model preset: tiny, base or large.
    #[arg(long, default_value = "tiny")]
    preset: String,
    /// Override the preset's face limit.
    #[arg(long)]
    max_faces: Option<usize>,
    /// Folder of meshes; with a manifest.csv its split column picks the rows. Without it the
    /// run trains on procedural shapes only.
    #[arg(long)]
    data: Option<PathBuf>,
    #[arg(long, default_value = "train")]
    split: String,
    #[arg(long, default_value = "dev")]
    eval_split: String,
    /// Length of the run: the learning-rate schedule spans this many steps.
    #[arg(long, default_value_t = 10_000)]
    steps: u64,
    /// End this session at this step (checkpointed; continue later with --resume). The
    /// schedule still spans --steps.
    #[arg(long)]
    stop_at: Option<u64>,
    #[arg(long, default_value_t = 1e-3)]
    lr: f64,
    #[arg(long, default_value_t = 200)]
    warmup: u64,
    /// The cosine schedule ends at lr x this.
    #[arg(long, default_value_t = 0.1)]
    min_lr_ratio: f64,
    #[arg(long, default_value_t = 0.1)]
    weight_decay: f64,
    #[arg(long, default_value_t = 1.0)]
    grad_clip: f64,
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
    /// Curriculum as STEP:MAX_FACES pairs, e.g. "0:100,3000:400".
    #[arg(long, default_value = "0:100,3000:400")]
    curriculum: String,
    #[arg(long, value_enum, default_value_t = Rotation::Upright)]
    rotation: Rotation,
    #[arg(long, default_value_t = 0.5)]
    flip_probability: f32,
    #[arg(long, default_value_t = 0.25)]
    scale_jitter: f32,
    #[arg(long, default_value_t = 250)]
    checkpoint_every: u64,
    #[arg(long, default_value_t = 1000)]
    eval_every: u64,
    #[arg(long, default_value_t = 16)]
    eval_meshes: usize,
    #[arg(long, default_value_t = 16)]
    eval_procedural: usize,
    #[arg(long, default_value_t = 50_000)]
    eval_samples: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// cpu or cuda:N (with --features cuda).
    #[arg(long, default_value = "cpu")]
    device: String,
    /// No progress bar (logs only), e.g. under CI.
    #[arg(long)]
    no_progress: bool,
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Ae(args) => train_ae(&args),
        Command::Export { from, output, dtype } => {
            let from = model_folder(&from);
            let dtype = match dtype {
                WeightType::F16 => DType::F16,
                WeightType::F32 => DType::F32,
            };
            export(&from, &output, dtype)
                .with_context(|| format!("exporting {}", from.display()))?;
            eprintln!("exported {} to {}", from.display(), output.display());
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

/// A run folder stands for its best weights (or its latest checkpoint before any evaluation).
fn model_folder(from: &Path) -> PathBuf {
    let run = RunDir(from.to_path_buf());
    if run.best().is_dir() {
        run.best()
    } else if run.checkpoint().is_dir() {
        run.checkpoint()
    } else {
        from.to_path_buf()
    }
}

fn train_ae(args: &AeArgs) -> anyhow::Result<()> {
    let device = parse_device(&args.device)?;
    let mut trainer = if args.resume {
        Trainer::resume(args.out.clone(), device, Some(args.steps))
            .with_context(|| format!("resuming {}", args.out.display()))?
    } else {
        if RunDir(args.out.clone()).checkpoint().exists() {
            bail!(
                "{} already holds a run: pass --resume, or choose another --out",
                args.out.display()
            );
        }
        Trainer::create(config_from_args(args)?, args.out.clone(), args.init.as_deref(), device)?
    };
    eprintln!("{}", trainer.data_summary());
    let mut counts: Vec<_> = trainer.parameter_counts().into_iter().collect();
    counts.sort();
    eprintln!("parameters by optimizer: {counts:?}");
    let stop = stop_flag_on_ctrl_c();
    let summary = trainer.run(&stop, args.stop_at, !args.no_progress)?;
    let state = &summary.state;
    eprintln!(
        "{} at step {} after {:.0} s of training; checkpoint in {}",
        if summary.interrupted || state.step < args.steps { "stopped" } else { "finished" },
        state.step,
        state.elapsed_s,
        RunDir(args.out.clone()).checkpoint().display()
    );
    if let Some((step, report)) = &summary.last_eval {
        eprintln!("{}", eval_line(*step, report));
    }
    Ok(())
}

fn config_from_args(args: &AeArgs) -> anyhow::Result<TrainConfig> {
    let mut model = FaceConfig::preset(&args.preset)?;
    if let Some(max_faces) = args.max_faces {
        model.max_faces = max_faces;
        model.validate()?;
    }
    let levels = u16::try_from(model.quant_levels).context("quantization levels")?;
    Ok(TrainConfig {
        data: args.data.clone(),
        train_split: args.split.clone(),
        eval_split: args.eval_split.clone(),
        batch: BatchConfig {
            sample: SampleConfig {
                levels,
                num_points: model.num_points,
                num_queries: model.num_latents,
                augment: AugmentConfig {
                    rotation: args.rotation,
                    flip_probability: args.flip_probability,
                    scale_jitter: args.scale_jitter,
                },
            },
            faces_per_batch: args.batch_faces,
            procedural_ratio: args.procedural_ratio,
            curriculum: parse_curriculum(&args.curriculum)?,
            max_faces: model.max_faces,
            seed: args.seed,
            max_padding: args.max_padding,
        },
        optim: OptimConfig { weight_decay: args.weight_decay, ..OptimConfig::default() },
        lr: args.lr,
        warmup_steps: args.warmup,
        min_lr_ratio: args.min_lr_ratio,
        steps: args.steps,
        grad_clip: args.grad_clip,
        accumulate: args.accumulate,
        checkpoint_every: args.checkpoint_every,
        eval_every: args.eval_every,
        eval_folder_meshes: args.eval_meshes,
        eval_procedural: args.eval_procedural,
        eval_metric_samples: args.eval_samples,
        model,
    })
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
