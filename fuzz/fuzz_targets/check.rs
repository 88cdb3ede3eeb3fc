//! What every reader target checks: no panic, and any mesh returned is valid and within the
//! limits.

use meshstream::mesh::{Format, ReadLimits, read_mesh};

const LIMITS: ReadLimits =
    ReadLimits { max_bytes: 1 << 20, max_vertices: 100_000, max_faces: 200_000 };

pub fn read(data: &[u8], format: Format) {
    if let Ok(mesh) = read_mesh(data, format, &LIMITS) {
        assert!(mesh.validate().is_ok());
        assert!(mesh.vertices.len() <= LIMITS.max_vertices);
        assert!(mesh.faces.len() <= LIMITS.max_faces);
    }
}
