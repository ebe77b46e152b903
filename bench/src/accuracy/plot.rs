//! `accuracy.png`: error against render time per scene (log-log, one curve per
//! interpolation, Pareto front ringed) and the convergence of trilinear's sampling error.
//!
//! plotters draws text only with a font it has been given, and we read one at run time
//! rather than build against fontconfig. Where no font is found the plot is drawn without
//! text (curves, markers and the grid of decades only) and stderr says so: the figure is still the data,
//! and a run never ends without one.

use std::path::Path;

use anyhow::{anyhow, Context, Result};
use plotters::coord::Shift;
use plotters::prelude::*;
use trove_tests::reference::Reference;

use super::interpolations;
use super::summary::Summary;
use super::sweep::{Config, Point};

/// Width and height of the plot in pixels.
pub(super) const SIZE: (u32, u32) = (1800, 1150);

/// The family our font is registered under. A name of our own rather than plotters'
/// default `sans-serif`: a text element that does not go through [`Text`] then fails to
/// draw on every machine, not only on one without fonts.
const FAMILY: &str = "trove-plot";

/// Where a sans-serif TrueType font may be. `TROVE_FONT` wins.
const FONT_PATHS: [&str; 5] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/System/Library/Fonts/Supplemental/Arial.ttf",
];

/// Colours per interpolation, in the order of [`interpolations`].
const COLOURS: [RGBColor; 4] =
    [RGBColor(214, 39, 40), RGBColor(31, 119, 180), RGBColor(44, 160, 44), RGBColor(148, 103, 189)];
/// Log axes cannot show 0: errors at or below this are drawn at it.
const ERROR_FLOOR: f64 = 1e-16;

/// Whether the plot can carry text.
#[derive(Clone, Copy, Debug)]
pub(super) struct Text {
    font: bool,
}

impl Text {
    /// Registers the first readable font (`TROVE_FONT`, then [`FONT_PATHS`]); without one,
    /// says on stderr that the plot will have no text.
    pub fn find() -> Text {
        let env = std::env::var("TROVE_FONT").ok();
        for path in env.iter().map(String::as_str).chain(FONT_PATHS) {
            if let Ok(bytes) = std::fs::read(path) {
                // plotters keeps fonts for the whole process; one small leak per run.
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                if plotters::style::register_font(FAMILY, FontStyle::Normal, bytes).is_ok() {
                    return Text { font: true };
                }
            }
        }
        eprintln!(
            "warning: no TrueType font found (looked in {}; set TROVE_FONT to a .ttf file): \
             accuracy.png is drawn without titles, labels or legends",
            FONT_PATHS.join(", ")
        );
        Text::none()
    }

    /// A plot without text.
    pub fn none() -> Text {
        Text { font: false }
    }

    /// Our font at `size` pixels, or `None` without one.
    fn at(self, size: f64) -> Option<FontDesc<'static>> {
        self.font.then(|| (FAMILY, size).into_font())
    }
}

type Area<'a> = DrawingArea<BitMapBackend<'a>, Shift>;
type LogChart<'a, 'b> = ChartContext<'a, BitMapBackend<'b>, Cartesian2d<LogCoord<f64>, LogCoord<f64>>>;

fn plot_err<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow!("drawing the plot: {e:?}")
}

/// Draws the six panels and writes them to `path` as a PNG.
pub(super) fn plot(path: &Path, points: &[Point], summary: &Summary, cfg: &Config, text: Text) -> Result<()> {
    let (w, h) = SIZE;
    let mut buf = vec![0u8; w as usize * h as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        let root = match text.at(22.0) {
            Some(font) => {
                let title = format!(
                    "Error against exact integrals vs render time: {d}³ voxels, {s}×{s} pixels, steps 4 … 1/8 \
                     voxel (solid ●: opacity correction on; faded ×: off; ○: Pareto front)",
                    d = cfg.dims,
                    s = cfg.image_side
                );
                root.titled(&title, font).map_err(plot_err)?
            }
            None => root,
        };
        let panels = root.split_evenly((2, 3));
        for (k, (area, scene)) in panels.iter().zip(Reference::ALL).enumerate() {
            scene_panel(area, points, scene, k == 0, text)?;
        }
        convergence_panel(&panels[5], points, summary, text)?;
        root.present().map_err(plot_err)?;
    }
    image::save_buffer(path, &buf, w, h, image::ExtendedColorType::Rgb8)
        .with_context(|| format!("writing {}", path.display()))
}

fn log_range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values.fold((f64::INFINITY, 0.0f64), |(lo, hi), v| (lo.min(v), hi.max(v)));
    (lo / 1.6, hi * 1.6)
}

fn scientific(v: &f64) -> String {
    format!("{v:.0e}")
}

fn plain(v: &f64) -> String {
    format!("{v}")
}

/// A log-log chart on `area`, with its caption, axes and (with a font) labels.
fn log_chart<'a, 'b>(
    area: &'a Area<'b>,
    caption: &str,
    (x, y): ((f64, f64), (f64, f64)),
    (x_desc, y_desc): (&str, &str),
    x_format: &'static dyn Fn(&f64) -> String,
    text: Text,
) -> Result<LogChart<'a, 'b>> {
    let mut builder = ChartBuilder::on(area);
    builder.margin(10);
    if let Some(font) = text.at(20.0) {
        // Label areas hold the axes and their tick labels; without a font there are none,
        // and the grid of decades alone shows the scale.
        builder.caption(caption, font).x_label_area_size(40).y_label_area_size(70);
    }
    let mut chart = builder.build_cartesian_2d((x.0..x.1).log_scale(), (y.0..y.1).log_scale()).map_err(plot_err)?;
    let mut mesh = chart.configure_mesh();
    mesh.light_line_style(WHITE.mix(0.0));
    if let (Some(labels), Some(descs)) = (text.at(13.0), text.at(15.0)) {
        mesh.x_desc(x_desc)
            .y_desc(y_desc)
            .x_label_formatter(x_format)
            .y_label_formatter(&scientific)
            .label_style(labels)
            .axis_desc_style(descs);
    }
    mesh.draw().map_err(plot_err)?;
    Ok(chart)
}

/// The legend box, with a font.
fn legend<'a, 'b: 'a>(chart: &mut LogChart<'a, 'b>, position: SeriesLabelPosition, text: Text) -> Result<()> {
    if let Some(font) = text.at(14.0) {
        chart
            .configure_series_labels()
            .position(position)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.5))
            .label_font(font)
            .draw()
            .map_err(plot_err)?;
    }
    Ok(())
}

/// One scene: total RMSE against median time, a curve per interpolation and correction.
fn scene_panel(area: &Area, points: &[Point], scene: Reference, with_legend: bool, text: Text) -> Result<()> {
    let pts: Vec<&Point> = points.iter().filter(|p| p.scene == scene).collect();
    let xy = |p: &Point| (p.seconds.max(1e-6), p.rmse.max(ERROR_FLOOR));
    let range = (log_range(pts.iter().map(|p| xy(p).0)), log_range(pts.iter().map(|p| xy(p).1)));
    let descs = ("median render time (s)", "RMSE vs exact");
    let mut chart = log_chart(area, scene.name(), range, descs, &scientific, text)?;
    for (interp, colour) in interpolations().iter().zip(COLOURS) {
        for correction in [true, false] {
            let mut series: Vec<&Point> = pts
                .iter()
                .copied()
                .filter(|p| p.interpolation.name() == interp.name() && p.correction == correction)
                .collect();
            series.sort_by(|a, b| b.step.total_cmp(&a.step));
            let line: Vec<(f64, f64)> = series.iter().map(|p| xy(p)).collect();
            let label = (with_legend && correction).then_some(interp.name());
            draw_curve(&mut chart, &line, colour, correction, label)?;
        }
    }
    let mut front: Vec<(f64, f64)> = pts.iter().filter(|p| p.pareto).map(|p| xy(p)).collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    let drawn = chart.draw_series(LineSeries::new(front.clone(), BLACK.mix(0.6).stroke_width(1))).map_err(plot_err)?;
    if with_legend {
        drawn.label("Pareto front").legend(|(x, y)| Circle::new((x + 10, y), 6, BLACK.stroke_width(1)));
    }
    chart.draw_series(front.iter().map(|&p| Circle::new(p, 8, BLACK.stroke_width(1)))).map_err(plot_err)?;
    if with_legend {
        legend(&mut chart, SeriesLabelPosition::UpperRight, text)?;
    }
    Ok(())
}

/// A polyline as separate segments. plotters joins the segments of a wide line with
/// mitred corners, and where a curve turns back on itself (noisy timings do that) the mitre
/// of the inner side runs off across the whole figure; segments have no joins.
fn segments(line: &[(f64, f64)], style: ShapeStyle) -> impl Iterator<Item = PathElement<(f64, f64)>> + '_ {
    line.windows(2).map(move |w| PathElement::new(vec![w[0], w[1]], style))
}

/// One curve: solid with dots (opacity correction on) or faded with crosses (off).
fn draw_curve(
    chart: &mut LogChart,
    line: &[(f64, f64)],
    colour: RGBColor,
    correction: bool,
    label: Option<&str>,
) -> Result<()> {
    if correction {
        let drawn = chart.draw_series(segments(line, colour.stroke_width(2))).map_err(plot_err)?;
        if let Some(label) = label {
            drawn
                .label(label)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
        }
        chart.draw_series(line.iter().map(|&p| Circle::new(p, 4, colour.filled()))).map_err(plot_err)?;
    } else {
        chart.draw_series(LineSeries::new(line.to_vec(), colour.mix(0.35).stroke_width(1))).map_err(plot_err)?;
        chart.draw_series(line.iter().map(|&p| Cross::new(p, 4, colour.mix(0.5)))).map_err(plot_err)?;
    }
    Ok(())
}

/// Trilinear's sampling error against the step on the smooth scenes, with a slope-2 guide.
fn convergence_panel(area: &Area, points: &[Point], summary: &Summary, text: Text) -> Result<()> {
    let smooth: Vec<Reference> = Reference::ALL.iter().copied().filter(|s| s.smooth()).collect();
    let pts: Vec<&Point> = points
        .iter()
        .filter(|p| smooth.contains(&p.scene) && p.interpolation.name() == "trilinear" && p.correction)
        .collect();
    let (e0, e1) = log_range(pts.iter().map(|p| p.sampling_rmse.max(ERROR_FLOOR)));
    let caption = "sampling error, trilinear + correction";
    let descs = ("sampling distance (voxels)", "RMSE vs converged render");
    let mut chart = log_chart(area, caption, ((0.02, 5.0), (e0, e1)), descs, &plain, text)?;
    let scene_colours = [RGBColor(255, 127, 14), RGBColor(23, 190, 207), RGBColor(140, 86, 75)];
    for (scene, colour) in smooth.iter().zip(scene_colours) {
        let mut xy: Vec<(f64, f64)> =
            pts.iter().filter(|p| p.scene == *scene).map(|p| (p.step, p.sampling_rmse.max(ERROR_FLOOR))).collect();
        xy.sort_by(|a, b| a.0.total_cmp(&b.0));
        let order = summary.asymptotic_order(*scene).unwrap_or(f64::NAN);
        chart
            .draw_series(segments(&xy, colour.stroke_width(2)))
            .map_err(plot_err)?
            .label(format!("{}: order {order:.2} (fit ¼ … 1/32)", scene.name()))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
        chart.draw_series(xy.iter().map(|&p| Circle::new(p, 4, colour.filled()))).map_err(plot_err)?;
    }
    // A slope-2 guide through the middle of the plot.
    let mid = (e0 * e1).sqrt();
    let guide = [(1.0 / 32.0, mid / 1024.0), (1.0, mid)];
    chart
        .draw_series(LineSeries::new(guide, BLACK.mix(0.4).stroke_width(1)))
        .map_err(plot_err)?
        .label("slope 2 (midpoint rule)")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.mix(0.4).stroke_width(1)));
    legend(&mut chart, SeriesLabelPosition::LowerRight, text)
}

#[cfg(test)]
mod tests {
    use super::super::sweep::tests::point;
    use super::*;

    /// Points of every scene and interpolation, with and without correction.
    fn points() -> Vec<Point> {
        let mut points = Vec::new();
        for scene in Reference::ALL {
            for interpolation in interpolations() {
                for (k, step) in [4.0, 2.0, 1.0, 0.5, 0.25, 0.125, 1.0 / 16.0, 1.0 / 32.0].into_iter().enumerate() {
                    for correction in [true, false] {
                        let e = 1e-2 * step * step;
                        let base = point(step, 1e-3 * (k + 1) as f64, e, e);
                        points.push(Point { scene, interpolation, correction, pareto: k == 0, ..base });
                    }
                }
            }
        }
        points
    }

    /// Pixels that are not white.
    fn inked(path: &Path) -> usize {
        let img = image::open(path).expect("a readable PNG").to_rgb8();
        assert_eq!(img.dimensions(), SIZE);
        img.pixels().filter(|p| p.0 != [255, 255, 255]).count()
    }

    #[test]
    fn without_a_font_the_plot_is_still_drawn_with_its_curves() {
        // Plotters' default family is never registered and ours is not used without a
        // font, so any text drawn here would fail: success proves the path draws none.
        let dir = std::env::temp_dir().join(format!("trove-bench-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let points = points();
        let summary = Summary::new(&points, &[]);
        let path = dir.join("no-font.png");
        plot(&path, &points, &summary, &Config::new(true), Text::none()).expect("drawn without text");
        let bare = inked(&path);
        assert!(bare > 10_000, "only {bare} pixels drawn: curves and axes should show");
        let text = Text::find();
        if text.font {
            let path = dir.join("font.png");
            plot(&path, &points, &summary, &Config::new(true), text).expect("drawn with text");
            assert!(inked(&path) > bare, "text adds ink");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
