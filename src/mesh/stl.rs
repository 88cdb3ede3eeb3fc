//! STL, ASCII and binary. STL stores every triangle with its own three corners; the reader
//! welds corners at exactly the same position into one vertex, giving an indexed mesh.

use std::collections::HashMap;

use super::assemble::Assembler;
use super::text::{fields, lines, next_vec3};
use super::{Mesh, MeshError, ReadLimits, position_key};

const FORMAT: &str = "STL";
const HEADER: usize = 80;
/// The header and the triangle count.
const PREAMBLE: usize = HEADER + 4;
/// Normal, three corners (12 floats) and the attribute byte count.
const TRIANGLE: usize = 50;

fn malformed(message: impl Into<String>) -> MeshError {
    MeshError::malformed(FORMAT, message)
}

/// The triangle count a binary STL's preamble claims, if the bytes are long enough to have one.
fn claimed_triangles(bytes: &[u8]) -> Option<u64> {
    let count = bytes.get(HEADER..PREAMBLE)?;
    Some(u64::from(u32::from_le_bytes(count.try_into().ok()?)))
}

/// Whether the bytes are a binary STL (else they are read as ASCII).
///
/// Many binary files start with "solid" too (exporters copy the ASCII keyword into the
/// header), so the keyword alone decides nothing: a file whose size is exactly what its
/// triangle count says is binary; otherwise one that starts with "solid" and has no NUL byte
/// early on (text never has one, binary headers and floats nearly always do) is ASCII.
pub(crate) fn is_binary(bytes: &[u8]) -> bool {
    size_matches_claim(bytes) || !looks_like_ascii(bytes)
}

/// Whether the bytes are exactly as long as the binary triangle count they start with says.
pub(crate) fn size_matches_claim(bytes: &[u8]) -> bool {
    claimed_triangles(bytes)
        .is_some_and(|n| PREAMBLE as u64 + TRIANGLE as u64 * n == bytes.len() as u64)
}

pub(crate) fn looks_like_ascii(bytes: &[u8]) -> bool {
    let start = bytes.iter().position(|b| !b.is_ascii_whitespace()).unwrap_or(bytes.len());
    let head = &bytes[start..bytes.len().min(start + 1024)];
    head.starts_with(b"solid") && !head.contains(&0)
}

pub(crate) fn read(bytes: &[u8], limits: &ReadLimits) -> Result<Mesh, MeshError> {
    if is_binary(bytes) { read_binary(bytes, limits) } else { read_ascii(bytes, limits) }
}

/// Gives each distinct position one vertex, in order of first appearance.
struct Welder<'a> {
    asm: Assembler<'a>,
    index_of: HashMap<[u32; 3], u32>,
}

impl<'a> Welder<'a> {
    fn new(limits: &'a ReadLimits) -> Self {
        Self { asm: Assembler::new(FORMAT, limits), index_of: HashMap::new() }
    }

    fn vertex(&mut self, p: [f32; 3]) -> Result<u32, MeshError> {
        // NaN is caught below.
        let key = position_key(p);
        if let Some(&i) = self.index_of.get(&key) {
            return Ok(i);
        }
        let i =
            u32::try_from(self.asm.vertices.len()).map_err(|_| malformed("too many vertices"))?;
        self.asm.push_vertex(p)?;
        self.index_of.insert(key, i);
        Ok(i)
    }

    fn triangle(&mut self, corners: [[f32; 3]; 3]) -> Result<(), MeshError> {
        let [a, b, c] = corners;
        let t = [self.vertex(a)?, self.vertex(b)?, self.vertex(c)?];
        self.asm.push_triangle(t)
    }
}

fn read_binary(bytes: &[u8], limits: &ReadLimits) -> Result<Mesh, MeshError> {
    let Some(count) = claimed_triangles(bytes) else {
        return Err(malformed(format!("{} bytes is too short for a binary STL", bytes.len())));
    };
    let mut welder = Welder::new(limits);
    welder.asm.check_limits(0, count)?;
    let room = (bytes.len() - PREAMBLE) / TRIANGLE;
    if count > room as u64 {
        return Err(malformed(format!(
            "the header claims {count} triangles, the file holds {room}"
        )));
    }
    // Trailing bytes after the last triangle are tolerated (some exporters pad files).
    welder.asm.reserve(0, count)?;
    for record in bytes[PREAMBLE..].chunks_exact(TRIANGLE).take(count as usize) {
        let float = |k: usize| {
            let b = [record[4 * k], record[4 * k + 1], record[4 * k + 2], record[4 * k + 3]];
            f32::from_le_bytes(b)
        };
        // Floats 0..3 are the facet normal, recomputed from the corners when needed.
        let corner = |c: usize| [float(3 + 3 * c), float(4 + 3 * c), float(5 + 3 * c)];
        welder.triangle([corner(0), corner(1), corner(2)])?;
    }
    welder.asm.finish(None)
}

fn read_ascii(bytes: &[u8], limits: &ReadLimits) -> Result<Mesh, MeshError> {
    let mut welder = Welder::new(limits);
    // The corners of the facet being read, None outside a facet.
    let mut facet: Option<([[f32; 3]; 3], usize)> = None;
    for (line_no, line) in lines(bytes).enumerate() {
        let at = |message: &str| malformed(format!("line {}: {message}", line_no + 1));
        let mut f = fields(line);
        match (f.next(), &mut facet) {
            (Some(b"facet"), None) => facet = Some(([[0.0; 3]; 3], 0)),
            (Some(b"vertex"), Some((corners, n))) => {
                let slot =
                    corners.get_mut(*n).ok_or_else(|| at("a facet with more than 3 vertices"))?;
                *slot = next_vec3(&mut f, FORMAT, "vertex")?;
                *n += 1;
            }
            (Some(b"endfacet"), Some((corners, 3))) => {
                welder.triangle(*corners)?;
                facet = None;
            }
            (Some(b"endfacet"), _) => return Err(at("a facet without 3 vertices")),
            (Some(b"outer" | b"endloop"), Some(_)) => {}
            (Some(b"solid" | b"endsolid"), None) | (None, _) => {}
            (Some(keyword), _) => {
                return Err(at(&format!("unexpected {:?}", String::from_utf8_lossy(keyword))));
            }
        }
    }
    if facet.is_some() {
        return Err(malformed("the file ends inside a facet"));
    }
    welder.asm.finish(None)
}

/// Binary STL with face normals; STL has no points, so a point cloud is refused.
pub(crate) fn write(mesh: &Mesh) -> Result<Vec<u8>, MeshError> {
    if mesh.is_point_cloud() {
        return Err(MeshError::invalid("STL stores triangles only; a point cloud has none"));
    }
    let count = u32::try_from(mesh.faces.len())
        .map_err(|_| MeshError::invalid("binary STL holds at most 2^32 - 1 triangles"))?;
    let mut out = Vec::with_capacity(PREAMBLE + TRIANGLE * mesh.faces.len());
    // The header must not start with "solid", or naive readers would take the file for ASCII.
    let mut header = [b' '; HEADER];
    let text = b"binary STL written by meshstream";
    header[..text.len()].copy_from_slice(text);
    out.extend_from_slice(&header);
    out.extend_from_slice(&count.to_le_bytes());
    for (f, normal) in mesh.faces.iter().zip(mesh.face_normals()) {
        for c in normal.iter().chain(mesh.triangle(f).iter().flatten()) {
            out.extend_from_slice(&c.to_le_bytes());
        }
        out.extend_from_slice(&0u16.to_le_bytes());
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read_bytes(b: &[u8]) -> Result<Mesh, MeshError> {
        read(b, &ReadLimits::default())
    }

    const TETRA: &str = "solid tetra\n\
        facet normal 0 0 -1\n outer loop\n  vertex 0 0 0\n  vertex 0 1 0\n  vertex 1 0 0\n endloop\nendfacet\n\
        facet normal 0 -1 0\n outer loop\n  vertex 0 0 0\n  vertex 1 0 0\n  vertex 0 0 1\n endloop\nendfacet\n\
        facet normal -1 0 0\n outer loop\n  vertex 0 0 0\n  vertex 0 0 1\n  vertex 0 1 0\n endloop\nendfacet\n\
        facet normal 1 1 1\n outer loop\n  vertex 1 0 0\n  vertex 0 1 0\n  vertex 0 0 1\n endloop\nendfacet\n\
        endsolid tetra\n";

    fn assert_tetra(mesh: &Mesh) {
        assert_eq!(
            mesh.vertices,
            vec![[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
        );
        assert_eq!(mesh.faces, vec![[0, 1, 2], [0, 2, 3], [0, 3, 1], [2, 1, 3]]);
    }

    #[test]
    fn ascii_is_welded_into_an_indexed_mesh() {
        assert_tetra(&read_bytes(TETRA.as_bytes()).unwrap());
        assert_tetra(&read_bytes(TETRA.replace('\n', "\r\n").as_bytes()).unwrap());
    }

    #[test]
    fn binary_starting_with_solid_is_read_as_binary() {
        let ascii = read_bytes(TETRA.as_bytes()).unwrap();
        let mut binary = write(&ascii).unwrap();
        binary[..HEADER].fill(b' ');
        binary[..11].copy_from_slice(b"solid tetra");
        assert!(is_binary(&binary));
        assert_tetra(&read_bytes(&binary).unwrap());
        // Negative zero welds with zero.
        let mut m = ascii.clone();
        m.vertices.push([-0.0, 0.0, 0.0]);
        m.faces.push([4, 1, 2]);
        let back = read_bytes(&write(&m).unwrap()).unwrap();
        assert_eq!(back.vertices.len(), 4);
    }

    #[test]
    fn lies_and_truncations_are_malformed() {
        let binary = write(&read_bytes(TETRA.as_bytes()).unwrap()).unwrap();
        for cut in [binary.len() - 1, 100, 84, 83, 10, 0] {
            let err = read_bytes(&binary[..cut]).unwrap_err();
            assert!(matches!(err, MeshError::Malformed { .. }), "cut at {cut}: {err}");
        }
        for cut in [TETRA.len() - 30, 60, 30] {
            let err = read_bytes(&TETRA.as_bytes()[..cut]).unwrap_err();
            assert!(matches!(err, MeshError::Malformed { .. }), "cut at {cut}: {err}");
        }
        let extra_vertex = TETRA.replacen("endloop", "vertex 5 5 5\nendloop", 1);
        assert!(read_bytes(extra_vertex.as_bytes()).is_err());
        assert!(
            read_bytes(TETRA.replacen("vertex 0 0 0", "vertex nan 0 0", 1).as_bytes()).is_err()
        );
    }

    #[test]
    fn huge_claimed_count_fails_fast() {
        let mut b = vec![0u8; 100];
        b[HEADER..PREAMBLE].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(read_bytes(&b), Err(MeshError::TooLarge { .. })));
        let unlimited =
            ReadLimits { max_bytes: u64::MAX, max_vertices: usize::MAX, max_faces: usize::MAX };
        assert!(matches!(read(&b, &unlimited), Err(MeshError::Malformed { .. })));
    }

    #[test]
    fn point_cloud_cannot_be_written() {
        let cloud = Mesh::new(vec![[0.0; 3]], vec![]);
        assert!(matches!(write(&cloud), Err(MeshError::Invalid(_))));
    }
}
