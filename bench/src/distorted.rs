//! Exact inversion against the paper's straight-line approximation for distorted boxes
//! (SPEC §4.2): what exactness costs in time and what the approximation costs in error.
//!
//! One generated dataset is placed three times: in a parallelepiped (the affine path, for
//! scale), and in two distorted boxes — a mildly twisted one and a strongly pinched one.
//! The scene is rendered with `distorted_sampling = "exact"` and `"straight"`; the exact
//! image is the reference.

use anyhow::{Context, Result};
use trove_core::render::{Algorithm, Image, RenderOptions, Rendered};
use trove_core::scene::Scene;
use trove_tests::Header;

/// `trove-bench distorted` options.
#[derive(clap::Args)]
pub struct Args {
    /// Image width and height in pixels.
    #[arg(long, default_value_t = 512)]
    size: u32,
    /// Renders per mode; the median is reported.
    #[arg(long, default_value_t = 3)]
    repeat: u32,
}

fn scene_text(size: u32) -> String {
    let header = Header::new(size, [0.0, 0.6, 4.2], [0.0, 0.0, 0.0], 40.0);
    format!(
        r#"{header}
[[datasets]]
name = "ml"
dims = [64, 64, 64]
[datasets.channels.voxel]
generator = {{ kind = "marschner_lobb" }}
[[objects]]
name = "affine"
dataset = "ml"
colour = {{ type = "ramp", points = [[0.3, 0.1, 0.3, 0.9], [0.9, 1.0, 0.9, 0.6]] }}
opacity = {{ type = "ramp", points = [[0.45, 0.0], [0.9, 0.25]] }}
transform = {{ matrix = [[0.9, 0, 0, -1.95], [0, 0.9, 0, -0.45], [0, 0, 0.9, -0.45], [0, 0, 0, 1]] }}
[[objects]]
name = "twisted"
dataset = "ml"
colour = {{ type = "ramp", points = [[0.3, 0.1, 0.3, 0.9], [0.9, 1.0, 0.9, 0.6]] }}
opacity = {{ type = "ramp", points = [[0.45, 0.0], [0.9, 0.25]] }}
transform = {{ corners = [[-0.45, -0.45, -0.45], [0.45, -0.45, -0.45], [-0.45, 0.45, -0.45], [0.45, 0.45, -0.45],
                          [-0.3, -0.55, 0.45], [0.55, -0.3, 0.45], [-0.55, 0.3, 0.45], [0.3, 0.55, 0.45]] }}
[[objects]]
name = "pinched"
dataset = "ml"
colour = {{ type = "ramp", points = [[0.3, 0.1, 0.3, 0.9], [0.9, 1.0, 0.9, 0.6]] }}
opacity = {{ type = "ramp", points = [[0.45, 0.0], [0.9, 0.25]] }}
transform = {{ corners = [[1.05, -0.5, -0.5], [1.95, -0.5, -0.5], [1.05, 0.5, -0.5], [1.95, 0.5, -0.5],
                          [1.35, -0.2, 0.5], [1.65, -0.2, 0.5], [1.35, 0.2, 0.5], [1.65, 0.2, 0.5]] }}
"#
    )
}

fn median_run(scene: &Scene, repeat: u32) -> Result<Rendered> {
    let options = RenderOptions { algorithm: Algorithm::Grouped, ..Default::default() };
    super::median_render(scene, &options, repeat, |_| {})
}

/// Runs the comparison and prints a table.
pub fn run(args: Args) -> Result<()> {
    let mut scene = Scene::parse(&scene_text(args.size), "bench-distorted.toml").context("building the scene")?;
    scene.set_straight_distorted_sampling(false);
    let exact = median_run(&scene, args.repeat)?;
    scene.set_straight_distorted_sampling(true);
    let straight = median_run(&scene, args.repeat)?;
    let (e, s) = (&exact.stats, &straight.stats);
    println!("Distorted boxes, {0}×{0}, median of {1} renders (grouped)\n", args.size, args.repeat.max(1));
    println!("| mode | volume rendering (s) | total (s) | samples |");
    println!("|---|---:|---:|---:|");
    for (name, st) in [("exact (SPEC default)", e), ("straight (paper)", s)] {
        println!("| {name} | {:.3} | {:.3} | {} |", st.seconds.volume_rendering, st.seconds.total, st.samples);
    }
    let ratio = e.seconds.volume_rendering / s.seconds.volume_rendering.max(1e-9);
    println!("\nexact / straight volume-rendering time: {ratio:.2}×");
    println!("straight vs exact image: {}", difference(&straight.image, &exact.image));
    Ok(())
}

fn difference(a: &Image, b: &Image) -> String {
    let max = a
        .pixels()
        .iter()
        .zip(b.pixels())
        .flat_map(|(p, q)| (0..3).map(move |i| (p[i] - q[i]).abs()))
        .fold(0.0, f64::max);
    let differing = a.to_rgb8().iter().zip(b.to_rgb8()).filter(|(x, y)| x != &y).count();
    format!(
        "PSNR {:.1} dB, max difference {:.4} ({} of 255), {differing} of {} bytes differ",
        a.psnr(b),
        max,
        a.max_byte_difference(b),
        a.pixels().len() * 3
    )
}
