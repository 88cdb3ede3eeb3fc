//! Constrained decoding: which values coordinate j of the next face may take so that the face
//! is canonical (v0 the strict minimum vertex, v1 != v2), strictly after the previous face in
//! lexicographic ZYX order, not a repeat of an earlier face with the opposite winding (the
//! tokenizer drops those: same three vertices), and not flat (three collinear vertices: a face
//! with no area covers nothing, and an undertrained decoder emits runs of them).
//!
//! A value is allowed iff some completion of the face satisfies every constraint, so once a
//! face has started its masks are never empty. The exceptions are the opposite-winding and
//! flat-face rules, which are only checked once v0 and v1 are known (coordinates 5..8): on a
//! tiny grid they could then exclude every remaining v2. Generation treats an empty mask like
//! the dead end at coordinate 0 (no canonical face can follow the last one): the mesh ends.

use super::FaceToken;
use super::config::COORDS_PER_FACE;

/// Rank of a vertex whose first `part.len()` coordinates are given and the rest set to `fill`,
/// in the lexicographic (z, y, x) order of the q^3 grid.
fn rank(part: &[u16], fill: u16, q: u64) -> u64 {
    (0..3).fold(0, |acc, i| acc * q + u64::from(*part.get(i).unwrap_or(&fill)))
}

/// Does some completion of `prefix` (at most 5 coordinates: v1 not complete) form a canonical
/// face (v1 > v0, v2 > v0, v1 != v2)?
fn canonical_completion_exists(prefix: &[u16], q: u64) -> bool {
    let top = q * q * q - 1;
    if prefix.len() <= 3 {
        // The smallest completion of v0 leaves the most room; two distinct vertices above it
        // are needed.
        return top - rank(prefix, 0, q) >= 2;
    }
    let v0 = rank(&prefix[..3], 0, q);
    // v1's largest completion must exceed v0, and v2 needs another vertex above v0.
    top - v0 >= 2 && rank(&prefix[3..], q as u16 - 1, q) > v0
}

/// With v0 and v1 fixed (`prefix` has 6..=9 coordinates): is there a v2 completing the prefix
/// that is above v0, differs from v1, is off the line through them, makes the face exceed
/// `prev`, and does not repeat an earlier face (v0, v2, v1) with the opposite winding?
fn last_vertex_exists(prefix: &[u16], earlier: &[FaceToken], q: u64) -> bool {
    let Some(rule) = LastVertex::new(&prefix[..6], earlier, q) else {
        return false;
    };
    let Some((lo, hi)) = rule.range(&prefix[6..], q) else {
        return false;
    };
    let span = hi - lo + 1;
    // A line meets the grid in at most q points: only a narrow range can run out of them.
    span > rule.taken_within(lo, hi) + q
        || span > rule.with_line(&prefix[..6], q).taken_within(lo, hi)
}

/// What a face's last vertex v2 may be once v0 and v1 are fixed: a rank above `floor` and
/// none of `taken`. Built once for all the values of a v2 coordinate (see
/// [`allowed_values`]): the flat-face line alone is up to q grid points to walk.
struct LastVertex {
    /// v2 must be above v0, and above prev's v2 when the face starts as prev does.
    floor: u64,
    /// Sorted ranks v2 may not take: v1, the v2 of opposite windings of earlier faces, and
    /// once [`Self::with_line`] has added them, the grid points on the line through v0 and v1.
    taken: Vec<u64>,
}

impl LastVertex {
    /// The rule after the sequence `earlier` for the first two vertices `v0v1` (6
    /// coordinates), without the line; `None` when no v2 can complete them (v1 not above v0,
    /// or the face would come before prev).
    fn new(v0v1: &[u16], earlier: &[FaceToken], q: u64) -> Option<Self> {
        let v0 = rank(&v0v1[..3], 0, q);
        let v1 = rank(&v0v1[3..], 0, q);
        if v1 <= v0 {
            return None;
        }
        let mut floor = v0;
        if let Some(prev) = earlier.last() {
            match v0v1.cmp(&prev[..6]) {
                std::cmp::Ordering::Less => return None,
                std::cmp::Ordering::Equal => floor = floor.max(rank(&prev[6..], 0, q)),
                std::cmp::Ordering::Greater => {}
            }
        }
        // Faces sharing v0 form the tail of a sorted sequence.
        let windings = earlier
            .iter()
            .rev()
            .take_while(|f| f[..3] == v0v1[..3])
            .filter(|f| f[6..] == v0v1[3..])
            .map(|f| rank(&f[3..6], 0, q));
        let mut taken: Vec<u64> = windings.chain([v1]).collect();
        taken.sort_unstable();
        taken.dedup();
        Some(Self { floor, taken })
    }

    /// The rule with the points of the line through v0 and v1 taken too (flat faces).
    fn with_line(mut self, v0v1: &[u16], q: u64) -> Self {
        self.taken.extend(line_beyond(&v0v1[..3], &v0v1[3..], q).map(|p| rank(&p, 0, q)));
        self.taken.sort_unstable();
        self.taken.dedup();
        self
    }

    /// The ranks (lo, hi) of the v2 that complete `part` (its first coordinates) within the
    /// floor; `None` when there are none.
    fn range(&self, part: &[u16], q: u64) -> Option<(u64, u64)> {
        let lo = rank(part, 0, q).max(self.floor + 1);
        let hi = rank(part, q as u16 - 1, q);
        (lo <= hi).then_some((lo, hi))
    }

    /// How many of `lo..=hi` are taken.
    fn taken_within(&self, lo: u64, hi: u64) -> u64 {
        let below = |bound: u64| self.taken.partition_point(|&w| w < bound);
        (below(hi + 1) - below(lo)) as u64
    }
}

/// The grid points after `v0` on the line through `v0` and `v1` (v1 > v0), in order: the
/// places where v2 would make a flat face.
fn line_beyond(v0: &[u16], v1: &[u16], q: u64) -> impl Iterator<Item = [u16; 3]> {
    let d: [i64; 3] = std::array::from_fn(|i| i64::from(v1[i]) - i64::from(v0[i]));
    let g = d.iter().fold(0, |g, &c| gcd(g, c.unsigned_abs())).max(1) as i64;
    let step = d.map(|c| c / g);
    let start: [i64; 3] = std::array::from_fn(|i| i64::from(v0[i]));
    (1..).map_while(move |k| {
        let p: [i64; 3] = std::array::from_fn(|i| start[i] + k * step[i]);
        p.iter().all(|&c| (0..q as i64).contains(&c)).then(|| p.map(|c| c as u16))
    })
}

fn gcd(a: u64, b: u64) -> u64 {
    if b == 0 { a } else { gcd(b, a % b) }
}

/// Does some completion of `prefix` give a face allowed after the sequence `earlier`?
pub fn completion_exists(prefix: &[u16], earlier: &[FaceToken], q: usize) -> bool {
    let q64 = q as u64;
    if prefix.len() > COORDS_PER_FACE {
        return false;
    }
    if prefix.len() >= 6 {
        return last_vertex_exists(prefix, earlier, q64);
    }
    if !canonical_completion_exists(prefix, q64) {
        return false;
    }
    let Some(prev) = earlier.last() else { return true };
    match prefix.cmp(&prev[..prefix.len()]) {
        std::cmp::Ordering::Greater => true,
        std::cmp::Ordering::Less => false,
        std::cmp::Ordering::Equal => {
            // The face must first exceed prev at some coordinate k >= len. At a v0 coordinate
            // the smallest such value leaves the most room, at v1's first two coordinates the
            // largest does; if v0 and v1 end up equal to prev's, the exact v2 check decides.
            // At v1's last coordinate every value is tried: the exact check there also
            // weighs the earlier faces.
            let mut base = prefix.to_vec();
            for (k, &p) in prev.iter().enumerate().take(6).skip(prefix.len()) {
                let above = usize::from(p) + 1;
                let tries = match k {
                    0..3 => above..(above + 1).min(q),
                    3 | 4 => (q - 1).max(above)..q,
                    _ => above..q,
                };
                for c in tries {
                    base.push(c as u16);
                    let ok = completion_exists(&base, earlier, q);
                    base.pop();
                    if ok {
                        return true;
                    }
                }
                base.push(p);
            }
            last_vertex_exists(&base, earlier, q64)
        }
    }
}

/// Which values coordinate `prefix.len()` of the next face may take after the sequence
/// `earlier`, asked a value at a time: a face beam asks only about the few values that could
/// enter it, not about all q.
pub struct NextValues<'a> {
    prefix: &'a [u16],
    earlier: &'a [FaceToken],
    q: usize,
    /// At v2's coordinates every value shares v0 and v1, and so the rule for v2: built once,
    /// it decides each value as [`completion_exists`] would. `Some(None)`: no v2 can follow.
    last_vertex: Option<Option<LastVertex>>,
}

impl<'a> NextValues<'a> {
    /// The values after `prefix`, the next face's coordinates so far.
    pub fn new(prefix: &'a [u16], earlier: &'a [FaceToken], q: usize) -> Self {
        let last_vertex = (6..COORDS_PER_FACE).contains(&prefix.len()).then(|| {
            LastVertex::new(&prefix[..6], earlier, q as u64)
                .map(|rule| rule.with_line(&prefix[..6], q as u64))
        });
        Self { prefix, earlier, q, last_vertex }
    }

    /// Does some completion of the prefix and `value` give a face allowed after `earlier`?
    pub fn allows(&self, value: usize) -> bool {
        let len = self.prefix.len();
        if len >= COORDS_PER_FACE || value >= self.q {
            return false;
        }
        let mut candidate = [0u16; COORDS_PER_FACE];
        candidate[..len].copy_from_slice(self.prefix);
        candidate[len] = value as u16;
        match &self.last_vertex {
            None => completion_exists(&candidate[..=len], self.earlier, self.q),
            Some(None) => false,
            Some(Some(rule)) => rule
                .range(&candidate[6..=len], self.q as u64)
                .is_some_and(|(lo, hi)| hi - lo + 1 > rule.taken_within(lo, hi)),
        }
    }
}

/// Writes into `allowed` (resized to q) which values coordinate `prefix.len()` of the next
/// face may take after the sequence `earlier`. Returns how many are allowed.
pub fn allowed_values(
    prefix: &[u16],
    earlier: &[FaceToken],
    q: usize,
    allowed: &mut Vec<bool>,
) -> usize {
    let next = NextValues::new(prefix, earlier, q);
    allowed.clear();
    allowed.extend((0..q).map(|v| next.allows(v)));
    allowed.iter().filter(|&&a| a).count()
}

/// A face that satisfies the constraints after the sequence `earlier`.
pub fn is_valid_next(face: &FaceToken, earlier: &[FaceToken], q: usize) -> bool {
    face.iter().all(|&c| usize::from(c) < q) && completion_exists(face, earlier, q)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tokenize::is_canonical_sequence;
    use proptest::prelude::*;

    /// Every canonical face of a q^3 grid, by brute force, in increasing order.
    fn all_canonical(q: u16) -> Vec<FaceToken> {
        let verts: Vec<[u16; 3]> =
            (0..q).flat_map(|z| (0..q).flat_map(move |y| (0..q).map(move |x| [z, y, x]))).collect();
        let mut out = Vec::new();
        for a in &verts {
            for b in verts.iter().filter(|b| *b > a) {
                for c in verts.iter().filter(|c| *c > a && *c != b) {
                    out.push([a[0], a[1], a[2], b[0], b[1], b[2], c[0], c[1], c[2]]);
                }
            }
        }
        out.sort_unstable();
        out
    }

    /// A tokenizer-valid sequence made of the canonical faces at the given picks.
    fn sequence_from(all: &[FaceToken], picks: &[usize]) -> Vec<FaceToken> {
        let mut seq: Vec<FaceToken> = picks.iter().map(|p| all[p % all.len()]).collect();
        seq.sort_unstable();
        seq.dedup();
        let mut out: Vec<FaceToken> = Vec::new();
        for f in seq {
            let mut candidate = out.clone();
            candidate.push(f);
            if is_canonical_sequence(&candidate) {
                out = candidate;
            }
        }
        out
    }

    /// Are the three vertices of `face` on one line?
    fn is_flat(face: &FaceToken) -> bool {
        let v = |i: usize| -> [i64; 3] { std::array::from_fn(|k| i64::from(face[3 * i + k])) };
        let (a, b, c) = (v(0), v(1), v(2));
        let (u, w) =
            ([b[0] - a[0], b[1] - a[1], b[2] - a[2]], [c[0] - a[0], c[1] - a[1], c[2] - a[2]]);
        u[1] * w[2] == u[2] * w[1] && u[2] * w[0] == u[0] * w[2] && u[0] * w[1] == u[1] * w[0]
    }

    fn reversed(f: &FaceToken) -> FaceToken {
        [f[0], f[1], f[2], f[6], f[7], f[8], f[3], f[4], f[5]]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]

        /// Exact once v1 is known (6+ coordinates); before that it never rules out a face that
        /// could follow.
        #[test]
        fn completion_exists_agrees_with_brute_force(
            q in 2u16..=3,
            picks in proptest::collection::vec(any::<usize>(), 0..12),
            prefix in proptest::collection::vec(0u16..3, 0..=9),
        ) {
            let all = all_canonical(q);
            let earlier = sequence_from(&all, &picks);
            let prefix: Vec<u16> = prefix.into_iter().map(|c| c.min(q - 1)).collect();
            let brute = all.iter().any(|f| {
                f.starts_with(&prefix)
                    && earlier.last().is_none_or(|p| f > p)
                    && !earlier.contains(&reversed(f))
                    && !is_flat(f)
            });
            let ours = completion_exists(&prefix, &earlier, q as usize);
            if prefix.len() >= 6 {
                prop_assert_eq!(ours, brute);
            } else {
                prop_assert!(ours || !brute, "ruled out a possible face");
            }
        }

        /// At v2's coordinates one rule decides every value: as the exact check would, value
        /// by value.
        #[test]
        fn v2_masks_agree_with_the_check_of_each_value(
            q in 2usize..=6,
            picks in proptest::collection::vec(any::<usize>(), 0..40),
            prefix in proptest::collection::vec(0u16..6, 6..=8),
        ) {
            let earlier = sequence_from(&all_canonical(q as u16), &picks);
            let mut prefix: Vec<u16> = prefix.into_iter().map(|c| c.min(q as u16 - 1)).collect();
            let mut allowed = Vec::new();
            let n = allowed_values(&prefix, &earlier, q, &mut allowed);
            let each: Vec<bool> = (0..q as u16)
                .map(|v| {
                    prefix.push(v);
                    let ok = completion_exists(&prefix, &earlier, q);
                    prefix.pop();
                    ok
                })
                .collect();
            prop_assert_eq!(&allowed, &each);
            prop_assert_eq!(n, each.iter().filter(|&&a| a).count());
        }

        /// Walking the masks with arbitrary choices: a face that has started finds a value at
        /// every coordinate except possibly v1's last (5), where the opposite-winding rule is
        /// first weighed; every completed face extends the sequence validly.
        #[test]
        fn masks_only_run_dry_where_documented(
            q in 2usize..=6,
            picks in proptest::collection::vec(any::<usize>(), 0..40),
            choices in proptest::collection::vec(any::<u16>(), 9 * 20),
        ) {
            let all = all_canonical(q as u16);
            let mut seq = sequence_from(&all, &picks);
            let mut allowed = Vec::new();
            'faces: for choice in choices.chunks(9) {
                let mut face = Vec::new();
                for (j, pick) in choice.iter().enumerate() {
                    let n = allowed_values(&face, &seq, q, &mut allowed);
                    if n == 0 {
                        prop_assert!(j == 0 || j == 5, "empty mask at coordinate {j} after {face:?}");
                        break 'faces;
                    }
                    let v = allowed.iter().enumerate().filter(|(_, a)| **a).nth(usize::from(*pick) % n).unwrap().0;
                    face.push(v as u16);
                }
                let face: FaceToken = face.try_into().unwrap();
                prop_assert!(is_valid_next(&face, &seq, q));
                seq.push(face);
                prop_assert!(is_canonical_sequence(&seq), "{seq:?}");
            }
        }
    }

    #[test]
    fn the_last_face_is_a_dead_end() {
        let q = 4u16;
        let last = *all_canonical(q).last().unwrap();
        let mut allowed = Vec::new();
        assert_eq!(allowed_values(&[], &[last], q as usize, &mut allowed), 0);
        assert!(allowed_values(&[], &[], q as usize, &mut allowed) > 0);
    }

    #[test]
    fn flat_faces_are_masked() {
        let q = 8;
        let mut allowed = Vec::new();
        // v0 = (0,0,0), v1 = (1,2,3): v2 = (2,4,6) is on their line, (2,4,5) is not.
        allowed_values(&[0, 0, 0, 1, 2, 3, 2, 4], &[], q, &mut allowed);
        assert!(!allowed[6] && allowed[5] && allowed[7]);
        assert!(is_flat(&[0, 0, 0, 1, 2, 3, 2, 4, 6]) && !is_flat(&[0, 0, 0, 1, 2, 3, 2, 4, 5]));
        // v0 and v1 differ in x only: once v2 shares their z and y, no x is left.
        assert_eq!(allowed_values(&[1, 1, 0, 1, 1, 5, 1, 1], &[], q, &mut allowed), 0);
        assert!(allowed_values(&[1, 1, 0, 1, 1, 5, 1], &[], q, &mut allowed) > 0);
        assert!(!allowed[1] && allowed[2]);
    }

    #[test]
    fn the_opposite_winding_of_an_earlier_face_is_masked() {
        let q = 8;
        let earlier = [[0, 0, 0, 1, 0, 0, 2, 0, 0]];
        let mut allowed = Vec::new();
        // v0 = (0,0,0), v1 = (2,0,0): v2 = (1,0,0) would repeat the earlier face.
        allowed_values(&[0, 0, 0, 2, 0, 0, 1, 0], &earlier, q, &mut allowed);
        assert!(!allowed[0]);
        assert!(allowed[1]);
    }
}
