//! Which waiting requests start now: first come, first served among those that fit, except
//! that a request that has waited past the aging limit is no longer overtaken.

use std::time::Duration;

/// A waiting request as admission sees it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate {
    /// Face budget the request reserves while it runs.
    pub faces: usize,
    pub waited: Duration,
}

/// Free capacity of the running batch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Capacity {
    pub slots: usize,
    pub faces: usize,
    /// Requests that may start (be encoded) in this iteration.
    pub starts: usize,
}

/// Indices (in queue order) of the candidates to start.
pub fn admit(queue: &[Candidate], mut free: Capacity, aging: Duration) -> Vec<usize> {
    let mut picked = Vec::new();
    for (i, c) in queue.iter().enumerate() {
        if free.slots == 0 || free.starts == 0 {
            break;
        }
        if c.faces <= free.faces {
            picked.push(i);
            free.slots -= 1;
            free.starts -= 1;
            free.faces -= c.faces;
        } else if c.waited >= aging {
            // It waits for room; nobody behind it takes that room first.
            break;
        }
    }
    picked
}

#[cfg(test)]
mod tests {
    use super::*;

    fn c(faces: usize, waited_ms: u64) -> Candidate {
        Candidate { faces, waited: Duration::from_millis(waited_ms) }
    }

    const AGING: Duration = Duration::from_secs(1);

    #[test]
    fn first_come_first_served_within_slots_and_starts() {
        let q = [c(10, 0), c(10, 0), c(10, 0)];
        assert_eq!(admit(&q, Capacity { slots: 2, faces: 100, starts: 5 }, AGING), [0, 1]);
        assert_eq!(admit(&q, Capacity { slots: 5, faces: 100, starts: 1 }, AGING), [0]);
    }

    #[test]
    fn small_requests_pass_one_that_does_not_fit_until_it_has_aged() {
        let young = [c(500, 100), c(10, 0), c(20, 0)];
        assert_eq!(admit(&young, Capacity { slots: 4, faces: 100, starts: 4 }, AGING), [1, 2]);
        let aged = [c(500, 1500), c(10, 0), c(20, 0)];
        assert!(admit(&aged, Capacity { slots: 4, faces: 100, starts: 4 }, AGING).is_empty());
        assert_eq!(admit(&aged, Capacity { slots: 4, faces: 510, starts: 4 }, AGING), [0, 1]);
    }
}
