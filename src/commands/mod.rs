//! One module per subcommand of `meshstream`.

pub mod bench;
pub mod bench_decode;
pub mod convert;
pub mod eval;
pub mod reconstruct;
pub mod render;
pub mod sample;
pub mod serve;
pub mod stats;

use std::path::Path;

use anyhow::Context;
use meshstream::mesh::{Mesh, ReadLimits, read_mesh_file};

/// Reads a mesh with the default limits, naming the file in the error.
pub fn load_mesh(path: &Path) -> anyhow::Result<Mesh> {
    read_mesh_file(path, &ReadLimits::default())
        .with_context(|| format!("reading {}", path.display()))
}

/// A table printed as Markdown, so figures paste straight into notes and model cards.
pub fn table() -> comfy_table::Table {
    let mut table = comfy_table::Table::new();
    table.load_style(comfy_table::presets::ASCII_MARKDOWN);
    table
}

/// A file's name without its folder, for tables.
pub fn display_name(path: &Path) -> String {
    path.file_name()
        .map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned())
}
