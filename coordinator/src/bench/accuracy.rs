//! `trove bench accuracy`: what accuracy costs in time.
//!
//! Every reference scene of [`trove_core::reference`] is rendered over the sweep sampling
//! distance (4, 2, 1, ½, ¼, ⅛ voxel) × interpolation (nearest, trilinear, nonlinear,
//! cubic) × opacity correction on/off. Each point records the median render time of
//! several renders and two errors over the image (RMSE and max, in linear pixel values):
//! against the exact integral (*total* error) and against a converged render of the same
//! voxels with the same interpolation (*sampling* error, see the reference module for why
//! the two differ). A second sweep grows the resolution at a fine step to isolate the
//! *representation* error. Renders use the per-ray algorithm, which accumulates in f64
//! only, so there is no f32/f64 axis.
//!
//! Outputs in `--out` (default `docs/`): `accuracy.csv` (the sweep),
//! `accuracy_representation.csv`, `accuracy.png` (error against time, log-log, one curve per
//! interpolation, Pareto front ringed, plus the convergence panel) and `accuracy.md` (the
//! measured orders and costs, written as the README paragraph and the BENCHMARKS section).
//!
//! The run fails when trilinear interpolation with opacity correction converges with a
//! measured order below [`MIN_ORDER`] on a smooth field (the midpoint rule's order is 2).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use plotters::coord::Shift;
use plotters::prelude::*;
use trove_core::interp::Interpolation;
use trove_core::reference::{log_log_slope, rmse_and_max, Reference, Setup};
use trove_core::render::{render, Algorithm, RenderOptions};

/// The lowest acceptable convergence order of trilinear + opacity correction on smooth fields.
pub const MIN_ORDER: f64 = 1.8;

/// Sampling distances of the sweep, in voxels.
const STEPS: [f64; 6] = [4.0, 2.0, 1.0, 0.5, 0.25, 0.125];
/// Extra, finer steps for trilinear with opacity correction, to follow its convergence into
/// the asymptotic range.
const FINE_STEPS: [f64; 2] = [1.0 / 16.0, 1.0 / 32.0];
/// The steps over which the asymptotic order is fitted. At 1 and ½ voxel the samples are
/// commensurate with the voxel grid: along a ray nearly parallel to an axis they fall at the
/// same place in every cell, errors of neighbouring cells partly cancel, and the error comes
/// out up to 2× below the s² trend (measured on the Gaussian at 32³ and 64³ alike). A fit
/// that includes them reports that luck as a lower order; from ¼ voxel on, the error
/// follows the midpoint rule's s².
const ORDER_STEPS: [f64; 4] = [0.25, 0.125, 1.0 / 16.0, 1.0 / 32.0];

/// Arguments of `trove bench accuracy`.
#[derive(clap::Args, Debug)]
pub struct AccuracyArgs {
    /// Folder for accuracy.csv, accuracy_representation.csv, accuracy.png and accuracy.md.
    #[arg(long, default_value = "docs")]
    pub out: PathBuf,
    /// A smoke run: small volumes and images, one timing per point (minutes → seconds).
    #[arg(long)]
    pub quick: bool,
}

/// Sizes of one run.
struct Config {
    dims: u32,
    image_side: u32,
    repeats: usize,
    /// Step of the converged render that sampling errors are measured against.
    converged_step: f64,
    /// Finer converged step for trilinear, whose convergence is followed further.
    fine_converged_step: f64,
    representation_dims: Vec<u32>,
    representation_step: f64,
}

impl Config {
    fn new(quick: bool) -> Config {
        if quick {
            Config {
                dims: 16,
                image_side: 32,
                repeats: 1,
                converged_step: 1.0 / 32.0,
                fine_converged_step: 1.0 / 128.0,
                representation_dims: vec![8, 16, 32],
                representation_step: 1.0 / 8.0,
            }
        } else {
            Config {
                dims: 64,
                image_side: 128,
                repeats: 3,
                converged_step: 1.0 / 64.0,
                fine_converged_step: 1.0 / 128.0,
                representation_dims: vec![16, 32, 64, 128],
                representation_step: 1.0 / 16.0,
            }
        }
    }
}

/// The interpolations of the sweep. `nonlinear` uses h(t) = ½t + ½t² (ω = [0, ½, ½]): it
/// keeps h(0) = 0 and h(1) = 1, so it interpolates the voxels, but bends between them.
fn interpolations() -> [Interpolation; 4] {
    [
        Interpolation::Nearest,
        Interpolation::Trilinear,
        Interpolation::Nonlinear { omega: [0.0, 0.5, 0.5] },
        Interpolation::Cubic,
    ]
}

/// One point of the sweep.
#[derive(Clone, Debug)]
struct Point {
    scene: Reference,
    interpolation: Interpolation,
    correction: bool,
    step: f64,
    samples: u64,
    seconds: f64,
    rmse: f64,
    max: f64,
    sampling_rmse: f64,
    sampling_max: f64,
    pareto: bool,
}

/// One point of the resolution sweep.
struct Representation {
    scene: Reference,
    dims: u32,
    rmse: f64,
    max: f64,
}

/// A rendered reference image (the red channel: accumulated opacity), its render time
/// without dataset generation, and its sample count.
fn render_reference(r: Reference, s: &Setup) -> Result<(Vec<f64>, f64, u64)> {
    let scene = r.scene(s).with_context(|| format!("building the {} scene", r.name()))?;
    // Per ray: it accumulates in f64 end to end, while the grouped algorithm's piece results
    // are f32 on the wire (about 6e-8 per piece), which would floor the finest errors here.
    let options = RenderOptions { algorithm: Algorithm::PerRay, ..Default::default() };
    let out = render(&scene, &options).with_context(|| format!("rendering {}", r.name()))?;
    let seconds = (out.stats.seconds.total - out.stats.seconds.loading).max(0.0);
    Ok((out.image.pixels().iter().map(|p| p[0]).collect(), seconds, out.stats.samples))
}

/// Runs the benchmark and writes its files.
pub fn run(args: AccuracyArgs) -> Result<()> {
    let cfg = Config::new(args.quick);
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let started = std::time::Instant::now();
    let mut points = Vec::new();
    for scene in Reference::ALL {
        let base = Setup {
            dims: cfg.dims,
            image_side: cfg.image_side,
            interpolation: Interpolation::Trilinear,
            step_voxels: 1.0,
            opacity_correction: true,
        };
        let camera = *scene.scene(&base)?.camera();
        let truth = scene.exact_image(&camera, cfg.image_side, cfg.image_side);
        for interpolation in interpolations() {
            let trilinear = interpolation == Interpolation::Trilinear;
            let converged_step = if trilinear { cfg.fine_converged_step } else { cfg.converged_step };
            let converged =
                render_reference(scene, &Setup { interpolation, step_voxels: converged_step, ..base.clone() })?.0;
            for correction in [true, false] {
                let fine: &[f64] = if trilinear && correction { &FINE_STEPS } else { &[] };
                for &step in STEPS.iter().chain(fine) {
                    let setup =
                        Setup { interpolation, step_voxels: step, opacity_correction: correction, ..base.clone() };
                    let mut times = Vec::with_capacity(cfg.repeats);
                    let mut last = None;
                    for _ in 0..cfg.repeats {
                        let (img, t, n) = render_reference(scene, &setup)?;
                        times.push(t);
                        last = Some((img, n));
                    }
                    let (img, samples) = last.expect("at least one repeat");
                    let (rmse, max) = rmse_and_max(img.iter().copied(), truth.iter().copied());
                    let (sampling_rmse, sampling_max) = rmse_and_max(img.iter().copied(), converged.iter().copied());
                    points.push(Point {
                        scene,
                        interpolation,
                        correction,
                        step,
                        samples,
                        seconds: median(&mut times),
                        rmse,
                        max,
                        sampling_rmse,
                        sampling_max,
                        pareto: false,
                    });
                }
            }
            eprintln!(
                "{:>15} {:<10} done ({:.0} s)",
                scene.name(),
                interpolation.name(),
                started.elapsed().as_secs_f64()
            );
        }
    }
    mark_pareto(&mut points);

    let mut representation = Vec::new();
    for scene in Reference::ALL {
        for &dims in &cfg.representation_dims {
            let setup = Setup {
                dims,
                image_side: cfg.image_side,
                interpolation: Interpolation::Trilinear,
                step_voxels: cfg.representation_step,
                opacity_correction: true,
            };
            let camera = *scene.scene(&setup)?.camera();
            let truth = scene.exact_image(&camera, cfg.image_side, cfg.image_side);
            let (img, _, _) = render_reference(scene, &setup)?;
            let (rmse, max) = rmse_and_max(img, truth);
            representation.push(Representation { scene, dims, rmse, max });
        }
        eprintln!("{:>15} representation done ({:.0} s)", scene.name(), started.elapsed().as_secs_f64());
    }

    let summary = Summary::new(&points, &representation);
    let out = &args.out;
    write_csv(&out.join("accuracy.csv"), &points)?;
    write_representation_csv(&out.join("accuracy_representation.csv"), &representation, cfg.representation_step)?;
    plot(&out.join("accuracy.png"), &points, &summary, &cfg)?;
    let md = report(&summary, &points, &representation, &cfg, args.quick, started.elapsed().as_secs_f64());
    std::fs::write(out.join("accuracy.md"), &md).with_context(|| format!("writing {}", out.display()))?;
    println!("{}", summary.check_line());
    println!("wrote accuracy.csv, accuracy_representation.csv, accuracy.png and accuracy.md to {}", out.display());
    if summary.worst_trilinear_order() < MIN_ORDER {
        if args.quick {
            eprintln!("warning: below the required order (a --quick run is too small to be conclusive)");
        } else {
            bail!(
                "trilinear with opacity correction converged with order {:.2} < {MIN_ORDER}",
                summary.worst_trilinear_order()
            );
        }
    }
    Ok(())
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Marks, per scene, the points no other point beats in both time and total RMSE.
fn mark_pareto(points: &mut [Point]) {
    for scene in Reference::ALL {
        let idx: Vec<usize> = (0..points.len()).filter(|&i| points[i].scene == scene).collect();
        for &i in &idx {
            let p = &points[i];
            let dominated = idx.iter().any(|&j| {
                let q = &points[j];
                j != i && q.seconds <= p.seconds && q.rmse <= p.rmse && (q.seconds < p.seconds || q.rmse < p.rmse)
            });
            points[i].pareto = !dominated;
        }
    }
}

/// Orders and costs drawn from the sweep.
struct Summary {
    /// (scene, interpolation name, order of the sampling RMSE over the sweep's steps 1 … ⅛
    /// voxel), with opacity correction.
    orders: Vec<(Reference, &'static str, Option<f64>)>,
    /// Per scene: order of trilinear's sampling RMSE over [`ORDER_STEPS`] (the check).
    asymptotic: Vec<(Reference, Option<f64>)>,
    /// Per smooth scene: time factor that halves trilinear's sampling error, over [`ORDER_STEPS`].
    halving_cost: Vec<(Reference, Option<f64>)>,
    /// Per scene: representation order of trilinear (RMSE against voxel size).
    representation_orders: Vec<(Reference, Option<f64>)>,
}

impl Summary {
    fn new(points: &[Point], representation: &[Representation]) -> Summary {
        let series = |scene: Reference, interp: &str, steps: &[f64]| -> Vec<&Point> {
            points
                .iter()
                .filter(|p| {
                    p.scene == scene && p.interpolation.name() == interp && p.correction && steps.contains(&p.step)
                })
                .collect()
        };
        let sweep = [1.0, 0.5, 0.25, 0.125];
        let mut orders = Vec::new();
        let mut asymptotic = Vec::new();
        let mut halving_cost = Vec::new();
        for scene in Reference::ALL {
            for i in interpolations() {
                let s = series(scene, i.name(), &sweep);
                let order = log_log_slope(&s.iter().map(|p| (p.step, p.sampling_rmse)).collect::<Vec<_>>());
                orders.push((scene, i.name(), order));
            }
            let s = series(scene, "trilinear", &ORDER_STEPS);
            asymptotic.push((scene, log_log_slope(&s.iter().map(|p| (p.step, p.sampling_rmse)).collect::<Vec<_>>())));
            if scene.smooth() {
                // time ∝ error^k, so halving the error multiplies the time by 2^(−k).
                let k = log_log_slope(&s.iter().map(|p| (p.sampling_rmse, p.seconds)).collect::<Vec<_>>());
                halving_cost.push((scene, k.map(|k| 2f64.powf(-k))));
            }
        }
        let representation_orders = Reference::ALL
            .iter()
            .map(|&scene| {
                let pts: Vec<(f64, f64)> =
                    representation.iter().filter(|r| r.scene == scene).map(|r| (1.0 / r.dims as f64, r.rmse)).collect();
                (scene, log_log_slope(&pts))
            })
            .collect();
        Summary { orders, asymptotic, halving_cost, representation_orders }
    }

    /// Trilinear's asymptotic order on `scene`.
    fn asymptotic_order(&self, scene: Reference) -> Option<f64> {
        self.asymptotic.iter().find(|o| o.0 == scene).and_then(|o| o.1)
    }

    fn order(&self, scene: Reference, interp: &str) -> Option<f64> {
        self.orders.iter().find(|o| o.0 == scene && o.1 == interp).and_then(|o| o.2)
    }

    /// The smallest asymptotic trilinear order over the smooth scenes.
    fn worst_trilinear_order(&self) -> f64 {
        Reference::ALL
            .iter()
            .filter(|s| s.smooth())
            .map(|&s| self.asymptotic_order(s).unwrap_or(0.0))
            .fold(f64::INFINITY, f64::min)
    }

    fn check_line(&self) -> String {
        let orders: Vec<String> = Reference::ALL
            .iter()
            .filter(|s| s.smooth())
            .map(|&s| format!("{} {:.2}", s.name(), self.asymptotic_order(s).unwrap_or(f64::NAN)))
            .collect();
        let verdict = if self.worst_trilinear_order() >= MIN_ORDER { "PASS" } else { "FAIL" };
        format!(
            "{verdict}: trilinear + opacity correction, sampling-error order over steps ¼ … 1/32 voxel: {} \
             (required ≥ {MIN_ORDER})",
            orders.join(", ")
        )
    }
}

fn write_csv(path: &Path, points: &[Point]) -> Result<()> {
    let mut s = String::from(
        "scene,interpolation,opacity_correction,step_voxels,samples,median_seconds,rmse,max_error,sampling_rmse,sampling_max_error,pareto\n",
    );
    for p in points {
        writeln!(
            s,
            "{},{},{},{},{},{:.6e},{:.6e},{:.6e},{:.6e},{:.6e},{}",
            p.scene.name(),
            p.interpolation.name(),
            p.correction,
            p.step,
            p.samples,
            p.seconds,
            p.rmse,
            p.max,
            p.sampling_rmse,
            p.sampling_max,
            p.pareto
        )?;
    }
    std::fs::write(path, s).with_context(|| format!("writing {}", path.display()))
}

fn write_representation_csv(path: &Path, rows: &[Representation], step: f64) -> Result<()> {
    let mut s = String::from("scene,dims,step_voxels,rmse,max_error\n");
    for r in rows {
        writeln!(s, "{},{},{},{:.6e},{:.6e}", r.scene.name(), r.dims, step, r.rmse, r.max)?;
    }
    std::fs::write(path, s).with_context(|| format!("writing {}", path.display()))
}

/// Where a sans-serif TrueType font may be (plotters draws text only with a font it is
/// given; reading one at run time avoids building against fontconfig). `TROVE_FONT` wins.
const FONT_PATHS: [&str; 5] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/System/Library/Fonts/Supplemental/Arial.ttf",
];

fn register_font() -> Result<()> {
    let env = std::env::var("TROVE_FONT").ok();
    let candidates = env.iter().map(String::as_str).chain(FONT_PATHS);
    for path in candidates {
        if let Ok(bytes) = std::fs::read(path) {
            // plotters keeps fonts for the whole process; one small leak per run.
            let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
            if plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).is_ok() {
                return Ok(());
            }
        }
    }
    bail!(
        "no TrueType font for the plot's labels: set TROVE_FONT to a .ttf file (looked in {}); \
         the CSV files were written",
        FONT_PATHS.join(", ")
    )
}

/// Colours per interpolation, in the order of [`interpolations`].
const COLOURS: [RGBColor; 4] =
    [RGBColor(214, 39, 40), RGBColor(31, 119, 180), RGBColor(44, 160, 44), RGBColor(148, 103, 189)];
/// Log axes cannot show 0: errors at or below this are drawn at it.
const ERROR_FLOOR: f64 = 1e-16;

fn plot_err<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow!("drawing the plot: {e:?}")
}

fn plot(path: &Path, points: &[Point], summary: &Summary, cfg: &Config) -> Result<()> {
    register_font()?;
    let (w, h) = (1800u32, 1150u32);
    let mut buf = vec![0u8; w as usize * h as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        let title = format!(
            "Error against exact integrals vs render time: {d}³ voxels, {s}×{s} pixels, steps 4 … 1/8 voxel \
             (solid ●: opacity correction on; faded ×: off; ○: Pareto front)",
            d = cfg.dims,
            s = cfg.image_side
        );
        let root = root.titled(&title, ("sans-serif", 22)).map_err(plot_err)?;
        let panels = root.split_evenly((2, 3));
        for (k, (area, scene)) in panels.iter().zip(Reference::ALL).enumerate() {
            scene_panel(area, points, scene, k == 0)?;
        }
        convergence_panel(&panels[5], points, summary)?;
        root.present().map_err(plot_err)?;
    }
    image::save_buffer(path, &buf, w, h, image::ExtendedColorType::Rgb8)
        .with_context(|| format!("writing {}", path.display()))
}

fn log_range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values.fold((f64::INFINITY, 0.0f64), |(lo, hi), v| (lo.min(v), hi.max(v)));
    (lo / 1.6, hi * 1.6)
}

fn scene_panel(
    area: &DrawingArea<BitMapBackend, Shift>,
    points: &[Point],
    scene: Reference,
    legend: bool,
) -> Result<()> {
    let pts: Vec<&Point> = points.iter().filter(|p| p.scene == scene).collect();
    let (t0, t1) = log_range(pts.iter().map(|p| p.seconds.max(1e-6)));
    let (e0, e1) = log_range(pts.iter().map(|p| p.rmse.max(ERROR_FLOOR)));
    let mut chart = ChartBuilder::on(area)
        .caption(scene.name(), ("sans-serif", 20))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d((t0..t1).log_scale(), (e0..e1).log_scale())
        .map_err(plot_err)?;
    chart
        .configure_mesh()
        .x_desc("median render time (s)")
        .y_desc("RMSE vs exact")
        .x_label_formatter(&|v| format!("{v:.0e}"))
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .label_style(("sans-serif", 13))
        .axis_desc_style(("sans-serif", 15))
        .light_line_style(WHITE.mix(0.0))
        .draw()
        .map_err(plot_err)?;
    for (interp, colour) in interpolations().iter().zip(COLOURS) {
        for correction in [true, false] {
            let mut series: Vec<&Point> = pts
                .iter()
                .copied()
                .filter(|p| p.interpolation.name() == interp.name() && p.correction == correction)
                .collect();
            series.sort_by(|a, b| b.step.total_cmp(&a.step));
            let xy: Vec<(f64, f64)> = series.iter().map(|p| (p.seconds.max(1e-6), p.rmse.max(ERROR_FLOOR))).collect();
            if correction {
                let drawn = chart.draw_series(LineSeries::new(xy.clone(), colour.stroke_width(2))).map_err(plot_err)?;
                if legend {
                    drawn
                        .label(interp.name())
                        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
                }
                chart.draw_series(xy.iter().map(|&p| Circle::new(p, 4, colour.filled()))).map_err(plot_err)?;
            } else {
                chart.draw_series(LineSeries::new(xy.clone(), colour.mix(0.35).stroke_width(1))).map_err(plot_err)?;
                chart.draw_series(xy.iter().map(|&p| Cross::new(p, 4, colour.mix(0.5)))).map_err(plot_err)?;
            }
        }
    }
    let mut front: Vec<(f64, f64)> =
        pts.iter().filter(|p| p.pareto).map(|p| (p.seconds.max(1e-6), p.rmse.max(ERROR_FLOOR))).collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    let drawn = chart.draw_series(LineSeries::new(front.clone(), BLACK.mix(0.6).stroke_width(1))).map_err(plot_err)?;
    if legend {
        drawn.label("Pareto front").legend(|(x, y)| Circle::new((x + 10, y), 6, BLACK.stroke_width(1)));
    }
    chart.draw_series(front.iter().map(|&p| Circle::new(p, 8, BLACK.stroke_width(1)))).map_err(plot_err)?;
    if legend {
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.5))
            .label_font(("sans-serif", 14))
            .draw()
            .map_err(plot_err)?;
    }
    Ok(())
}

fn convergence_panel(area: &DrawingArea<BitMapBackend, Shift>, points: &[Point], summary: &Summary) -> Result<()> {
    let smooth: Vec<Reference> = Reference::ALL.iter().copied().filter(|s| s.smooth()).collect();
    let pts: Vec<&Point> = points
        .iter()
        .filter(|p| smooth.contains(&p.scene) && p.interpolation.name() == "trilinear" && p.correction)
        .collect();
    let (e0, e1) = log_range(pts.iter().map(|p| p.sampling_rmse.max(ERROR_FLOOR)));
    let mut chart = ChartBuilder::on(area)
        .caption("sampling error, trilinear + correction", ("sans-serif", 20))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d((0.02f64..5.0).log_scale(), (e0..e1).log_scale())
        .map_err(plot_err)?;
    chart
        .configure_mesh()
        .x_desc("sampling distance (voxels)")
        .y_desc("RMSE vs converged render")
        .x_label_formatter(&|v| format!("{v}"))
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .label_style(("sans-serif", 13))
        .axis_desc_style(("sans-serif", 15))
        .light_line_style(WHITE.mix(0.0))
        .draw()
        .map_err(plot_err)?;
    let scene_colours = [RGBColor(255, 127, 14), RGBColor(23, 190, 207), RGBColor(140, 86, 75)];
    for (scene, colour) in smooth.iter().zip(scene_colours) {
        let mut xy: Vec<(f64, f64)> =
            pts.iter().filter(|p| p.scene == *scene).map(|p| (p.step, p.sampling_rmse.max(ERROR_FLOOR))).collect();
        xy.sort_by(|a, b| a.0.total_cmp(&b.0));
        let order = summary.asymptotic_order(*scene).unwrap_or(f64::NAN);
        chart
            .draw_series(LineSeries::new(xy.clone(), colour.stroke_width(2)))
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
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK.mix(0.5))
        .label_font(("sans-serif", 14))
        .draw()
        .map_err(plot_err)?;
    Ok(())
}

fn point<'a>(points: &'a [Point], scene: Reference, interp: &str, correction: bool, step: f64) -> Option<&'a Point> {
    points
        .iter()
        .find(|p| p.scene == scene && p.interpolation.name() == interp && p.correction == correction && p.step == step)
}

/// 0.125 → "⅛", 0.5 → "½", 2 → "2".
fn step_name(step: f64) -> String {
    match step {
        0.5 => "½".into(),
        0.25 => "¼".into(),
        0.125 => "⅛".into(),
        s if s >= 1.0 => format!("{s}"),
        s => format!("1/{}", (1.0 / s).round()),
    }
}

fn fmt_opt(v: Option<f64>, digits: usize) -> String {
    v.map_or("–".to_string(), |v| format!("{v:.digits$}"))
}

/// docs/accuracy.md: the README paragraph and the BENCHMARKS section, numbers filled in.
fn report(
    summary: &Summary,
    points: &[Point],
    representation: &[Representation],
    cfg: &Config,
    quick: bool,
    seconds: f64,
) -> String {
    let mut s = String::new();
    let smooth: Vec<Reference> = Reference::ALL.iter().copied().filter(|s| s.smooth()).collect();
    let tri_orders: Vec<String> = smooth
        .iter()
        .map(|&r| format!("{} on {}", fmt_opt(summary.asymptotic_order(r), 2), r.name().replace('_', "–")))
        .collect();
    let halving: Vec<String> = summary
        .halving_cost
        .iter()
        .map(|(r, c)| format!("{}× on {}", fmt_opt(*c, 2), r.name().replace('_', "–")))
        .collect();
    // What cubic buys over trilinear at the default step of one voxel, on the Gaussian.
    let g = Reference::Gaussian;
    let ratio = |interp: &str, step: f64| -> Option<(f64, f64, f64)> {
        let t = point(points, g, "trilinear", true, step)?;
        let c = point(points, g, interp, true, step)?;
        Some((t.rmse / c.rmse, c.seconds / t.seconds, c.sampling_rmse / t.sampling_rmse))
    };
    let cubic1 = ratio("cubic", 1.0);
    let cubic_fine = ratio("cubic", 0.125);
    let uncorrected = point(points, g, "trilinear", false, 0.125).map(|p| p.rmse);
    let corrected = point(points, g, "trilinear", true, 0.125).map(|p| p.rmse);
    let repr_g = summary.representation_orders.iter().find(|r| r.0 == g).and_then(|r| r.1);
    let sweep_orders: Vec<String> = smooth
        .iter()
        .map(|&r| format!("{} on {}", fmt_opt(summary.order(r, "trilinear"), 2), r.name().replace('_', "–")))
        .collect();
    // The coarsest step at which trilinear's sampling error is below a tenth of what the
    // voxels get wrong anyway (its total error at the finest step), per smooth scene.
    let enough_steps: Vec<String> = smooth
        .iter()
        .filter_map(|&r| {
            let floor = point(points, r, "trilinear", true, 0.125)?.rmse;
            let step = STEPS
                .iter()
                .find(|&&st| point(points, r, "trilinear", true, st).is_some_and(|p| p.sampling_rmse <= 0.1 * floor))?;
            Some(format!("{} voxel on {}", step_name(*step), r.name().replace('_', "–")))
        })
        .collect();
    let enough = if enough_steps.is_empty() {
        String::new()
    } else {
        format!(
            "At {d}³ voxels the sampling error of trilinear drops below a tenth of the representation error at \
             a step of {}: finer steps cost time and buy nothing a finer volume would not buy better, which is \
             where the Pareto fronts in the plot turn flat.",
            enough_steps.join(", "),
            d = cfg.dims
        )
    };

    let _ = writeln!(
        s,
        "<!-- Generated by `trove bench accuracy{}`; do not edit by hand. -->\n",
        if quick { " --quick" } else { "" }
    );
    let _ = writeln!(s, "# Accuracy and what it costs\n");
    let _ = writeln!(s, "## README paragraph\n");
    let _ = writeln!(s, "![Error against render time](accuracy.png)\n");
    let _ = writeln!(
        s,
        "Rendered against scenes whose ray integrals have closed forms (`trove bench accuracy`), \
         trilinear interpolation with opacity correction converges as the midpoint rule should: the sampling \
         error falls with measured order {} (fitted over steps of ¼ … 1/32 voxel; over the sweep's 1 … ⅛ the \
         fit gives {}, because at 1 and ½ voxel the samples are commensurate with the voxel grid and the \
         errors of neighbouring cells partly cancel), so halving it costs {} the render time. Cubic \
         interpolation changes the total error on the Gaussian by a factor {} at one voxel per step \
         (trilinear error / cubic error; above 1 means cubic is better) for {}× the time, and by {} at ⅛ \
         voxel, where what remains is representation error (trilinear's falls with order {} in the voxel \
         size). Without opacity correction the image does not converge at all: at ⅛ voxel the error on the \
         Gaussian is {} instead of {}. {}\n",
        tri_orders.join(", "),
        sweep_orders.join(", "),
        halving.join(", "),
        fmt_opt(cubic1.map(|c| c.0), 2),
        fmt_opt(cubic1.map(|c| c.1), 1),
        fmt_opt(cubic_fine.map(|c| c.0), 2),
        fmt_opt(repr_g, 2),
        uncorrected.map_or("–".into(), |v| format!("{v:.1e}")),
        corrected.map_or("–".into(), |v| format!("{v:.1e}")),
        enough,
    );

    let _ = writeln!(s, "## BENCHMARKS section: Accuracy\n");
    let _ = writeln!(
        s,
        "Command: `cargo run --release -p trove-coordinator -- bench accuracy --out docs/{}` \
         ({:.0} s on this machine, {} logical CPUs). It writes `accuracy.csv` (one row per point), \
         `accuracy_representation.csv`, `accuracy.png` and this file.\n",
        if quick { " --quick" } else { "" },
        seconds,
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    let _ = writeln!(
        s,
        "Setup: every reference scene at {d}³ voxels in the unit cube, {p}×{p} pixels, termination 1.0, \
         white objects on black so a pixel is 1 − T; sampling distance {{4, 2, 1, ½, ¼, ⅛}} voxel × \
         {{nearest, trilinear, nonlinear ω = [0, ½, ½], cubic}} × opacity correction on/off; the median of {r} \
         renders per point (render time without dataset generation). *Total* error is against the exact \
         integral; *sampling* error against a render of the same voxels at 1/{c} voxel. Renders use \
         the per-ray algorithm, which accumulates in f64 only (the grouped algorithm's piece results are \
         f32 on the wire), so f32 accumulation is not an axis (its error over 10⁵ samples is bounded \
         in `tests/tests/numerics.rs`, see `docs/numerics.md`).\n",
        d = cfg.dims,
        p = cfg.image_side,
        r = cfg.repeats,
        c = (1.0 / cfg.converged_step).round()
    );
    let _ = writeln!(
        s,
        "How extinction becomes opacity: a voxel of extinction σ (per world unit) and world length h gets \
         O = 1 − e^(−σh); with opacity correction a sample over ℓ voxels then has α = 1 − (1 − O)^ℓ = \
         1 − e^(−σ·hℓ), and hℓ is the sample's world length, so T = exp(−Σ σₖΔsₖ), the midpoint rule for \
         ∫σ ds. Fields with σ = κ·v use a `polynomial` opacity map holding the Taylor series of 1 − e^(−κhv). \
         See `trove-core/src/reference.rs`.\n"
    );

    let _ = writeln!(s, "### Convergence order of the sampling error (opacity correction on)\n");
    let _ = writeln!(s, "Least-squares slope of log(sampling RMSE) against log(step) over the sweep's steps 1 … ⅛ voxel, and for trilinear also over ¼ … 1/32 voxel (two extra steps, against a render at 1/{} voxel).\n", (1.0 / cfg.fine_converged_step).round());
    let _ = writeln!(s, "| scene | nearest | trilinear | nonlinear | cubic | trilinear, ¼ … 1/32 |");
    let _ = writeln!(s, "|---|---|---|---|---|---|");
    for r in Reference::ALL {
        let cells: Vec<String> = interpolations().iter().map(|i| fmt_opt(summary.order(r, i.name()), 2)).collect();
        let _ = writeln!(s, "| {} | {} | {} |", r.name(), cells.join(" | "), fmt_opt(summary.asymptotic_order(r), 2));
    }
    let _ = writeln!(
        s,
        "\nThe two constant boxes are integrated exactly at every step (errors at rounding level), so their \
         \"order\" is noise. The sphere's surface is a jump in the field, which the midpoint rule integrates \
         at order 1. {}\n",
        summary.check_line()
    );

    let _ = writeln!(s, "### Total error at one voxel per step and at ⅛ voxel (RMSE, correction on) and time\n");
    let _ =
        writeln!(s, "| scene | interpolation | RMSE @1 | RMSE @⅛ | sampling RMSE @⅛ | time @1 (ms) | time @⅛ (ms) |");
    let _ = writeln!(s, "|---|---|---|---|---|---|---|");
    for r in Reference::ALL {
        for i in interpolations() {
            if let (Some(a), Some(b)) = (point(points, r, i.name(), true, 1.0), point(points, r, i.name(), true, 0.125))
            {
                let _ = writeln!(
                    s,
                    "| {} | {} | {:.2e} | {:.2e} | {:.2e} | {:.1} | {:.1} |",
                    r.name(),
                    i.name(),
                    a.rmse,
                    b.rmse,
                    b.sampling_rmse,
                    a.seconds * 1e3,
                    b.seconds * 1e3
                );
            }
        }
    }

    let _ = writeln!(
        s,
        "\n### Representation error (trilinear, correction on, step 1/{} voxel, against the exact integral)\n",
        (1.0 / cfg.representation_step).round()
    );
    let dims_header: Vec<String> = cfg.representation_dims.iter().map(|d| format!("{d}³")).collect();
    let _ = writeln!(s, "| scene | {} | order |", dims_header.join(" | "));
    let _ = writeln!(s, "|---|{}---|", "---|".repeat(cfg.representation_dims.len()));
    for r in Reference::ALL {
        let cells: Vec<String> = cfg
            .representation_dims
            .iter()
            .map(|&d| {
                representation
                    .iter()
                    .find(|x| x.scene == r && x.dims == d)
                    .map_or("–".into(), |x| format!("{:.2e}", x.rmse))
            })
            .collect();
        let order = summary.representation_orders.iter().find(|o| o.0 == r).and_then(|o| o.1);
        let _ = writeln!(s, "| {} | {} | {} |", r.name(), cells.join(" | "), fmt_opt(order, 2));
    }

    let _ = writeln!(s, "\n### Pareto fronts (time vs total RMSE, all configurations)\n");
    for r in Reference::ALL {
        let mut front: Vec<&Point> = points.iter().filter(|p| p.scene == r && p.pareto).collect();
        front.sort_by(|a, b| a.seconds.total_cmp(&b.seconds));
        let items: Vec<String> = front
            .iter()
            .map(|p| {
                format!(
                    "{}{} @{} ({:.1} ms, {:.1e})",
                    p.interpolation.name(),
                    if p.correction { "" } else { " uncorrected" },
                    p.step,
                    p.seconds * 1e3,
                    p.rmse
                )
            })
            .collect();
        let _ = writeln!(s, "- **{}**: {}", r.name(), items.join(" → "));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_quick_run_writes_the_csv_the_plot_and_the_summary() {
        let out = std::env::temp_dir().join(format!("trove-bench-accuracy-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&out);
        let result = run(AccuracyArgs { out: out.clone(), quick: true });
        let csv = std::fs::read_to_string(out.join("accuracy.csv")).expect("accuracy.csv");
        // 5 scenes × 4 interpolations × 2 corrections × 6 steps, plus trilinear's 2 fine steps.
        assert_eq!(csv.lines().count(), 1 + 5 * (4 * 2 * 6 + 2), "{csv}");
        assert!(csv.lines().skip(1).all(|l| l.split(',').count() == 11));
        assert!(out.join("accuracy_representation.csv").is_file());
        match result {
            Ok(()) => {
                assert!(out.join("accuracy.png").is_file());
                let md = std::fs::read_to_string(out.join("accuracy.md")).unwrap();
                assert!(md.contains("README paragraph") && md.contains("BENCHMARKS section"));
            }
            // A machine without any of the known fonts still gets the CSV files.
            Err(e) => assert!(e.to_string().contains("TrueType font"), "{e:#}"),
        }
        let _ = std::fs::remove_dir_all(&out);
    }

    #[test]
    fn pareto_marks_exactly_the_undominated_points() {
        let p = |seconds: f64, rmse: f64| Point {
            scene: Reference::Gaussian,
            interpolation: Interpolation::Trilinear,
            correction: true,
            step: 1.0,
            samples: 0,
            seconds,
            rmse,
            max: rmse,
            sampling_rmse: rmse,
            sampling_max: rmse,
            pareto: false,
        };
        let mut points = vec![p(1.0, 1.0), p(2.0, 0.5), p(2.0, 0.8), p(3.0, 0.5), p(0.5, 2.0)];
        mark_pareto(&mut points);
        let front: Vec<bool> = points.iter().map(|p| p.pareto).collect();
        assert_eq!(front, vec![true, true, false, false, true]);
    }
}
