//! Benchmarks that print a table. Timings on shared 2-core machines are noisy: compare the
//! figures of one run with each other, never against a fixed threshold.

use std::hint::black_box;
use std::time::{Duration, Instant};

use clap::Subcommand;
use meshstream::candidates::{DEFAULT_HULL_FACES, hull_candidate, lighter_hull};
use meshstream::mesh::{
    DEFAULT_MAX_HOLE_EDGES, FitOptions, FitTarget, Format, Mesh, REFERENCE_POINTS, ReadLimits,
    farthest_point_sampling, fit_to_points, input_clouds, primitives, read_mesh, sample_surface,
    with_faces_facing_out, with_small_holes_filled, without_folded_faces, without_stray_parts,
    without_stray_sheets, write_mesh,
};
use meshstream::metrics::{MeshQuality, MetricOptions, mesh_distances};
use meshstream::render::{RenderOptions, render_grid};
use meshstream::tokenize::{Quantizer, tokenize_mesh};

use super::out;

#[derive(Subcommand)]
pub enum BenchCommand {
    /// Parsing, tokenization, farthest point sampling, evaluation and fitting.
    Mesh {
        /// Minimum time spent on each measurement, in seconds.
        #[arg(long, default_value_t = 1.0)]
        seconds: f64,
    },
    /// Decoding speed of the FACE model (random weights) against the per-coordinate baseline.
    Decode(super::bench_decode::DecodeBenchArgs),
    /// A real server in this process under 1, 4 and 16 concurrent gRPC clients: throughput
    /// and time to first face.
    Serve(super::bench_serve::ServeBenchArgs),
    /// Sustained mixed traffic against a `serve` process (HTTP and gRPC, whole meshes and
    /// streams, clients that leave, garbage, retries after 429): what completed, what was
    /// refused and why, what was lost, latencies and the server's memory.
    Soak(super::bench_soak::SoakArgs),
    /// The image model: one diffusion step at batch 1 and 8, and whole image requests.
    Diffusion(super::bench_diffusion::DiffusionBenchArgs),
    /// Software rendering of a 5,000-face mesh at a few image sizes.
    Render {
        /// Minimum time spent on each measurement, in seconds.
        #[arg(long, default_value_t = 1.0)]
        seconds: f64,
    },
}

pub fn run(cmd: &BenchCommand) -> anyhow::Result<()> {
    match cmd {
        BenchCommand::Mesh { seconds } => bench_mesh(Duration::from_secs_f64(*seconds)),
        BenchCommand::Decode(args) => super::bench_decode::run(args),
        BenchCommand::Serve(args) => super::bench_serve::run(args),
        BenchCommand::Soak(args) => super::bench_soak::run(args),
        BenchCommand::Diffusion(args) => super::bench_diffusion::run(args),
        BenchCommand::Render { seconds } => bench_render(Duration::from_secs_f64(*seconds)),
    }
}

/// Runs `f` until `budget` has passed (at least once) and returns the mean time per run.
fn time_per_run<T>(budget: Duration, mut f: impl FnMut() -> T) -> Duration {
    let start = Instant::now();
    let mut runs = 0u32;
    while runs == 0 || start.elapsed() < budget {
        black_box(f());
        runs += 1;
    }
    start.elapsed() / runs
}

/// A row of a timing table: what ran on which input, its time per run and how many `unit` it
/// handles a second, doing `per_run` of them a run.
fn timed_row(
    what: impl Into<String>,
    input: impl Into<String>,
    t: Duration,
    per_run: f64,
    unit: &str,
) -> [String; 4] {
    let (ms, rate) = (t.as_secs_f64() * 1e3, per_run / t.as_secs_f64());
    let ms = if ms < 10.0 { format!("{ms:.2} ms") } else { format!("{ms:.1} ms") };
    let rate =
        if rate < 100.0 { format!("{rate:.1} {unit}/s") } else { format!("{rate:.0} {unit}/s") };
    [what.into(), input.into(), ms, rate]
}

fn bench_mesh(budget: Duration) -> anyhow::Result<()> {
    // A dense, closed test surface: 512 x 256 UV sphere, about 262,000 faces.
    let dense = primitives::uv_sphere(1.0, 512, 256);
    let faces = dense.faces.len();
    let mut table = super::table();
    table.set_header(["measurement", "input", "time per run", "throughput"]);

    let limits = ReadLimits::default();
    for format in Format::ALL {
        let bytes = write_mesh(&dense, format)?;
        let t = time_per_run(budget, || read_mesh(&bytes, format, &limits));
        let mb = bytes.len() as f64 / 1e6;
        table.add_row(timed_row(
            format!("parse {format}"),
            format!("{faces} faces, {mb:.1} MB"),
            t,
            mb,
            "MB",
        ));
    }

    let q = Quantizer::new(meshstream::tokenize::DEFAULT_LEVELS)?;
    let t = time_per_run(budget, || tokenize_mesh(&dense, q));
    table.add_row(timed_row(
        "tokenize (normalize, quantize, weld, split, order)",
        format!("{faces} faces, Q = {}", q.levels()),
        t,
        faces as f64 / 1e6,
        "M faces",
    ));

    let cloud = sample_surface(&dense, 65_536, 0)?;
    let t = time_per_run(budget, || farthest_point_sampling(&cloud.vertices, 2048, 0));
    table.add_row(timed_row(
        "farthest point sampling",
        "2,048 of 65,536 points",
        t,
        65_536.0 / 1e3,
        "K points",
    ));

    // What a request's input costs before the model sees it: the encoder's 1,024 points
    // (drawn independently, or spread over 4 times as many) and the reference, from a mesh
    // and from a cloud with normals.
    let points = Mesh { faces: Vec::new(), ..cloud.clone() };
    for (input, what) in [(&dense, format!("{faces} faces")), (&points, "65,536 points".into())] {
        for oversampling in [1, 4] {
            let t = time_per_run(budget, || {
                input_clouds(input, 1024, oversampling, REFERENCE_POINTS, 0, 1)
            });
            table.add_row(timed_row(
                format!("input points (oversampling {oversampling})"),
                format!("{what} -> 1,024 + {REFERENCE_POINTS}"),
                t,
                1.0,
                "inputs",
            ));
        }
    }

    let pred = primitives::uv_sphere(1.1, 64, 32);
    let gt = primitives::uv_sphere(1.0, 256, 128);
    let opts = MetricOptions::default();
    let t = time_per_run(budget, || mesh_distances(&pred, &gt, &opts));
    table.add_row(timed_row(
        "eval one pair (sample, k-d trees, CD + HD)",
        format!("N = {} points per surface", opts.samples),
        t,
        1.0,
        "pairs",
    ));

    // What a reconstruction's fitting does: a 400-face mesh (the model's size) off its points
    // by a scale and a shift, fitted to an encoder's 1,024 points and to the reference's.
    let truth = primitives::uv_sphere(0.9, 20, 11);
    let off = primitives::uv_sphere(0.8, 20, 11).translated([0.05, 0.0, 0.0]);
    let fit = FitOptions::default();
    for n in [1024, REFERENCE_POINTS] {
        let points = sample_surface(&truth, n, 0)?;
        let t = time_per_run(budget, || fit_to_points(&off, &points, &fit, 0));
        table.add_row(timed_row(
            format!("fit to points ({} rounds)", fit.rounds),
            format!("{} faces, {n} points", off.faces.len()),
            t,
            fit.rounds as f64,
            "rounds",
        ));
    }

    // What a fitted reconstruction's end costs for its parts: the sphere with small cubes
    // inside it, each weighed against the sphere's own points (so each goes).
    let points = sample_surface(&truth, REFERENCE_POINTS, 0)?.vertices;
    for strays in [4, 16] {
        let mut cluttered = truth.clone();
        for i in 0..strays {
            let cube = primitives::cuboid([0.1; 3]).translated([0.02 * i as f32, 0.0, 0.0]);
            cluttered.append(&cube);
        }
        let t = time_per_run(budget, || without_stray_parts(&cluttered, &points, 0));
        table.add_row(timed_row(
            "stray parts",
            format!(
                "{} faces, {strays} in cubes inside, {REFERENCE_POINTS} points",
                cluttered.faces.len()
            ),
            t,
            strays as f64,
            "parts",
        ));
    }
    // Fins off the sphere's edges, each a sheet of one face the points do not need.
    for fins in [4, 16] {
        let mut finned = truth.clone();
        for i in 0..fins {
            let [a, b, _] = truth.faces[i * truth.faces.len() / fins];
            let [p, q] = [a, b].map(|v| truth.vertices[v as usize]);
            finned.vertices.push(std::array::from_fn(|k| 0.65 * (p[k] + q[k])));
            finned.faces.push([b, a, finned.vertices.len() as u32 - 1]);
        }
        let t = time_per_run(budget, || without_stray_sheets(&finned, &points, 0));
        table.add_row(timed_row(
            "stray sheets",
            format!(
                "{} faces, {fins} fins off its edges, {REFERENCE_POINTS} points",
                finned.faces.len()
            ),
            t,
            fins as f64,
            "sheets",
        ));
    }
    // The convex hull a fitted request judges beside its candidates, in both its forms (each
    // fitted as timed above).
    let reference = Mesh::new(points.clone(), Vec::new());
    let t = time_per_run(budget, || {
        hull_candidate(&reference, q, DEFAULT_HULL_FACES).map(|hull| lighter_hull(&hull))
    });
    table.add_row(timed_row(
        "convex hull candidate",
        format!(
            "{REFERENCE_POINTS} points -> at most {DEFAULT_HULL_FACES} faces on the grid, and \
             its lighter form"
        ),
        t,
        1.0,
        "hulls",
    ));
    // A whole mesh decoded twice over: every edge non-manifold, every face lying on another.
    let mut twice = truth.clone();
    twice.append(&truth);
    let t = time_per_run(budget, || without_folded_faces(&twice));
    table.add_row(timed_row(
        "folded faces",
        format!("{} faces, each twice", truth.faces.len()),
        t,
        twice.faces.len() as f64,
        "faces",
    ));
    // Holes to close: every eighth face of the sphere gone, each a loop of 3 on its points.
    let target = FitTarget::new(&sample_surface(&truth, REFERENCE_POINTS, 0)?)?;
    let holed = Mesh {
        faces: truth
            .faces
            .iter()
            .enumerate()
            .filter(|(i, _)| i % 8 != 0)
            .map(|(_, f)| *f)
            .collect(),
        ..truth.clone()
    };
    let missing = truth.faces.len() - holed.faces.len();
    let (_, closed) = with_small_holes_filled(&holed, &target, DEFAULT_MAX_HOLE_EDGES);
    let t =
        time_per_run(budget, || with_small_holes_filled(&holed, &target, DEFAULT_MAX_HOLE_EDGES));
    table.add_row(timed_row(
        "small holes",
        format!(
            "{} faces, {missing} missing as {closed} loops, {REFERENCE_POINTS} points",
            holed.faces.len()
        ),
        t,
        closed as f64,
        "loops",
    ));
    // Faces to turn: a third of the sphere's faces wound inward.
    let mut scrambled = truth.clone();
    scrambled.faces.iter_mut().step_by(3).for_each(|f| f.swap(1, 2));
    let t = time_per_run(budget, || with_faces_facing_out(&scrambled));
    table.add_row(timed_row(
        "faces facing out",
        format!("{} faces, a third wound inward", scrambled.faces.len()),
        t,
        scrambled.faces.len() as f64,
        "faces",
    ));
    // What every answer adds to its request: its build and its distance to the input points.
    let t = time_per_run(budget, || MeshQuality::measure(&truth, Some(&points)));
    table.add_row(timed_row(
        "answer quality (edges, parts, input CD)",
        format!("{} faces, {REFERENCE_POINTS} points", truth.faces.len()),
        t,
        1.0,
        "answers",
    ));
    out(&table)?;
    Ok(())
}

fn bench_render(budget: Duration) -> anyhow::Result<()> {
    // 64 x 40 UV sphere: 4,992 faces, about the size of a large artist mesh.
    let mesh = primitives::uv_sphere(1.0, 64, 40);
    let faces = mesh.faces.len();
    let mut table = super::table();
    table.set_header(["measurement", "input", "time per image", "throughput"]);
    for side in [128, 256, 512] {
        let options = RenderOptions { width: side, height: side, ..RenderOptions::default() };
        for (name, views) in [("render one view", 1), ("render a grid of 4 views", 4)] {
            let t = time_per_run(budget, || render_grid(&mesh, &options, views));
            table.add_row(timed_row(
                name.to_string(),
                format!("{faces} faces, {side}x{side} per view"),
                t,
                f64::from(views),
                "views",
            ));
        }
    }
    out(&table)?;
    Ok(())
}
