use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use meshstream::mesh::{Format, Normalization, write_mesh_file};
use meshstream::tokenize::{Quantizer, detokenize, tokenize_mesh};

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
    /// Snap to the FACE quantization grid with Q levels per axis (128 to 1024): welds
    /// vertices, drops collapsed and repeated faces, and keeps the input's coordinates.
    #[arg(long, value_name = "Q")]
    quantize: Option<u16>,
    /// Move the result into the models' frame (bounding box centred at the origin, longest
    /// side from -1 to 1), where meshes generated from images are: to compare them.
    #[arg(long)]
    normalize: bool,
}

pub fn run(args: &ConvertArgs) -> anyhow::Result<()> {
    let mut mesh = load_mesh(&args.input)?;
    if let Some(levels) = args.quantize {
        let q = Quantizer::new(levels)?;
        let (tokenized, normalization) = tokenize_mesh(&mesh, q).context("quantizing")?;
        let before = mesh.faces.len();
        mesh = normalization.invert_mesh(&detokenize(&tokenized.faces, q));
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
