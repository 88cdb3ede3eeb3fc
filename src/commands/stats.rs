use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use comfy_table::Table;
use meshstream::mesh::expand_mesh_paths;
use meshstream::tokenize::{Quantizer, sequence_stats, tokenize_mesh};
use serde::Serialize;

use super::out;

use super::{display_name, load_mesh};

#[derive(Args)]
pub struct StatsArgs {
    /// Mesh files, or folders whose mesh files are all read.
    #[arg(required = true)]
    paths: Vec<PathBuf>,
    /// Quantization levels Q per axis (128 to 1024).
    #[arg(long, short = 'q', default_value_t = meshstream::tokenize::DEFAULT_LEVELS)]
    levels: u16,
    /// Print only the summary of the whole set, not a row per mesh.
    #[arg(long)]
    summary: bool,
    /// Print JSON instead of tables.
    #[arg(long)]
    json: bool,
}

/// One mesh's numbers: as read, and as the FACE sequence sees it after quantization.
#[derive(Serialize)]
struct MeshStats {
    name: String,
    vertices: usize,
    faces: usize,
    /// Faces left after quantization, welding and removal of collapsed and repeated faces.
    quantized_faces: usize,
    /// Positions the decoder's attention processes (one per face; the start token not counted).
    face_sequence_len: usize,
    /// Length of the one-token-per-coordinate baseline sequence (9 per face).
    per_coordinate_len: usize,
    compression_ratio: f64,
}

/// Face-count buckets, as in the data set's README.
const BUCKETS: [(usize, &str); 6] = [
    (100, "<= 100"),
    (400, "101-400"),
    (800, "401-800"),
    (2000, "801-2000"),
    (4000, "2001-4000"),
    (usize::MAX, "> 4000"),
];

#[derive(Serialize)]
struct Summary {
    meshes: usize,
    failures: usize,
    failed: Vec<String>,
    faces: usize,
    quantized_faces: usize,
    face_sequence_len: usize,
    per_coordinate_len: usize,
    compression_ratio: f64,
    quantized_faces_min: Option<usize>,
    quantized_faces_median: Option<usize>,
    quantized_faces_max: Option<usize>,
    /// Meshes per bucket of quantized face count.
    histogram: Vec<(String, usize)>,
}

pub fn run(args: &StatsArgs) -> anyhow::Result<()> {
    let q = Quantizer::new(args.levels)?;
    let files = expand_mesh_paths(&args.paths)?;
    anyhow::ensure!(!files.is_empty(), "no mesh files found in the given paths");
    let mut rows = Vec::new();
    let mut failed = Vec::new();
    for path in &files {
        match mesh_stats(path, q) {
            Ok(row) => rows.push(row),
            Err(err) => failed.push(format!("{}: {err:#}", display_name(path))),
        }
    }
    let summary = summarize(&rows, failed);
    if args.json {
        let report = if args.summary {
            serde_json::json!({ "summary": summary })
        } else {
            serde_json::json!({ "meshes": rows, "summary": summary })
        };
        out(serde_json::to_string_pretty(&report)?)?;
    } else {
        if !args.summary {
            out(rows_table(&rows))?;
        }
        print_summary(&summary)?;
    }
    Ok(())
}

fn mesh_stats(path: &std::path::Path, q: Quantizer) -> anyhow::Result<MeshStats> {
    let mesh = load_mesh(path)?;
    let (tokenized, _) = tokenize_mesh(&mesh, q).context("tokenizing")?;
    let seq = sequence_stats(&tokenized.faces);
    Ok(MeshStats {
        name: display_name(path),
        vertices: mesh.vertices.len(),
        faces: mesh.faces.len(),
        quantized_faces: tokenized.faces.len(),
        face_sequence_len: seq.face_sequence_len,
        per_coordinate_len: seq.per_coordinate_len,
        compression_ratio: seq.compression_ratio,
    })
}

fn summarize(rows: &[MeshStats], failed: Vec<String>) -> Summary {
    let mut counts: Vec<usize> = rows.iter().map(|r| r.quantized_faces).collect();
    counts.sort_unstable();
    let face_sequence_len = rows.iter().map(|r| r.face_sequence_len).sum();
    let per_coordinate_len: usize = rows.iter().map(|r| r.per_coordinate_len).sum();
    let mut histogram: Vec<(String, usize)> =
        BUCKETS.iter().map(|(_, label)| (label.to_string(), 0)).collect();
    for &n in &counts {
        if let Some(i) = BUCKETS.iter().position(|&(upper, _)| n <= upper) {
            histogram[i].1 += 1;
        }
    }
    Summary {
        meshes: rows.len() + failed.len(),
        failures: failed.len(),
        failed,
        faces: rows.iter().map(|r| r.faces).sum(),
        quantized_faces: counts.iter().sum(),
        face_sequence_len,
        per_coordinate_len,
        compression_ratio: if per_coordinate_len == 0 {
            0.0
        } else {
            face_sequence_len as f64 / per_coordinate_len as f64
        },
        quantized_faces_min: counts.first().copied(),
        quantized_faces_median: counts.get(counts.len() / 2).copied(),
        quantized_faces_max: counts.last().copied(),
        histogram,
    }
}

fn rows_table(rows: &[MeshStats]) -> Table {
    let mut table = super::table();
    table.set_header([
        "mesh",
        "vertices",
        "faces",
        "quantized faces",
        "FACE length",
        "per-coord length",
        "ratio",
    ]);
    for r in rows {
        table.add_row([
            r.name.clone(),
            r.vertices.to_string(),
            r.faces.to_string(),
            r.quantized_faces.to_string(),
            r.face_sequence_len.to_string(),
            r.per_coordinate_len.to_string(),
            format!("{:.3}", r.compression_ratio),
        ]);
    }
    table
}

fn print_summary(s: &Summary) -> anyhow::Result<()> {
    let opt = |v: Option<usize>| v.map_or_else(|| "-".to_string(), |v| v.to_string());
    let mut table = super::table();
    table.set_header(["set", "value"]);
    table.add_row(["meshes".to_string(), s.meshes.to_string()]);
    table.add_row(["unreadable".to_string(), s.failures.to_string()]);
    table.add_row(["faces as read".to_string(), s.faces.to_string()]);
    table.add_row(["faces after quantization".to_string(), s.quantized_faces.to_string()]);
    table.add_row(["FACE sequence length (sum)".to_string(), s.face_sequence_len.to_string()]);
    table.add_row(["per-coordinate length (sum)".to_string(), s.per_coordinate_len.to_string()]);
    table.add_row(["compression ratio".to_string(), format!("{:.3}", s.compression_ratio)]);
    table.add_row([
        "quantized faces min / median / max".to_string(),
        format!(
            "{} / {} / {}",
            opt(s.quantized_faces_min),
            opt(s.quantized_faces_median),
            opt(s.quantized_faces_max)
        ),
    ]);
    for (label, n) in &s.histogram {
        table.add_row([format!("meshes with {label} faces"), n.to_string()]);
    }
    out(&table)?;
    for f in &s.failed {
        eprintln!("unreadable: {f}");
    }
    Ok(())
}
