//! `trove-bench accuracy`: what accuracy costs in time.
//!
//! Every reference scene of [`trove_tests::reference`] is rendered over the sweep sampling
//! distance (4, 2, 1, ½, ¼, ⅛ voxel) × interpolation (nearest, trilinear, nonlinear,
//! cubic) × opacity correction on/off. Each point records the median render time of
//! several renders and two errors over the image (RMSE and max, in linear pixel values):
//! against the exact integral (*total* error) and against a converged render of the same
//! voxels with the same interpolation (*sampling* error, see the reference module for why
//! the two differ). A second sweep grows the resolution at a fine step to isolate the
//! *representation* error. Renders use the per-ray algorithm, which accumulates in f64
//! only, so there is no f32/f64 axis.
//!
//! The stages are modules: [`sweep`] renders and measures, [`summary`] fits orders and
//! costs and gives the verdict, [`csv`], [`plot`] and [`report`] write the outputs. They go
//! to `--out DIR` (default: a new folder under the system temp dir, so that a trial run
//! never touches the tracked `docs/`; `--out docs/` regenerates them there):
//! `accuracy.csv` (the sweep), `accuracy_representation.csv`, `accuracy.png` (error against
//! time, log-log, one curve per interpolation, Pareto front ringed, plus the convergence
//! panel) and `accuracy.md` (the measured orders and costs, written as the README paragraph
//! and the BENCHMARKS section).
//!
//! The run fails (non-zero exit, after writing every file) when trilinear interpolation with
//! opacity correction converges with a measured order below [`MIN_ORDER`] on a smooth field
//! (the midpoint rule's order is 2).

mod csv;
mod plot;
mod report;
mod summary;
mod sweep;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use trove_core::Interpolation;

use summary::Summary;
use sweep::{Config, Point, Representation};

/// The lowest acceptable convergence order of trilinear + opacity correction on smooth fields.
const MIN_ORDER: f64 = 1.8;

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

/// Arguments of `trove-bench accuracy`.
#[derive(clap::Args, Debug)]
pub struct AccuracyArgs {
    /// Folder for accuracy.csv, accuracy_representation.csv, accuracy.png and accuracy.md,
    /// created if missing. Default: a new folder under the system temp dir. `--out docs/`
    /// regenerates the files the README and BENCHMARKS.md cite.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// A smoke run: small volumes and images, one timing per point (minutes → seconds).
    #[arg(long)]
    pub quick: bool,
}

impl AccuracyArgs {
    /// The command line that reproduces this run, as the report quotes it.
    fn command(&self) -> String {
        let mut c = "cargo run --release -p trove-bench -- accuracy".to_string();
        if let Some(out) = &self.out {
            c += &format!(" --out {}", out.display());
        }
        if self.quick {
            c += " --quick";
        }
        c
    }
}

/// Runs the benchmark, writes its files and fails when the verdict is FAIL.
pub fn run(args: AccuracyArgs) -> Result<()> {
    let cfg = Config::new(args.quick);
    let out = args.out.clone().unwrap_or_else(scratch_folder);
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let started = Instant::now();
    let points = sweep::sweep(&cfg, &started)?;
    let representation = sweep::representation(&cfg, &started)?;
    let summary = Summary::new(&points, &representation);
    let seconds = started.elapsed().as_secs_f64();
    write_outputs(&out, &cfg, &args, seconds, (&points, &representation, &summary))?;
    println!("{}", summary.check_line());
    println!("wrote accuracy.csv, accuracy_representation.csv, accuracy.png and accuracy.md to {}", out.display());
    if !summary.passes() {
        bail!(
            "FAIL: trilinear with opacity correction converged with order {:.2} < {MIN_ORDER}{}",
            summary.worst_trilinear_order(),
            if args.quick { " (in a --quick run; a full run samples the convergence more finely)" } else { "" }
        );
    }
    Ok(())
}

/// A fresh folder for this run's files under the system temp dir.
fn scratch_folder() -> PathBuf {
    std::env::temp_dir().join(format!("trove-bench-accuracy-{}", std::process::id()))
}

/// Writes the two CSV files, the plot and the report into `out`.
fn write_outputs(
    out: &Path,
    cfg: &Config,
    args: &AccuracyArgs,
    seconds: f64,
    (points, representation, summary): (&[Point], &[Representation], &Summary),
) -> Result<()> {
    csv::write_points(&out.join("accuracy.csv"), points)?;
    csv::write_representation(&out.join("accuracy_representation.csv"), representation, cfg.representation_step)?;
    plot::plot(&out.join("accuracy.png"), points, summary, cfg, plot::Text::find())?;
    let run = report::Run { cfg, command: args.command(), quick: args.quick, seconds };
    let md = report::report(&run, summary, points, representation);
    let path = out.join("accuracy.md");
    std::fs::write(&path, md).with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_quick_run_writes_the_csv_the_plot_and_the_summary_and_passes() {
        let out = std::env::temp_dir().join(format!("trove-bench-accuracy-test-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&out);
        let result = run(AccuracyArgs { out: Some(out.clone()), quick: true });
        let csv = std::fs::read_to_string(out.join("accuracy.csv")).expect("accuracy.csv");
        // 5 scenes × 4 interpolations × 2 corrections × 6 steps, plus trilinear's 2 fine steps.
        assert_eq!(csv.lines().count(), 1 + 5 * (4 * 2 * 6 + 2), "{csv}");
        assert!(csv.lines().skip(1).all(|l| l.split(',').count() == 11));
        assert!(out.join("accuracy_representation.csv").is_file());
        // The plot is written whether or not a font for its labels exists.
        let png = image::open(out.join("accuracy.png")).expect("accuracy.png is a readable image");
        assert_eq!((png.width(), png.height()), plot::SIZE);
        let md = std::fs::read_to_string(out.join("accuracy.md")).expect("accuracy.md");
        assert!(md.contains("README paragraph") && md.contains("BENCHMARKS section"), "{md}");
        assert!(md.contains("-- accuracy --out ") && md.contains(" --quick`"), "the command that made it: {md}");
        // The quick sizes still resolve second-order convergence: the verdict is PASS.
        result.expect("a quick run passes");
        assert!(md.contains("PASS: "), "{md}");
        let _ = std::fs::remove_dir_all(&out);
    }

    #[test]
    fn the_default_folder_is_scratch_space_not_the_tracked_docs() {
        let args = AccuracyArgs { out: None, quick: true };
        let dir = args.out.clone().unwrap_or_else(scratch_folder);
        assert!(dir.starts_with(std::env::temp_dir()), "{}", dir.display());
        assert_eq!(args.command(), "cargo run --release -p trove-bench -- accuracy --quick");
        let docs = AccuracyArgs { out: Some("docs/".into()), quick: false };
        assert_eq!(docs.command(), "cargo run --release -p trove-bench -- accuracy --out docs/");
    }
}
