//! Bounds on what a reader accepts, so that hostile or accidental input cannot exhaust memory.

use super::MeshError;

/// The most a reader accepts before it gives up with [`MeshError::TooLarge`].
///
/// Readers check claimed counts against these limits (and against the bytes actually present)
/// *before* they allocate, so a header that lies costs nothing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadLimits {
    /// Size of the input: the file, or for a `.gltf` file the file plus its external buffers.
    pub max_bytes: u64,
    pub max_vertices: usize,
    /// Triangles after fan triangulation.
    pub max_faces: usize,
}

impl Default for ReadLimits {
    /// 1 GiB, 20 M vertices, 40 M triangles.
    ///
    /// Generous: the largest meshes people scan or sculpt (tens of millions of triangles) still
    /// load, while the worst case stays a few GiB of memory on a 24 GiB machine (20 M vertices
    /// with normals take 480 MB, 40 M triangles 480 MB). A closed surface has about twice as
    /// many triangles as vertices, hence the 2:1 ratio. A binary STL of 40 M triangles is 2 GB,
    /// so for STL the byte limit binds first; that is deliberate, STL being the most wasteful
    /// format per triangle.
    fn default() -> Self {
        Self { max_bytes: 1 << 30, max_vertices: 20_000_000, max_faces: 40_000_000 }
    }
}

impl ReadLimits {
    pub(crate) fn check_bytes(&self, bytes: u64) -> Result<(), MeshError> {
        check("input bytes", bytes, self.max_bytes)
    }

    pub(crate) fn check_vertices(&self, vertices: u64) -> Result<(), MeshError> {
        check("vertex count", vertices, self.max_vertices as u64)
    }

    pub(crate) fn check_faces(&self, faces: u64) -> Result<(), MeshError> {
        check("face count", faces, self.max_faces as u64)
    }
}

fn check(what: &'static str, value: u64, limit: u64) -> Result<(), MeshError> {
    if value > limit { Err(MeshError::TooLarge { what, limit }) } else { Ok(()) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limits_are_inclusive() {
        let limits = ReadLimits { max_bytes: 10, max_vertices: 3, max_faces: 1 };
        assert!(limits.check_bytes(10).is_ok());
        assert!(matches!(limits.check_bytes(11), Err(MeshError::TooLarge { limit: 10, .. })));
        assert!(limits.check_vertices(3).is_ok());
        assert!(limits.check_vertices(4).is_err());
        assert!(limits.check_faces(1).is_ok());
        assert!(limits.check_faces(2).is_err());
    }
}
