//! Face-for-face agreement: how many of the ground truth's triangles the prediction has, corner
//! for corner. The Chamfer distance cannot tell a rebuilt box from a box-shaped heap of
//! slivers; this can, and it is what "rebuilds a primitive with every face right" means.

use kiddo::{ImmutableKdTree, SquaredEuclidean};

use crate::mesh::{Mesh, MeshError, Normalization};

use super::MetricsError;

/// One grid step of the 128-level grid over [-1, 1] is 2/127 = 0.0157. A prediction made from
/// a point cloud is decoded on the points' grid, not the ground truth's: the points' bounding
/// box falls short of the surface's (by 0.015 on average at 1,024 points on 40 lowpoly dev
/// meshes), so a right corner can land one step off. 1.5 steps accepts that and still rejects
/// the next grid line.
pub const DEFAULT_FACE_TOLERANCE: f32 = 0.024;

/// Faces of a prediction paired one to one with faces of the ground truth.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct FaceMatch {
    /// Predicted faces that have a ground-truth face of their own with the same corners.
    pub matched: usize,
    pub predicted: usize,
    pub truth: usize,
}

impl FaceMatch {
    /// Share of the ground truth's faces the prediction has.
    pub fn recall(&self) -> f64 {
        ratio(self.matched, self.truth)
    }

    /// Share of the prediction's faces that are in the ground truth.
    pub fn precision(&self) -> f64 {
        ratio(self.matched, self.predicted)
    }

    /// Every face right and none extra.
    pub fn is_exact(&self) -> bool {
        self.matched == self.truth && self.matched == self.predicted
    }
}

/// Face agreement over a set: means of the per-mesh shares, and how many meshes are exact.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct FaceSummary {
    pub meshes: usize,
    /// `None` when no mesh was matched.
    pub recall_mean: Option<f64>,
    pub precision_mean: Option<f64>,
    pub exact: usize,
}

pub fn summarize_faces(matches: &[FaceMatch]) -> FaceSummary {
    let mean = |f: fn(&FaceMatch) -> f64| {
        (!matches.is_empty()).then(|| matches.iter().map(f).sum::<f64>() / matches.len() as f64)
    };
    FaceSummary {
        meshes: matches.len(),
        recall_mean: mean(FaceMatch::recall),
        precision_mean: mean(FaceMatch::precision),
        exact: matches.iter().filter(|m| m.is_exact()).count(),
    }
}

/// `part / whole`, 0 when there is no whole.
pub(super) fn ratio(part: usize, whole: usize) -> f64 {
    if whole == 0 { 0.0 } else { part as f64 / whole as f64 }
}

/// Pairs predicted faces with ground-truth faces whose three corners are each within
/// `tolerance` of theirs (in either winding and any corner order), in the ground truth's
/// normalized frame (DESIGN.md's evaluation frame), each ground-truth face used once.
///
/// Faces are taken in the prediction's order and each takes the nearest free match by
/// centroid. With a tolerance below half the smallest edge, as for low-poly meshes at the
/// default, a face can match only its own counterpart and the pairing is the best one.
pub fn face_match(pred: &Mesh, gt: &Mesh, tolerance: f32) -> Result<FaceMatch, MetricsError> {
    gt.validate().map_err(MetricsError::InvalidGroundTruth)?;
    pred.validate().map_err(MetricsError::InvalidPrediction)?;
    if gt.faces.is_empty() {
        return Err(MetricsError::NoGroundTruthFaces);
    }
    if pred.faces.is_empty() {
        return Err(MetricsError::EmptyPrediction);
    }
    if !(tolerance.is_finite() && tolerance >= 0.0) {
        return Err(MetricsError::InvalidTolerance(tolerance));
    }
    let frame = Normalization::fit(&gt.vertices).map_err(MetricsError::InvalidGroundTruth)?;
    let truth = triangles(&frame.apply_mesh(gt));
    let predicted = triangles(&frame.apply_mesh(pred));

    let centroids: Vec<[f32; 3]> = truth.iter().map(centroid).collect();
    // Only a ground truth past 2^32 faces fails to build; it cannot have been loaded.
    let tree = ImmutableKdTree::<f32, 3>::new_from_slice(&centroids)
        .map_err(|e| MetricsError::InvalidGroundTruth(MeshError::invalid(e.to_string())))?;
    let mut taken = vec![false; truth.len()];
    let mut matched = 0;
    for face in &predicted {
        // Matching corners put the centroids within the tolerance too: a safe pre-filter.
        let near = tree
            .query(&centroid(face))
            .within::<SquaredEuclidean<f32>>(tolerance * tolerance)
            .execute();
        let hit = near
            .iter()
            .map(|n| n.item as usize)
            .find(|&i| !taken[i] && same_corners(face, &truth[i], tolerance));
        if let Some(i) = hit {
            taken[i] = true;
            matched += 1;
        }
    }
    Ok(FaceMatch { matched, predicted: predicted.len(), truth: truth.len() })
}

type Triangle = [[f32; 3]; 3];

fn triangles(mesh: &Mesh) -> Vec<Triangle> {
    mesh.faces.iter().map(|f| mesh.triangle(f)).collect()
}

fn centroid(t: &Triangle) -> [f32; 3] {
    std::array::from_fn(|a| (t[0][a] + t[1][a] + t[2][a]) / 3.0)
}

/// Some ordering of `b`'s corners puts each within `tolerance` (Euclidean) of `a`'s.
fn same_corners(a: &Triangle, b: &Triangle, tolerance: f32) -> bool {
    const ORDERS: [[usize; 3]; 6] =
        [[0, 1, 2], [1, 2, 0], [2, 0, 1], [0, 2, 1], [2, 1, 0], [1, 0, 2]];
    let close = |p: [f32; 3], q: [f32; 3]| {
        (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f32>() <= tolerance * tolerance
    };
    ORDERS.iter().any(|o| (0..3).all(|k| close(a[k], b[o[k]])))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::cuboid;
    use proptest::prelude::*;

    fn box_mesh() -> Mesh {
        cuboid([1.0, 0.6, 0.4])
    }

    #[test]
    fn a_mesh_matches_itself_in_any_face_order_and_winding() {
        let gt = box_mesh();
        let mut pred = gt.clone();
        pred.faces.reverse();
        // Reversed winding is the same face.
        pred.faces[0].swap(1, 2);
        let m = face_match(&pred, &gt, DEFAULT_FACE_TOLERANCE).unwrap();
        assert_eq!(m, FaceMatch { matched: 12, predicted: 12, truth: 12 });
        assert!(m.is_exact());
        assert_eq!((m.recall(), m.precision()), (1.0, 1.0));
    }

    #[test]
    fn a_missing_face_and_a_duplicate_are_both_counted() {
        let gt = box_mesh();
        let mut pred = gt.clone();
        pred.faces.pop();
        let first = pred.faces[0];
        pred.faces.push(first);
        let m = face_match(&pred, &gt, DEFAULT_FACE_TOLERANCE).unwrap();
        // The duplicate cannot take the face its twin already has.
        assert_eq!(m, FaceMatch { matched: 11, predicted: 12, truth: 12 });
        assert!(!m.is_exact());
    }

    #[test]
    fn corners_count_within_the_tolerance_and_not_beyond() {
        let gt = box_mesh();
        // The box spans 1.0 on x, so the normalized frame scales by 2.
        let nudge = |d: f32| {
            let mut pred = gt.clone();
            pred.vertices[0][0] += d / 2.0;
            face_match(&pred, &gt, DEFAULT_FACE_TOLERANCE).unwrap()
        };
        assert!(nudge(0.0157).is_exact(), "one grid step off still counts");
        let far = nudge(0.04);
        // Vertex 0 is a corner of some faces; exactly those stop matching.
        let touching = gt.faces.iter().filter(|f| f.contains(&0)).count();
        assert_eq!(far.matched, 12 - touching);
    }

    #[test]
    fn a_set_summary_averages_per_mesh_shares() {
        let exact = FaceMatch { matched: 12, predicted: 12, truth: 12 };
        let half = FaceMatch { matched: 3, predicted: 4, truth: 6 };
        let s = summarize_faces(&[exact, half]);
        assert_eq!((s.meshes, s.exact), (2, 1));
        assert_eq!(s.recall_mean, Some(0.75));
        assert_eq!(s.precision_mean, Some(0.875));
        assert_eq!(summarize_faces(&[]).recall_mean, None);
    }

    #[test]
    fn empty_or_faceless_inputs_are_errors_not_numbers() {
        let gt = box_mesh();
        let points = Mesh { faces: vec![], ..gt.clone() };
        assert!(matches!(face_match(&points, &gt, 0.02), Err(MetricsError::EmptyPrediction)));
        assert!(matches!(face_match(&gt, &points, 0.02), Err(MetricsError::NoGroundTruthFaces)));
        assert!(matches!(face_match(&gt, &gt, f32::NAN), Err(MetricsError::InvalidTolerance(_))));
    }

    /// Any vertices (NaN and infinities included) and any indices give a figure or an error.
    fn any_mesh() -> impl Strategy<Value = Mesh> {
        let coord = prop_oneof![8 => -2.0f32..2.0, 1 => Just(f32::NAN), 1 => Just(f32::INFINITY)];
        (
            prop::collection::vec(prop::array::uniform3(coord), 0..12),
            prop::collection::vec(prop::array::uniform3(0u32..14), 0..12),
        )
            .prop_map(|(vertices, faces)| Mesh { vertices, faces, normals: None })
    }

    proptest! {
        #[test]
        fn never_panics_and_matches_at_most_both_counts(
            pred in any_mesh(),
            gt in any_mesh(),
            tolerance in prop_oneof![0.0f32..0.5, Just(f32::NAN), Just(-1.0)],
        ) {
            if let Ok(m) = face_match(&pred, &gt, tolerance) {
                prop_assert!(m.matched <= m.predicted.min(m.truth));
                prop_assert_eq!((m.predicted, m.truth), (pred.faces.len(), gt.faces.len()));
            }
        }
    }
}
