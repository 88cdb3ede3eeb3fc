//! What every reader does alike: collect vertices and triangles within the limits, split
//! polygons into triangles, and hand back a mesh that passes [`Mesh::validate`].

use super::{Mesh, MeshError, ReadLimits};

/// Collects the geometry of one file, checking limits and values as it goes.
pub(crate) struct Assembler<'a> {
    format: &'static str,
    limits: &'a ReadLimits,
    pub(crate) vertices: Vec<[f32; 3]>,
    pub(crate) faces: Vec<[u32; 3]>,
}

impl<'a> Assembler<'a> {
    pub(crate) fn new(format: &'static str, limits: &'a ReadLimits) -> Self {
        Self { format, limits, vertices: Vec::new(), faces: Vec::new() }
    }

    pub(crate) fn malformed(&self, message: impl Into<String>) -> MeshError {
        MeshError::malformed(self.format, message)
    }

    /// Fails when `vertices` more vertices or `faces` more triangles would exceed the limits.
    pub(crate) fn check_limits(&self, vertices: u64, faces: u64) -> Result<(), MeshError> {
        self.limits.check_vertices((self.vertices.len() as u64).saturating_add(vertices))?;
        self.limits.check_faces((self.faces.len() as u64).saturating_add(faces))
    }

    /// Reserves room for `vertices` more vertices and `faces` more triangles, after checking
    /// them against the limits. Callers must also have bounded the counts by the input's size
    /// (a count within the limits can still be a lie).
    pub(crate) fn reserve(&mut self, vertices: u64, faces: u64) -> Result<(), MeshError> {
        self.check_limits(vertices, faces)?;
        // Both fit in usize now: the limits are usize.
        self.vertices.reserve(vertices as usize);
        self.faces.reserve(faces as usize);
        Ok(())
    }

    pub(crate) fn push_vertex(&mut self, p: [f32; 3]) -> Result<(), MeshError> {
        if !p.iter().all(|c| c.is_finite()) {
            return Err(self.malformed(format!(
                "vertex {} has a non-finite coordinate {p:?}",
                self.vertices.len()
            )));
        }
        self.limits.check_vertices(self.vertices.len() as u64 + 1)?;
        self.vertices.push(p);
        Ok(())
    }

    pub(crate) fn push_triangle(&mut self, t: [u32; 3]) -> Result<(), MeshError> {
        self.limits.check_faces(self.faces.len() as u64 + 1)?;
        self.faces.push(t);
        Ok(())
    }

    /// Fan-triangulates a polygon: (0, i, i + 1) for every i. Exact for convex polygons, which
    /// is what exporters write; the face count is `n - 2`.
    pub(crate) fn push_polygon(&mut self, polygon: &[u32]) -> Result<(), MeshError> {
        let Some((&first, rest)) = polygon.split_first() else {
            return Err(self.malformed("a face without vertices"));
        };
        if rest.len() < 2 {
            return Err(self.malformed(format!(
                "a face needs at least 3 vertices, this one has {}",
                polygon.len()
            )));
        }
        for pair in rest.windows(2) {
            self.push_triangle([first, pair[0], pair[1]])?;
        }
        Ok(())
    }

    /// The finished mesh. Indices are checked here, so readers whose files may list faces
    /// before vertices (PLY) need not check them as they go.
    pub(crate) fn finish(self, normals: Option<Vec<[f32; 3]>>) -> Result<Mesh, MeshError> {
        let n = self.vertices.len();
        if let Some((f, face)) =
            self.faces.iter().enumerate().find(|(_, face)| face.iter().any(|&i| i as usize >= n))
        {
            return Err(self.malformed(format!(
                "face {f} {face:?} refers to a vertex beyond the {n} there are"
            )));
        }
        if let Some(normals) = &normals {
            if normals.len() != n {
                return Err(self.malformed(format!("{} normals for {n} vertices", normals.len())));
            }
            if let Some(i) = normals.iter().position(|v| !v.iter().all(|c| c.is_finite())) {
                return Err(self.malformed(format!("normal {i} has a non-finite component")));
            }
        }
        let mesh = Mesh { vertices: self.vertices, faces: self.faces, normals };
        mesh.validate()?;
        Ok(mesh)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fan_triangulation_of_a_pentagon() {
        let limits = ReadLimits::default();
        let mut asm = Assembler::new("test", &limits);
        for i in 0..5 {
            asm.push_vertex([i as f32, 0.0, 0.0]).unwrap();
        }
        asm.push_polygon(&[0, 1, 2, 3, 4]).unwrap();
        let mesh = asm.finish(None).unwrap();
        assert_eq!(mesh.faces, vec![[0, 1, 2], [0, 2, 3], [0, 3, 4]]);
    }

    #[test]
    fn rejects_short_polygons_bad_indices_nan_and_excess() {
        let limits = ReadLimits { max_bytes: 100, max_vertices: 2, max_faces: 1 };
        let mut asm = Assembler::new("test", &limits);
        assert!(asm.push_polygon(&[0, 1]).is_err());
        assert!(asm.push_vertex([f32::NAN, 0.0, 0.0]).is_err());
        asm.push_vertex([0.0; 3]).unwrap();
        asm.push_vertex([1.0; 3]).unwrap();
        assert!(matches!(asm.push_vertex([2.0; 3]), Err(MeshError::TooLarge { .. })));
        assert!(matches!(asm.push_polygon(&[0, 1, 0, 1]), Err(MeshError::TooLarge { .. })));
        let mut asm = Assembler::new("test", &limits);
        asm.push_vertex([0.0; 3]).unwrap();
        asm.push_triangle([0, 0, 5]).unwrap();
        assert!(matches!(asm.finish(None), Err(MeshError::Malformed { .. })));
    }
}
