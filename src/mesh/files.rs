use std::path::{Path, PathBuf};

use super::{Format, MeshError};

/// The mesh files directly inside `dir` (every format we read, by extension), sorted by name
/// so that every listing of a folder is the same.
pub fn mesh_files_in(dir: &Path) -> Result<Vec<PathBuf>, MeshError> {
    let io = |error| MeshError::Io { path: dir.to_path_buf(), error };
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let path = entry.map_err(io)?.path();
        if path.is_file() && Format::from_path(&path).is_some() {
            files.push(path);
        }
    }
    files.sort();
    Ok(files)
}

/// Expands a list of files and folders into mesh files: a folder stands for the mesh files
/// inside it; a file is taken as it is (its reader reports what is wrong with it).
pub fn expand_mesh_paths(paths: &[PathBuf]) -> Result<Vec<PathBuf>, MeshError> {
    let mut out = Vec::new();
    for path in paths {
        if path.is_dir() {
            out.extend(mesh_files_in(path)?);
        } else {
            out.push(path.clone());
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lists_only_mesh_files_sorted() {
        let dir = tempfile::tempdir().unwrap();
        for name in ["b.ply", "a.OBJ", "notes.txt", "c.glb", "d.stl"] {
            std::fs::write(dir.path().join(name), b"").unwrap();
        }
        std::fs::create_dir(dir.path().join("sub.ply")).unwrap();
        let names: Vec<String> = mesh_files_in(dir.path())
            .unwrap()
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["a.OBJ", "b.ply", "c.glb", "d.stl"]);
    }

    #[test]
    fn missing_folder_is_an_io_error() {
        let err = mesh_files_in(Path::new("/no/such/folder")).unwrap_err();
        assert!(matches!(err, MeshError::Io { .. }), "{err}");
    }
}
