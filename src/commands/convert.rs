use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use meshstream::mesh::transform::rotation;
use meshstream::mesh::{Format, Normalization, write_mesh_file};
use meshstream::tokenize::{Quantizer, detokenize, tokenize_mesh, weld_near_corners};

use super::load_mesh;

#[derive(Args)]
pub struct ConvertArgs {
    /// The mesh to read (OBJ, PLY, STL, GLB/glTF).
    input: PathBuf,
    /// Where to write it; the format comes from the extension unless --format is given.
    output: PathBuf,
    /// Output format: obj, ply, stl or glb.
    #[arg(long)]
    format: Option<Format>,
    /// Turn the mesh about the vertical axis (y) by this many degrees first: to see how a
    /// model does on a mesh whose walls are not on the axes.
    #[arg(long, value_name = "DEGREES", allow_hyphen_values = true)]
    turn: Option<f32>,
    /// Snap to the FACE quantization grid with Q levels per axis (128 to 1024): welds
    /// vertices, drops collapsed and repeated faces, splits each flat convex polygon as a fan
    /// from its smallest corner (as training data is), and keeps the input's coordinates.
    #[arg(long, value_name = "Q")]
    quantize: Option<u16>,
    /// With --quantize: then merge corners within this many grid cells of each other on
    /// every axis and split faces at corners this close to their open edges, as
    /// reconstructions do (`reconstruct --weld-radius`): what welding would do to a right mesh.
    #[arg(long, value_name = "CELLS", default_value_t = 0, requires = "quantize")]
    weld_radius: u16,
    /// Move the result into the models' frame (bounding box centred at the origin, longest
    /// side from -1 to 1), where meshes generated from images are: to compare them.
    #[arg(long)]
    normalize: bool,
}

pub fn run(args: &ConvertArgs) -> anyhow::Result<()> {
    let mut mesh = load_mesh(&args.input)?;
    if let Some(degrees) = args.turn {
        anyhow::ensure!(degrees.is_finite(), "--turn {degrees} is not a number of degrees");
        mesh = mesh.transformed(&rotation([0.0, 1.0, 0.0], degrees.to_radians()), [0.0; 3]);
    }
    if let Some(levels) = args.quantize {
        let q = Quantizer::new(levels)?;
        let (tokenized, normalization) = tokenize_mesh(&mesh, q).context("quantizing")?;
        let before = mesh.faces.len();
        let faces = weld_near_corners(&tokenized.faces, args.weld_radius);
        if args.weld_radius > 0 {
            eprintln!(
                "welded within {} cells: {} faces -> {}",
                args.weld_radius,
                tokenized.faces.len(),
                faces.len()
            );
        }
        mesh = normalization.invert_mesh(&detokenize(&faces, q));
        eprintln!(
            "quantized to Q = {levels}: {before} faces -> {} ({} collapsed, {} repeated)",
            mesh.faces.len(),
            tokenized.collapsed_faces,
            tokenized.duplicate_faces
        );
    }
    if args.normalize {
        mesh = Normalization::fit(&mesh.vertices).context("normalizing")?.apply_mesh(&mesh);
    }
    write_mesh_file(&mesh, &args.output, args.format)
        .with_context(|| format!("writing {}", args.output.display()))?;
    eprintln!(
        "wrote {} ({} vertices, {} faces)",
        args.output.display(),
        mesh.vertices.len(),
        mesh.faces.len()
    );
    Ok(())
}
