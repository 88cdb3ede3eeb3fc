use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use meshstream::candidates::{
    DEFAULT_CANDIDATES, DEFAULT_HULL_FACES, DEFAULT_WELD_RADIUS, Ending, MAX_WELD_RADIUS,
};
use meshstream::mesh::{
    DEFAULT_MAX_HOLE_EDGES, FitOptions, MAX_HOLE_EDGES, REFERENCE_POINTS, UpAxis, input_clouds,
};
use meshstream::model::{Quantize, parse_device};

use super::decode::{DecodeArgs, FromPoints, decode, write_decoded};
use super::{candidate_count, load_face_model, normalized_input, point_count};

#[derive(Args)]
pub struct ReconstructArgs {
    /// A point cloud (PLY/OBJ with vertices only; normals used when present, estimated when
    /// not) or a mesh (its surface is sampled). The mesh is written in its coordinates.
    input: PathBuf,
    #[command(flatten)]
    decode: DecodeArgs,
    /// Model folder (config.json + model.safetensors).
    #[arg(long, env = "MESHSTREAM_MODEL", default_value = "models/default")]
    model: PathBuf,
    /// Seed of the point sampling and of the decoding when it samples.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// cpu or cuda:N (with --features cuda).
    #[arg(long, default_value = "cpu")]
    device: String,
    /// Decode this many meshes, each from its own draw of the input's points (the first as
    /// asked; greedy ones when greedy, else one greedy and the rest sampled), and keep the one
    /// that ends closest to the input points: better meshes for more decoding work; 1 decodes
    /// one mesh.
    #[arg(long, default_value_t = DEFAULT_CANDIDATES, value_parser = candidate_count())]
    candidates: usize,
    /// Rounds of moving each candidate's corners to fit the input points before they are
    /// judged (the same faces, flat polygons split again for the moved corners); the winner
    /// then drops the faces that lie on other faces and the connected parts the points do not
    /// need. 0 keeps the corners where the model put them, and every face.
    #[arg(long, default_value_t = FitOptions::default().rounds)]
    fit_rounds: usize,
    /// Merge each candidate's corners that lie within this many grid cells of each other on
    /// every axis, and split its faces at corners this close to their open edges, before
    /// fitting (at most 4): closes the cracks between faces that should share a corner or an
    /// edge; 0 keeps them as decoded.
    #[arg(long, default_value_t = DEFAULT_WELD_RADIUS,
          value_parser = clap::value_parser!(u16).range(..=i64::from(MAX_WELD_RADIUS)))]
    weld_radius: u16,
    /// Close a fitted mesh's loops of at most this many open edges where the input points
    /// cover them, with new faces wound like those around; below 3 leaves every hole open.
    #[arg(long, default_value_t = DEFAULT_MAX_HOLE_EDGES as u64,
          value_parser = clap::value_parser!(u64).range(..=MAX_HOLE_EDGES as u64))]
    max_hole_edges: u64,
    /// The furthest fitting may move a corner, in units of half the input's longest side.
    #[arg(long, default_value_t = FitOptions::default().max_shift)]
    fit_max_shift: f32,
    /// A fit ends before --fit-rounds once this many rounds in a row moved its corners no
    /// less on average than an earlier round had; 0 runs every round.
    #[arg(long, default_value_t = FitOptions::default().patience)]
    fit_patience: usize,
    /// The most input points the candidates are judged and the corners fitted against (the
    /// encoder takes the model's num_points of them): a mesh's surface is sampled this often,
    /// a larger cloud subsampled.
    #[arg(long, default_value_t = REFERENCE_POINTS, value_parser = point_count())]
    reference_points: usize,
    /// Number format of the model's linear layers: f32, q8_0 or q4k (quantized when the model
    /// loads; the encoder and layers whose inputs do not fit the blocks stay f32).
    #[arg(long, default_value_t = Quantize::F32)]
    quantize: Quantize,
    /// The input's up axis: y (glTF's), z (Blender, CAD, most scans), x, or one of them
    /// negated. The model's training shapes mostly stand on +y: the input is turned onto it,
    /// and the mesh written turned back.
    #[arg(long, default_value = "y")]
    up: UpAxis,
    /// A fitted reconstruction judges the convex hull of the input points, with at most this many
    /// faces (and --max-faces), beside its decoded candidates, and answers with it when it ends at
    /// least 10% closer to the points (finish reason convex_hull); 0 never.
    #[arg(long, default_value_t = DEFAULT_HULL_FACES)]
    hull_faces: usize,
}

pub fn run(args: &ReconstructArgs) -> anyhow::Result<()> {
    let device = parse_device(&args.device)?;
    let (model, report) = load_face_model(&args.model, &device, args.quantize)?;
    if report.quantize != Quantize::F32 {
        eprintln!("{report}");
    }
    let cfg = model.config().clone();
    let (input, normalization) = normalized_input(&args.input, args.up)?;
    // A draw of the input's points per candidate (see `meshstream::candidates`).
    let clouds = input_clouds(
        &input,
        cfg.num_points,
        cfg.point_oversampling,
        args.reference_points,
        args.seed,
        args.candidates,
    )
    .context("preparing the input points")?;
    let start = Instant::now();
    let latents = clouds
        .encoder
        .iter()
        .map(|cloud| model.encode_point_cloud(cloud))
        .collect::<Result<Vec<_>, _>>()?;
    let fit = FitOptions {
        rounds: args.fit_rounds,
        max_shift: args.fit_max_shift,
        patience: args.fit_patience,
        ..FitOptions::default()
    };
    let fit = (fit.rounds > 0).then_some(fit);
    let ending = Ending {
        weld_radius: args.weld_radius,
        fit,
        max_hole_edges: args.max_hole_edges as usize,
        hull_faces: Ending::hull_faces_for(
            fit,
            args.hull_faces,
            args.decode.max_faces.unwrap_or(cfg.max_faces),
        ),
    };
    let from_points = FromPoints { cloud: &clouds.reference, candidates: args.candidates, ending };
    let decoded = decode(&model, &latents, &args.decode, Some(from_points), args.seed)?;
    let input = Some(&clouds.reference.vertices[..]);
    write_decoded(decoded, &args.decode, normalization, input, start)
}
