//! Table 1 of the paper (§3.3): a scene of 15 objects like Fig. 1's, built once from 15
//! datasets and once from a single shared one, rendered at 512×512 by Algorithm 1
//! (per ray) and Algorithm 2 (grouped by dataset), with the time broken down as the paper
//! does and the paper's figures printed beside ours.
//!
//! The datasets are generated (a CT-like head: air, skin, skull and a textured interior,
//! 12-bit values in u16 voxels, 81³ like the paper's) and written to raw files first, so
//! that loading one really reads a file. The memory budget is a quarter of the 15
//! datasets' bytes: under it Algorithm 1 must evict and re-read datasets as its rays move
//! between objects (the paper's disk swapping), while Algorithm 2 reads each file once.
//! The single shared dataset fits the same budget, which is the paper's second case.
//!
//! A second, smaller experiment checks the early termination that the grouped algorithm
//! recovers (the paper gives it up): samples cast by each algorithm on the Fig. 1-like
//! scene and on a Fig. 10-like one (translucent and opaque objects in front of each other).

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use trove_core::render::workunit::{RESULT_BYTES, TASK_BYTES};
use trove_core::render::{Algorithm, RenderOptions, RenderStats, Rendered};
use trove_core::scene::Scene;
use trove_tests::Header;

use crate::stats::{median, median_run};

/// `trove-bench table1` options.
#[derive(clap::Args)]
pub struct Args {
    /// Image width and height in pixels (the paper: 512).
    #[arg(long, default_value_t = 512)]
    size: u32,
    /// Voxels per axis of each dataset, stored as u16 (the paper: 81).
    #[arg(long, default_value_t = 81)]
    dims: u32,
    /// Runs of each configuration that does not thrash; the median is reported (the
    /// thrashing per-ray run is run once; the two 15/1 configurations alternate, round by
    /// round).
    #[arg(long, default_value_t = 3)]
    repeat: u32,
    /// How the datasets are stored: `gzip` NRRD files (a load reads and inflates one, a
    /// real cost like the paper's disk) or `raw` files (a load copies the file from the
    /// operating system's page cache, which holds every file whatever our budget).
    #[arg(long, value_enum, default_value_t = Storage::Gzip)]
    storage: Storage,
    /// Where to write the generated datasets, and the scenes as `table1-15.toml`,
    /// `table1-1.toml` and `fig10.toml` for `trove render`, and with `--storage raw` the
    /// 15-dataset scene for VTK as `table1-15-vtk.json` (`vtk_raycast.py --scene`; default:
    /// a fresh folder under the system temporary folder, removed afterwards).
    #[arg(long)]
    data_dir: Option<PathBuf>,
    /// Run only the 15/1 configuration (every object on one shared dataset, which fits the
    /// budget): per-ray and grouped alternately for `--repeat` rounds, printing every round
    /// and the medians. Alternating spreads a shared machine's drifting load over both
    /// algorithms, which back-to-back blocks of runs do not.
    #[arg(long)]
    shared_only: bool,
}

/// How the benchmark stores its datasets.
#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Storage {
    /// Attached-header NRRD with gzip encoding.
    Gzip,
    /// Raw little-endian u16.
    Raw,
}

impl Storage {
    fn file_name(self, v: u32) -> String {
        match self {
            Storage::Gzip => format!("head{v:02}.nrrd"),
            Storage::Raw => format!("head{v:02}.raw"),
        }
    }
}

/// The paper's Table 1, in seconds: rows as in [`ROWS`], columns Algorithm 1 and 2 with 15
/// datasets, then Algorithm 1 and 2 with 1 dataset. NaN marks the paper's "–".
const PAPER: [[f64; 4]; 6] = [
    [261.76, 241.95, 248.03, 244.35],
    [19.30, 18.33, 18.32, 17.83],
    [f64::NAN, 1.10, f64::NAN, 1.00],
    [6670.28, 2.55, 0.28, 0.30],
    [279.11, 127.22, 39.68, 33.24],
    [7230.45, 391.15, 306.31, 296.72],
];
const ROWS: [&str; 6] = [
    "Volume rendering",
    "Intersection computation",
    "Image composition",
    "Data loading and swapping",
    "Other computation",
    "Total time",
];

/// Runs the experiment and prints the tables.
pub fn run(args: Args) -> Result<()> {
    let (dir, remove) = match &args.data_dir {
        Some(d) => (d.clone(), false),
        None => (std::env::temp_dir().join(format!("trove-table1-{}", std::process::id())), true),
    };
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let result = run_in(&args, &dir);
    if remove {
        let _ = std::fs::remove_dir_all(&dir);
    }
    result
}

fn run_in(args: &Args, dir: &Path) -> Result<()> {
    let n = args.dims;
    let storage = args.storage;
    for v in 0..15 {
        write_dataset(&dir.join(storage.file_name(v)), v, n, storage)?;
    }
    let dataset_bytes = 2 * (n as u64).pow(3);
    let budget = 15 * dataset_bytes / 4;
    let threads = rayon::current_num_threads();
    println!("{}", crate::machine::describe()?);
    println!(
        "Table 1: 15 objects, {s}×{s} pixels, datasets {n}³ u16 ({} bytes each, {} files), memory budget {budget} bytes \
         (a quarter of the 15 datasets), {threads} threads",
        dataset_bytes,
        if storage == Storage::Gzip { "gzip NRRD" } else { "raw" },
        s = args.size
    );

    let texts = [
        table1_scene(args.size, n, storage, false),
        table1_scene(args.size, n, storage, true),
        fig10_scene(args.size, n, storage),
    ];
    if args.data_dir.is_some() {
        for (name, text) in ["table1-15.toml", "table1-1.toml", "fig10.toml"].iter().zip(&texts) {
            std::fs::write(dir.join(name), text).with_context(|| format!("writing {name}"))?;
        }
        if storage == Storage::Raw {
            std::fs::write(dir.join("table1-15-vtk.json"), vtk_scene(n)).context("writing table1-15-vtk.json")?;
        }
    }
    let shared = load_scene(dir, &texts[1])?;
    let budgeted = |algorithm| RenderOptions { algorithm, memory_budget: Some(budget), ..Default::default() };
    if args.shared_only {
        return shared_only(&shared, &budgeted(Algorithm::PerRay), &budgeted(Algorithm::Grouped), args.repeat);
    }
    let separate = load_scene(dir, &texts[0])?;
    let per_ray_separate = median_of("15/15", &separate, &budgeted(Algorithm::PerRay), 1)?;
    let grouped_separate = median_of("15/15", &separate, &budgeted(Algorithm::Grouped), args.repeat)?;
    // The two 15/1 columns are close, so they alternate under the same load.
    let (per_ray_shared, grouped_shared) =
        alternate("15/1", &shared, &budgeted(Algorithm::PerRay), &budgeted(Algorithm::Grouped), args.repeat)?;
    let runs = [per_ray_separate, grouped_separate, median_run(per_ray_shared), median_run(grouped_shared)];
    print!("{}", table(&runs));

    println!(
        "\nWork units in memory: {TASK_BYTES} bytes per piece task, {RESULT_BYTES} bytes per piece result \
         (on the wire: `trove-bench farm`)."
    );

    println!("\nEarly termination (samples cast; skipped = samples of pieces never cast behind opaque rays):\n");
    let fig10 = load_scene(dir, &texts[2])?;
    let plain = |algorithm| RenderOptions { algorithm, memory_budget: None, ..Default::default() };
    let fig10_runs = [
        median_of("Fig. 10", &fig10, &plain(Algorithm::PerRay), 1)?,
        median_of("Fig. 10", &fig10, &plain(Algorithm::Grouped), 1)?,
    ];
    println!(
        "| scene | per-ray samples | grouped samples | grouped / per-ray | grouped skipped | max image difference |"
    );
    println!("|---|---:|---:|---:|---:|---:|");
    for (name, pr, gr) in [
        ("Fig. 1-like, 15 datasets", &runs[0], &runs[1]),
        ("Fig. 1-like, 1 dataset", &runs[2], &runs[3]),
        ("Fig. 10-like, 3 datasets", &fig10_runs[0], &fig10_runs[1]),
    ] {
        println!(
            "| {name} | {} | {} | {:.3} | {} | {}/255 |",
            pr.stats.samples,
            gr.stats.samples,
            gr.stats.samples as f64 / pr.stats.samples.max(1) as f64,
            gr.stats.samples_skipped,
            pr.image.max_byte_difference(&gr.image)
        );
    }
    Ok(())
}

fn load_scene(dir: &Path, text: &str) -> Result<Scene> {
    Scene::parse(text, dir.join("scene.toml")).context("building the benchmark scene")
}

/// The median of `repeat` renders, each reported on standard error as it finishes.
fn median_of(label: &str, scene: &Scene, options: &RenderOptions, repeat: u32) -> Result<Rendered> {
    super::median_render(scene, options, repeat, |r| {
        eprintln!(
            "  {} {label}: {:.2} s, {} loads",
            options.algorithm.name(),
            r.stats.seconds.total,
            r.stats.dataset_loads
        )
    })
}

/// Renders `scene` with `a` and `b` alternately, `repeat` rounds (at least one), each run
/// reported on standard error as it finishes: on a shared machine whose load drifts,
/// back-to-back blocks of runs of one and then the other can differ by more than the two
/// algorithms do, while alternating rounds see the same load.
fn alternate(
    label: &str,
    scene: &Scene,
    a: &RenderOptions,
    b: &RenderOptions,
    repeat: u32,
) -> Result<(Vec<Rendered>, Vec<Rendered>)> {
    let (mut runs_a, mut runs_b) = (Vec::new(), Vec::new());
    for _ in 0..repeat.max(1) {
        for (options, runs) in [(a, &mut runs_a), (b, &mut runs_b)] {
            let r = trove_core::render::render(scene, options)?;
            eprintln!(
                "  {} {label}: {:.2} s, {} loads",
                options.algorithm.name(),
                r.stats.seconds.total,
                r.stats.dataset_loads
            );
            runs.push(r);
        }
    }
    Ok((runs_a, runs_b))
}

/// `--shared-only`: the 15/1 configuration, per-ray and grouped alternately for `repeat`
/// rounds; prints every round, the median of each time (taken separately) and the median of
/// the rounds' total-time ratios (each round's two runs saw the same load).
fn shared_only(scene: &Scene, per_ray: &RenderOptions, grouped: &RenderOptions, repeat: u32) -> Result<()> {
    let (a, b) = alternate("15/1", scene, per_ray, grouped, repeat)?;
    println!("\n15/1, per-ray and grouped alternately, {} rounds (seconds):\n", a.len());
    println!("| round | per-ray volume rendering | per-ray total | grouped volume rendering | grouped total | max image difference |");
    println!("|---|---:|---:|---:|---:|---:|");
    for (round, (pr, gr)) in a.iter().zip(&b).enumerate() {
        let (p, g) = (&pr.stats.seconds, &gr.stats.seconds);
        println!(
            "| {} | {:.3} | {:.3} | {:.3} | {:.3} | {}/255 |",
            round + 1,
            p.volume_rendering,
            p.total,
            g.volume_rendering,
            g.total,
            pr.image.max_byte_difference(&gr.image)
        );
    }
    println!("\n| median (s) | per-ray | grouped | grouped / per-ray |");
    println!("|---|---:|---:|---:|");
    type Time = fn(&RenderStats) -> f64;
    let rows: [(&str, Time); 5] = [
        ("Volume rendering", |s| s.seconds.volume_rendering),
        ("Intersection computation", |s| s.seconds.intersection),
        ("Image composition", |s| s.seconds.composition),
        ("Data loading and swapping", |s| s.seconds.loading),
        ("Total time", |s| s.seconds.total),
    ];
    for (name, f) in rows {
        let x = median(a.iter().map(|r| f(&r.stats))).unwrap_or(f64::NAN);
        let y = median(b.iter().map(|r| f(&r.stats))).unwrap_or(f64::NAN);
        let ratio = if x > 0.0 { format!("{:.2}", y / x) } else { "–".to_string() };
        println!("| {name} | {x:.3} | {y:.3} | {ratio} |");
    }
    let ratios = a.iter().zip(&b).map(|(p, g)| g.stats.seconds.total / p.stats.seconds.total);
    println!("| Total time, median of the rounds' ratios | | | {:.2} |", median(ratios).unwrap_or(f64::NAN));
    println!("| Samples | {} | {} | |", a[0].stats.samples, b[0].stats.samples);
    Ok(())
}

/// The paper's table with our seconds and, in brackets, the paper's.
fn table(runs: &[Rendered; 4]) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "\n| Algorithm | Algorithm 1 | Algorithm 2 | Algorithm 1 | Algorithm 2 |");
    let _ = writeln!(out, "|---|---:|---:|---:|---:|");
    let _ = writeln!(out, "| No. objects / volumes | 15/15 | 15/15 | 15/1 | 15/1 |");
    for (row, name) in ROWS.iter().enumerate() {
        let _ = write!(out, "| {name} |");
        for (col, r) in runs.iter().enumerate() {
            let s = &r.stats.seconds;
            let ours = [s.volume_rendering, s.intersection, s.composition, s.loading, s.other, s.total][row];
            let paper = PAPER[row][col];
            let ours =
                if row == 2 && r.stats.algorithm == "per-ray" { "–".to_string() } else { format!("{ours:.2}") };
            let paper = if paper.is_nan() { "–".to_string() } else { format!("{paper:.2}") };
            let _ = write!(out, " {ours} ({paper}) |");
        }
        let _ = writeln!(out);
    }
    let speedup = |a: &Rendered, b: &Rendered| a.stats.seconds.total / b.stats.seconds.total;
    let _ = writeln!(
        out,
        "| Speedup (Alg1/Alg2) | – | {:.2} (18.49) | – | {:.2} (1.03) |",
        speedup(&runs[0], &runs[1]),
        speedup(&runs[2], &runs[3])
    );
    let count_row = |out: &mut String, name: &str, f: &dyn Fn(&Rendered) -> String| {
        let _ = writeln!(out, "| {name} | {} | {} | {} | {} |", f(&runs[0]), f(&runs[1]), f(&runs[2]), f(&runs[3]));
    };
    count_row(&mut out, "Dataset loads", &|r| r.stats.dataset_loads.to_string());
    count_row(&mut out, "Bytes loaded", &|r| r.stats.bytes_loaded.to_string());
    count_row(&mut out, "Peak resident bytes", &|r| r.stats.peak_resident_bytes.to_string());
    count_row(&mut out, "Pieces", &|r| r.stats.pieces.to_string());
    count_row(&mut out, "Samples", &|r| r.stats.samples.to_string());
    count_row(&mut out, "Samples skipped (early termination)", &|r| r.stats.samples_skipped.to_string());
    let _ = writeln!(
        out,
        "| Max image difference vs Alg. 1 | | {}/255 | | {}/255 |",
        runs[0].image.max_byte_difference(&runs[1].image),
        runs[2].image.max_byte_difference(&runs[3].image)
    );
    let _ = writeln!(out, "\nOur seconds, the paper's (DEC Alpha 2100, 275 MHz) in brackets.");
    out
}

/// Writes variant `v` of the head dataset, `n`³ little-endian u16 voxels.
pub(crate) fn write_dataset(path: &Path, v: u32, n: u32, storage: Storage) -> Result<()> {
    let mut bytes = Vec::with_capacity(2 * (n as usize).pow(3));
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                bytes.extend_from_slice(&head_value(v, [i, j, k], n).to_le_bytes());
            }
        }
    }
    let bytes = match storage {
        Storage::Raw => bytes,
        Storage::Gzip => {
            let header =
                format!("NRRD0004\ntype: uint16\ndimension: 3\nsizes: {n} {n} {n}\nendian: little\nencoding: gzip\n\n");
            let mut gz = flate2::write::GzEncoder::new(header.into_bytes(), flate2::Compression::default());
            gz.write_all(&bytes)?;
            gz.finish()?
        }
    };
    std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))
}

/// A CT-like head: 12-bit values of air (0), skin (1000), skull (3000) and a textured
/// interior (about 1500), as shells of an ellipsoid whose radii and texture vary with `v`.
fn head_value(v: u32, [i, j, k]: [u32; 3], n: u32) -> u16 {
    let p = [i, j, k].map(|c| (c as f64 + 0.5) / n as f64 - 0.5);
    let radii = [0.40 - 0.01 * (v % 3) as f64, 0.46 - 0.01 * (v % 4) as f64, 0.42 - 0.01 * (v % 5) as f64];
    let r = (0..3).map(|a| (p[a] / radii[a]).powi(2)).sum::<f64>().sqrt();
    let f = 5.0 + (v % 4) as f64;
    let tau = std::f64::consts::TAU;
    let texture = (tau * f * p[0] + v as f64).sin() * (tau * f * p[1]).sin() * (tau * f * p[2] + 0.5 * v as f64).sin();
    // Piecewise-linear radial profile, so surfaces are smooth at any resolution.
    let ramp = |x: f64, x0: f64, x1: f64, a: f64, b: f64| a + (b - a) * ((x - x0) / (x1 - x0)).clamp(0.0, 1.0);
    let value = if r < 0.70 {
        1500.0 + 400.0 * texture
    } else if r < 0.75 {
        ramp(r, 0.70, 0.75, 1500.0, 3000.0)
    } else if r < 0.85 {
        3000.0
    } else if r < 0.90 {
        ramp(r, 0.85, 0.90, 3000.0, 1000.0)
    } else if r < 0.97 {
        1000.0
    } else {
        ramp(r, 0.97, 1.0, 1000.0, 0.0)
    };
    value.round().clamp(0.0, 4095.0) as u16
}

/// Colour and opacity maps, by look.
const LOOKS: [(&str, &str); 4] = [
    // Opaque bone under a faint skin.
    (
        "[[0, 0.9, 0.6, 0.5], [1000, 0.95, 0.7, 0.6], [3000, 1.0, 1.0, 0.95]]",
        "[[500, 0.0], [1000, 0.01], [2400, 0.01], [2800, 0.9]]",
    ),
    // Translucent everywhere: skin and skull shells, glowing interior.
    (
        "[[0, 0.3, 0.5, 1.0], [1500, 0.4, 1.0, 0.6], [3000, 1.0, 1.0, 1.0]]",
        "[[500, 0.0], [1000, 0.02], [1500, 0.04], [3000, 0.08]]",
    ),
    // Opaque skin.
    ("[[0, 0.8, 0.5, 0.4], [1000, 0.9, 0.6, 0.5], [3000, 1.0, 0.9, 0.8]]", "[[400, 0.0], [900, 0.95]]"),
    // Interior texture only.
    (
        "[[1100, 0.9, 0.2, 0.2], [1500, 1.0, 0.8, 0.3], [1900, 1.0, 1.0, 0.6]]",
        "[[1150, 0.0], [1300, 0.05], [1900, 0.15], [2100, 0.0]]",
    ),
];

/// The TOML of one dataset.
fn dataset_toml(v: u32, n: u32, storage: Storage) -> String {
    let file = storage.file_name(v);
    match storage {
        Storage::Gzip => format!("[[datasets]]\nname = \"head{v:02}\"\nfile = \"{file}\"\n\n"),
        Storage::Raw => format!(
            "[[datasets]]\nname = \"head{v:02}\"\ndims = [{n}, {n}, {n}]\n[datasets.channels.voxel]\nraw = \"{file}\"\ntype = \"u16\"\n\n"
        ),
    }
}

/// One object: dataset, look, a box of side `s` with its base centre at `c`, turned by
/// `angle` degrees about the vertical.
fn object_toml(name: &str, dataset: u32, look: usize, s: f64, c: [f64; 3], angle: f64) -> String {
    let (sin, cos) = angle.to_radians().sin_cos();
    // Box coordinates q ∈ [0,1]³ → world: centre the box on its base, turn, move.
    let m = [
        [s * cos, 0.0, s * sin, c[0] - s / 2.0 * (cos + sin)],
        [0.0, s, 0.0, c[1]],
        [-s * sin, 0.0, s * cos, c[2] - s / 2.0 * (cos - sin)],
    ];
    let (colour, opacity) = LOOKS[look];
    format!(
        "[[objects]]\nname = \"{name}\"\ndataset = \"head{dataset:02}\"\n\
         colour = {{ type = \"ramp\", points = {colour} }}\nopacity = {{ type = \"ramp\", points = {opacity} }}\n\
         transform = {{ matrix = [{:?}, {:?}, {:?}, [0, 0, 0, 1]] }}\n\n",
        m[0], m[1], m[2]
    )
}

fn header(size: u32, eye: [f64; 3], target: [f64; 3], fov: f64) -> String {
    Header::new(size, eye, target, fov).background([0.05, 0.05, 0.08]).to_string()
}

/// The Fig. 1-like scene: a floor and 14 heads in three staggered rows, so that most rays
/// through a head go on into others behind it. `shared`: every object uses dataset 0;
/// otherwise object i uses dataset i.
pub fn table1_scene(size: u32, n: u32, storage: Storage, shared: bool) -> String {
    let mut text = header(size, [0.0, 1.6, 6.5], [0.0, -0.3, -0.6], 42.0);
    for v in 0..if shared { 1 } else { 15 } {
        text += &dataset_toml(v, n, storage);
    }
    let ds = |i: u32| if shared { 0 } else { i };
    // The floor: a thin, wide, opaque slab.
    text += &format!(
        "[[objects]]\nname = \"floor\"\ndataset = \"head{:02}\"\n\
         colour = {{ type = \"ramp\", points = [[0, 0.25, 0.25, 0.3], [3000, 0.6, 0.6, 0.7]] }}\n\
         opacity = {{ type = \"constant\", coefficients = [1.0] }}\n\
         transform = {{ matrix = [[7.5, 0, 0, -3.75], [0, 0.08, 0, -1.28], [0, 0, 6.5, -4.5], [0, 0, 0, 1]] }}\n\n",
        ds(14)
    );
    let mut i = 0;
    for (z, y, xs) in HEAD_ROWS {
        for &x in xs {
            let look = HEAD_LOOKS[i as usize % 7];
            text += &object_toml(&format!("head{i}"), ds(i), look, HEAD_SIDE, [x, y, z], 15.0 * (i as f64 - 7.0));
            i += 1;
        }
    }
    text
}

/// The Fig. 1-like scene's heads: three rows (z, base y, the x of each head).
const HEAD_ROWS: [(f64, f64, &[f64]); 3] = [
    (1.0, -1.2, &[-2.4, -1.2, 0.0, 1.2, 2.4]),
    (-0.4, -0.75, &[-1.8, -0.6, 0.6, 1.8]),
    (-1.9, -0.3, &[-2.4, -1.2, 0.0, 1.2, 2.4]),
];
/// Head i's look ([`LOOKS`]) is `HEAD_LOOKS[i % 7]`; every head's box has side `HEAD_SIDE`.
const HEAD_LOOKS: [usize; 7] = [1, 3, 0, 1, 2, 3, 1];
const HEAD_SIDE: f64 = 1.15;

/// The Fig. 10-like scene: objects of varying colour and translucency in front of each
/// other, from 3 datasets.
pub fn fig10_scene(size: u32, n: u32, storage: Storage) -> String {
    let mut text = header(size, [0.3, 0.8, 5.0], [0.0, 0.0, 0.0], 40.0);
    for v in 0..3 {
        text += &dataset_toml(v, n, storage);
    }
    let objects: [(u32, usize, f64, [f64; 3], f64); 8] = [
        (0, 1, 1.3, [-0.7, -0.6, 1.0], 10.0),
        (1, 1, 1.3, [0.7, -0.6, 1.0], -20.0),
        (2, 0, 1.2, [0.0, -0.5, -0.2], 30.0),
        (0, 2, 1.0, [-1.4, -0.4, -0.8], 0.0),
        (1, 3, 1.2, [1.3, -0.5, -0.6], 45.0),
        (2, 1, 1.6, [0.0, -0.8, -1.8], 0.0),
        (0, 0, 1.0, [-0.4, 0.2, 0.3], -35.0),
        (1, 2, 0.9, [0.8, 0.3, -1.2], 60.0),
    ];
    for (i, (d, look, s, c, angle)) in objects.into_iter().enumerate() {
        text += &object_toml(&format!("o{i}"), d, look, s, c, angle);
    }
    text
}

/// The 15-dataset scene (raw storage) for `../shared/peers/vtk_raycast.py --scene`: the same
/// files, maps, boxes and termination-free settings as far as VTK can take them. VTK places
/// volumes by origin and spacing only, so each head's box is the same box unturned (the
/// heads are near-symmetric ellipsoids, so a ray meets about as many of their voxels), with
/// `voxel_model = cell` (SPEC §2's cell-centred box) and an opacity unit distance of one
/// voxel of its own dataset (TROVE's opacity correction for a step of ℓ voxels).
fn vtk_scene(n: u32) -> String {
    let tf = |colour: &str, opacity: &str, unit: f64| {
        format!("{{\"color\": {colour}, \"opacity\": {opacity}, \"scalar_opacity_unit_distance\": {unit:?}}}")
    };
    let volume = |v: u32, origin: [f64; 3], spacing: [f64; 3], tf: String| {
        format!(
            "{{\"raw\": \"{}\", \"dims\": [{n}, {n}, {n}], \"dtype\": \"uint16\", \"endian\": \"little\", \
             \"origin\": {origin:?}, \"spacing\": {spacing:?}, \"voxel_model\": \"cell\", \"tf\": {tf}}}",
            Storage::Raw.file_name(v)
        )
    };
    let nf = f64::from(n);
    // The floor: a constant opacity of 1.
    let floor = [7.5, 0.08, 6.5];
    let mut volumes = vec![volume(
        14,
        [-3.75, -1.28, -4.5],
        floor.map(|s| s / nf),
        tf("[[0, 0.25, 0.25, 0.3], [3000, 0.6, 0.6, 0.7]]", "[[0, 1.0], [4095, 1.0]]", floor[1] / nf),
    )];
    let mut i = 0;
    for (z, y, xs) in HEAD_ROWS {
        for &x in xs {
            let (colour, opacity) = LOOKS[HEAD_LOOKS[i as usize % 7]];
            let s = HEAD_SIDE;
            volumes.push(volume(i, [x - s / 2.0, y, z - s / 2.0], [s / nf; 3], tf(colour, opacity, s / nf)));
            i += 1;
        }
    }
    format!("{{\"volumes\": [\n  {}\n]}}\n", volumes.join(",\n  "))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The VTK scene is JSON that `vtk_raycast.py --scene` reads: the floor and the 14 heads,
    /// each a raw file of the 15 datasets with the right dims, and each head's box where the
    /// TROVE scene puts it (unturned): its side over the voxels, its base at the row's height.
    #[test]
    fn vtk_scene_has_the_fifteen_volumes_where_trove_puts_them() {
        let scene: serde_json::Value = serde_json::from_str(&vtk_scene(96)).expect("valid JSON");
        let volumes = scene["volumes"].as_array().expect("a list of volumes");
        assert_eq!(volumes.len(), 15);
        let files: std::collections::BTreeSet<_> = volumes.iter().map(|v| v["raw"].as_str().unwrap()).collect();
        assert_eq!(files.len(), 15, "each dataset once");
        for v in volumes {
            assert_eq!(v["dims"], serde_json::json!([96, 96, 96]));
            assert_eq!(v["voxel_model"], "cell");
        }
        // Head 0: the first row's first x, its base at the row's y.
        let head = &volumes[1];
        assert_eq!(head["raw"], "head00.raw");
        let origin: Vec<f64> = head["origin"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
        let (z, y, xs) = HEAD_ROWS[0];
        let expected = [xs[0] - HEAD_SIDE / 2.0, y, z - HEAD_SIDE / 2.0];
        assert!(origin.iter().zip(expected).all(|(a, b)| (a - b).abs() < 1e-12), "{origin:?}");
        assert_eq!(head["spacing"][0].as_f64().unwrap(), HEAD_SIDE / 96.0);
    }
}
