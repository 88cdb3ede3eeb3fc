//! Loss and evaluation curves of a run, drawn from its JSONL log into a PNG.

use std::path::Path;

use plotters::prelude::*;

use super::TrainError;
use super::log::LogRecord;

/// Draws two panels: the training loss (raw and smoothed) with the evaluation loss, and the
/// evaluation Chamfer distance with the share of open edges of what the evaluation rebuilt
/// (on its own axis, where the log has it).
pub fn plot_curves(records: &[LogRecord], out: &Path) -> Result<(), TrainError> {
    let fail =
        |e: &dyn std::fmt::Display| TrainError::Config(format!("plotting {}: {e}", out.display()));
    // The font is embedded, so plotting needs nothing installed on the machine.
    plotters::style::register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular())
        .map_err(|_| fail(&"invalid embedded font"))?;
    let mut train = Vec::new();
    let mut eval_loss = Vec::new();
    let mut eval_other = Vec::new();
    let mut eval_cd = Vec::new();
    let mut eval_open = Vec::new();
    // A log holds one kind of run; a diffusion run's records name its own loss and pipeline.
    let mut diffusion = false;
    for r in records {
        let (step, eval) = match r {
            LogRecord::Step { step, coord_loss, .. } => {
                train.push((*step as f64, *coord_loss));
                continue;
            }
            LogRecord::DitStep { step, loss, .. } => {
                diffusion = true;
                train.push((*step as f64, *loss));
                continue;
            }
            LogRecord::Eval { step, report, .. } => {
                if let Some(other) = report.loss_other_points {
                    eval_other.push((*step as f64, other));
                }
                (step, (report.loss, report.chamfer_mean, report.topology))
            }
            LogRecord::DitEval { step, report, .. } => {
                (step, (report.loss, report.chamfer_mean, report.topology))
            }
        };
        eval_loss.push((*step as f64, eval.0));
        if let Some(cd) = eval.1 {
            eval_cd.push((*step as f64, cd));
        }
        if let Some(open) = eval.2.and_then(|t| t.boundary_share_mean) {
            eval_open.push((*step as f64, 100.0 * open));
        }
    }
    let (loss_caption, cd_caption) = if diffusion {
        (
            "flow-matching loss (velocity MSE, normalized latents)",
            "evaluation Chamfer distance (fixed view -> DiT -> greedy decoding)",
        )
    } else {
        (
            "loss (nats per face, 9 coordinates summed)",
            "evaluation Chamfer distance (greedy reconstruction)",
        )
    };
    if train.is_empty() {
        return Err(fail(&"the log has no training steps"));
    }
    let smoothed = exponential_moving_average(&train, 0.98);
    let max_step = train.iter().map(|p| p.0).fold(1.0, f64::max);
    let losses = train.iter().chain(&eval_loss).chain(&eval_other).map(|p| p.1);
    let (lo, hi) =
        losses.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));

    let root = BitMapBackend::new(out, (1000, 800)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| fail(&e))?;
    let (top, bottom) = root.split_vertically(480);
    let mut chart = ChartBuilder::on(&top)
        .caption(loss_caption, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(56)
        .build_cartesian_2d(0.0..max_step, (lo * 0.95).max(0.0)..hi * 1.02)
        .map_err(|e| fail(&e))?;
    chart.configure_mesh().x_desc("step").draw().map_err(|e| fail(&e))?;
    chart
        .draw_series(LineSeries::new(train.iter().copied(), BLUE.mix(0.25)))
        .map_err(|e| fail(&e))?
        .label("train (raw)")
        .legend(key(BLUE.mix(0.25)));
    chart
        .draw_series(LineSeries::new(smoothed, BLUE.stroke_width(2)))
        .map_err(|e| fail(&e))?
        .label("train (smoothed)")
        .legend(key(BLUE.stroke_width(2)));
    chart
        .draw_series(LineSeries::new(eval_loss.iter().copied(), RED.stroke_width(2)).point_size(4))
        .map_err(|e| fail(&e))?
        .label("evaluation")
        .legend(key(RED.stroke_width(2)));
    if !eval_other.is_empty() {
        // The gap to the evaluation curve is what the decoder reads from the shape's points.
        let orange = RGBColor(230, 140, 0);
        chart
            .draw_series(LineSeries::new(eval_other, orange.stroke_width(2)).point_size(4))
            .map_err(|e| fail(&e))?
            .label("evaluation, another mesh's points")
            .legend(key(orange.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|e| fail(&e))?;

    let cd_hi = eval_cd.iter().map(|p| p.1).fold(0.01, f64::max);
    let mut chart = ChartBuilder::on(&bottom)
        .caption(cd_caption, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(56)
        .right_y_label_area_size(56)
        .build_cartesian_2d(0.0..max_step, 0.0..cd_hi * 1.05)
        .map_err(|e| fail(&e))?
        .set_secondary_coord(0.0..max_step, 0.0..100.0);
    chart.configure_mesh().x_desc("step").draw().map_err(|e| fail(&e))?;
    chart
        .draw_series(LineSeries::new(eval_cd, GREEN.stroke_width(2)).point_size(4))
        .map_err(|e| fail(&e))?
        .label("Chamfer distance")
        .legend(key(GREEN.stroke_width(2)));
    if !eval_open.is_empty() {
        let purple = RGBColor(130, 60, 170);
        chart.configure_secondary_axes().y_desc("open edges, %").draw().map_err(|e| fail(&e))?;
        chart
            .draw_secondary_series(LineSeries::new(eval_open, purple.stroke_width(2)).point_size(4))
            .map_err(|e| fail(&e))?
            .label("open edges (right axis)")
            .legend(key(purple.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|e| fail(&e))?;
    root.present().map_err(|e| fail(&e))?;
    Ok(())
}

/// A legend's key for a series drawn in `style`: a short stroke.
fn key(style: impl Into<ShapeStyle>) -> impl Fn((i32, i32)) -> PathElement<(i32, i32)> {
    let style = style.into();
    move |(x, y)| PathElement::new([(x, y), (x + 16, y)], style)
}

fn exponential_moving_average(points: &[(f64, f64)], decay: f64) -> Vec<(f64, f64)> {
    let mut avg = None;
    points
        .iter()
        .map(|&(x, y)| {
            let a = avg.map_or(y, |a: f64| decay * a + (1.0 - decay) * y);
            avg = Some(a);
            (x, a)
        })
        .collect()
}
