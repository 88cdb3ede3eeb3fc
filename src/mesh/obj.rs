//! Wavefront OBJ: positions (`v`), normals (`vn`) and faces (`f`); everything else (texture
//! coordinates, groups, materials, smoothing, lines, unknown keywords) is ignored.

use std::io::Write;

use super::assemble::Assembler;
use super::text::{fields, lines, next_vec3, parse};
use super::{Mesh, MeshError, ReadLimits};

const FORMAT: &str = "OBJ";

/// No normal named for this position yet.
const UNNAMED: u32 = u32::MAX;

/// How the face corners seen so far name normals.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum CornerNormals {
    /// No face corner yet.
    NoCorners,
    /// Every corner names a normal, and each position always the same one.
    Consistent,
    /// No corner names a normal.
    Absent,
    /// Some corners name one and others do not, or a position was given two normals: the
    /// normals do not map one-to-one onto positions, so they are dropped.
    Inconsistent,
}

pub(crate) fn read(bytes: &[u8], limits: &ReadLimits) -> Result<Mesh, MeshError> {
    let mut reader = Reader {
        asm: Assembler::new(FORMAT, limits),
        limits,
        normals: Vec::new(),
        normal_of: Vec::new(),
        corners: CornerNormals::NoCorners,
        polygon: Vec::new(),
    };
    for (line_no, line) in lines(bytes).enumerate() {
        reader.line(line).map_err(|e| with_line(e, line_no + 1))?;
    }
    let normals = match reader.corners {
        CornerNormals::Consistent => per_position(&reader.normal_of, &reader.normals),
        CornerNormals::NoCorners | CornerNormals::Absent => {
            by_order(reader.normal_of.len(), reader.normals)
        }
        CornerNormals::Inconsistent => None,
    };
    reader.asm.finish(normals)
}

struct Reader<'a> {
    asm: Assembler<'a>,
    limits: &'a ReadLimits,
    normals: Vec<[f32; 3]>,
    /// For each position, the normal its face corners name (UNNAMED until one does).
    normal_of: Vec<u32>,
    corners: CornerNormals,
    /// Reused for every face, so that a face costs no allocation.
    polygon: Vec<u32>,
}

impl Reader<'_> {
    fn line(&mut self, line: &[u8]) -> Result<(), MeshError> {
        let line = line.split(|&b| b == b'#').next().unwrap_or_default();
        let mut f = fields(line);
        match f.next() {
            Some(b"v") => {
                self.asm.push_vertex(next_vec3(&mut f, FORMAT, "vertex")?)?;
                self.normal_of.push(UNNAMED);
            }
            Some(b"vn") => {
                let n = next_vec3(&mut f, FORMAT, "normal")?;
                if !n.iter().all(|c| c.is_finite()) {
                    return Err(self.asm.malformed(format!("non-finite normal {n:?}")));
                }
                // Normals are bounded like vertices: one nobody uses still costs memory.
                self.limits.check_vertices(self.normals.len() as u64 + 1)?;
                self.normals.push(n);
            }
            Some(b"f") => {
                self.polygon.clear();
                for corner in f {
                    let (v, n) = parse_corner(corner, self.asm.vertices.len(), self.normals.len())?;
                    self.polygon.push(v);
                    // parse_corner checked v against the positions defined, one slot each.
                    if let Some(named) = self.normal_of.get_mut(v as usize) {
                        self.corners = note_corner(self.corners, named, n);
                    }
                }
                self.asm.push_polygon(&self.polygon)?;
            }
            _ => {}
        }
        Ok(())
    }
}

/// Adds the line number to a malformed-line error.
fn with_line(e: MeshError, line: usize) -> MeshError {
    match e {
        MeshError::Malformed { format, message } => {
            MeshError::Malformed { format, message: format!("line {line}: {message}") }
        }
        other => other,
    }
}

fn note_corner(state: CornerNormals, named: &mut u32, normal: Option<u32>) -> CornerNormals {
    use CornerNormals::*;
    match (state, normal) {
        (Inconsistent, _) => Inconsistent,
        (NoCorners | Absent, None) => Absent,
        (Absent, Some(_)) | (Consistent, None) => Inconsistent,
        (NoCorners | Consistent, Some(n)) => {
            if *named == UNNAMED || *named == n {
                *named = n;
                Consistent
            } else {
                Inconsistent
            }
        }
    }
}

/// Normals named by the faces; a position no face uses falls back to the normal of the same
/// rank when there are as many normals as positions (what our writer produces).
fn per_position(normal_of: &[u32], normals: &[[f32; 3]]) -> Option<Vec<[f32; 3]>> {
    let same_count = normals.len() == normal_of.len();
    normal_of
        .iter()
        .enumerate()
        .map(|(i, &n)| match n {
            UNNAMED if same_count => normals.get(i).copied(),
            UNNAMED => None,
            n => normals.get(n as usize).copied(),
        })
        .collect()
}

/// Without faces to pair them, normals belong to positions by order, if the counts agree.
fn by_order(positions: usize, normals: Vec<[f32; 3]>) -> Option<Vec<[f32; 3]>> {
    (positions > 0 && normals.len() == positions).then_some(normals)
}

/// One face corner, `v`, `v/t`, `v//n` or `v/t/n`, as a 0-based position index and an optional
/// 0-based normal index. Indices count from 1, or back from the last one defined when negative.
fn parse_corner(
    corner: &[u8],
    positions: usize,
    normals: usize,
) -> Result<(u32, Option<u32>), MeshError> {
    let mut parts = corner.split(|&b| b == b'/');
    let v = parts.next().unwrap_or_default();
    let _texture = parts.next();
    let n = parts.next().filter(|n| !n.is_empty());
    if parts.next().is_some() {
        let corner = String::from_utf8_lossy(corner);
        return Err(MeshError::malformed(FORMAT, format!("bad face corner {corner:?}")));
    }
    let v = resolve(v, positions, "vertex")?;
    let n = n.map(|n| resolve(n, normals, "normal")).transpose()?;
    Ok((v, n))
}

fn resolve(index: &[u8], defined: usize, what: &str) -> Result<u32, MeshError> {
    let i: i64 = parse(index, FORMAT, what)?;
    let resolved = if i > 0 { i - 1 } else { defined as i64 + i };
    if i == 0 || resolved < 0 || resolved >= defined as i64 {
        let message = format!("{what} index {i} with {defined} defined so far");
        return Err(MeshError::malformed(FORMAT, message));
    }
    Ok(resolved as u32)
}

/// `v` lines, `vn` lines when the mesh has normals, and `f` lines with 1-based indices
/// (`a//a` when there are normals, so that they map one-to-one back onto positions).
pub(crate) fn write(mesh: &Mesh) -> Vec<u8> {
    let mut out = Vec::with_capacity(32 * (mesh.vertices.len() + mesh.faces.len()) + 16);
    // Writing to a Vec cannot fail; the results are discarded for that reason only.
    let _ = writeln!(out, "# meshstream");
    for [x, y, z] in &mesh.vertices {
        let _ = writeln!(out, "v {x} {y} {z}");
    }
    if let Some(normals) = &mesh.normals {
        for [x, y, z] in normals {
            let _ = writeln!(out, "vn {x} {y} {z}");
        }
    }
    for f in &mesh.faces {
        let [a, b, c] = f.map(|i| u64::from(i) + 1);
        if mesh.normals.is_some() {
            let _ = writeln!(out, "f {a}//{a} {b}//{b} {c}//{c}");
        } else {
            let _ = writeln!(out, "f {a} {b} {c}");
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read_str(s: &str) -> Result<Mesh, MeshError> {
        read(s.as_bytes(), &ReadLimits::default())
    }

    const SQUARE: &str = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n";

    #[test]
    fn every_face_form_reads_the_same_quad() {
        let forms = [
            "f 1 2 3 4",
            "f 1/1 2/2 3/3 4/4",
            "f 1/1/1 2/2/1 3/3/1 4/4/1",
            "f -4 -3 -2 -1",
            "f -4/-1 -3/-1 -2/-1 -1/-1",
        ];
        for form in forms {
            let text = format!("{SQUARE}vt 0 0\nvn 0 0 1\n{form}\n");
            let mesh = read_str(&text).unwrap_or_else(|e| panic!("{form}: {e}"));
            assert_eq!(mesh.vertices.len(), 4, "{form}");
            assert_eq!(mesh.faces, vec![[0, 1, 2], [0, 2, 3]], "{form}");
        }
    }

    #[test]
    fn normals_kept_when_one_to_one() {
        let text = format!("{SQUARE}vn 0 0 1\nvn 0 0 -1\nf 1//1 2//1 3//1\nf 1//1 3//1 4//2\n");
        let mesh = read_str(&text).unwrap();
        assert_eq!(
            mesh.normals.unwrap(),
            vec![[0.0, 0.0, 1.0]; 3].into_iter().chain([[0.0, 0.0, -1.0]]).collect::<Vec<_>>()
        );
    }

    #[test]
    fn normals_dropped_when_a_position_has_two() {
        let text = format!("{SQUARE}vn 0 0 1\nvn 0 0 -1\nf 1//1 2//1 3//1\nf 1//2 3//1 4//2\n");
        let mesh = read_str(&text).unwrap();
        assert_eq!(mesh.faces.len(), 2);
        assert!(mesh.normals.is_none());
        // Some corners with a normal, some without: dropped as well.
        let text = format!("{SQUARE}vn 0 0 1\nf 1//1 2//1 3//1\nf 1 3 4\n");
        assert!(read_str(&text).unwrap().normals.is_none());
    }

    #[test]
    fn ngon_is_fan_triangulated_and_other_lines_ignored() {
        let text = "# a hexagon\nmtllib x.mtl\no hex\ng part\nusemtl red\ns off\n\
                    v 0 0 0\nv 1 0 0\nv 2 1 0\nv 1 2 0\nv 0 2 0\nv -1 1 0 # trailing comment\n\
                    vt 0 0\nl 1 2\nunknown keyword here\nf 1 2 3 4 5 6\n";
        let mesh = read_str(text).unwrap();
        assert_eq!(mesh.faces, vec![[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5]]);
        assert!(mesh.normals.is_none());
    }

    #[test]
    fn only_positions_is_a_point_cloud_and_normals_pair_by_order() {
        let mesh = read_str("v 1 2 3\r\nv 4 5 6\r\nvn 0 0 1\r\nvn 1 0 0\r\n").unwrap();
        assert!(mesh.is_point_cloud());
        assert_eq!(mesh.vertices, vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        assert_eq!(mesh.normals, Some(vec![[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]));
        assert!(read_str("v 1 2 3\nv 4 5 6\nvn 0 0 1\n").unwrap().normals.is_none());
    }

    #[test]
    fn bad_indices_and_values_are_malformed() {
        for bad in [
            "f 1 2 5",
            "f 0 1 2",
            "f -5 1 2",
            "f 1 2",
            "f 1//2 2 3",
            "f 1/2/3/4 2 3",
            "f a b c",
            "v nan 0 0",
            "v inf 0 0",
            "v 1 2",
            "vn 0 0 nan",
        ] {
            let text = format!("{SQUARE}vn 0 0 1\n{bad}\n");
            let err = read_str(&text).unwrap_err();
            assert!(matches!(err, MeshError::Malformed { .. }), "{bad}: {err}");
        }
    }

    #[test]
    fn limits_apply() {
        let limits = ReadLimits { max_bytes: 1 << 20, max_vertices: 3, max_faces: 1 };
        assert!(matches!(read(SQUARE.as_bytes(), &limits), Err(MeshError::TooLarge { .. })));
        let text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3\nf 3 2 1\n";
        assert!(matches!(read(text.as_bytes(), &limits), Err(MeshError::TooLarge { .. })));
    }

    #[test]
    fn write_then_read_keeps_everything() {
        let mut mesh = Mesh::new(
            vec![[0.1, -2.5, 3e-7], [1.0, 0.0, 1e20], [0.0, 1.0, 0.0], [5.0, 5.0, 5.0]],
            vec![[0, 1, 2], [2, 1, 0]],
        );
        assert_eq!(read(&write(&mesh), &ReadLimits::default()).unwrap(), mesh);
        mesh.normals =
            Some(vec![[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.6, 0.8, 0.0]]);
        assert_eq!(read(&write(&mesh), &ReadLimits::default()).unwrap(), mesh);
    }
}
