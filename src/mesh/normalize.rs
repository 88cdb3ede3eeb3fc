use std::str::FromStr;

use super::{Mesh, MeshError, bounds};

/// Which of the caller's axes points up. The models' training shapes mostly stand on +y
/// (glTF's convention; the data set's Kenney kits lie, see `docs/decisions.md`, "The caller
/// says which axis is up"); many tools (Blender, CAD, 3D printing, most scans) put +z up, and
/// some shapes sent lying come back as clutter. Turning the input so that its up axis is +y,
/// and the result back, costs nothing: each turn swaps and negates coordinates, exactly.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum UpAxis {
    #[serde(rename = "x")]
    X,
    #[serde(rename = "-x")]
    NegX,
    #[default]
    #[serde(rename = "y")]
    Y,
    #[serde(rename = "-y")]
    NegY,
    #[serde(rename = "z")]
    Z,
    #[serde(rename = "-z")]
    NegZ,
}

impl UpAxis {
    /// Every axis by its name, as requests and the command line give it.
    pub const NAMES: [&str; 6] = ["x", "-x", "y", "-y", "z", "-z"];
    const ALL: [UpAxis; 6] = [Self::X, Self::NegX, Self::Y, Self::NegY, Self::Z, Self::NegZ];

    /// The caller's frame turned so that this axis is +y (a proper rotation).
    pub fn to_y_up(self, [x, y, z]: [f32; 3]) -> [f32; 3] {
        match self {
            Self::X => [-y, x, z],
            Self::NegX => [y, -x, z],
            Self::Y => [x, y, z],
            Self::NegY => [x, -y, -z],
            Self::Z => [x, z, -y],
            Self::NegZ => [x, -z, y],
        }
    }

    /// The inverse of [`Self::to_y_up`].
    pub fn from_y_up(self, [x, y, z]: [f32; 3]) -> [f32; 3] {
        match self {
            Self::X => [y, -x, z],
            Self::NegX => [-y, x, z],
            Self::Y => [x, y, z],
            Self::NegY => [x, -y, -z],
            Self::Z => [x, -z, y],
            Self::NegZ => [x, z, -y],
        }
    }
}

impl FromStr for UpAxis {
    type Err = String;

    /// "y", "z", "-z", ... ("+z" too, in either case).
    fn from_str(name: &str) -> Result<Self, String> {
        let lower = name.trim().to_ascii_lowercase();
        let plain = lower.strip_prefix('+').unwrap_or(&lower);
        Self::NAMES
            .iter()
            .position(|n| *n == plain)
            .map(|i| Self::ALL[i])
            .ok_or_else(|| format!("up axis {name:?}: use one of {}", Self::NAMES.join(", ")))
    }
}

/// The bounding-box normalization of DESIGN.md: the box's centre goes to the origin and its
/// longest side spans [-1, 1], after which the frame is turned so that the caller's up axis is
/// +y. It remembers the transform so that results can be put back in the caller's coordinates.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Normalization {
    /// Centre of the bounding box, in the caller's coordinates.
    pub center: [f64; 3],
    /// Half the longest side of the bounding box, in the caller's units.
    pub half_extent: f64,
    /// The caller's up axis (+y: no turn).
    #[serde(default)]
    pub up: UpAxis,
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
        Ok(Self { center, half_extent, up: UpAxis::Y })
    }

    /// The identity: for data already in the normalized frame.
    pub fn identity() -> Self {
        Self { center: [0.0; 3], half_extent: 1.0, up: UpAxis::Y }
    }

    /// The same, for a caller whose up axis is `up`. The box is the same either way: a turn
    /// between axes keeps it aligned with them.
    pub fn with_up(self, up: UpAxis) -> Self {
        Self { up, ..self }
    }

    /// Caller's coordinates -> normalized frame.
    pub fn apply(&self, p: [f32; 3]) -> [f32; 3] {
        let scaled =
            std::array::from_fn(|k| ((p[k] as f64 - self.center[k]) / self.half_extent) as f32);
        self.up.to_y_up(scaled)
    }

    /// Normalized frame -> caller's coordinates.
    pub fn invert(&self, p: [f32; 3]) -> [f32; 3] {
        let p = self.up.from_y_up(p);
        std::array::from_fn(|k| (p[k] as f64 * self.half_extent + self.center[k]) as f32)
    }

    /// A copy of the mesh in the normalized frame (normals turn with it; the rest of the
    /// transform is a uniform scale and a shift, which leaves them as they are).
    pub fn apply_mesh(&self, mesh: &Mesh) -> Mesh {
        Mesh {
            vertices: mesh.vertices.iter().map(|&p| self.apply(p)).collect(),
            normals: mesh.normals.as_ref().map(|n| n.iter().map(|&n| self.up.to_y_up(n)).collect()),
            ..mesh.clone()
        }
    }

    /// A copy of the mesh in the caller's coordinates.
    pub fn invert_mesh(&self, mesh: &Mesh) -> Mesh {
        Mesh {
            vertices: mesh.vertices.iter().map(|&p| self.invert(p)).collect(),
            normals: mesh
                .normals
                .as_ref()
                .map(|n| n.iter().map(|&n| self.up.from_y_up(n)).collect()),
            ..mesh.clone()
        }
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

    #[test]
    fn every_up_axis_turns_onto_y_and_back_without_mirroring() {
        let (x, y, z) = ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]);
        let cross = |a: [f32; 3], b: [f32; 3]| {
            [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
        };
        for (name, axis) in UpAxis::NAMES.iter().zip([x, x, y, y, z, z]) {
            let up: UpAxis = name.parse().unwrap();
            let sign = if name.starts_with('-') { -1.0 } else { 1.0 };
            assert_eq!(up.to_y_up(axis.map(|c| c * sign)), y, "{name}");
            // A rotation keeps handedness: x cross y stays z.
            assert_eq!(cross(up.to_y_up(x), up.to_y_up(y)), up.to_y_up(z), "{name}");
            for p in [x, y, z, [0.5, -2.0, 3.0]] {
                assert_eq!(up.from_y_up(up.to_y_up(p)), p, "{name}");
            }
        }
        assert_eq!("+Z".parse::<UpAxis>(), Ok(UpAxis::Z));
        assert!("w".parse::<UpAxis>().unwrap_err().contains("x, -x, y, -y, z, -z"));
    }

    #[test]
    fn a_z_up_mesh_is_normalized_standing_on_y_and_comes_back_as_it_was() {
        let mesh = Mesh {
            vertices: vec![[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 4.0]],
            faces: vec![[0, 1, 2]],
            normals: Some(vec![[0.0, -1.0, 0.0]; 3]),
        };
        let n = Normalization::fit(&mesh.vertices).unwrap().with_up(UpAxis::Z);
        let normalized = n.apply_mesh(&mesh);
        assert_eq!(
            normalized.vertices,
            vec![[-0.5, -1.0, 0.0], [0.5, -1.0, 0.0], [-0.5, 1.0, 0.0]]
        );
        assert_eq!(normalized.normals, Some(vec![[0.0, 0.0, 1.0]; 3]));
        assert_eq!(n.invert_mesh(&normalized), mesh);
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
