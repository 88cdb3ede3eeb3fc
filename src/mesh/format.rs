//! The file formats we read and write, how to tell them apart, and the entry points that
//! dispatch to each format's reader and writer.

use std::fmt;
use std::path::Path;
use std::str::FromStr;

use super::{Mesh, MeshError, ReadLimits, gltf_read, gltf_write, obj, ply, stl};

/// A mesh file format. `Gltf` covers both glTF 2.0 forms: we read `.gltf` (JSON) and `.glb`,
/// and always write `.glb`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Format {
    Obj,
    Ply,
    Stl,
    Gltf,
}

impl Format {
    pub const ALL: [Format; 4] = [Format::Obj, Format::Ply, Format::Stl, Format::Gltf];

    /// The format a file name's extension names (case-insensitive).
    pub fn from_path(path: &Path) -> Option<Format> {
        path.extension()?.to_str()?.parse().ok()
    }

    /// The format an HTTP content type names; parameters such as `; charset=utf-8` are ignored.
    pub fn from_content_type(ct: &str) -> Option<Format> {
        let essence = ct.split(';').next().unwrap_or_default().trim().to_ascii_lowercase();
        Some(match essence.as_str() {
            "model/obj" | "text/x-obj" | "application/x-tgif" => Format::Obj,
            "application/ply" | "model/ply" | "text/x-ply" | "application/x-ply" => Format::Ply,
            "model/stl"
            | "model/x.stl-binary"
            | "model/x.stl-ascii"
            | "application/sla"
            | "application/vnd.ms-pki.stl" => Format::Stl,
            "model/gltf-binary" | "model/gltf+json" => Format::Gltf,
            _ => return None,
        })
    }

    /// The format of some bytes, from magic numbers and keywords; `None` when nothing fits.
    pub fn sniff(bytes: &[u8]) -> Option<Format> {
        let text = trim_start(bytes);
        if bytes.starts_with(b"glTF") {
            Some(Format::Gltf)
        } else if bytes.starts_with(b"ply\n") || bytes.starts_with(b"ply\r\n") {
            Some(Format::Ply)
        } else if stl::looks_like_ascii(bytes) || stl::size_matches_claim(bytes) {
            Some(Format::Stl)
        } else if text.starts_with(b"{") {
            Some(Format::Gltf)
        } else if looks_like_obj(text) {
            Some(Format::Obj)
        } else {
            None
        }
    }

    /// The extension of the files we write.
    pub fn extension(self) -> &'static str {
        match self {
            Format::Obj => "obj",
            Format::Ply => "ply",
            Format::Stl => "stl",
            Format::Gltf => "glb",
        }
    }

    /// The content type of what we write (PLY has no registered type; `application/ply` is
    /// the most common one in use).
    pub fn content_type(self) -> &'static str {
        match self {
            Format::Obj => "model/obj",
            Format::Ply => "application/ply",
            Format::Stl => "model/stl",
            Format::Gltf => "model/gltf-binary",
        }
    }
}

impl FromStr for Format {
    type Err = MeshError;

    /// `obj`, `ply`, `stl`, `glb` or `gltf`, in any case.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "obj" => Ok(Format::Obj),
            "ply" => Ok(Format::Ply),
            "stl" => Ok(Format::Stl),
            "glb" | "gltf" => Ok(Format::Gltf),
            _ => Err(MeshError::UnknownFormat(format!(
                "{s:?} (expected one of obj, ply, stl, glb, gltf)"
            ))),
        }
    }
}

impl fmt::Display for Format {
    /// The extension, so that `format.to_string().parse()` gives the format back.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.extension())
    }
}

fn trim_start(bytes: &[u8]) -> &[u8] {
    let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    let start = bytes.iter().position(|b| !b.is_ascii_whitespace()).unwrap_or(bytes.len());
    &bytes[start..]
}

/// Whether the first lines that say something are OBJ statements.
fn looks_like_obj(text: &[u8]) -> bool {
    const KEYWORDS: [&[u8]; 12] =
        [b"v", b"vn", b"vt", b"vp", b"f", b"l", b"p", b"o", b"g", b"s", b"usemtl", b"mtllib"];
    let mut statements = super::text::lines(text)
        .map(|line| super::text::fields(line).next())
        .filter(|keyword| !matches!(keyword, None | Some([b'#', ..])))
        .take(8)
        .peekable();
    statements.peek().is_some() && statements.all(|k| k.is_some_and(|k| KEYWORDS.contains(&k)))
}

/// Reads a mesh of a known format from bytes. External glTF buffers cannot be resolved here
/// (there is no file to resolve them against): use [`read_mesh_file`] or a `.glb`.
pub fn read_mesh(bytes: &[u8], format: Format, limits: &ReadLimits) -> Result<Mesh, MeshError> {
    limits.check_bytes(bytes.len() as u64)?;
    match format {
        Format::Obj => obj::read(bytes, limits),
        Format::Ply => ply::read(bytes, limits),
        Format::Stl => stl::read(bytes, limits),
        Format::Gltf => gltf_read::read(bytes, None, limits),
    }
}

/// Reads a mesh file; the format comes from the extension, or from the content when the
/// extension names none. The size is checked before anything is read.
pub fn read_mesh_file(path: &Path, limits: &ReadLimits) -> Result<Mesh, MeshError> {
    let io = |error| MeshError::Io { path: path.to_owned(), error };
    limits.check_bytes(std::fs::metadata(path).map_err(io)?.len())?;
    let bytes = std::fs::read(path).map_err(io)?;
    let format = Format::from_path(path).or_else(|| Format::sniff(&bytes)).ok_or_else(|| {
        MeshError::UnknownFormat(format!("{}: neither the name nor the content", path.display()))
    })?;
    match format {
        Format::Gltf => {
            limits.check_bytes(bytes.len() as u64)?;
            gltf_read::read(&bytes, Some(path.parent().unwrap_or(Path::new("."))), limits)
        }
        _ => read_mesh(&bytes, format, limits),
    }
}

/// Writes a mesh (checked with [`Mesh::validate`] first) in a format.
pub fn write_mesh(mesh: &Mesh, format: Format) -> Result<Vec<u8>, MeshError> {
    mesh.validate()?;
    match format {
        Format::Obj => Ok(obj::write(mesh)),
        Format::Ply => ply::write(mesh),
        Format::Stl => stl::write(mesh),
        Format::Gltf => gltf_write::write(mesh),
    }
}

/// Writes a mesh file; `None` takes the format from the extension. `Format::Gltf` always
/// writes binary glTF, even to a `.gltf` name (readers tell the two apart by content).
pub fn write_mesh_file(mesh: &Mesh, path: &Path, format: Option<Format>) -> Result<(), MeshError> {
    let format = format.or_else(|| Format::from_path(path)).ok_or_else(|| {
        MeshError::UnknownFormat(format!("{}: the extension names no format", path.display()))
    })?;
    let bytes = write_mesh(mesh, format)?;
    std::fs::write(path, bytes).map_err(|error| MeshError::Io { path: path.to_owned(), error })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_extensions_and_content_types() {
        for format in Format::ALL {
            assert_eq!(format.to_string().parse::<Format>().unwrap(), format);
            assert_eq!(Format::from_content_type(format.content_type()), Some(format));
            let name = format!("a/b.{}", format.extension().to_uppercase());
            assert_eq!(Format::from_path(Path::new(&name)), Some(format));
        }
        assert_eq!(Format::from_path(Path::new("x.gltf")), Some(Format::Gltf));
        assert_eq!(Format::from_path(Path::new("x.txt")), None);
        assert_eq!(Format::from_path(Path::new("obj")), None);
        assert_eq!("GLTF".parse::<Format>().unwrap(), Format::Gltf);
        let err = "fbx".parse::<Format>().unwrap_err().to_string();
        assert!(err.contains("fbx") && err.contains("obj, ply, stl, glb, gltf"), "{err}");
        assert_eq!(Format::from_content_type("Model/GLTF+JSON; charset=utf-8"), Some(Format::Gltf));
        assert_eq!(Format::from_content_type("application/sla"), Some(Format::Stl));
        assert_eq!(Format::from_content_type("text/x-ply"), Some(Format::Ply));
        assert_eq!(Format::from_content_type("text/plain"), None);
    }

    #[test]
    fn sniffing_by_content() {
        assert_eq!(Format::sniff(b"glTF\x02\0\0\0"), Some(Format::Gltf));
        assert_eq!(Format::sniff(b"\n  {\"asset\": {}}"), Some(Format::Gltf));
        assert_eq!(Format::sniff(b"ply\nformat ascii 1.0\n"), Some(Format::Ply));
        assert_eq!(Format::sniff(b"solid x\nfacet normal 0 0 1\n"), Some(Format::Stl));
        assert_eq!(
            Format::sniff(b"# exported\n\nmtllib a.mtl\no cube\nv 0 0 0\n"),
            Some(Format::Obj)
        );
        let mut binary_stl = vec![0u8; 84 + 50];
        binary_stl[..5].copy_from_slice(b"solid");
        binary_stl[80] = 1;
        assert_eq!(Format::sniff(&binary_stl), Some(Format::Stl));
        assert_eq!(Format::sniff(b""), None);
        assert_eq!(Format::sniff(b"hello world\n"), None);
        assert_eq!(Format::sniff(&[0u8; 200]), None);
    }

    #[test]
    fn files_round_trip_and_size_is_checked_first() {
        let dir = tempfile::tempdir().unwrap();
        let mesh =
            Mesh::new(vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], vec![[0, 1, 2]]);
        for format in Format::ALL {
            let path = dir.path().join(format!("m.{format}"));
            write_mesh_file(&mesh, &path, None).unwrap();
            let back = read_mesh_file(&path, &ReadLimits::default()).unwrap();
            assert_eq!((back.vertices, back.faces), (mesh.vertices.clone(), mesh.faces.clone()));
            // Without a telling name, the content decides.
            let anonymous = dir.path().join(format!("m-{format}.bin"));
            std::fs::copy(&path, &anonymous).unwrap();
            assert_eq!(
                read_mesh_file(&anonymous, &ReadLimits::default()).unwrap().faces,
                mesh.faces
            );
            let tiny = ReadLimits { max_bytes: 10, ..ReadLimits::default() };
            assert!(matches!(read_mesh_file(&path, &tiny), Err(MeshError::TooLarge { .. })));
        }
        let unnamed = dir.path().join("m.xyz");
        assert!(matches!(write_mesh_file(&mesh, &unnamed, None), Err(MeshError::UnknownFormat(_))));
        assert!(matches!(
            read_mesh_file(&unnamed, &ReadLimits::default()),
            Err(MeshError::Io { .. })
        ));
        let obj = write_mesh(&mesh, Format::Obj).unwrap();
        let just_under = ReadLimits { max_bytes: obj.len() as u64 - 1, ..ReadLimits::default() };
        assert!(matches!(
            read_mesh(&obj, Format::Obj, &just_under),
            Err(MeshError::TooLarge { .. })
        ));
        let bad = Mesh::new(vec![[0.0; 3]], vec![[0, 0, 1]]);
        assert!(matches!(write_mesh(&bad, Format::Obj), Err(MeshError::Invalid(_))));
    }
}
