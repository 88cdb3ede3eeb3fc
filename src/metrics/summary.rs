//! Set-level results: the figures `meshstream eval` and training evaluation report.

use super::Distances;

/// The outcome for one mesh of an evaluation set.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EvalRecord {
    pub name: String,
    /// The distances, or why there are none (missing, empty, unreadable output).
    pub result: Result<Distances, String>,
}

/// Means and medians over the evaluated meshes; failures are counted and listed, never dropped.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct EvalSummary {
    /// All records.
    pub count: usize,
    /// Records with distances.
    pub evaluated: usize,
    /// Records without: `count = evaluated + failures`.
    pub failures: usize,
    /// One `"name: reason"` per failure, in record order.
    pub failed: Vec<String>,
    /// `None` when nothing was evaluated.
    pub chamfer_mean: Option<f64>,
    pub chamfer_median: Option<f64>,
    pub hausdorff_mean: Option<f64>,
    pub hausdorff_median: Option<f64>,
    /// Means of the Chamfer distance's halves (see [`Distances`]).
    pub accuracy_mean: Option<f64>,
    pub completeness_mean: Option<f64>,
}

pub fn summarize(records: &[EvalRecord]) -> EvalSummary {
    let ok: Vec<&Distances> = records.iter().filter_map(|r| r.result.as_ref().ok()).collect();
    let failed: Vec<String> = records
        .iter()
        .filter_map(|r| r.result.as_ref().err().map(|why| format!("{}: {why}", r.name)))
        .collect();
    let chamfer: Vec<f64> = ok.iter().map(|d| d.chamfer).collect();
    let hausdorff: Vec<f64> = ok.iter().map(|d| d.hausdorff).collect();
    let accuracy: Vec<f64> = ok.iter().map(|d| d.accuracy).collect();
    let completeness: Vec<f64> = ok.iter().map(|d| d.completeness).collect();
    EvalSummary {
        count: records.len(),
        evaluated: ok.len(),
        failures: failed.len(),
        failed,
        chamfer_mean: mean(&chamfer),
        chamfer_median: median(chamfer),
        hausdorff_mean: mean(&hausdorff),
        hausdorff_median: median(hausdorff),
        accuracy_mean: mean(&accuracy),
        completeness_mean: mean(&completeness),
    }
}

fn mean(xs: &[f64]) -> Option<f64> {
    (!xs.is_empty()).then(|| xs.iter().sum::<f64>() / xs.len() as f64)
}

/// The middle value, or the mean of the two middle values for an even count; `None` for none.
pub fn median(mut xs: Vec<f64>) -> Option<f64> {
    xs.sort_by(f64::total_cmp);
    let mid = xs.len() / 2;
    match xs.len() {
        0 => None,
        n if n % 2 == 1 => Some(xs[mid]),
        _ => Some((xs[mid - 1] + xs[mid]) / 2.0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A record whose Chamfer distance splits 1 : 3 into accuracy and completeness.
    fn ok(name: &str, chamfer: f64, hausdorff: f64) -> EvalRecord {
        let (accuracy, completeness) = (chamfer / 4.0, 3.0 * chamfer / 4.0);
        EvalRecord {
            name: name.into(),
            result: Ok(Distances { chamfer, hausdorff, accuracy, completeness }),
        }
    }

    fn failed(name: &str, why: &str) -> EvalRecord {
        EvalRecord { name: name.into(), result: Err(why.into()) }
    }

    #[test]
    fn failures_are_counted_and_listed() {
        let records = [
            ok("a", 0.1, 0.5),
            failed("b", "empty output"),
            ok("c", 0.4, 0.2),
            ok("d", 0.2, 0.3),
            failed("e", "missing"),
            ok("f", 0.3, 0.4),
        ];
        let s = summarize(&records);
        assert_eq!((s.count, s.evaluated, s.failures), (6, 4, 2));
        assert_eq!(s.failed, ["b: empty output", "e: missing"]);
        let close = |x: Option<f64>, y: f64| (x.unwrap() - y).abs() < 1e-12;
        assert!(close(s.chamfer_mean, 0.25));
        assert!(close(s.chamfer_median, 0.25)); // (0.2 + 0.3) / 2
        assert!(close(s.hausdorff_mean, 0.35));
        assert!(close(s.hausdorff_median, 0.35)); // (0.3 + 0.4) / 2
        assert!(close(s.accuracy_mean, 0.0625));
        assert!(close(s.completeness_mean, 0.1875));
    }

    #[test]
    fn odd_counts_take_the_middle_value() {
        let s = summarize(&[ok("a", 3.0, 1.0), ok("b", 1.0, 9.0), ok("c", 2.0, 5.0)]);
        assert_eq!((s.chamfer_median, s.hausdorff_median), (Some(2.0), Some(5.0)));
    }

    #[test]
    fn nothing_evaluated_has_no_figures() {
        let s = summarize(&[failed("a", "unreadable")]);
        assert_eq!((s.count, s.evaluated, s.failures), (1, 0, 1));
        assert_eq!((s.chamfer_mean, s.chamfer_median), (None, None));
        assert_eq!((s.hausdorff_mean, s.hausdorff_median), (None, None));
        assert_eq!((s.accuracy_mean, s.completeness_mean), (None, None));
        let empty = summarize(&[]);
        assert_eq!((empty.count, empty.chamfer_mean), (0, None));
        let json = serde_json::to_value(&s).unwrap();
        assert_eq!(json["failed"][0], "a: unreadable");
        assert!(json["chamfer_mean"].is_null());
    }
}
