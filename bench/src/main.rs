//! `trove-bench`: the paper's experiments and TROVE's own measurements, runnable, printed
//! beside the paper's figures. They live apart from the `trove` binary so that the command
//! line and the farm never carry what only a benchmark needs (plots, dataset writers).
//!
//! Each experiment is one variant of [`Command`] and one module; adding one is a variant, a
//! `mod` line and a match arm.

mod accuracy;
mod coordinator;
mod distorted;
mod farm;
mod farm_sim;
mod machine;
mod peers;
mod stats;
mod table1;

use std::process::ExitCode;

use anyhow::Result;
use clap::Parser;
use trove_core::render::{self, RenderOptions, Rendered};
use trove_core::scene::Scene;

#[derive(Parser)]
#[command(name = "trove-bench", version, about = "Runs TROVE's benchmarks and prints their tables")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// The experiments.
#[derive(clap::Subcommand)]
enum Command {
    /// Table 1 (paper §3.3): 15 objects from 15 datasets and from 1, both algorithms,
    /// under a memory budget of a quarter of the 15 datasets.
    Table1(table1::Args),
    /// Distorted boxes: exact inversion (SPEC default) against the paper's straight-line
    /// approximation, in time and in image error.
    Distorted(distorted::Args),
    /// What accuracy costs in time: sampling distance × interpolation × opacity correction
    /// on reference scenes with closed-form ray integrals; writes a CSV and a plot.
    Accuracy(accuracy::AccuracyArgs),
    /// The farm beyond one machine: a discrete-event simulation of a coordinator and 8 to
    /// 256 workers, fed by costs measured here; predicts speedup, efficiency and where the
    /// coordinator becomes the bottleneck.
    FarmSim(farm_sim::Args),
    /// The farm on this machine: a coordinator and 1–3 worker processes on loopback
    /// against local mode, in time, bytes on the wire and coordinator memory.
    Farm(farm::Args),
    /// The coordinator alone: the real coordinator in this process with stand-in workers
    /// that answer each batch at once from recorded results; pieces per second, CPU per
    /// piece by stage, and throughput on 1 and 2 coordinator cores.
    Coordinator(coordinator::Args),
    /// Issue 10: TROVE against VTK's fixed-point CPU ray caster on the CT head and the
    /// synthetic 256³ volume, same view, step and threads, alternating runs; medians, the
    /// time ratio, samples per second and each image's error against a converged TROVE image.
    Peers(peers::Args),
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()))
        .with_writer(std::io::stderr)
        .init();
    let result = match Cli::parse().command {
        Command::Table1(args) => table1::run(args),
        Command::Distorted(args) => distorted::run(args),
        Command::Accuracy(args) => accuracy::run(args),
        Command::FarmSim(args) => farm_sim::run(args),
        Command::Farm(args) => farm::run(args),
        Command::Coordinator(args) => coordinator::run(args),
        Command::Peers(args) => peers::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Renders `repeat` times (at least once) and keeps the run with the median total time
/// ([`stats::median_run`]): the machines are shared and noisy, so one fast run proves little.
/// `each` sees every run as it finishes (for progress lines).
fn median_render(
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
    Ok(stats::median_run(runs))
}
