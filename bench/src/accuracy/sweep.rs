//! The renders: every reference scene over steps × interpolations × opacity correction
//! (the sweep), and over resolutions at a fine step (the representation error).

use std::time::Instant;

use anyhow::{Context, Result};
use trove_core::render::{Algorithm, RenderOptions};
use trove_core::Interpolation;
use trove_tests::reference::{rmse_and_max, Reference, Setup};

use super::{interpolations, FINE_STEPS, STEPS};

/// Sizes of one run.
pub(super) struct Config {
    pub dims: u32,
    pub image_side: u32,
    pub repeats: u32,
    /// Step of the converged render that sampling errors are measured against.
    pub converged_step: f64,
    /// Finer converged step for trilinear, whose convergence is followed further.
    pub fine_converged_step: f64,
    pub representation_dims: Vec<u32>,
    pub representation_step: f64,
}

impl Config {
    pub fn new(quick: bool) -> Config {
        if quick {
            // 48 pixels, not fewer: the order fit averages over rays that meet the voxel grid
            // at different phases, and with 32×32 rays it wandered below the threshold (1.78
            // on the Gaussian) while from 40 pixels up it settled at 1.83–1.88, as in the
            // full run.
            Config {
                dims: 16,
                image_side: 48,
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

    /// Trilinear, one voxel per step, with correction, at `dims` voxels.
    fn setup(&self, dims: u32) -> Setup {
        Setup {
            dims,
            image_side: self.image_side,
            interpolation: Interpolation::Trilinear,
            step_voxels: 1.0,
            opacity_correction: true,
        }
    }
}

/// One point of the sweep.
#[derive(Clone, Debug)]
pub(super) struct Point {
    pub scene: Reference,
    pub interpolation: Interpolation,
    pub correction: bool,
    pub step: f64,
    pub samples: u64,
    pub seconds: f64,
    pub rmse: f64,
    pub max: f64,
    pub sampling_rmse: f64,
    pub sampling_max: f64,
    pub pareto: bool,
}

impl Point {
    /// The point of `scene` with interpolation `interp`, correction and step, if swept.
    pub fn find<'a>(
        points: &'a [Point],
        scene: Reference,
        interp: &str,
        correction: bool,
        step: f64,
    ) -> Option<&'a Point> {
        points.iter().find(|p| {
            p.scene == scene && p.interpolation.name() == interp && p.correction == correction && p.step == step
        })
    }
}

/// One point of the resolution sweep.
pub(super) struct Representation {
    pub scene: Reference,
    pub dims: u32,
    pub rmse: f64,
    pub max: f64,
}

/// A reference render: the red channel (accumulated opacity: white objects on black), the
/// render time without dataset generation, and the sample count.
struct Measured {
    alpha: Vec<f64>,
    seconds: f64,
    samples: u64,
}

/// Renders `r` set up as `s`, `repeats` times, keeping the run with the median time.
fn render_reference(r: Reference, s: &Setup, repeats: u32) -> Result<Measured> {
    let scene = r.scene(s).with_context(|| format!("building the {} scene", r.name()))?;
    // Per ray: it accumulates in f64 end to end, while the grouped algorithm's piece results
    // are f32 on the wire (about 6e-8 per piece), which would floor the finest errors here.
    let options = RenderOptions { algorithm: Algorithm::PerRay, ..Default::default() };
    let out =
        crate::median_render(&scene, &options, repeats, |_| {}).with_context(|| format!("rendering {}", r.name()))?;
    // Every render generates its datasets again; that is not what the step costs.
    let seconds = (out.stats.seconds.total - out.stats.seconds.loading).max(0.0);
    Ok(Measured { alpha: out.image.pixels().iter().map(|p| p[0]).collect(), seconds, samples: out.stats.samples })
}

/// The exact image of `r` set up as `s` (SPEC §4.1's rays, closed-form integrals).
fn exact(r: Reference, s: &Setup) -> Result<Vec<f64>> {
    let camera = *r.scene(s).with_context(|| format!("building the {} scene", r.name()))?.camera();
    Ok(r.exact_image(&camera, s.image_side, s.image_side))
}

/// The whole sweep, Pareto fronts marked. Prints a line per (scene, interpolation) done.
pub(super) fn sweep(cfg: &Config, started: &Instant) -> Result<Vec<Point>> {
    let mut points = Vec::new();
    for scene in Reference::ALL {
        let truth = exact(scene, &cfg.setup(cfg.dims))?;
        for interpolation in interpolations() {
            points.extend(sweep_interpolation(cfg, scene, interpolation, &truth)?);
            let elapsed = started.elapsed().as_secs_f64();
            eprintln!("{:>15} {:<10} done ({elapsed:.0} s)", scene.name(), interpolation.name());
        }
    }
    mark_pareto(&mut points);
    Ok(points)
}

/// Every step, with and without correction, of one scene and interpolation; trilinear with
/// correction also takes [`FINE_STEPS`], against a finer converged render.
fn sweep_interpolation(
    cfg: &Config,
    scene: Reference,
    interpolation: Interpolation,
    truth: &[f64],
) -> Result<Vec<Point>> {
    let trilinear = interpolation == Interpolation::Trilinear;
    let converged_step = if trilinear { cfg.fine_converged_step } else { cfg.converged_step };
    let base = Setup { interpolation, ..cfg.setup(cfg.dims) };
    let converged = render_reference(scene, &Setup { step_voxels: converged_step, ..base.clone() }, 1)?.alpha;
    let mut points = Vec::new();
    for correction in [true, false] {
        let fine: &[f64] = if trilinear && correction { &FINE_STEPS } else { &[] };
        for &step in STEPS.iter().chain(fine) {
            let setup = Setup { step_voxels: step, opacity_correction: correction, ..base.clone() };
            let m = render_reference(scene, &setup, cfg.repeats)?;
            let (rmse, max) = rmse_and_max(m.alpha.iter().copied(), truth.iter().copied());
            let (sampling_rmse, sampling_max) = rmse_and_max(m.alpha.iter().copied(), converged.iter().copied());
            points.push(Point {
                scene,
                interpolation,
                correction,
                step,
                samples: m.samples,
                seconds: m.seconds,
                rmse,
                max,
                sampling_rmse,
                sampling_max,
                pareto: false,
            });
        }
    }
    Ok(points)
}

/// Trilinear with correction at [`Config::representation_step`] over growing resolutions,
/// against the exact integral: what the voxels get wrong, not the steps.
pub(super) fn representation(cfg: &Config, started: &Instant) -> Result<Vec<Representation>> {
    let mut rows = Vec::new();
    for scene in Reference::ALL {
        for &dims in &cfg.representation_dims {
            let setup = Setup { step_voxels: cfg.representation_step, ..cfg.setup(dims) };
            let truth = exact(scene, &setup)?;
            let img = render_reference(scene, &setup, 1)?.alpha;
            let (rmse, max) = rmse_and_max(img, truth);
            rows.push(Representation { scene, dims, rmse, max });
        }
        eprintln!("{:>15} representation done ({:.0} s)", scene.name(), started.elapsed().as_secs_f64());
    }
    Ok(rows)
}

/// Marks, per scene, the points no other point beats in both time and total RMSE.
pub(super) fn mark_pareto(points: &mut [Point]) {
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

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// A point of the Gaussian with trilinear and correction, for unit tests.
    pub fn point(step: f64, seconds: f64, rmse: f64, sampling_rmse: f64) -> Point {
        Point {
            scene: Reference::Gaussian,
            interpolation: Interpolation::Trilinear,
            correction: true,
            step,
            samples: 0,
            seconds,
            rmse,
            max: rmse,
            sampling_rmse,
            sampling_max: sampling_rmse,
            pareto: false,
        }
    }

    #[test]
    fn pareto_marks_exactly_the_undominated_points() {
        let p = |seconds: f64, rmse: f64| point(1.0, seconds, rmse, rmse);
        let mut points = vec![p(1.0, 1.0), p(2.0, 0.5), p(2.0, 0.8), p(3.0, 0.5), p(0.5, 2.0)];
        mark_pareto(&mut points);
        let front: Vec<bool> = points.iter().map(|p| p.pareto).collect();
        assert_eq!(front, vec![true, true, false, false, true]);
    }
}
