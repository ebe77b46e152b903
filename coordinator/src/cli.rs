//! The command line: argument parsing and the `render` command.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
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
}

#[derive(clap::Args)]
struct RenderArgs {
    /// The scene file (TOML, SPEC §1).
    scene: PathBuf,
    /// Output image: .png (8-bit) or .pfm (linear float).
    #[arg(short, long)]
    output: PathBuf,
    /// Ray-casting algorithm.
    #[arg(long, value_enum, default_value_t = AlgorithmArg::Grouped)]
    algorithm: AlgorithmArg,
    /// Most voxel bytes kept resident (e.g. 512MiB, 1.5GiB, 4000000); datasets beyond it
    /// are evicted least-recently-used and loaded again when needed. It must hold the
    /// largest dataset.
    #[arg(long, value_name = "BYTES", value_parser = parse_bytes)]
    memory_budget: Option<u64>,
    /// Write counts and the Table-1 timing breakdown as JSON.
    #[arg(long)]
    stats: Option<PathBuf>,
    /// Override the scene's `[render] distorted_sampling` for every distorted box.
    #[arg(long, value_enum)]
    distorted_sampling: Option<DistortedSampling>,
}

#[derive(Clone, Copy, ValueEnum)]
enum DistortedSampling {
    /// Invert the trilinear map at every sample (SPEC §4.2).
    Exact,
    /// The paper's approximation: the straight VC line between the mapped end points.
    Straight,
}

#[derive(Clone, Copy, ValueEnum)]
enum AlgorithmArg {
    /// Algorithm 1: per ray, datasets in ray order.
    PerRay,
    /// Algorithm 2: grouped by dataset, each loaded once (the default).
    Grouped,
}

impl From<AlgorithmArg> for Algorithm {
    fn from(a: AlgorithmArg) -> Algorithm {
        match a {
            AlgorithmArg::PerRay => Algorithm::PerRay,
            AlgorithmArg::Grouped => Algorithm::Grouped,
        }
    }
}

/// A byte count: a plain number of bytes, or a number (decimals allowed) followed by
/// `B`, `KiB`, `MiB` or `GiB` (any case, optional space). Fractions of a byte round down.
pub fn parse_bytes(text: &str) -> Result<u64, String> {
    let t = text.trim();
    let split = t.find(|c: char| !(c.is_ascii_digit() || c == '.')).unwrap_or(t.len());
    let (number, unit) = (&t[..split], t[split..].trim());
    let scale: u64 = match unit.to_ascii_lowercase().as_str() {
        "" | "b" => 1,
        "kib" => 1 << 10,
        "mib" => 1 << 20,
        "gib" => 1 << 30,
        _ => {
            return Err(format!(
                "`{text}`: unknown unit `{unit}`; expected bytes, or a number followed by KiB, MiB or GiB"
            ))
        }
    };
    let bad = || format!("`{text}`: expected a number of bytes, optionally followed by KiB, MiB or GiB");
    if number.is_empty() || number.matches('.').count() > 1 {
        return Err(bad());
    }
    let bytes = if number.contains('.') {
        let v: f64 = number.parse().map_err(|_| bad())?;
        let b = v * scale as f64;
        if !b.is_finite() || b >= u64::MAX as f64 {
            return Err(format!("`{text}`: too large"));
        }
        b.floor() as u64
    } else {
        let v: u64 = number.parse().map_err(|_| format!("`{text}`: too large"))?;
        v.checked_mul(scale).ok_or_else(|| format!("`{text}`: too large"))?
    };
    if bytes == 0 {
        return Err(format!("`{text}`: a memory budget must be at least one byte"));
    }
    Ok(bytes)
}

/// Parses the arguments and runs the command.
pub fn run() -> Result<()> {
    match Cli::parse().command {
        Command::Render(args) => render_command(args),
    }
}

fn render_command(args: RenderArgs) -> Result<()> {
    check_output(&args.output, &["png", "pfm"])?;
    if let Some(stats) = &args.stats {
        check_output(stats, &["json"])?;
    }
    let mut scene = Scene::load(&args.scene)?;
    if let Some(mode) = args.distorted_sampling {
        scene.set_straight_distorted_sampling(matches!(mode, DistortedSampling::Straight));
    }
    let bar = progress_bar(scene.image().height as u64);
    let options = RenderOptions {
        algorithm: args.algorithm.into(),
        memory_budget: args.memory_budget,
        progress: bar.clone().map(|b| Arc::new(move |rows: u64| b.set_position(rows)) as render::Progress),
    };
    let rendered = render::render(&scene, &options).map_err(|e| {
        let hint = match &e {
            render::RenderError::Store(render::StoreError::BudgetTooSmall { .. }) => " (see --memory-budget)",
            _ => "",
        };
        anyhow::Error::new(e).context(format!("rendering {}{hint}", args.scene.display()))
    })?;
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

/// Refuses, before any work, an output whose folder does not exist or whose extension we do
/// not write — a long render should not be lost to a typo in `-o`.
fn check_output(path: &Path, extensions: &[&str]) -> Result<()> {
    let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    if !ext.as_deref().is_some_and(|e| extensions.contains(&e)) {
        bail!("cannot write {}: expected a file ending in .{}", path.display(), extensions.join(" or ."));
    }
    let folder = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    if !folder.is_dir() {
        bail!("cannot write {}: folder {} does not exist", path.display(), folder.display());
    }
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

#[cfg(test)]
mod tests {
    use super::parse_bytes;

    #[test]
    fn byte_counts_take_binary_suffixes() {
        assert_eq!(parse_bytes("4096"), Ok(4096));
        assert_eq!(parse_bytes("64KiB"), Ok(64 << 10));
        assert_eq!(parse_bytes("3 MiB"), Ok(3 << 20));
        assert_eq!(parse_bytes("1.5GiB"), Ok(3 << 29));
        assert_eq!(parse_bytes("2gib"), Ok(2 << 30));
        assert_eq!(parse_bytes("100B"), Ok(100));
        for bad in ["", "MiB", "12 MB", "1.2.3KiB", "-5", "0", "99999999999999999999", "20000000000GiB", "1e3"] {
            assert!(parse_bytes(bad).is_err(), "{bad}");
        }
        assert!(parse_bytes("12 MB").unwrap_err().contains("KiB, MiB or GiB"));
    }
}
