//! `trove bench …`: the paper's experiments, runnable, printed beside the paper's figures.
//!
//! Each experiment is one variant of [`BenchCommand`] and one module; adding one is a
//! variant, a `mod` line and a match arm.

pub mod accuracy;
mod distorted;
mod table1;

use anyhow::Result;

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
