//! Checks shared by the baselines: finite points, enough of them, and how many dimensions
//! they span (a closed surface needs all three).

use super::BaselineError;

/// Points closer than this fraction of the set's bounding-box diagonal to a line or plane
/// count as lying on it: f32 input cannot place them more precisely than that.
const FLATNESS_TOLERANCE: f64 = 1e-6;

/// The points in f64, after checking that there are at least `needed` of them and that every
/// coordinate is finite.
pub(crate) fn checked_points(
    points: &[[f32; 3]],
    method: &'static str,
    needed: usize,
) -> Result<Vec<[f64; 3]>, BaselineError> {
    if points.len() < needed {
        return Err(BaselineError::TooFewPoints { method, needed, got: points.len() });
    }
    if let Some(index) = points.iter().position(|p| p.iter().any(|c| !c.is_finite())) {
        return Err(BaselineError::NonFinite { index });
    }
    Ok(points.iter().map(|p| p.map(f64::from)).collect())
}

/// Fails with [`BaselineError::Flat`] unless the points span three dimensions.
pub(crate) fn require_volume(points: &[[f64; 3]]) -> Result<(), BaselineError> {
    match affine_dimension(points) {
        0 => Err(BaselineError::Flat("all equal")),
        1 => Err(BaselineError::Flat("collinear")),
        2 => Err(BaselineError::Flat("coplanar")),
        _ => Ok(()),
    }
}

/// How many dimensions (0 to 3) the points span: grow a simplex greedily, each time taking the
/// point farthest from the span of the ones already taken.
fn affine_dimension(points: &[[f64; 3]]) -> usize {
    let Some(&origin) = points.first() else {
        return 0;
    };
    let tolerance = FLATNESS_TOLERANCE * bbox_diagonal(points);
    let farthest = |distance: &dyn Fn(&[f64; 3]) -> f64| {
        points.iter().map(|p| (distance(p), *p)).max_by(|a, b| a.0.total_cmp(&b.0))
    };
    let Some((d, p1)) = farthest(&|p| norm(sub(*p, origin))) else {
        return 0;
    };
    if d <= tolerance {
        return 0;
    }
    let axis = scale(sub(p1, origin), 1.0 / d);
    let from_line = |p: &[f64; 3]| norm(cross(axis, sub(*p, origin)));
    let Some((d, p2)) = farthest(&from_line) else {
        return 1;
    };
    if d <= tolerance {
        return 1;
    }
    let normal = cross(axis, sub(p2, origin));
    let normal = scale(normal, 1.0 / norm(normal));
    match farthest(&|p| dot(normal, sub(*p, origin)).abs()) {
        Some((d, _)) if d > tolerance => 3,
        _ => 2,
    }
}

fn bbox_diagonal(points: &[[f64; 3]]) -> f64 {
    let (lo, hi) =
        points.iter().fold(([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]), |(lo, hi), p| {
            (std::array::from_fn(|k| lo[k].min(p[k])), std::array::from_fn(|k| hi[k].max(p[k])))
        });
    norm(sub(hi, lo))
}

pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|k| a[k] - b[k])
}

pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

fn scale(a: [f64; 3], s: f64) -> [f64; 3] {
    a.map(|c| c * s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dimensions_of_simple_sets() {
        let o = [0.0; 3];
        assert_eq!(affine_dimension(&[o, o, o]), 0);
        assert_eq!(affine_dimension(&[o, [1.0, 1.0, 1.0], [2.0, 2.0, 2.0], o]), 1);
        assert_eq!(affine_dimension(&[o, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]]), 2);
        assert_eq!(affine_dimension(&[o, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), 3);
        // A tilted plane far from the origin is still a plane.
        let plane: Vec<[f64; 3]> = (0..50)
            .map(|i| {
                let (u, v) = ((i % 7) as f64, (i / 7) as f64);
                [1e3 + u, 2e3 + v, 3e3 + 0.5 * u - 0.25 * v]
            })
            .collect();
        assert_eq!(affine_dimension(&plane), 2);
    }

    #[test]
    fn checks_count_and_finiteness() {
        assert_eq!(
            checked_points(&[[0.0; 3]; 2], "hull", 4),
            Err(BaselineError::TooFewPoints { method: "hull", needed: 4, got: 2 })
        );
        let mut pts = vec![[0.0f32; 3]; 5];
        pts[3][1] = f32::NAN;
        assert_eq!(checked_points(&pts, "hull", 4), Err(BaselineError::NonFinite { index: 3 }));
    }
}
