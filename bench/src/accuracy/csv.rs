//! The sweep's raw numbers as CSV, one row per point, for anyone who wants to replot them.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::{Context, Result};

use super::sweep::{Point, Representation};

/// `accuracy.csv`: one row per point of the sweep.
pub(super) fn write_points(path: &Path, points: &[Point]) -> Result<()> {
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

/// `accuracy_representation.csv`: one row per scene and resolution.
pub(super) fn write_representation(path: &Path, rows: &[Representation], step: f64) -> Result<()> {
    let mut s = String::from("scene,dims,step_voxels,rmse,max_error\n");
    for r in rows {
        writeln!(s, "{},{},{},{:.6e},{:.6e}", r.scene.name(), r.dims, step, r.rmse, r.max)?;
    }
    std::fs::write(path, s).with_context(|| format!("writing {}", path.display()))
}
