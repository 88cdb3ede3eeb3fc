//! A folder of meshes as training data: every mesh file in it, or the rows of its
//! `manifest.csv` with a given split, each stood on y when its source puts another axis up.
//! Meshes that fail to parse, are degenerate, or exceed the face limit after quantization are
//! skipped and counted, never fatal.

use std::path::{Path, PathBuf};
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use crate::mesh::{Mesh, ReadLimits, UpAxis, mesh_files_in, read_mesh_file};
use crate::tokenize::{Quantizer, tokenize_mesh};

use super::TrainError;

/// One usable mesh, kept in its own normalized frame.
#[derive(Debug, Clone)]
pub struct MeshRecord {
    pub name: String,
    pub mesh: Mesh,
    /// Faces after quantization (without augmentation).
    pub faces: usize,
}

/// What was left out of a folder, and why.
#[derive(Debug, Default, Clone, Serialize)]
pub struct Skipped {
    /// File name and error.
    pub unreadable: Vec<(String, String)>,
    pub no_faces: usize,
    pub over_face_limit: usize,
}

#[derive(Debug, Clone)]
pub struct FolderData {
    pub meshes: Vec<MeshRecord>,
    pub skipped: Skipped,
}

/// Which meshes of a folder have another axis than y up: the files whose names start with a
/// prefix. Why: a data set gathered from several sources keeps each one's convention, and
/// training turns meshes about y only, so a z-up source is learnt lying. The low-poly set's
/// Kenney kits stand on z = 0 (1,084 of its 3,984 meshes; `docs/decisions.md`, "The caller
/// says which axis is up").
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct UpAxes(pub Vec<UpRule>);

/// Files whose names start with `prefix` have `up` up.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct UpRule {
    pub prefix: String,
    pub up: UpAxis,
}

impl FromStr for UpRule {
    type Err = String;

    /// `PREFIX=AXIS`, for example `kenney-road=z`.
    fn from_str(rule: &str) -> Result<Self, String> {
        let (prefix, up) = rule
            .rsplit_once('=')
            .ok_or_else(|| format!("{rule:?}: write PREFIX=AXIS, for example kenney-road=z"))?;
        Ok(Self { prefix: prefix.to_string(), up: up.parse()? })
    }
}

impl UpAxes {
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// The up axis of the file `name`: the first rule whose prefix it starts with, else y.
    pub fn of(&self, name: &str) -> UpAxis {
        self.0.iter().find(|r| name.starts_with(&r.prefix)).map_or(UpAxis::Y, |r| r.up)
    }

    /// `mesh`, the file `name`, stood on y.
    fn stood_up(&self, name: &str, mesh: Mesh) -> Mesh {
        let up = self.of(name);
        if up == UpAxis::Y {
            return mesh;
        }
        let turn = |v: &[[f32; 3]]| v.iter().map(|&p| up.to_y_up(p)).collect();
        Mesh {
            vertices: turn(&mesh.vertices),
            normals: mesh.normals.as_deref().map(turn),
            faces: mesh.faces,
        }
    }
}

/// Loads `dir`. With `split` and a `manifest.csv` in the folder (columns `file` and `split`),
/// only that split's rows; otherwise every mesh file in the folder. Each mesh is stood on y as
/// `up` says.
pub fn load_folder(
    dir: &Path,
    split: Option<&str>,
    max_faces: usize,
    q: Quantizer,
    up: &UpAxes,
) -> Result<FolderData, TrainError> {
    let manifest = dir.join("manifest.csv");
    let files = match split {
        Some(split) if manifest.is_file() => manifest_files(&manifest, split)?,
        _ => mesh_files_in(dir)?,
    };
    let mut data = FolderData { meshes: Vec::new(), skipped: Skipped::default() };
    let limits = ReadLimits::default();
    for path in files {
        let name = path.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let mesh = match read_mesh_file(&path, &limits) {
            Ok(mesh) if mesh.faces.is_empty() => {
                data.skipped.no_faces += 1;
                continue;
            }
            Ok(mesh) => up.stood_up(&name, mesh),
            Err(err) => {
                data.skipped.unreadable.push((name, err.to_string()));
                continue;
            }
        };
        match tokenize_mesh(&mesh, q) {
            Ok((tokens, _)) if tokens.faces.is_empty() => data.skipped.no_faces += 1,
            Ok((tokens, _)) if tokens.faces.len() > max_faces => data.skipped.over_face_limit += 1,
            Ok((tokens, normalization)) => data.meshes.push(MeshRecord {
                name,
                mesh: normalization.apply_mesh(&mesh),
                faces: tokens.faces.len(),
            }),
            Err(err) => data.skipped.unreadable.push((name, err.to_string())),
        }
    }
    Ok(data)
}

/// The files of one split listed in a manifest, resolved next to it.
fn manifest_files(manifest: &Path, split: &str) -> Result<Vec<PathBuf>, TrainError> {
    let bad = |message: String| TrainError::Manifest { path: manifest.to_path_buf(), message };
    let mut reader = csv::Reader::from_path(manifest).map_err(|e| bad(e.to_string()))?;
    let headers = reader.headers().map_err(|e| bad(e.to_string()))?.clone();
    let column = |name: &str| {
        headers.iter().position(|h| h == name).ok_or_else(|| bad(format!("no '{name}' column")))
    };
    let (file_col, split_col) = (column("file")?, column("split")?);
    let dir = manifest.parent().unwrap_or(Path::new("."));
    let mut files = Vec::new();
    for row in reader.records() {
        let row = row.map_err(|e| bad(e.to_string()))?;
        if row.get(split_col) == Some(split)
            && let Some(file) = row.get(file_col)
        {
            files.push(dir.join(file));
        }
    }
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::cuboid;
    use crate::mesh::{Format, write_mesh_file};

    #[test]
    fn manifest_split_and_skips_are_counted() {
        let dir = tempfile::tempdir().unwrap();
        let write = |name: &str, mesh: &Mesh| {
            write_mesh_file(mesh, &dir.path().join(name), Some(Format::Ply)).unwrap()
        };
        write("a.ply", &cuboid([1.0, 2.0, 3.0]));
        write("b.ply", &crate::mesh::primitives::uv_sphere(1.0, 32, 16));
        write("c.ply", &cuboid([1.0; 3]));
        std::fs::write(dir.path().join("broken.ply"), b"ply\nformat nonsense\n").unwrap();
        std::fs::write(
            dir.path().join("manifest.csv"),
            "file,split\na.ply,train\nb.ply,train\nbroken.ply,train\nc.ply,dev\n",
        )
        .unwrap();
        let q = Quantizer::new(128).unwrap();
        let train = load_folder(dir.path(), Some("train"), 100, q, &UpAxes::default()).unwrap();
        assert_eq!(train.meshes.len(), 1);
        assert_eq!(train.meshes[0].name, "a.ply");
        assert_eq!(train.meshes[0].faces, 12);
        assert_eq!(train.skipped.over_face_limit, 1);
        assert_eq!(train.skipped.unreadable.len(), 1);
        let dev = load_folder(dir.path(), Some("dev"), 100, q, &UpAxes::default()).unwrap();
        assert_eq!(dev.meshes.len(), 1);
        // Without a split: every mesh file in the folder.
        let all = load_folder(dir.path(), None, 10_000, q, &UpAxes::default()).unwrap();
        assert_eq!(all.meshes.len(), 3);
    }

    #[test]
    fn meshes_of_a_z_up_source_are_stood_on_y() {
        let dir = tempfile::tempdir().unwrap();
        // A tall box standing on z (z up), and the same box standing on y.
        let tall = cuboid([1.0, 0.5, 4.0]).translated([0.0, 0.0, 2.0]);
        write_mesh_file(&tall, &dir.path().join("kit-z__box.ply"), Some(Format::Ply)).unwrap();
        let standing = cuboid([1.0, 4.0, 0.5]).translated([0.0, 2.0, 0.0]);
        write_mesh_file(&standing, &dir.path().join("kit-y__box.ply"), Some(Format::Ply)).unwrap();
        let q = Quantizer::new(128).unwrap();
        let up = UpAxes(vec!["kit-z=z".parse().unwrap()]);
        let mut folder = load_folder(dir.path(), None, 100, q, &up).unwrap();
        folder.meshes.sort_by(|a, b| a.name.cmp(&b.name));
        let [y, z] = [&folder.meshes[0].mesh, &folder.meshes[1].mesh];
        // Both stand on y, as tall as 2 in the normalized frame, and face the same way.
        for mesh in [y, z] {
            let (lo, hi) = mesh.bounds().unwrap();
            assert_eq!((lo[1], hi[1]), (-1.0, 1.0), "{lo:?} {hi:?}");
        }
        assert!((z.area() - y.area()).abs() < 1e-4);
        assert_eq!(up.of("kit-y__box.ply"), UpAxis::Y);
        assert!("kit-z".parse::<UpRule>().is_err());
        assert!("kit-z=w".parse::<UpRule>().is_err());
    }

    #[test]
    fn shared_lowpoly_dev_split_loads() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/lowpoly");
        if !dir.is_dir() {
            eprintln!("skipped: {} is absent", dir.display());
            return;
        }
        let dev =
            load_folder(&dir, Some("dev"), 4000, Quantizer::new(128).unwrap(), &UpAxes::default())
                .unwrap();
        assert!(dev.skipped.unreadable.is_empty(), "{:?}", dev.skipped.unreadable);
        assert!(dev.meshes.len() >= 80, "{} dev meshes", dev.meshes.len());
    }
}
