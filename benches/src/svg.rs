//! SVG charts of a run (`--svg DIR`, issue 21): throughput per variant with min–max
//! whiskers over the rounds, and timer overshoot as a cumulative distribution per variant.
//! Our executors are drawn in blue, baselines in grey.

use std::path::Path;

use plotters::coord::ranged1d::SegmentValue;
use plotters::prelude::*;

use crate::latency::is_executor;
use crate::stats::Summary;

const OURS: RGBColor = RGBColor(31, 119, 180);
const BASELINE: RGBColor = RGBColor(160, 160, 160);

/// The label of a variant in a chart: without the bracketed explanation.
fn short(name: &str) -> &str {
    name.split(" [").next().unwrap_or(name)
}

fn err(path: &Path) -> impl Fn(String) -> String + '_ {
    move |e| format!("{}: {e}", path.display())
}

/// Horizontal bars of the median rate (M tasks/s) of each variant, a whisker from the
/// slowest to the fastest round.
pub(crate) fn throughput(path: &Path, title: &str, rows: &[(&str, Summary)]) -> Result<(), String> {
    let e = err(path);
    let height = 80 + 34 * rows.len() as u32;
    let root = SVGBackend::new(path, (900, height)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(x.to_string()))?;
    let top = rows.iter().map(|r| r.1.max).fold(0.0, f64::max) / 1e6 * 1.08;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(170)
        .build_cartesian_2d(0f64..top.max(0.01), (0..rows.len()).into_segmented())
        .map_err(|x| e(x.to_string()))?;
    chart
        .configure_mesh()
        .disable_y_mesh()
        .y_labels(rows.len())
        .y_label_formatter(&|v| match v {
            SegmentValue::CenterOf(i) => rows.get(*i).map_or(String::new(), |r| short(r.0).into()),
            _ => String::new(),
        })
        .x_desc("M tasks/s (bar: median; whisker: min–max over the rounds)")
        .draw()
        .map_err(|x| e(x.to_string()))?;
    chart
        .draw_series(rows.iter().enumerate().map(|(i, (name, s))| {
            let color = if is_executor(name) { OURS } else { BASELINE };
            let mut bar = Rectangle::new(
                [
                    (0.0, SegmentValue::Exact(i)),
                    (s.median / 1e6, SegmentValue::Exact(i + 1)),
                ],
                color.filled(),
            );
            bar.set_margin(6, 6, 0, 0);
            bar
        }))
        .map_err(|x| e(x.to_string()))?;
    chart
        .draw_series(rows.iter().enumerate().map(|(i, (_, s))| {
            PathElement::new(
                vec![
                    (s.min / 1e6, SegmentValue::CenterOf(i)),
                    (s.max / 1e6, SegmentValue::CenterOf(i)),
                ],
                BLACK.stroke_width(2),
            )
        }))
        .map_err(|x| e(x.to_string()))?;
    root.present().map_err(|x| e(x.to_string()))
}

/// One line per variant: the share of samples (y) with an overshoot of at most x µs, x on
/// a log scale (samples under 1 µs, and early ones, are drawn at 1 µs).
pub(crate) fn overshoot_cdf(
    path: &Path,
    title: &str,
    series: &[(&str, Vec<f64>)],
) -> Result<(), String> {
    let e = err(path);
    let root = SVGBackend::new(path, (900, 520)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(x.to_string()))?;
    let right = series
        .iter()
        .filter_map(|(_, v)| {
            v.iter()
                .copied()
                .fold(None, |m: Option<f64>, x| Some(m.map_or(x, |m| m.max(x))))
        })
        .fold(10.0, f64::max)
        * 1.2;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(50)
        .build_cartesian_2d((1f64..right).log_scale(), 0f64..1.0)
        .map_err(|x| e(x.to_string()))?;
    chart
        .configure_mesh()
        .x_desc("overshoot, µs (log)")
        .y_desc("share of timers")
        .draw()
        .map_err(|x| e(x.to_string()))?;
    for (k, (name, samples)) in series.iter().enumerate() {
        let mut v = samples.clone();
        v.sort_by(f64::total_cmp);
        let n = v.len().max(1) as f64;
        let step = (v.len() / 400).max(1);
        let points: Vec<(f64, f64)> = v
            .iter()
            .enumerate()
            .filter(|(i, _)| i % step == 0 || *i + 1 == v.len())
            .map(|(i, x)| (x.max(1.0), (i + 1) as f64 / n))
            .collect();
        let color = if is_executor(name) {
            Palette99::pick(k).to_rgba()
        } else {
            BASELINE.mix(0.5 + 0.5 * (k % 2) as f64)
        };
        let style = ShapeStyle {
            color,
            filled: false,
            stroke_width: if is_executor(name) { 2 } else { 1 },
        };
        chart
            .draw_series(LineSeries::new(points, style))
            .map_err(|x| e(x.to_string()))?
            .label(short(name))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], style));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|x| e(x.to_string()))?;
    root.present().map_err(|x| e(x.to_string()))
}
