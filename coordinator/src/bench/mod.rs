//! `trove bench …`: the paper's experiments, runnable, printed beside the paper's figures.
//!
//! Each experiment is one variant of [`BenchCommand`] and one module; adding one is a
//! variant, a `mod` line and a match arm.

pub mod accuracy;
mod distorted;
mod table1;

use anyhow::Result;
use trove_core::render::{self, RenderOptions, Rendered};
use trove_core::scene::Scene;

/// The experiments.
#[derive(clap::Subcommand)]
pub enum BenchCommand {
    /// Table 1 (paper §3.3): 15 objects from 15 datasets and from 1, both algorithms,
    /// under a memory budget of a quarter of the 15 datasets.
    Table1(table1::Args),
    /// Distorted boxes: exact inversion (SPEC default) against the paper's straight-line
    /// approximation, in time and in image error.
    Distorted(distorted::Args),
    /// What accuracy costs in time: sampling distance × interpolation × opacity correction
    /// on reference scenes with closed-form ray integrals; writes a CSV and a plot.
    Accuracy(accuracy::AccuracyArgs),
}

impl BenchCommand {
    /// Runs the experiment and prints its tables on standard output.
    pub fn run(self) -> Result<()> {
        match self {
            BenchCommand::Table1(args) => table1::run(args),
            BenchCommand::Distorted(args) => distorted::run(args),
            BenchCommand::Accuracy(args) => accuracy::run(args),
        }
    }
}

/// Renders `repeat` times (at least once) and keeps the run with the median total time: the
/// machines are shared and noisy, so one fast run proves little. `each` sees every run as it
/// finishes (for progress lines).
pub(crate) fn median_render(
    scene: &Scene,
    options: &RenderOptions,
    repeat: u32,
    mut each: impl FnMut(&Rendered),
) -> Result<Rendered> {
    let mut runs = Vec::new();
    for _ in 0..repeat.max(1) {
        let r = render::render(scene, options)?;
        each(&r);
        runs.push(r);
    }
    runs.sort_by(|a, b| a.stats.seconds.total.total_cmp(&b.stats.seconds.total));
    let middle = runs.len() / 2;
    Ok(runs.swap_remove(middle))
}
