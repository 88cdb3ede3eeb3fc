//! `meshstream bench decode`: decoding speed of the FACE model, with random weights (against
//! the per-coordinate baseline running the same transformer) or a model folder's, in f32 and
//! quantized side by side. Every step runs as the engine runs it ([`DecodePools`]): a batch in
//! parts on the decode threads, one part on a single thread.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use meshstream::candidates::DEFAULT_CANDIDATES;
use meshstream::engine::{
    DecodePools, EncoderPoints, EngineConfig, EngineError, encode_batch, encode_pass,
};
use meshstream::mesh::primitives::uv_sphere;
use meshstream::mesh::{farthest_point_sampling, sample_surface};
use meshstream::model::{
    BaselineState, CoordinateBaseline, DEFAULT_FACE_BEAM, DEFAULT_TEMPERATURE, FaceConfig,
    FaceModel, GenerateOptions, Generation, Quantize, SamplingParams, checkpoint, few_rows,
    parse_device,
};

use super::out;

#[derive(clap::Args, Debug, Clone)]
pub struct DecodeBenchArgs {
    /// Model preset (random weights).
    #[arg(long, default_value = "tiny")]
    pub preset: String,
    /// A model folder to measure instead of random weights (the shipped one: models/default).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Number formats of the linear layers (f32, q8_0, q4k): one result each, with its ratio
    /// against f32 measured in the same run.
    #[arg(long, value_delimiter = ',', default_values_t = vec![Quantize::F32])]
    pub quantize: Vec<Quantize>,
    /// Rounds of every measurement: the formats take turns, the best round counts.
    #[arg(long, default_value_t = 3)]
    pub rounds: usize,
    /// cpu or cuda:N.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Faces per sequence for the throughput rows.
    #[arg(long, default_value_t = 200)]
    pub faces: usize,
    /// Batch sizes for the throughput rows (aggregate faces/s).
    #[arg(long, value_delimiter = ',', default_values_t = vec![1, 4, 16])]
    pub batches: Vec<usize>,
    /// Face counts at which FACE and the per-coordinate baseline are compared.
    #[arg(long, value_delimiter = ',', default_values_t = vec![200, 800])]
    pub compare: Vec<usize>,
    /// Decode threads, as `serve --decode-threads` (0: one per core).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
}

fn random_weights(
    cfg: &FaceConfig,
    device: &Device,
) -> anyhow::Result<(FaceModel, CoordinateBaseline)> {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, device);
    FaceModel::new(cfg, vb.pp("face"))?;
    CoordinateBaseline::new(cfg, vb.pp("baseline"))?;
    let weights = checkpoint::detached_weights(&varmap);
    let vb = VarBuilder::from_tensors(weights, DType::F32, device);
    Ok((FaceModel::new(cfg, vb.pp("face"))?, CoordinateBaseline::new(cfg, vb.pp("baseline"))?))
}

/// How the benchmark decodes.
#[derive(Debug, Clone)]
struct Decoding {
    sampling: SamplingParams,
    constrained: bool,
    face_beam: usize,
}

/// Decodes up to `faces` faces (no end of mesh) for `batch` sequences together; returns the
/// seconds taken, the faces decoded, and one sequence's KV-cache bytes (self, cross) at the
/// end.
fn decode_face(
    pools: &DecodePools,
    model: &FaceModel,
    latents: &Tensor,
    batch: usize,
    faces: usize,
    decoding: &Decoding,
) -> anyhow::Result<(f64, usize, (usize, usize))> {
    let options = GenerateOptions {
        sampling: decoding.sampling.clone(),
        max_faces: faces,
        // No early end of mesh: every row decodes its budget (constrained rows stop early only
        // at a dead end, when no canonical face can follow).
        min_faces: faces,
        constrained: decoding.constrained,
        face_beam: decoding.face_beam,
    };
    let mut gens = (0..batch)
        .map(|_| Generation::new(model, latents, options.clone()))
        .collect::<Result<Vec<_>, _>>()?;
    let t = Instant::now();
    while gens.iter().any(|g| !g.is_finished()) {
        let mut refs: Vec<&mut Generation> = gens.iter_mut().filter(|g| !g.is_finished()).collect();
        for part in pools.step(model, &mut refs, |g| &mut **g) {
            part?;
        }
    }
    let secs = t.elapsed().as_secs_f64();
    let decoded = gens.iter().map(|g| g.faces().len()).sum();
    let cache = gens[0].state().cache();
    Ok((secs, decoded, (cache.self_attention_bytes(), cache.cross_attention_bytes())))
}

/// The baseline decodes 9 tokens per face for `faces` faces (one sequence, on the thread
/// FACE's one sequence runs on).
fn decode_baseline(
    pools: &DecodePools,
    model: &CoordinateBaseline,
    latents: &Tensor,
    faces: usize,
) -> anyhow::Result<(f64, usize)> {
    pools.pool_for(1).install(|| {
        let mut state: BaselineState = model.start_sequence(latents)?;
        let t = Instant::now();
        for _ in 0..9 * faces {
            model.step_greedy(&mut [&mut state])?;
        }
        Ok((t.elapsed().as_secs_f64(), state.cache().self_attention_bytes()))
    })
}

fn mib(bytes: usize) -> String {
    format!("{:.2} MiB", bytes as f64 / (1024.0 * 1024.0))
}

/// The models measured: one per `--quantize` value, f32 first (the ratios' reference).
fn variants(
    f32_model: &FaceModel,
    quantize: &[Quantize],
) -> anyhow::Result<Vec<(Quantize, FaceModel)>> {
    let mut list = vec![Quantize::F32];
    list.extend(quantize.iter().copied().filter(|&q| q != Quantize::F32));
    list.dedup();
    list.into_iter()
        .map(|q| {
            let mut model = f32_model.clone();
            let report = model.quantize(q)?;
            if q != Quantize::F32 {
                out(format_args!("{report}"))?;
            }
            Ok((q, model))
        })
        .collect()
}

/// The encoder's time for the clouds of a whole mesh's candidates as the engine encodes them
/// ([`encode_batch`]: on the CPU a pass each, in parallel) against all in one pass, best of
/// `rounds` each.
fn encode_whole_mesh(
    model: &FaceModel,
    cloud: &[[f32; 3]],
    rounds: usize,
) -> anyhow::Result<String> {
    fn timed(encode: impl FnOnce() -> Result<Tensor, EngineError>) -> anyhow::Result<f64> {
        let t = Instant::now();
        encode()?;
        Ok(t.elapsed().as_secs_f64())
    }
    let k = model.config().num_latents;
    let queries: Vec<u32> =
        farthest_point_sampling(cloud, k, 0).into_iter().map(|i| i as u32).collect();
    // The bench's cloud stands in for its normals too, as in the other encoder rows.
    let draw = EncoderPoints { points: cloud.to_vec(), normals: cloud.to_vec(), queries };
    let clouds = vec![&draw; DEFAULT_CANDIDATES];
    let (mut served, mut together) = (f64::INFINITY, f64::INFINITY);
    for _ in 0..rounds.max(1) {
        served = served.min(timed(|| encode_batch(model, &clouds))?);
        together = together.min(timed(|| encode_pass(model, &clouds))?);
    }
    Ok(format!("{:.1} vs {:.1} ms ({:.2}x)", served * 1e3, together * 1e3, together / served))
}

/// Best of `rounds` for every variant, the variants taking turns so that a busy machine slows
/// them alike.
fn best_of<T>(
    rounds: usize,
    variants: &[(Quantize, FaceModel)],
    mut run: impl FnMut(&FaceModel) -> anyhow::Result<(f64, T)>,
) -> anyhow::Result<Vec<(f64, T)>> {
    let mut best: Vec<Option<(f64, T)>> = variants.iter().map(|_| None).collect();
    for _ in 0..rounds.max(1) {
        for (slot, (_, model)) in best.iter_mut().zip(variants) {
            let (secs, extra) = run(model)?;
            if slot.as_ref().is_none_or(|(b, _)| secs < *b) {
                *slot = Some((secs, extra));
            }
        }
    }
    Ok(best.into_iter().flatten().collect())
}

/// "name value (ratio against the first)" for every variant; `rate` is higher-is-better.
fn compare(variants: &[(Quantize, FaceModel)], values: &[f64], unit: &str, rate: bool) -> String {
    let reference = values[0];
    variants
        .iter()
        .zip(values)
        .enumerate()
        .map(|(i, ((q, _), v))| {
            let ratio = if rate { v / reference } else { reference / v };
            if i == 0 {
                format!("{q} {v:.2} {unit}")
            } else {
                format!("{q} {v:.2} {unit} ({ratio:.2}x)")
            }
        })
        .collect::<Vec<_>>()
        .join(" | ")
}

pub fn run(args: &DecodeBenchArgs) -> anyhow::Result<()> {
    anyhow::ensure!(!args.batches.contains(&0), "--batches must be at least 1");
    let device = parse_device(&args.device)?;
    let longest = args.compare.iter().copied().chain([args.faces]).max().unwrap_or(args.faces);
    let (model, baseline, source) = match &args.model {
        Some(dir) => {
            let mut cfg = checkpoint::load_config(dir)
                .with_context(|| format!("loading the model in {}", dir.display()))?;
            // The rotary positions are computed, not learned: a longer table only lets the
            // benchmark time sequences past what the model was trained on.
            let trained = cfg.max_faces;
            cfg.max_faces = cfg.max_faces.max(longest);
            let model = checkpoint::load_with_config(dir, &cfg, &device)
                .with_context(|| format!("loading the model in {}", dir.display()))?;
            let note = if longest > trained {
                format!(", positions past its max_faces {trained} only timed")
            } else {
                String::new()
            };
            (model, None, format!("model {}{note}", dir.display()))
        }
        None => {
            let mut cfg = FaceConfig::preset(&args.preset)?;
            // Random weights: the position limit only has to cover the benchmark.
            cfg.max_faces = cfg.max_faces.max(longest);
            let (model, baseline) = random_weights(&cfg, &device).context("building the models")?;
            (model, Some(baseline), format!("preset {}, random weights", args.preset))
        }
    };
    let cfg = model.config().clone();
    let threads =
        EngineConfig { decode_threads: args.threads, ..EngineConfig::default() }.threads();
    let pools = DecodePools::new(threads)?;
    out(format_args!(
        "{source} ({:.2}M parameters), {threads} decode threads",
        cfg.parameter_count() as f64 / 1e6,
    ))?;
    let variants = variants(&model, &args.quantize)?;

    // Encoding: FPS on the CPU, then the encoder, on points of a unit sphere (whose positions
    // are their normals).
    let cloud = sample_surface(&uv_sphere(1.0, 64, 32), cfg.num_points, 0)?.vertices;
    let flat: Vec<f32> = cloud.iter().flatten().copied().collect();
    let points = Tensor::from_vec(flat, (1, cfg.num_points, 3), &device)?;
    let encode = |model: &FaceModel| -> anyhow::Result<(f64, Tensor)> {
        let t = Instant::now();
        let idx: Vec<u32> = farthest_point_sampling(&cloud, cfg.num_latents, 0)
            .into_iter()
            .map(|i| i as u32)
            .collect();
        let idx = Tensor::from_vec(idx, (1, cfg.num_latents), &device)?;
        let latents = pools.wide().install(|| model.encode(&points, &points, &idx))?;
        Ok((t.elapsed().as_secs_f64(), latents))
    };
    encode(&model)?; // warm-up
    let encoded = best_of(args.rounds, &variants, encode)?;
    // Every variant decodes from the f32 encoder's latents, so that only the decoding differs.
    let latents = encoded[0].1.clone();

    let mut table = super::table();
    table.set_header(vec!["measurement", "result"]);
    let ms: Vec<f64> = encoded.iter().map(|(s, _)| s * 1e3).collect();
    table.add_row(vec![
        format!(
            "encode one point cloud ({} points -> {} latents), FPS included",
            cfg.num_points, cfg.num_latents
        ),
        compare(&variants, &ms, "ms", false),
    ]);
    table.add_row(vec![
        format!("encode a whole mesh's {DEFAULT_CANDIDATES} clouds (f32): as served vs one pass"),
        encode_whole_mesh(&model, &cloud, args.rounds)?,
    ]);
    let greedy = Decoding { sampling: SamplingParams::greedy(), constrained: false, face_beam: 1 };
    decode_face(&pools, &model, &latents, 1, 8, &greedy)?; // warm-up
    for &b in &args.batches {
        let runs = best_of(args.rounds, &variants, |m| {
            let (secs, n, _) = decode_face(&pools, m, &latents, b, args.faces, &greedy)?;
            Ok((secs, n))
        })?;
        let rates: Vec<f64> = runs.iter().map(|(s, n)| *n as f64 / s).collect();
        table.add_row(vec![
            format!("FACE decode, batch {b} x {} faces, faces/s aggregate", args.faces),
            compare(&variants, &rates, "", true),
        ]);
    }
    // What a greedy request costs: masks on, per-coordinate (beam 1) or the default beam.
    for &b in &args.batches {
        let mut rates = Vec::new();
        for face_beam in [1, DEFAULT_FACE_BEAM] {
            let masked = Decoding { constrained: true, face_beam, ..greedy.clone() };
            let (secs, n, _) = decode_face(&pools, &model, &latents, b, args.faces, &masked)?;
            rates.push(n as f64 / secs);
        }
        table.add_row(vec![
            format!("FACE decode f32, batch {b}, masks on: face beam 1 vs {DEFAULT_FACE_BEAM}"),
            format!(
                "{:.0} vs {:.0} faces/s aggregate ({:.2}x)",
                rates[0],
                rates[1],
                rates[1] / rates[0]
            ),
        ]);
    }
    // The few-rows kernel against candle's gemm, as a whole mesh's candidates decode.
    let whole = Decoding { constrained: true, face_beam: DEFAULT_FACE_BEAM, ..greedy.clone() };
    for &b in &args.batches {
        let mut best = [f64::INFINITY; 2];
        for _ in 0..args.rounds.max(1) {
            for (kernel, slot) in [false, true].into_iter().zip(&mut best) {
                few_rows::set_enabled(kernel);
                let timed = decode_face(&pools, &model, &latents, b, args.faces, &whole);
                few_rows::set_enabled(true);
                let (secs, n, _) = timed?;
                *slot = slot.min(secs / n as f64);
            }
        }
        table.add_row(vec![
            format!(
                "FACE decode f32, batch {b}, masks on, face beam {DEFAULT_FACE_BEAM}: gemm vs \
                 few-rows kernel"
            ),
            format!(
                "{:.0} vs {:.0} faces/s aggregate ({:.2}x)",
                1.0 / best[0],
                1.0 / best[1],
                best[0] / best[1]
            ),
        ]);
    }
    // A request with the service's defaults: sampled, masks on, no early end of mesh.
    let request = Decoding {
        sampling: SamplingParams {
            temperature: DEFAULT_TEMPERATURE,
            top_k: None,
            top_p: None,
            seed: 7,
        },
        constrained: true,
        face_beam: DEFAULT_FACE_BEAM,
    };
    let mut cache_rows = Vec::new();
    for &faces in &args.compare {
        let runs = best_of(args.rounds, &variants, |m| {
            let (secs, n, cache) = decode_face(&pools, m, &latents, 1, faces, &request)?;
            Ok((secs, (n, cache)))
        })?;
        // A sequence may stop at a dead end, and the formats at different ones: each result
        // says how many faces it decoded, the ratio compares faces/s.
        let rates: Vec<f64> = runs.iter().map(|(s, (n, _))| *n as f64 / s).collect();
        let result = variants
            .iter()
            .zip(&runs)
            .zip(&rates)
            .map(|(((q, _), (secs, (n, _))), rate)| {
                format!("{q} {secs:.2} s for {n} faces ({:.2}x)", rate / rates[0])
            })
            .collect::<Vec<_>>()
            .join(" | ");
        table.add_row(vec![
            format!(
                "{faces}-face mesh at batch 1, a default request (T {DEFAULT_TEMPERATURE}, \
                 masks on), faces/s ratio"
            ),
            result,
        ]);
        cache_rows.push((faces, runs[0].1.1, None));
    }
    if let Some(baseline) = &baseline {
        for (faces, _, base) in cache_rows.iter_mut() {
            let (face_secs, _, _) = decode_face(&pools, &model, &latents, 1, *faces, &greedy)?;
            let (base_secs, base_cache) = decode_baseline(&pools, baseline, &latents, *faces)?;
            table.add_row(vec![
                format!(
                    "{faces} faces: FACE ({faces} steps) vs per-coordinate ({} steps)",
                    9 * *faces
                ),
                format!(
                    "{:.2} s vs {:.2} s: speedup {:.1}x ({:.0} vs {:.0} faces/s)",
                    face_secs,
                    base_secs,
                    base_secs / face_secs,
                    *faces as f64 / face_secs,
                    *faces as f64 / base_secs
                ),
            ]);
            *base = Some(base_cache);
        }
    }
    for (faces, (face_self, face_cross), base_self) in cache_rows {
        let base = base_self.map(|b| format!("; per-coordinate {} self-attn", mib(b)));
        table.add_row(vec![
            format!("KV cache per sequence at {faces} faces (allocated)"),
            format!(
                "FACE {} self-attn + {} cross-attn{}",
                mib(face_self),
                mib(face_cross),
                base.unwrap_or_default()
            ),
        ]);
    }
    out(&table)?;
    Ok(())
}
