use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use clap::Args;
use meshstream::mesh::mesh_files_in;
use meshstream::metrics::{
    DEFAULT_FACE_TOLERANCE, Distances, EvalRecord, EvalSummary, FaceMatch, FaceSummary,
    MetricOptions, PairedDifference, Topology, TopologySummary, back_faces_seen, face_match,
    mesh_distances, paired_chamfer, summarize, summarize_faces, summarize_topology, topology,
};
use serde::Serialize;

use super::out;

use super::{display_name, load_mesh};

#[derive(Args)]
pub struct EvalArgs {
    /// Predicted mesh, or a folder of them (matched to ground truth by file stem).
    #[arg(long)]
    pred: PathBuf,
    /// Ground-truth mesh, or a folder of them. Every ground-truth mesh is one row: a
    /// prediction that is missing, unreadable or empty is a failure, counted and listed.
    #[arg(long)]
    gt: PathBuf,
    /// Points sampled on each surface.
    #[arg(long, default_value_t = MetricOptions::default().samples)]
    samples: usize,
    /// Sampling seed.
    #[arg(long, default_value_t = MetricOptions::default().seed)]
    seed: u64,
    /// How far (in the ground truth's normalized frame, [-1, 1] on its longest side) each
    /// corner of a predicted face may be from a ground-truth face's for the face to count as
    /// right; the default is 1.5 steps of the 128-level grid.
    #[arg(long, default_value_t = DEFAULT_FACE_TOLERANCE)]
    face_tolerance: f32,
    /// Another prediction (mesh or folder, like --pred) of the same ground truth: also
    /// scored, and compared with --pred mesh by mesh (mean difference of CD, its standard
    /// error, and where each is closer).
    #[arg(long)]
    against: Option<PathBuf>,
    /// Print JSON instead of tables.
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct Row {
    name: String,
    chamfer: Option<f64>,
    hausdorff: Option<f64>,
    accuracy: Option<f64>,
    completeness: Option<f64>,
    /// Faces of the prediction that the ground truth has; `None` for a point-cloud ground
    /// truth or a failure.
    faces: Option<FaceMatch>,
    /// How the prediction and the ground truth are put together; `None` for a failure.
    topology: Option<Topology>,
    truth_topology: Option<Topology>,
    /// Shares of the rays from around each mesh that meet a face from behind
    /// ([`back_faces_seen`]); `None` for a failure or a mesh without faces.
    back_faces_seen: Option<f64>,
    truth_back_faces_seen: Option<f64>,
    failure: Option<String>,
}

/// What one pair of meshes scores beyond its distances.
#[derive(Clone, Copy)]
struct Shape {
    faces: Option<FaceMatch>,
    topology: Topology,
    truth_topology: Topology,
    back_faces_seen: Option<f64>,
    truth_back_faces_seen: Option<f64>,
}

pub fn run(args: &EvalArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.face_tolerance.is_finite() && args.face_tolerance >= 0.0,
        "--face-tolerance must be a finite distance, not negative"
    );
    let opts = MetricOptions { samples: args.samples, seed: args.seed };
    let (records, shapes) = evaluate_all(&args.pred, &args.gt, &opts, args.face_tolerance)?;
    let against = match &args.against {
        Some(other) => {
            let (other_records, _) = evaluate_all(other, &args.gt, &opts, args.face_tolerance)?;
            Some((summarize(&other_records), paired_chamfer(&records, &other_records)))
        }
        None => None,
    };
    let summary = summarize(&records);
    let scored: Vec<&Shape> = shapes.iter().flatten().collect();
    let face_summary = summarize_faces(&scored.iter().filter_map(|s| s.faces).collect::<Vec<_>>());
    let topology_summary = TopologySummaries {
        prediction: summarize_topology(&scored.iter().map(|s| s.topology).collect::<Vec<_>>()),
        truth: summarize_topology(&scored.iter().map(|s| s.truth_topology).collect::<Vec<_>>()),
        back_faces_seen: mean(scored.iter().filter_map(|s| s.back_faces_seen)),
        truth_back_faces_seen: mean(scored.iter().filter_map(|s| s.truth_back_faces_seen)),
    };
    let rows: Vec<Row> = records
        .iter()
        .zip(&shapes)
        .map(|(r, shape)| {
            let d = r.result.as_ref().ok();
            Row {
                name: r.name.clone(),
                chamfer: d.map(|d| d.chamfer),
                hausdorff: d.map(|d| d.hausdorff),
                accuracy: d.map(|d| d.accuracy),
                completeness: d.map(|d| d.completeness),
                faces: shape.and_then(|s| s.faces),
                topology: shape.map(|s| s.topology),
                truth_topology: shape.map(|s| s.truth_topology),
                back_faces_seen: shape.and_then(|s| s.back_faces_seen),
                truth_back_faces_seen: shape.and_then(|s| s.truth_back_faces_seen),
                failure: r.result.as_ref().err().cloned(),
            }
        })
        .collect();
    if args.json {
        let mut report = serde_json::json!({ "meshes": rows, "summary": summary, "faces": face_summary,
                "topology": topology_summary });
        if let Some((summary, paired)) = &against {
            report["against"] = serde_json::json!({ "summary": summary, "paired": paired });
        }
        out(serde_json::to_string_pretty(&report)?)?;
    } else {
        print_tables(&rows, &summary, &face_summary, args.face_tolerance)?;
        print_topology(&topology_summary)?;
        if let Some((summary, paired)) = &against {
            print_comparison(summary, paired)?;
        }
    }
    Ok(())
}

/// Both topologies' summaries, and the mean shares of back faces seen over the meshes that
/// have one.
#[derive(Serialize)]
struct TopologySummaries {
    prediction: TopologySummary,
    truth: TopologySummary,
    back_faces_seen: Option<f64>,
    truth_back_faces_seen: Option<f64>,
}

/// The mean of `values`, `None` for none.
fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let (sum, n) = values.fold((0.0, 0usize), |(sum, n), v| (sum + v, n + 1));
    (n > 0).then(|| sum / n as f64)
}

/// One record per ground-truth mesh, and what else its prediction scores (`None` for a
/// failure).
fn evaluate_all(
    pred: &Path,
    gt: &Path,
    opts: &MetricOptions,
    face_tolerance: f32,
) -> anyhow::Result<(Vec<EvalRecord>, Vec<Option<Shape>>)> {
    Ok(pair_up(pred, gt)?
        .iter()
        .map(|(name, pred, gt)| {
            let (result, shape) = match evaluate_pair(pred.as_deref(), gt, opts, face_tolerance) {
                Ok((d, shape)) => (Ok(d), Some(shape)),
                Err(e) => (Err(e), None),
            };
            (EvalRecord { name: name.clone(), result }, shape)
        })
        .unzip())
}

/// (name, prediction if found, ground truth) for every ground-truth mesh.
fn pair_up(pred: &Path, gt: &Path) -> anyhow::Result<Vec<(String, Option<PathBuf>, PathBuf)>> {
    anyhow::ensure!(gt.exists(), "--gt {} does not exist", gt.display());
    if !gt.is_dir() {
        anyhow::ensure!(!pred.is_dir(), "--pred is a folder but --gt is a single file");
        return Ok(vec![(display_name(gt), pred.exists().then(|| pred.to_path_buf()), gt.into())]);
    }
    anyhow::ensure!(pred.is_dir(), "--gt is a folder, so --pred must be a folder too");
    let mut by_stem: BTreeMap<String, PathBuf> = BTreeMap::new();
    for path in mesh_files_in(pred)? {
        // Files are sorted, so with two predictions of one stem the first by name wins.
        by_stem.entry(stem(&path)).or_insert(path);
    }
    let gts = mesh_files_in(gt)?;
    anyhow::ensure!(!gts.is_empty(), "no ground-truth meshes in {}", gt.display());
    Ok(gts
        .into_iter()
        .map(|g| {
            let name = stem(&g);
            let p = by_stem.get(&name).cloned();
            (name, p, g)
        })
        .collect())
}

fn stem(path: &Path) -> String {
    path.file_stem().map_or_else(String::new, |s| s.to_string_lossy().into_owned())
}

/// Distances for one pair, both topologies and, when the ground truth has faces, the faces
/// they share; or why the prediction counts as a failure.
fn evaluate_pair(
    pred: Option<&Path>,
    gt: &Path,
    opts: &MetricOptions,
    face_tolerance: f32,
) -> Result<(Distances, Shape), String> {
    let pred = pred.ok_or("missing prediction")?;
    let pred = load_mesh(pred).map_err(|e| format!("unreadable prediction: {e:#}"))?;
    let gt = load_mesh(gt).map_err(|e| format!("unreadable ground truth: {e:#}"))?;
    let distances = mesh_distances(&pred, &gt, opts).map_err(|e| e.to_string())?;
    // The distances passed and `run` checked the tolerance: only a faceless ground truth is
    // left to fail.
    let faces = face_match(&pred, &gt, face_tolerance).ok();
    Ok((
        distances,
        Shape {
            faces,
            topology: topology(&pred),
            truth_topology: topology(&gt),
            back_faces_seen: back_faces_seen(&pred),
            truth_back_faces_seen: back_faces_seen(&gt),
        },
    ))
}

fn print_tables(
    rows: &[Row],
    s: &EvalSummary,
    faces: &FaceSummary,
    face_tolerance: f32,
) -> anyhow::Result<()> {
    let mut table = super::table();
    // Accuracy: prediction -> ground truth; completeness: ground truth -> prediction.
    table.set_header([
        "mesh",
        "CD",
        "HD",
        "acc.",
        "compl.",
        "faces right",
        "boundary",
        "non-manif.",
        "parts (truth)",
        "failure",
    ]);
    for r in rows {
        table.add_row([
            r.name.clone(),
            figure(r.chamfer),
            figure(r.hausdorff),
            figure(r.accuracy),
            figure(r.completeness),
            r.faces.map_or_else(
                || "-".to_string(),
                |f| format!("{} of {} ({} made)", f.matched, f.truth, f.predicted),
            ),
            percent(r.topology.map(|t| t.boundary_share())),
            percent(r.topology.map(|t| t.non_manifold_share())),
            match (r.topology, r.truth_topology) {
                (Some(t), Some(truth)) => format!("{} ({})", t.parts, truth.parts),
                _ => "-".to_string(),
            },
            r.failure.clone().unwrap_or_default(),
        ]);
    }
    out(&table)?;
    let mut sum = super::table();
    sum.set_header(["set", "CD", "HD", "acc.", "compl."]);
    sum.add_row([
        "mean".to_string(),
        figure(s.chamfer_mean),
        figure(s.hausdorff_mean),
        figure(s.accuracy_mean),
        figure(s.completeness_mean),
    ]);
    let none = String::new();
    sum.add_row([
        "median".to_string(),
        figure(s.chamfer_median),
        figure(s.hausdorff_median),
        none.clone(),
        none,
    ]);
    out(&sum)?;
    out(format_args!("meshes: {}, evaluated: {}, failures: {}", s.count, s.evaluated, s.failures))?;
    if let (Some(recall), Some(precision)) = (faces.recall_mean, faces.precision_mean) {
        out(format_args!(
            "faces right (corners within {face_tolerance}): {:.1}% of the ground truth's, \
             {:.1}% of the prediction's (means over {} meshes); every face right and none \
             extra: {} of {}",
            100.0 * recall,
            100.0 * precision,
            faces.meshes,
            faces.exact,
            faces.meshes
        ))?;
    }
    Ok(())
}

fn print_comparison(other: &EvalSummary, p: &PairedDifference) -> anyhow::Result<()> {
    out(format_args!(
        "--against: CD mean {}, {} failures of {}",
        figure(other.chamfer_mean),
        other.failures,
        other.count
    ))?;
    out(format_args!(
        "paired CD, --pred minus --against: mean {} (standard error {}) over {} meshes, \
         {} left out for a failure; --pred closer on {}, --against on {}",
        figure(p.mean),
        figure(p.standard_error),
        p.pairs,
        p.unpaired,
        p.a_better,
        p.b_better
    ))
}

/// How the predictions are put together, beside the ground truth.
fn print_topology(t: &TopologySummaries) -> anyhow::Result<()> {
    let mut table = super::table();
    table.set_header([
        "topology (means)",
        "boundary edges",
        "non-manifold edges",
        "misoriented edges",
        "back faces seen",
        "parts",
    ]);
    for (name, s, back) in [
        ("prediction", &t.prediction, t.back_faces_seen),
        ("ground truth", &t.truth, t.truth_back_faces_seen),
    ] {
        table.add_row([
            name.to_string(),
            percent(s.boundary_share_mean),
            percent(s.non_manifold_share_mean),
            percent(s.misoriented_share_mean),
            percent(back),
            s.parts_mean.map_or_else(|| "-".to_string(), |p| format!("{p:.1}")),
        ]);
    }
    out(&table)
}

/// A share as a percentage to one place, or "-" where there is none.
fn percent(v: Option<f64>) -> String {
    v.map_or_else(|| "-".to_string(), |v| format!("{:.1}%", 100.0 * v))
}

/// A figure to four places, or "-" where there is none.
fn figure(v: Option<f64>) -> String {
    v.map_or_else(|| "-".to_string(), |v| format!("{v:.4}"))
}
