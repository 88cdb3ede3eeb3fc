//! One module per subcommand of `meshstream`.

pub mod bench;
pub mod convert;
pub mod eval;
pub mod sample;
pub mod stats;

use std::path::Path;

use anyhow::Context;
use meshstream::mesh::{Mesh, ReadLimits, read_mesh_file};

/// Reads a mesh with the default limits, naming the file in the error.
pub fn load_mesh(path: &Path) -> anyhow::Result<Mesh> {
    read_mesh_file(path, &ReadLimits::default())
        .with_context(|| format!("reading {}", path.display()))
}

/// A file's name without its folder, for tables.
pub fn display_name(path: &Path) -> String {
    path.file_name()
        .map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned())
}
