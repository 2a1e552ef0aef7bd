//! The bench's figures, drawn with `plotters` as SVG and PNG:
//!
//! - `cycles_per_iteration`: cycles per CG iteration against n, one line per MVU count, model A
//!   and model B side by side (thesis Fig. 5-2), with the thesis's 500-node figure marked;
//! - `mflops`: eq. 56 MFLOPS against n (Fig. 5-3), with the thesis's 5-MVU figures;
//! - `convergence`: ∞-norm error against CG iterations on the cube (Fig. 2-9), fixed point and
//!   f64, refinement steps marked;
//! - `realtime`: cycles per time step against the 1 kHz and 60 Hz budgets;
//! - `host_baseline`: the f64 reference's time per iteration and per nonzero against n.
//!
//! Text is drawn with `ab_glyph` from DejaVu Sans embedded in the binary (the `dejavu` crate),
//! so no system font library is needed: a fresh machine draws the same pictures.

use std::collections::BTreeSet;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Once;

use anyhow::anyhow;
use plotters::coord::ranged1d::ValueFormatter;
use plotters::coord::Shift;
use plotters::prelude::*;

use super::convergence::{Arithmetic, ConvergenceSeries};
use super::host_baseline::HostPoint;
use super::realtime::{RealtimeScenario, HAPTIC_HZ, VISUAL_HZ};
use super::report::BenchReport;
use super::sweep::SweepResult;
use super::{thesis, BenchModel, NOMINAL_CLOCK_HZ};

/// Pixels of every figure (the SVG's user units too).
const SIZE: (u32, u32) = (1200, 520);
const FONT: &str = "sans-serif";

const COLORS: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(255, 127, 14),
    RGBColor(23, 190, 207),
    RGBColor(140, 86, 75),
    RGBColor(127, 127, 127),
];

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // DejaVu Sans is a valid TrueType font; a failure here would only lose the text.
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular());
        let _ = plotters::style::register_font(FONT, FontStyle::Bold, dejavu::sans::bold());
    });
}

/// One polyline with its legend entry.
struct Line {
    label: String,
    color: RGBColor,
    points: Vec<(f64, f64)>,
    dashed: bool,
}

/// A point drawn as a large marker with its own legend entry.
struct Mark {
    label: String,
    color: RGBColor,
    at: (f64, f64),
}

/// One chart.
struct Panel {
    title: String,
    x_desc: &'static str,
    y_desc: &'static str,
    log_x: bool,
    log_y: bool,
    lines: Vec<Line>,
    marks: Vec<Mark>,
    /// Horizontal reference lines (y, label, colour).
    hlines: Vec<(f64, String, RGBColor)>,
    /// Vertical markers (x, colour), one legend entry per label.
    vlines: Vec<(f64, RGBColor)>,
    vline_label: Option<String>,
    legend: SeriesLabelPosition,
}

impl Panel {
    fn new(title: String, x_desc: &'static str, y_desc: &'static str) -> Panel {
        Panel {
            title,
            x_desc,
            y_desc,
            log_x: true,
            log_y: true,
            lines: Vec::new(),
            marks: Vec::new(),
            hlines: Vec::new(),
            vlines: Vec::new(),
            vline_label: None,
            legend: SeriesLabelPosition::UpperLeft,
        }
    }

    fn is_empty(&self) -> bool {
        self.lines.iter().all(|l| l.points.is_empty()) && self.marks.is_empty()
    }

    fn ranges(&self) -> (Range<f64>, Range<f64>) {
        let xs = self
            .lines
            .iter()
            .flat_map(|l| l.points.iter().map(|p| p.0))
            .chain(self.marks.iter().map(|m| m.at.0))
            .chain(self.vlines.iter().map(|v| v.0));
        let ys = self
            .lines
            .iter()
            .flat_map(|l| l.points.iter().map(|p| p.1))
            .chain(self.marks.iter().map(|m| m.at.1))
            .chain(self.hlines.iter().map(|h| h.0));
        (
            axis_range(xs, self.log_x, false),
            axis_range(ys, self.log_y, true),
        )
    }
}

/// A range covering `values` (positive ones only on a log axis), with a margin.
fn axis_range(values: impl Iterator<Item = f64>, log: bool, pad_linear: bool) -> Range<f64> {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values.filter(|v| v.is_finite() && (!log || *v > 0.0)) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        return if log { 1.0..10.0 } else { 0.0..1.0 };
    }
    if log {
        (lo / 1.6)..(hi * 1.6)
    } else {
        let span = (hi - lo).max(hi.abs() * 0.1).max(1e-12);
        let pad = if pad_linear { span * 0.08 } else { 0.0 };
        let lo = if lo >= 0.0 && pad_linear {
            0.0
        } else {
            lo - pad
        };
        lo..(hi + pad)
    }
}

/// Axis numbers: plain when short, else in exponent form.
fn number(v: f64) -> String {
    let a = v.abs();
    if a == 0.0 {
        "0".into()
    } else if (1e-2..1e6).contains(&a) {
        let s = format!("{v:.2}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        format!("{v:.0e}")
    }
}

/// Labels for a log axis: only values whose leading digit is 1, 2 or 5, so that the labels
/// between decades do not run into each other.
fn log_axis_number(v: f64) -> String {
    if v <= 0.0 {
        return String::new();
    }
    let lead = v / 10f64.powf(v.log10().floor());
    if [1.0, 2.0, 5.0].iter().any(|d| (lead - d).abs() < 1e-6) {
        number(v)
    } else {
        String::new()
    }
}

fn plot_error(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow!("drawing a plot: {e}")
}

fn draw_panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    panel: &Panel,
) -> anyhow::Result<()> {
    let (x, y) = panel.ranges();
    match (panel.log_x, panel.log_y) {
        (true, true) => draw_with(area, panel, x.log_scale(), y.log_scale()),
        (true, false) => draw_with(area, panel, x.log_scale(), y),
        (false, true) => draw_with(area, panel, x, y.log_scale()),
        (false, false) => draw_with(area, panel, x, y),
    }
}

fn draw_with<DB, XS, YS>(
    area: &DrawingArea<DB, Shift>,
    panel: &Panel,
    x_spec: XS,
    y_spec: YS,
) -> anyhow::Result<()>
where
    DB: DrawingBackend,
    XS: plotters::coord::ranged1d::AsRangedCoord<Value = f64>,
    YS: plotters::coord::ranged1d::AsRangedCoord<Value = f64>,
    XS::CoordDescType: Ranged<ValueType = f64> + ValueFormatter<f64>,
    YS::CoordDescType: Ranged<ValueType = f64> + ValueFormatter<f64>,
{
    let mut chart = ChartBuilder::on(area)
        .caption(&panel.title, (FONT, 22))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(75)
        .build_cartesian_2d(x_spec, y_spec)
        .map_err(plot_error)?;
    let axis_number = |log: bool, v: f64| if log { log_axis_number(v) } else { number(v) };
    chart
        .configure_mesh()
        .x_desc(panel.x_desc)
        .y_desc(panel.y_desc)
        .x_label_formatter(&|v| axis_number(panel.log_x, *v))
        .y_label_formatter(&|v| axis_number(panel.log_y, *v))
        .label_style((FONT, 14))
        .axis_desc_style((FONT, 16))
        .light_line_style(TRANSPARENT)
        .draw()
        .map_err(plot_error)?;
    draw_lines(&mut chart, panel)?;
    draw_rules(&mut chart, panel)?;
    draw_marks(&mut chart, panel)?;
    chart
        .configure_series_labels()
        .label_font((FONT, 14))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(panel.legend.clone())
        .draw()
        .map_err(plot_error)?;
    Ok(())
}

/// A panel's chart, whatever its axes' scales.
type Chart<'a, DB, X, Y> = ChartContext<'a, DB, Cartesian2d<X, Y>>;

/// The panel's data lines, solid or dashed, each point marked.
fn draw_lines<'a, DB, X, Y>(chart: &mut Chart<'a, DB, X, Y>, panel: &Panel) -> anyhow::Result<()>
where
    DB: DrawingBackend + 'a,
    X: Ranged<ValueType = f64>,
    Y: Ranged<ValueType = f64>,
{
    for line in &panel.lines {
        let color = line.color;
        let style = color.stroke_width(2);
        if line.dashed {
            chart
                .draw_series(DashedLineSeries::new(line.points.clone(), 8, 5, style))
                .map_err(plot_error)?
                .label(&line.label)
                .legend(move |(x, y)| {
                    EmptyElement::at((x, y))
                        + PathElement::new(vec![(0, 0), (7, 0)], color.stroke_width(2))
                        + PathElement::new(vec![(13, 0), (20, 0)], color.stroke_width(2))
                });
        } else {
            chart
                .draw_series(LineSeries::new(line.points.clone(), style))
                .map_err(plot_error)?
                .label(&line.label)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                });
        }
        chart
            .draw_series(
                line.points
                    .iter()
                    .map(|&p| Circle::new(p, 3, color.filled())),
            )
            .map_err(plot_error)?;
    }
    Ok(())
}

/// The panel's horizontal rules (labelled targets) and vertical ones (one label for all).
fn draw_rules<'a, DB, X, Y>(chart: &mut Chart<'a, DB, X, Y>, panel: &Panel) -> anyhow::Result<()>
where
    DB: DrawingBackend + 'a,
    X: Ranged<ValueType = f64>,
    Y: Ranged<ValueType = f64>,
{
    let (x_range, y_range) = panel.ranges();
    for (y, label, color) in &panel.hlines {
        let color = *color;
        chart
            .draw_series(DashedLineSeries::new(
                vec![(x_range.start, *y), (x_range.end, *y)],
                10,
                6,
                color.stroke_width(2),
            ))
            .map_err(plot_error)?
            .label(label)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
    }
    for (i, &(x, color)) in panel.vlines.iter().enumerate() {
        let series = chart
            .draw_series(DashedLineSeries::new(
                vec![(x, y_range.start), (x, y_range.end)],
                4,
                4,
                color.mix(0.7).stroke_width(1),
            ))
            .map_err(plot_error)?;
        if i == 0 {
            if let Some(label) = &panel.vline_label {
                series.label(label).legend(move |(x, y)| {
                    PathElement::new(
                        vec![(x + 10, y - 6), (x + 10, y + 6)],
                        color.stroke_width(1),
                    )
                });
            }
        }
    }
    Ok(())
}

/// The panel's single marked points (triangles), each with its legend entry.
fn draw_marks<'a, DB, X, Y>(chart: &mut Chart<'a, DB, X, Y>, panel: &Panel) -> anyhow::Result<()>
where
    DB: DrawingBackend + 'a,
    X: Ranged<ValueType = f64>,
    Y: Ranged<ValueType = f64>,
{
    for mark in &panel.marks {
        let color = mark.color;
        chart
            .draw_series(std::iter::once(TriangleMarker::new(
                mark.at,
                9,
                color.filled(),
            )))
            .map_err(plot_error)?
            .label(&mark.label)
            .legend(move |(x, y)| TriangleMarker::new((x + 10, y), 6, color.filled()));
    }
    Ok(())
}

/// Draws `panels` side by side on `root`.
fn draw_figure<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    panels: &[Panel],
) -> anyhow::Result<()> {
    root.fill(&WHITE).map_err(plot_error)?;
    let areas = root.split_evenly((1, panels.len().max(1)));
    for (area, panel) in areas.iter().zip(panels) {
        draw_panel(area, panel)?;
    }
    root.present().map_err(plot_error)?;
    Ok(())
}

/// Writes `stem.svg` and `stem.png`.
fn save(dir: &Path, stem: &str, panels: &[Panel]) -> anyhow::Result<Vec<PathBuf>> {
    register_font();
    let svg = dir.join(format!("{stem}.svg"));
    let png = dir.join(format!("{stem}.png"));
    draw_figure(SVGBackend::new(&svg, SIZE).into_drawing_area(), panels)?;
    draw_figure(BitMapBackend::new(&png, SIZE).into_drawing_area(), panels)?;
    Ok(vec![svg, png])
}

/// The thesis's DE2 board (Cyclone II EP2C35): 35 18×18 multipliers, of which its five MVUs
/// and SVU used at most all (thesis 5.1; Fig. 5-1's own values are not in its text).
const THESIS_DE2_MULTIPLIERS: f64 = 35.0;
const THESIS_DE2_MVUS: f64 = 5.0;

/// Fig. 5-1 with synthesised numbers (`cargo xtask bitstream`): the 18×18 multiplier blocks a
/// whole SoC uses against its MVUs, `points` as (MVUs, MULT18X18D used), beside the device's
/// `available` and the thesis's DE2. Writes `multipliers_per_mvu.svg` and `.png` in `dir`.
pub fn multipliers_per_mvu(
    points: &[(f64, f64)],
    available: f64,
    dir: &Path,
) -> anyhow::Result<Vec<PathBuf>> {
    let mut panel = Panel::new(
        "Multipliers against MVUs (thesis Fig. 5-1), synthesised for the LFE5U-85F".into(),
        "MVUs",
        "18×18 multipliers",
    );
    panel.log_x = false;
    panel.log_y = false;
    panel.lines.push(Line {
        label: "ours: MULT18X18D in the whole SoC (the CPU's included)".into(),
        color: COLORS[0],
        points: points.to_vec(),
        dashed: false,
    });
    panel.hlines.push((
        available,
        format!("LFE5U-85F: {available} MULT18X18D"),
        COLORS[1],
    ));
    panel.marks.push(Mark {
        label: "thesis: 5 MVUs on the DE2's 35 multipliers".into(),
        color: BLACK,
        at: (THESIS_DE2_MVUS, THESIS_DE2_MULTIPLIERS),
    });
    save(dir, "multipliers_per_mvu", &[panel])
}

fn mvu_label(mvus: u8) -> String {
    if mvus == 1 {
        "1 MVU".into()
    } else {
        format!("{mvus} MVUs")
    }
}

/// One panel per model, one line per MVU count, y from `value`.
fn sweep_panels(
    sweep: &SweepResult,
    title: &str,
    y_desc: &'static str,
    value: impl Fn(&super::sweep::SweepPoint) -> f64,
) -> Vec<Panel> {
    let mvus: BTreeSet<u8> = sweep.points.iter().map(|p| p.mvus).collect();
    BenchModel::BOTH
        .iter()
        .filter(|m| sweep.points.iter().any(|p| p.model == **m))
        .map(|&model| {
            let mut panel = Panel::new(
                format!("{title}, model {}", model.label()),
                "n (nodes)",
                y_desc,
            );
            for (i, &m) in mvus.iter().enumerate() {
                let mut points: Vec<(f64, f64)> = sweep
                    .points
                    .iter()
                    .filter(|p| p.model == model && p.mvus == m)
                    .map(|p| (p.n as f64, value(p)))
                    .collect();
                points.sort_by(|a, b| a.0.total_cmp(&b.0));
                panel.lines.push(Line {
                    label: format!("ours, {}", mvu_label(m)),
                    color: COLORS[i % COLORS.len()],
                    points,
                    dashed: false,
                });
            }
            panel
        })
        .collect()
}

fn cycles_figure(sweep: &SweepResult) -> Vec<Panel> {
    let mut panels = sweep_panels(
        sweep,
        "Cycles per CG iteration",
        "cycles per iteration",
        |p| p.cycles_per_iteration,
    );
    for (panel, model) in panels.iter_mut().zip(
        BenchModel::BOTH
            .iter()
            .filter(|m| sweep.points.iter().any(|p| p.model == **m)),
    ) {
        panel.marks.push(Mark {
            label: "thesis FPGA, 1 MVU (16.6/56.1 ms ÷ 500 iter.)".into(),
            color: BLACK,
            at: (
                thesis::NODES as f64,
                thesis::cycles_per_iteration_500(*model),
            ),
        });
    }
    panels
}

fn mflops_figure(sweep: &SweepResult) -> Vec<Panel> {
    let mut panels = sweep_panels(sweep, "MFLOPS at 100 MHz (eq. 56)", "MFLOPS", |p| p.mflops);
    for (panel, model) in panels.iter_mut().zip(
        BenchModel::BOTH
            .iter()
            .filter(|m| sweep.points.iter().any(|p| p.model == **m)),
    ) {
        panel.hlines.push((
            thesis::mflops_5_mvus(*model),
            format!(
                "thesis FPGA, 5 MVUs: > {} MFLOPS",
                thesis::mflops_5_mvus(*model)
            ),
            BLACK,
        ));
    }
    panels
}

fn convergence_figure(series: &[ConvergenceSeries]) -> Vec<Panel> {
    let edge = series.first().map_or(0, |s| s.edge);
    let mut panel = Panel::new(
        format!("CG error on the {edge}³ cube, x direction"),
        "CG iterations (cumulative over refinement steps)",
        "‖u − u*‖∞",
    );
    panel.log_x = false;
    panel.vline_label = Some("refinement step begins (fixed point)".into());
    for s in series {
        let color = COLORS[(s.model as usize) % COLORS.len()];
        panel.lines.push(Line {
            label: format!("model {}, {}", s.model.label(), s.arithmetic.label()),
            color,
            // An exact zero error cannot be drawn on a log axis.
            points: s
                .points
                .iter()
                .filter(|p| p.1 > 0.0)
                .map(|&(k, e)| (k as f64, e))
                .collect(),
            dashed: s.arithmetic == Arithmetic::F64,
        });
        if s.arithmetic == Arithmetic::FixedPoint {
            panel.vlines.extend(
                s.refinement_starts
                    .iter()
                    .filter(|&&k| k > 0)
                    .map(|&k| (k as f64, color)),
            );
        }
    }
    vec![panel]
}

fn realtime_figure(scenarios: &[RealtimeScenario]) -> Vec<Panel> {
    let mut panel = Panel::new(
        "Cycles per time step (x, y, z solves, warm starts)".into(),
        "time step",
        "cycles per step",
    );
    panel.log_x = false;
    panel.legend = SeriesLabelPosition::LowerRight;
    // One colour per grid and model, dashed with more than one MVU.
    let mut grids: Vec<(BenchModel, usize)> = Vec::new();
    for s in scenarios {
        if !grids.contains(&(s.model, s.edge)) {
            grids.push((s.model, s.edge));
        }
    }
    for s in scenarios {
        let i = grids
            .iter()
            .position(|g| *g == (s.model, s.edge))
            .unwrap_or(0);
        panel.lines.push(Line {
            label: format!(
                "model {}, {}³ (n = {}), {}",
                s.model.label(),
                s.edge,
                s.n,
                mvu_label(s.mvus)
            ),
            color: COLORS[i % COLORS.len()],
            points: s
                .steps
                .iter()
                .map(|st| (st.step as f64, st.cycles as f64))
                .collect(),
            dashed: s.mvus > 1,
        });
    }
    panel.hlines.push((
        NOMINAL_CLOCK_HZ / HAPTIC_HZ,
        "1 kHz budget at 100 MHz".into(),
        BLACK,
    ));
    panel.hlines.push((
        NOMINAL_CLOCK_HZ / VISUAL_HZ,
        "60 Hz budget at 100 MHz".into(),
        RGBColor(120, 120, 120),
    ));
    vec![panel]
}

fn host_figure(points: &[HostPoint]) -> Vec<Panel> {
    let mut time = Panel::new(
        "f64 reference CG on the host".into(),
        "n (nodes)",
        "seconds per iteration",
    );
    let mut per_nnz = Panel::new(
        "… per nonzero (flat = linear in nnz)".into(),
        "n (nodes)",
        "ns per nonzero per iteration",
    );
    per_nnz.log_y = false;
    for (i, model) in BenchModel::BOTH.iter().enumerate() {
        let mine: Vec<&HostPoint> = points.iter().filter(|p| p.model == *model).collect();
        if mine.is_empty() {
            continue;
        }
        let color = COLORS[i];
        time.lines.push(Line {
            label: format!("model {}", model.label()),
            color,
            points: mine
                .iter()
                .map(|p| (p.n as f64, p.seconds_per_iteration))
                .collect(),
            dashed: false,
        });
        per_nnz.lines.push(Line {
            label: format!("model {}", model.label()),
            color,
            points: mine
                .iter()
                .map(|p| (p.n as f64, p.nanoseconds_per_nonzero))
                .collect(),
            dashed: false,
        });
    }
    vec![time, per_nnz]
}

/// Draws every figure the report has data for into `dir`; returns the files written.
pub fn draw_all(report: &BenchReport, dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let mut figures: Vec<(&str, Vec<Panel>)> = Vec::new();
    if let Some(sweep) = report.sweep.as_ref().filter(|s| !s.points.is_empty()) {
        figures.push(("cycles_per_iteration", cycles_figure(sweep)));
        figures.push(("mflops", mflops_figure(sweep)));
    }
    if let Some(series) = report.convergence.as_ref().filter(|s| !s.is_empty()) {
        figures.push(("convergence", convergence_figure(series)));
    }
    if let Some(scenarios) = report.realtime.as_ref().filter(|s| !s.is_empty()) {
        figures.push(("realtime", realtime_figure(scenarios)));
    }
    if let Some(points) = report.host_baseline.as_ref().filter(|p| !p.is_empty()) {
        figures.push(("host_baseline", host_figure(points)));
    }
    let mut written = Vec::new();
    for (stem, panels) in figures {
        let panels: Vec<Panel> = panels.into_iter().filter(|p| !p.is_empty()).collect();
        if !panels.is_empty() {
            written.extend(save(dir, stem, &panels)?);
        }
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_cover_the_data_with_a_margin() {
        let r = axis_range([10.0, 1000.0, 0.0].into_iter(), true, true);
        assert!(r.start < 10.0 && r.start > 0.0 && r.end > 1000.0);
        let r = axis_range([2.0, 5.0].into_iter(), false, true);
        assert!(r.start == 0.0 && r.end > 5.0);
        assert_eq!(axis_range(std::iter::empty(), true, true), 1.0..10.0);
        assert_eq!(number(1500.0), "1500");
        assert_eq!(number(0.25), "0.25");
        assert_eq!(number(1e-7), "1e-7");
        assert_eq!(log_axis_number(500.0), "500");
        assert_eq!(log_axis_number(2000.0), "2000");
        assert_eq!(log_axis_number(700.0), "");
    }

    #[test]
    fn draws_svg_and_png_with_text_without_system_fonts() {
        let dir = std::env::temp_dir().join(format!("deform-plots-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut panel = Panel::new("t".into(), "x", "y");
        panel.lines.push(Line {
            label: "a line".into(),
            color: COLORS[0],
            points: vec![(1.0, 2.0), (10.0, 30.0)],
            dashed: false,
        });
        let files = save(&dir, "test", &[panel]).unwrap();
        let svg = std::fs::read_to_string(&files[0]).unwrap();
        assert!(svg.contains("<svg") && svg.contains("a line"), "{svg}");
        let png = std::fs::read(&files[1]).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
