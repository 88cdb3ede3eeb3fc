//! Constrained decoding: which values coordinate j of the next face may take so that the face
//! is canonical (v0 the strict minimum vertex, v1 != v2) and strictly after the previous face
//! in lexicographic ZYX order. The mask is exact: a value is allowed iff some completion of the
//! face satisfies every constraint, so once a face has started the mask is never empty; only at
//! coordinate 0 can nothing be allowed (the previous face is already the last possible one),
//! and then the sequence ends.

use super::FaceToken;
use super::config::COORDS_PER_FACE;

/// Rank of a vertex whose first `part.len()` coordinates are given and the rest set to `fill`,
/// in the lexicographic (z, y, x) order of the q^3 grid.
fn rank(part: &[u16], fill: u16, q: u64) -> u64 {
    (0..3).fold(0, |acc, i| acc * q + u64::from(*part.get(i).unwrap_or(&fill)))
}

/// Does some completion of `prefix` form a canonical face (v1 > v0, v2 > v0, v1 != v2)?
fn canonical_completion_exists(prefix: &[u16], q: u64) -> bool {
    let top = q * q * q - 1;
    let len = prefix.len();
    if len <= 3 {
        // The smallest completion of v0 leaves the most room; two distinct vertices above it
        // are needed.
        return top - rank(prefix, 0, q) >= 2;
    }
    let v0 = rank(&prefix[..3], 0, q);
    if top - v0 < 2 {
        return false;
    }
    if len <= 6 {
        // v1's largest completion must exceed v0; v2 then has another vertex above v0.
        return rank(&prefix[3..], q as u16 - 1, q) > v0;
    }
    let v1 = rank(&prefix[3..6], 0, q);
    if v1 <= v0 {
        return false;
    }
    let lo = rank(&prefix[6..], 0, q).max(v0 + 1);
    let hi = rank(&prefix[6..], q as u16 - 1, q);
    lo <= hi && hi - lo + 1 > u64::from((lo..=hi).contains(&v1))
}

/// Does some completion of `prefix` give a canonical face strictly after `prev`?
pub fn completion_exists(prefix: &[u16], prev: Option<&FaceToken>, q: usize) -> bool {
    let q64 = q as u64;
    if prefix.len() > COORDS_PER_FACE || !canonical_completion_exists(prefix, q64) {
        return false;
    }
    let Some(prev) = prev else { return true };
    match prefix.cmp(&prev[..prefix.len()]) {
        std::cmp::Ordering::Greater => true,
        std::cmp::Ordering::Less => false,
        std::cmp::Ordering::Equal => {
            // The face must first exceed prev at some k >= len. At a v0 coordinate the
            // smallest such value is best, at a v1 coordinate the largest; at a v2 coordinate
            // the largest, or the one below it when the largest is exactly v1.
            let mut base = prefix.to_vec();
            for k in prefix.len()..COORDS_PER_FACE {
                let above = usize::from(prev[k]) + 1;
                let candidates = [above, q.saturating_sub(1), q.saturating_sub(2)];
                for c in candidates.into_iter().filter(|&c| c >= above && c < q) {
                    base.push(c as u16);
                    let ok = canonical_completion_exists(&base, q64);
                    base.pop();
                    if ok {
                        return true;
                    }
                }
                base.push(prev[k]);
            }
            false
        }
    }
}

/// Writes into `allowed` (resized to q) which values coordinate `prefix.len()` may take.
/// Returns how many are allowed.
pub fn allowed_values(
    prefix: &[u16],
    prev: Option<&FaceToken>,
    q: usize,
    allowed: &mut Vec<bool>,
) -> usize {
    allowed.clear();
    allowed.resize(q, false);
    if prefix.len() >= COORDS_PER_FACE {
        return 0;
    }
    let mut candidate = Vec::with_capacity(COORDS_PER_FACE);
    candidate.extend_from_slice(prefix);
    candidate.push(0);
    let mut count = 0;
    for (v, slot) in allowed.iter_mut().enumerate() {
        candidate[prefix.len()] = v as u16;
        *slot = completion_exists(&candidate, prev, q);
        count += usize::from(*slot);
    }
    count
}

/// A face that satisfies the constraints: canonical and strictly after `prev`.
pub fn is_valid_next(face: &FaceToken, prev: Option<&FaceToken>, q: usize) -> bool {
    face.iter().all(|&c| usize::from(c) < q) && completion_exists(face, prev, q)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Every canonical face of a q^3 grid, by brute force.
    fn all_canonical(q: u16) -> Vec<FaceToken> {
        let verts: Vec<[u16; 3]> =
            (0..q).flat_map(|z| (0..q).flat_map(move |y| (0..q).map(move |x| [z, y, x]))).collect();
        let mut out = Vec::new();
        for a in &verts {
            for b in verts.iter().filter(|b| *b > a) {
                for c in verts.iter().filter(|c| *c > a && *c != b) {
                    let f = [a[0], a[1], a[2], b[0], b[1], b[2], c[0], c[1], c[2]];
                    out.push(f);
                }
            }
        }
        out
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(400))]

        #[test]
        fn completion_exists_agrees_with_brute_force(
            q in 2u16..=3,
            prev in proptest::option::of(proptest::array::uniform9(0u16..3)),
            prefix in proptest::collection::vec(0u16..3, 0..=9),
        ) {
            let prev = prev.map(|p| p.map(|c| c.min(q - 1)));
            let prefix: Vec<u16> = prefix.into_iter().map(|c| c.min(q - 1)).collect();
            let brute = all_canonical(q)
                .iter()
                .any(|f| f.starts_with(&prefix) && prev.is_none_or(|p| *f > p));
            prop_assert_eq!(completion_exists(&prefix, prev.as_ref(), q as usize), brute);
        }

        #[test]
        fn a_started_face_never_runs_out_of_values(
            q in 2usize..=8,
            prev in proptest::option::of(proptest::array::uniform9(0u16..8)),
            picks in proptest::array::uniform9(any::<u16>()),
        ) {
            let prev = prev.map(|p| p.map(|c| c.min(q as u16 - 1)));
            let mut allowed = Vec::new();
            let mut face = Vec::new();
            for (j, pick) in picks.iter().enumerate() {
                let n = allowed_values(&face, prev.as_ref(), q, &mut allowed);
                if j == 0 && n == 0 {
                    // Dead end: no canonical face after prev. Only possible at coordinate 0.
                    prop_assert!(!completion_exists(&[], prev.as_ref(), q));
                    return Ok(());
                }
                prop_assert!(n > 0, "empty mask at coordinate {j} after {face:?}");
                let v = allowed.iter().enumerate().filter(|(_, a)| **a).nth(usize::from(*pick) % n).unwrap().0;
                face.push(v as u16);
            }
            let face: FaceToken = face.try_into().unwrap();
            prop_assert!(is_valid_next(&face, prev.as_ref(), q));
            prop_assert!(prev.is_none_or(|p| face > p));
        }
    }

    #[test]
    fn the_last_face_is_a_dead_end() {
        let q = 4u16;
        let last = *all_canonical(q).iter().max().unwrap();
        let mut allowed = Vec::new();
        assert_eq!(allowed_values(&[], Some(&last), q as usize, &mut allowed), 0);
        assert!(allowed_values(&[], None, q as usize, &mut allowed) > 0);
    }
}
