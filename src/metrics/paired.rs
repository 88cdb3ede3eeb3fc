//! Two predictions of one set compared mesh by mesh. Set means of two models often differ by
//! less than their spread over meshes; the per-mesh difference and its standard error say
//! whether a change is a gain or noise.

use std::collections::HashMap;

use super::EvalRecord;

/// Chamfer distance of A minus that of B, over the meshes both have a distance for.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PairedDifference {
    /// Meshes with a distance in both.
    pub pairs: usize,
    /// Meshes of A left out: a failure in A or in B, or no record of that name in B.
    pub unpaired: usize,
    /// Mean of A - B: negative when A is closer. `None` without pairs.
    pub mean: Option<f64>,
    /// Standard error of the mean (sample deviation / sqrt(pairs)). `None` under two pairs.
    pub standard_error: Option<f64>,
    /// Pairs where A is strictly closer, and where B is.
    pub a_better: usize,
    pub b_better: usize,
}

/// Pairs A's records with B's by name.
pub fn paired_chamfer(a: &[EvalRecord], b: &[EvalRecord]) -> PairedDifference {
    let chamfer = |r: &EvalRecord| r.result.as_ref().ok().map(|d| d.chamfer);
    let b_by_name: HashMap<&str, f64> =
        b.iter().filter_map(|r| Some((r.name.as_str(), chamfer(r)?))).collect();
    let diffs: Vec<f64> =
        a.iter().filter_map(|r| Some(chamfer(r)? - b_by_name.get(r.name.as_str())?)).collect();
    let n = diffs.len();
    let mean = (n > 0).then(|| diffs.iter().sum::<f64>() / n as f64);
    let standard_error = mean.filter(|_| n > 1).map(|m| {
        let variance = diffs.iter().map(|d| (d - m).powi(2)).sum::<f64>() / (n - 1) as f64;
        (variance / n as f64).sqrt()
    });
    PairedDifference {
        pairs: n,
        unpaired: a.len() - n,
        mean,
        standard_error,
        a_better: diffs.iter().filter(|&&d| d < 0.0).count(),
        b_better: diffs.iter().filter(|&&d| d > 0.0).count(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::Distances;

    fn ok(name: &str, chamfer: f64) -> EvalRecord {
        let d = Distances { chamfer, hausdorff: chamfer, accuracy: 0.0, completeness: chamfer };
        EvalRecord { name: name.into(), result: Ok(d) }
    }

    fn failed(name: &str) -> EvalRecord {
        EvalRecord { name: name.into(), result: Err("missing prediction".into()) }
    }

    #[test]
    fn differences_pair_by_name_and_skip_failures_on_either_side() {
        let a = [ok("x", 0.1), ok("y", 0.5), failed("z"), ok("w", 0.3), ok("only-a", 9.0)];
        // B in another order, with its own failure.
        let b = [ok("y", 0.2), ok("x", 0.3), ok("z", 0.1), failed("w")];
        let p = paired_chamfer(&a, &b);
        assert_eq!((p.pairs, p.unpaired), (2, 3));
        // x: 0.1 - 0.3 = -0.2; y: 0.5 - 0.2 = 0.3.
        assert!((p.mean.unwrap() - 0.05).abs() < 1e-12);
        // Sample deviation of {-0.2, 0.3} is 0.25 sqrt(2); over sqrt(2): 0.25.
        assert!((p.standard_error.unwrap() - 0.25).abs() < 1e-12);
        assert_eq!((p.a_better, p.b_better), (1, 1));
    }

    #[test]
    fn ties_favour_neither_and_small_sets_have_no_error() {
        let p = paired_chamfer(&[ok("x", 0.4)], &[ok("x", 0.4)]);
        assert_eq!((p.pairs, p.mean, p.standard_error), (1, Some(0.0), None));
        assert_eq!((p.a_better, p.b_better), (0, 0));
        let none = paired_chamfer(&[failed("x")], &[ok("x", 0.4)]);
        assert_eq!((none.pairs, none.unpaired, none.mean), (0, 1, None));
    }
}
