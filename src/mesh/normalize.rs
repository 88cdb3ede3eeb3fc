use super::{Mesh, MeshError, bounds};

/// The bounding-box normalization of DESIGN.md: the box's centre goes to the origin and its
/// longest side spans [-1, 1]. It remembers the transform so that results can be put back in
/// the caller's coordinates.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Normalization {
    /// Centre of the bounding box, in the caller's coordinates.
    pub center: [f64; 3],
    /// Half the longest side of the bounding box, in the caller's units.
    pub half_extent: f64,
}

impl Normalization {
    /// The normalization of a point set. Fails for an empty set, non-finite coordinates, or a
    /// set whose bounding box has no extent (all points equal): nothing can be scaled to [-1, 1].
    pub fn fit(points: &[[f32; 3]]) -> Result<Self, MeshError> {
        let (lo, hi) = bounds(points).ok_or_else(|| MeshError::invalid("no vertices"))?;
        let center: [f64; 3] = std::array::from_fn(|k| (lo[k] as f64 + hi[k] as f64) / 2.0);
        let half_extent = (0..3).map(|k| (hi[k] as f64 - lo[k] as f64) / 2.0).fold(0.0, f64::max);
        if !half_extent.is_finite() || center.iter().any(|c| !c.is_finite()) {
            return Err(MeshError::invalid("non-finite coordinates"));
        }
        if half_extent <= 0.0 {
            return Err(MeshError::invalid("all points are equal: the shape has no extent"));
        }
        Ok(Self { center, half_extent })
    }

    /// The identity: for data already in the normalized frame.
    pub fn identity() -> Self {
        Self { center: [0.0; 3], half_extent: 1.0 }
    }

    /// Caller's coordinates -> normalized frame.
    pub fn apply(&self, p: [f32; 3]) -> [f32; 3] {
        std::array::from_fn(|k| ((p[k] as f64 - self.center[k]) / self.half_extent) as f32)
    }

    /// Normalized frame -> caller's coordinates.
    pub fn invert(&self, p: [f32; 3]) -> [f32; 3] {
        std::array::from_fn(|k| (p[k] as f64 * self.half_extent + self.center[k]) as f32)
    }

    /// A copy of the mesh in the normalized frame (normals are unchanged: the transform is a
    /// uniform scale and a shift).
    pub fn apply_mesh(&self, mesh: &Mesh) -> Mesh {
        Mesh { vertices: mesh.vertices.iter().map(|&p| self.apply(p)).collect(), ..mesh.clone() }
    }

    /// A copy of the mesh in the caller's coordinates.
    pub fn invert_mesh(&self, mesh: &Mesh) -> Mesh {
        Mesh { vertices: mesh.vertices.iter().map(|&p| self.invert(p)).collect(), ..mesh.clone() }
    }
}

impl Mesh {
    /// The mesh in its own normalized frame, with the transform that undoes it.
    pub fn normalized(&self) -> Result<(Mesh, Normalization), MeshError> {
        let n = Normalization::fit(&self.vertices)?;
        Ok((n.apply_mesh(self), n))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn box_maps_to_unit_cube_longest_side() {
        let pts = [[10.0, 20.0, 30.0], [14.0, 21.0, 30.5]];
        let n = Normalization::fit(&pts).unwrap();
        assert_eq!(n.center, [12.0, 20.5, 30.25]);
        assert_eq!(n.half_extent, 2.0);
        assert_eq!(n.apply(pts[0]), [-1.0, -0.25, -0.125]);
        assert_eq!(n.apply(pts[1]), [1.0, 0.25, 0.125]);
    }

    #[test]
    fn degenerate_inputs_are_errors() {
        assert!(Normalization::fit(&[]).is_err());
        assert!(Normalization::fit(&[[1.0, 2.0, 3.0]; 4]).is_err());
        assert!(Normalization::fit(&[[0.0; 3], [f32::INFINITY, 0.0, 0.0]]).is_err());
    }

    proptest! {
        #[test]
        fn invert_undoes_apply(
            pts in prop::collection::vec(prop::array::uniform3(-1e4f32..1e4), 2..50)
        ) {
            prop_assume!(Normalization::fit(&pts).is_ok());
            let n = Normalization::fit(&pts).unwrap();
            for p in &pts {
                let q = n.apply(*p);
                prop_assert!(q.iter().all(|c| c.abs() <= 1.0 + 1e-5));
                let back = n.invert(q);
                for k in 0..3 {
                    prop_assert!((back[k] - p[k]).abs() <= 1e-3 * (1.0 + p[k].abs()));
                }
            }
        }
    }
}
