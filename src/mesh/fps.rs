/// Exact farthest point sampling: `k` indices into `points`, starting at `start`, each next one
/// the point farthest from all chosen so far. O(k x m) time, O(m) memory.
///
/// Returns all indices (in FPS order) when `k >= points.len()`; an empty vector for no points.
/// `start` is taken modulo the number of points, so any seed is a valid start.
pub fn farthest_point_sampling(points: &[[f32; 3]], k: usize, start: usize) -> Vec<usize> {
    let m = points.len();
    if m == 0 || k == 0 {
        return Vec::new();
    }
    let k = k.min(m);
    // Structure of arrays so the inner loop vectorizes.
    let xs: Vec<f32> = points.iter().map(|p| p[0]).collect();
    let ys: Vec<f32> = points.iter().map(|p| p[1]).collect();
    let zs: Vec<f32> = points.iter().map(|p| p[2]).collect();
    let mut nearest = vec![f32::INFINITY; m];
    let mut chosen = Vec::with_capacity(k);
    let mut current = start % m;
    for _ in 0..k {
        chosen.push(current);
        let (cx, cy, cz) = (xs[current], ys[current], zs[current]);
        for i in 0..m {
            let (dx, dy, dz) = (xs[i] - cx, ys[i] - cy, zs[i] - cz);
            nearest[i] = nearest[i].min(dx * dx + dy * dy + dz * dz);
        }
        // Ties go to the lowest index, so the result is deterministic. Chosen points have
        // distance 0 and are never picked again while any other point is farther.
        let mut best = (0usize, -1.0f32);
        for (i, &d) in nearest.iter().enumerate() {
            if d > best.1 {
                best = (i, d);
            }
        }
        current = best.0;
    }
    chosen
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn picks_extremes_of_a_line() {
        let pts: Vec<[f32; 3]> = (0..11).map(|i| [i as f32, 0.0, 0.0]).collect();
        assert_eq!(farthest_point_sampling(&pts, 3, 0), vec![0, 10, 5]);
    }

    #[test]
    fn k_larger_than_m_returns_every_point_once() {
        let pts = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let mut idx = farthest_point_sampling(&pts, 10, 7);
        assert_eq!(idx[0], 1);
        idx.sort();
        assert_eq!(idx, vec![0, 1, 2]);
        assert!(farthest_point_sampling(&[], 4, 0).is_empty());
    }

    #[test]
    fn duplicate_points_are_not_chosen_twice_before_distinct_ones() {
        let pts = [[0.0; 3], [0.0; 3], [0.0; 3], [1.0, 0.0, 0.0]];
        let idx = farthest_point_sampling(&pts, 2, 0);
        assert_eq!(idx, vec![0, 3]);
    }
}
