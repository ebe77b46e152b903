//! The command line: argument parsing and the `render` command.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use trove_core::render::{self, Algorithm, RenderOptions};
use trove_core::scene::Scene;

#[derive(Parser)]
#[command(name = "trove", version, about = "Renders scenes composed of many volumetric datasets (Leu & Chen 1997)")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene to a PNG (or a .pfm float image) in this process.
    Render(RenderArgs),
    /// Run a benchmark and write its CSV, plot and summary.
    #[command(subcommand)]
    Bench(BenchCommand),
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Error against closed-form reference scenes versus render time, over sampling distance,
    /// interpolation and opacity correction (docs/accuracy.*).
    Accuracy(crate::bench::accuracy::AccuracyArgs),
}

#[derive(clap::Args)]
struct RenderArgs {
    /// The scene file (TOML, SPEC §1).
    scene: PathBuf,
    /// Output image: .png (8-bit) or .pfm (linear float).
    #[arg(short, long)]
    output: PathBuf,
    /// Ray-casting algorithm.
    #[arg(long, value_enum, default_value_t = AlgorithmArg::PerRay)]
    algorithm: AlgorithmArg,
    /// Write counts and the Table-1 timing breakdown as JSON.
    #[arg(long)]
    stats: Option<PathBuf>,
}

#[derive(Clone, Copy, ValueEnum)]
enum AlgorithmArg {
    /// Algorithm 1: per ray, datasets in ray order.
    PerRay,
}

impl From<AlgorithmArg> for Algorithm {
    fn from(a: AlgorithmArg) -> Algorithm {
        match a {
            AlgorithmArg::PerRay => Algorithm::PerRay,
        }
    }
}

/// Parses the arguments and runs the command.
pub fn run() -> Result<()> {
    match Cli::parse().command {
        Command::Render(args) => render_command(args),
        Command::Bench(BenchCommand::Accuracy(args)) => crate::bench::accuracy::run(args),
    }
}

fn render_command(args: RenderArgs) -> Result<()> {
    let scene = Scene::load(&args.scene)?;
    let bar = progress_bar(scene.image.height as u64);
    let options = RenderOptions {
        algorithm: args.algorithm.into(),
        progress: bar.clone().map(|b| Arc::new(move |rows: u64| b.set_position(rows)) as render::Progress),
    };
    let rendered = render::render(&scene, &options).with_context(|| format!("rendering {}", args.scene.display()))?;
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    rendered.image.save(&args.output)?;
    if let Some(path) = &args.stats {
        let json = serde_json::to_string_pretty(&rendered.stats).context("serialising statistics")?;
        std::fs::write(path, json + "\n").with_context(|| format!("writing statistics to {}", path.display()))?;
    }
    tracing::info!(seconds = rendered.stats.seconds.total, samples = rendered.stats.samples, "rendered");
    Ok(())
}

/// A bar over image rows, shown only when stderr is a terminal.
fn progress_bar(rows: u64) -> Option<ProgressBar> {
    if !std::io::stderr().is_terminal() {
        return None;
    }
    let bar = ProgressBar::new(rows);
    bar.set_style(
        ProgressStyle::with_template("{spinner} rendering [{bar:40}] {pos}/{len} rows, {elapsed} (eta {eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    Some(bar)
}
