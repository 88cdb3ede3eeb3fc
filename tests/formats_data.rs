//! Every mesh of the shared data set parses, with the vertex and face counts its manifest
//! lists. Skips (with a message) when the data is not there.

use std::path::{Path, PathBuf};

use meshstream::mesh::{ReadLimits, read_mesh_file};

fn data_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data")
}

/// `(file, vertices, faces)` for each row of a folder's manifest.csv.
fn manifest(folder: &Path) -> Vec<(String, usize, usize)> {
    let text = std::fs::read_to_string(folder.join("manifest.csv")).unwrap();
    let mut rows = text.lines();
    let header: Vec<&str> = rows.next().unwrap().split(',').collect();
    let column = |name: &str| header.iter().position(|c| *c == name).unwrap();
    let (file, vertices, faces) = (column("file"), column("vertices"), column("faces"));
    rows.filter(|r| !r.is_empty())
        .map(|row| {
            let cells: Vec<&str> = row.split(',').collect();
            assert_eq!(cells.len(), header.len(), "row {row:?}");
            (
                cells[file].to_owned(),
                cells[vertices].parse().unwrap(),
                cells[faces].parse().unwrap(),
            )
        })
        .collect()
}

#[test]
fn every_data_set_mesh_matches_its_manifest() {
    let data = data_dir();
    if !data.is_dir() {
        println!("SKIPPED: no data set at {} (the shared data folder is absent)", data.display());
        return;
    }
    let limits = ReadLimits::default();
    for folder in ["lowpoly", "famous-dev"] {
        let folder = data.join(folder);
        let rows = manifest(&folder);
        assert!(!rows.is_empty(), "{}: empty manifest", folder.display());
        for (file, vertices, faces) in &rows {
            let mesh = read_mesh_file(&folder.join(file), &limits)
                .unwrap_or_else(|e| panic!("{file}: {e}"));
            assert_eq!((mesh.vertices.len(), mesh.faces.len()), (*vertices, *faces), "{file}");
            mesh.validate().unwrap();
        }
        println!("{}: {} meshes match the manifest", folder.display(), rows.len());
    }
}
