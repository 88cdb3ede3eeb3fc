//! `meshstream bench decode`: decoding speed of the FACE model with random weights, against
//! the per-coordinate baseline running the same transformer.

use std::time::Instant;

use anyhow::Context;
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use meshstream::mesh::primitives::uv_sphere;
use meshstream::mesh::{farthest_point_sampling, sample_surface};
use meshstream::model::{
    BaselineState, CoordinateBaseline, DEFAULT_FACE_BEAM, FaceConfig, FaceModel, GenerateOptions,
    Generation, SamplingParams, checkpoint, parse_device, step_generations,
};

use super::out;

#[derive(clap::Args, Debug, Clone)]
pub struct DecodeBenchArgs {
    /// Model preset (random weights).
    #[arg(long, default_value = "tiny")]
    pub preset: String,
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

/// Decodes up to `faces` faces (no end of mesh) for `batch` sequences together, greedily with
/// `face_beam`; returns the seconds taken, the faces decoded, and one sequence's KV-cache bytes
/// (self, cross) at the end.
fn decode_face(
    model: &FaceModel,
    latents: &Tensor,
    batch: usize,
    faces: usize,
    constrained: bool,
    face_beam: usize,
) -> anyhow::Result<(f64, usize, (usize, usize))> {
    let options = GenerateOptions {
        sampling: SamplingParams::greedy(),
        max_faces: faces,
        // No early end of mesh: every row decodes its budget (constrained rows stop early only
        // at a dead end, when no canonical face can follow).
        min_faces: faces,
        constrained,
        face_beam,
    };
    let mut gens = (0..batch)
        .map(|_| Generation::new(model, latents, options.clone()))
        .collect::<Result<Vec<_>, _>>()?;
    let t = Instant::now();
    while gens.iter().any(|g| !g.is_finished()) {
        let mut refs: Vec<&mut Generation> = gens.iter_mut().filter(|g| !g.is_finished()).collect();
        step_generations(model, &mut refs)?;
    }
    let secs = t.elapsed().as_secs_f64();
    let decoded = gens.iter().map(|g| g.faces().len()).sum();
    let cache = gens[0].state().cache();
    Ok((secs, decoded, (cache.self_attention_bytes(), cache.cross_attention_bytes())))
}

/// The baseline decodes 9 tokens per face for `faces` faces (one sequence).
fn decode_baseline(
    model: &CoordinateBaseline,
    latents: &Tensor,
    faces: usize,
) -> anyhow::Result<(f64, usize)> {
    let mut state: BaselineState = model.start_sequence(latents)?;
    let t = Instant::now();
    for _ in 0..9 * faces {
        model.step_greedy(&mut [&mut state])?;
    }
    Ok((t.elapsed().as_secs_f64(), state.cache().self_attention_bytes()))
}

fn mib(bytes: usize) -> String {
    format!("{:.2} MiB", bytes as f64 / (1024.0 * 1024.0))
}

pub fn run(args: &DecodeBenchArgs) -> anyhow::Result<()> {
    let device = parse_device(&args.device)?;
    let mut cfg = FaceConfig::preset(&args.preset)?;
    let longest = args.compare.iter().copied().chain([args.faces]).max().unwrap_or(args.faces);
    // Random weights: the position limit only has to cover the benchmark.
    cfg.max_faces = cfg.max_faces.max(longest);
    let (model, baseline) = random_weights(&cfg, &device).context("building the models")?;
    out(format_args!(
        "preset {} ({:.2}M parameters), {} threads, random weights, greedy",
        args.preset,
        cfg.parameter_count() as f64 / 1e6,
        candle_core::utils::get_num_threads()
    ))?;

    // Encoding: FPS on the CPU, then the encoder.
    // Points on a unit sphere; their positions double as normals (random weights, so only
    // the shapes of the tensors matter).
    let cloud = sample_surface(&uv_sphere(1.0, 64, 32), cfg.num_points, 0)?.vertices;
    let flat: Vec<f32> = cloud.iter().flatten().copied().collect();
    let points = Tensor::from_vec(flat, (1, cfg.num_points, 3), &device)?;
    let encode = || -> anyhow::Result<(f64, f64, Tensor)> {
        let t = Instant::now();
        let idx: Vec<u32> = farthest_point_sampling(&cloud, cfg.num_latents, 0)
            .into_iter()
            .map(|i| i as u32)
            .collect();
        let fps = t.elapsed().as_secs_f64();
        let idx = Tensor::from_vec(idx, (1, cfg.num_latents), &device)?;
        let latents = model.encode(&points, &points, &idx)?;
        Ok((fps, t.elapsed().as_secs_f64(), latents))
    };
    encode()?; // warm-up
    let runs = (0..3).map(|_| encode()).collect::<anyhow::Result<Vec<_>>>()?;
    let (fps, total) = runs.iter().fold((f64::MAX, f64::MAX), |(a, b), r| (a.min(r.0), b.min(r.1)));
    let latents = runs[0].2.clone();

    let mut table = super::table();
    table.set_header(vec!["measurement", "result"]);
    table.add_row(vec![
        format!(
            "encode one point cloud ({} points -> {} latents)",
            cfg.num_points, cfg.num_latents
        ),
        format!("{:.1} ms (FPS {:.1} ms), best of 3", total * 1e3, fps * 1e3),
    ]);
    decode_face(&model, &latents, 1, 8, false, 1)?; // warm-up
    for &b in &args.batches {
        let (secs, n, _) = decode_face(&model, &latents, b, args.faces, false, 1)?;
        table.add_row(vec![
            format!("FACE decode, batch {b} x {} faces", args.faces),
            format!("{:.0} faces/s aggregate ({:.2} s)", n as f64 / secs, secs),
        ]);
    }
    // What a greedy request costs: masks on, per-coordinate (beam 1) or the default beam.
    for &b in &args.batches {
        let mut rates = Vec::new();
        for beam in [1, DEFAULT_FACE_BEAM] {
            let (secs, n, _) = decode_face(&model, &latents, b, args.faces, true, beam)?;
            rates.push(n as f64 / secs);
        }
        table.add_row(vec![
            format!("FACE decode, batch {b}, masks on: face beam 1 vs {DEFAULT_FACE_BEAM}"),
            format!(
                "{:.0} vs {:.0} faces/s aggregate ({:.2}x)",
                rates[0],
                rates[1],
                rates[1] / rates[0]
            ),
        ]);
    }
    let mut cache_rows = Vec::new();
    for &faces in &args.compare {
        let (face_secs, _, face_cache) = decode_face(&model, &latents, 1, faces, false, 1)?;
        let (base_secs, base_cache) = decode_baseline(&baseline, &latents, faces)?;
        table.add_row(vec![
            format!("{faces} faces: FACE ({faces} steps) vs per-coordinate ({} steps)", 9 * faces),
            format!(
                "{:.2} s vs {:.2} s: speedup {:.1}x ({:.0} vs {:.0} faces/s)",
                face_secs,
                base_secs,
                base_secs / face_secs,
                faces as f64 / face_secs,
                faces as f64 / base_secs
            ),
        ]);
        cache_rows.push((faces, face_cache, base_cache));
    }
    for (faces, (face_self, face_cross), base_self) in cache_rows {
        table.add_row(vec![
            format!("KV cache per sequence at {faces} faces (allocated)"),
            format!(
                "FACE {} self-attn + {} cross-attn; per-coordinate {} self-attn",
                mib(face_self),
                mib(face_cross),
                mib(base_self)
            ),
        ]);
    }
    out(&table)?;
    Ok(())
}
