//! The farm on one machine against local mode: the real `trove coordinator` and 1, 2 or 3
//! `trove-worker` processes on loopback, each worker holding every dataset, and the real
//! `trove render --coordinator` timed against `trove render` in one process, runs
//! alternating. Reports the median wall-time ratio, the bytes on the wire per piece each
//! way (from the farm's own statistics) and the coordinator's peak resident memory, and
//! checks that every farm image is byte for byte the local one.
//!
//! Processes rather than an in-process farm so that the coordinator's memory is its own
//! (`VmHWM` of its `/proc` entry) and the timing includes what a user waits for.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, ensure, Context, Result};

use crate::stats::median;
use crate::table1::{table1_scene, write_dataset, Storage};

/// `trove-bench farm` options.
#[derive(clap::Args)]
pub struct Args {
    /// Renders of each configuration; the median is reported.
    #[arg(long, default_value_t = 5)]
    repeat: u32,
    /// Worker counts to measure.
    #[arg(long, value_delimiter = ',', default_value = "1,2,3")]
    workers: Vec<u32>,
    /// Image width and height of the Table-1 scene.
    #[arg(long, default_value_t = 512)]
    size: u32,
    /// Voxels per axis of each Table-1 dataset.
    #[arg(long, default_value_t = 81)]
    dims: u32,
    /// Longer side of `scenes/fig01-fifteen-objects.toml` as rendered (0: skip it).
    #[arg(long, default_value_t = 512)]
    fig01_size: u32,
    /// The data folder that `scenes/fig01-fifteen-objects.toml` reads.
    #[arg(long, default_value = "../shared/data")]
    data_root: PathBuf,
    /// Only the large render: Fig. 1 at this size through 2 workers and in one process,
    /// once each, comparing bytes and peak memory (e.g. 8192).
    #[arg(long)]
    large: Option<u32>,
}

/// One scene as the benchmark renders it: a folder holding the scene file and, below it,
/// the files its keys name (locally the keys resolve under the scene's folder; the workers
/// resolve them under their data root, which is the same folder).
struct Case {
    name: String,
    scene: PathBuf,
    root: PathBuf,
}

/// Runs the benchmark and prints its tables.
pub fn run(args: Args) -> Result<()> {
    let bin = Binaries::beside_this_one()?;
    let dir = std::env::temp_dir().join(format!("trove-bench-farm-{}", std::process::id()));
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let result = run_in(&args, &bin, &dir);
    let _ = std::fs::remove_dir_all(&dir);
    result
}

fn run_in(args: &Args, bin: &Binaries, dir: &Path) -> Result<()> {
    if let Some(size) = args.large {
        let case = fig01_case(&args.data_root, size, dir)?;
        return large(bin, &case, dir);
    }
    let mut cases = vec![table1_case(args, dir)?];
    if args.fig01_size > 0 {
        cases.push(fig01_case(&args.data_root, args.fig01_size, dir)?);
    }
    println!(
        "| scene | workers | local s (median) | farm s (median) | farm / local | pieces | bytes/piece to workers | bytes/piece back | coordinator CPU ns/piece | workers' CPU ns/piece | coordinator peak RSS | same PNG |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|");
    for case in &cases {
        for &n in &args.workers {
            let row = measure(bin, case, n, args.repeat, dir)?;
            println!(
                "| {} | {n} | {:.3} | {:.3} | {:.2} | {} | {:.1} | {:.1} | {:.0} | {:.0} | {:.0} MiB | {} |",
                case.name,
                row.local,
                row.farm,
                row.farm / row.local,
                row.pieces,
                row.to_workers as f64 / row.pieces.max(1) as f64,
                row.from_workers as f64 / row.pieces.max(1) as f64,
                row.coordinator_ns_per_piece,
                row.workers_ns_per_piece,
                row.coordinator_peak as f64 / (1 << 20) as f64,
                if row.identical { "yes" } else { "NO" },
            );
            ensure!(row.identical, "{}: the farm's image differs from local mode's", case.name);
        }
    }
    Ok(())
}

/// The Table-1 scene with 15 datasets, stored raw.
fn table1_case(args: &Args, dir: &Path) -> Result<Case> {
    let root = dir.join("table1");
    std::fs::create_dir_all(&root)?;
    for v in 0..15 {
        write_dataset(&root.join(format!("head{v:02}.raw")), v, args.dims, Storage::Raw)?;
    }
    let scene = root.join("table1-15.toml");
    std::fs::write(&scene, table1_scene(args.size, args.dims, Storage::Raw, false))?;
    Ok(Case { name: format!("Table 1, 15 datasets, {0}×{0}", args.size), scene, root })
}

/// `scenes/fig01-fifteen-objects.toml` with its longer side `size`, written into a copy of
/// the data folder: its keys resolve there both for the local render (the scene's folder is
/// its data root) and for the workers, whose data root it is.
fn fig01_case(data: &Path, size: u32, dir: &Path) -> Result<Case> {
    let repo = trove_tests::repo_root();
    let path = repo.join("scenes/fig01-fifteen-objects.toml");
    ensure!(data.is_dir(), "{}: no such folder (pass --data-root, or --fig01-size 0 to skip Fig. 1)", data.display());
    let text = trove_tests::shrunk_scene_text(&path, size);
    let root = dir.join("fig01");
    std::fs::create_dir_all(&root)?;
    // Copies, not links: a worker refuses links that leave its root; and every file, since
    // a detached NRRD header names its data file.
    copy_files(data, &root)?;
    let table: toml::Table = text.parse()?;
    let scene = root.join("fig01.toml");
    std::fs::write(&scene, text)?;
    let (w, h) = image_size(&table);
    Ok(Case { name: format!("Fig. 1, {w}×{h}"), scene, root })
}

/// Copies the folder `from` into `to`, recursively (copies, not links: a worker refuses
/// links that leave its root).
pub(crate) fn copy_files(from: &Path, to: &Path) -> Result<()> {
    std::fs::create_dir_all(to)?;
    for entry in std::fs::read_dir(from).with_context(|| format!("reading {}", from.display()))? {
        let entry = entry?;
        let target = to.join(entry.file_name());
        if entry.file_type()?.is_dir() {
            copy_files(&entry.path(), &target)?;
        } else {
            std::fs::copy(entry.path(), &target).with_context(|| format!("copying {}", entry.path().display()))?;
        }
    }
    Ok(())
}

fn image_size(table: &toml::Table) -> (i64, i64) {
    let image = &table["image"];
    (image["width"].as_integer().unwrap_or(0), image["height"].as_integer().unwrap_or(0))
}

/// What one (scene, worker count) configuration measured.
struct Row {
    local: f64,
    farm: f64,
    pieces: u64,
    to_workers: u64,
    from_workers: u64,
    coordinator_peak: u64,
    /// CPU time (user + system, every thread) the coordinator process spent over the farm
    /// renders, per piece rendered.
    coordinator_ns_per_piece: f64,
    /// The same for the worker processes together.
    workers_ns_per_piece: f64,
    identical: bool,
}

fn measure(bin: &Binaries, case: &Case, workers: u32, repeat: u32, dir: &Path) -> Result<Row> {
    let farm = Farm::start(bin, &case.root, workers)?;
    let (local_png, farm_png, stats) = (dir.join("local.png"), dir.join("farm.png"), dir.join("farm.json"));
    farm.wait_until_ready(bin, &case.scene, &farm_png)?;
    let (mut local, mut remote) = (Vec::new(), Vec::new());
    let mut identical = true;
    let (mut coordinator_cpu, mut workers_cpu) = (0.0, 0.0);
    for _ in 0..repeat {
        local.push(bin.render(&case.scene, &local_png, &[])?);
        let before = (farm.coordinator_cpu()?, farm.workers_cpu()?);
        remote.push(bin.render(&case.scene, &farm_png, &["--coordinator", &farm.url, "--stats", path_str(&stats)?])?);
        coordinator_cpu += farm.coordinator_cpu()? - before.0;
        workers_cpu += farm.workers_cpu()? - before.1;
        identical &= std::fs::read(&local_png)? == std::fs::read(&farm_png)?;
        eprintln!(
            "{} / {workers} workers: local {:.3} s, farm {:.3} s",
            case.name,
            local[local.len() - 1],
            remote[remote.len() - 1]
        );
    }
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(&stats)?)?;
    let count = |key: &str| json[key].as_u64().with_context(|| format!("the farm's statistics have no `{key}`"));
    let pieces_rendered = (count("pieces")? * repeat as u64).max(1) as f64;
    Ok(Row {
        coordinator_ns_per_piece: coordinator_cpu * 1e9 / pieces_rendered,
        workers_ns_per_piece: workers_cpu * 1e9 / pieces_rendered,
        local: median(local).unwrap_or(f64::NAN),
        farm: median(remote).unwrap_or(f64::NAN),
        pieces: count("pieces")?,
        to_workers: count("wire_bytes_to_workers")?,
        from_workers: count("wire_bytes_from_workers")?,
        coordinator_peak: farm.coordinator_peak()?,
        identical,
    })
}

/// Fig. 1 at a large size: once in one process and once through two workers.
fn large(bin: &Binaries, case: &Case, dir: &Path) -> Result<()> {
    let (local_png, farm_png) = (dir.join("local.png"), dir.join("farm.png"));
    let farm = Farm::start(bin, &case.root, 2)?;
    farm.wait_until_ready(bin, &case.scene, &dir.join("warm.png"))?;
    let farm_seconds = bin.render(&case.scene, &farm_png, &["--coordinator", &farm.url])?;
    let coordinator_peak = farm.coordinator_peak()?;
    drop(farm);
    let (local_seconds, local_peak) = bin.render_measuring_memory(&case.scene, &local_png)?;
    let identical = std::fs::read(&local_png)? == std::fs::read(&farm_png)?;
    println!("| scene | local s | local peak RSS | farm (2 workers) s | coordinator peak RSS | same PNG |");
    println!("|---|---:|---:|---:|---:|---|");
    println!(
        "| {} | {local_seconds:.1} | {} | {farm_seconds:.1} | {} | {} |",
        case.name,
        local_peak.map_or("–".to_string(), |b| format!("{:.0} MiB", b as f64 / (1 << 20) as f64)),
        format_args!("{:.0} MiB", coordinator_peak as f64 / (1 << 20) as f64),
        if identical { "yes" } else { "NO" }
    );
    ensure!(identical, "{}: the farm's image differs from local mode's", case.name);
    Ok(())
}

fn path_str(path: &Path) -> Result<&str> {
    path.to_str().with_context(|| format!("{} is not UTF-8", path.display()))
}

/// The `trove` and `trove-worker` executables of this build.
struct Binaries {
    trove: PathBuf,
    worker: PathBuf,
}

impl Binaries {
    fn beside_this_one() -> Result<Binaries> {
        let me = std::env::current_exe()?;
        let exe = |name: &str| me.with_file_name(format!("{name}{}", std::env::consts::EXE_SUFFIX));
        let (trove, worker) = (exe("trove"), exe("trove-worker"));
        for b in [&trove, &worker] {
            if !b.exists() {
                bail!(
                    "{} is missing: build it first (cargo build --release --bin trove --bin trove-worker)",
                    b.display()
                );
            }
        }
        Ok(Binaries { trove, worker })
    }

    /// `trove render SCENE -o OUT extra…`, timed; a failure is an error with its stderr.
    fn render(&self, scene: &Path, out: &Path, extra: &[&str]) -> Result<f64> {
        let started = Instant::now();
        let output = Command::new(&self.trove)
            .args(["render", path_str(scene)?, "-o", path_str(out)?])
            .args(extra)
            // Every case's scene lies in its data root; a TROVE_DATA of the caller's must not move it.
            .env_remove("TROVE_DATA")
            .stdin(Stdio::null())
            .output()?;
        let seconds = started.elapsed().as_secs_f64();
        ensure!(output.status.success(), "trove render failed: {}", String::from_utf8_lossy(&output.stderr).trim());
        Ok(seconds)
    }

    /// A local render under `/usr/bin/time`, for its peak resident memory where that exists.
    fn render_measuring_memory(&self, scene: &Path, out: &Path) -> Result<(f64, Option<u64>)> {
        let time = Path::new("/usr/bin/time");
        if !time.exists() {
            return Ok((self.render(scene, out, &[])?, None));
        }
        let started = Instant::now();
        let output = Command::new(time)
            .args(["-f", "%M"])
            .arg(&self.trove)
            .args(["render", path_str(scene)?, "-o", path_str(out)?])
            .env_remove("TROVE_DATA")
            .stdin(Stdio::null())
            .output()?;
        let seconds = started.elapsed().as_secs_f64();
        let stderr = String::from_utf8_lossy(&output.stderr);
        ensure!(output.status.success(), "trove render failed: {}", stderr.trim());
        let kib = stderr.lines().last().and_then(|l| l.trim().parse::<u64>().ok());
        Ok((seconds, kib.map(|k| k * 1024)))
    }
}

/// A coordinator and its workers as child processes, killed when dropped.
struct Farm {
    url: String,
    coordinator: Child,
    workers: Vec<Child>,
}

impl Farm {
    fn start(bin: &Binaries, root: &Path, workers: u32) -> Result<Farm> {
        let (coordinator, address) =
            spawn_server(&bin.trove, &["coordinator", "--listen", "127.0.0.1:0", "--heartbeat-ms", "200"])?;
        let url = format!("http://{address}");
        let mut farm = Farm { url, coordinator, workers: Vec::new() };
        for _ in 0..workers {
            let args = ["--coordinator", &farm.url, "--listen", "127.0.0.1:0", "--data-root", path_str(root)?];
            farm.workers.push(spawn_server(&bin.worker, &args)?.0);
        }
        Ok(farm)
    }

    /// Renders once, retrying while the workers register (a job naming a dataset no
    /// registered worker holds is refused at once).
    fn wait_until_ready(&self, bin: &Binaries, scene: &Path, out: &Path) -> Result<()> {
        let started = Instant::now();
        loop {
            match bin.render(scene, out, &["--coordinator", &self.url]) {
                Ok(_) => return Ok(()),
                Err(_) if started.elapsed() < Duration::from_secs(30) => std::thread::sleep(Duration::from_millis(200)),
                Err(e) => return Err(e.context("the farm did not become ready within 30 s")),
            }
        }
    }

    /// CPU seconds (user + system, all threads) the coordinator has used so far.
    fn coordinator_cpu(&self) -> Result<f64> {
        cpu_seconds(self.coordinator.id())
    }

    /// CPU seconds the workers have used so far, together.
    fn workers_cpu(&self) -> Result<f64> {
        self.workers.iter().map(|w| cpu_seconds(w.id())).sum()
    }

    /// The coordinator's peak resident set so far (`VmHWM`), in bytes.
    fn coordinator_peak(&self) -> Result<u64> {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.coordinator.id()))
            .context("reading the coordinator's /proc status (Linux only)")?;
        let line = status.lines().find(|l| l.starts_with("VmHWM:")).context("no VmHWM in /proc status")?;
        let kib: u64 = line.split_whitespace().nth(1).context("VmHWM without a value")?.parse()?;
        Ok(kib * 1024)
    }
}

impl Drop for Farm {
    fn drop(&mut self) {
        for child in self.workers.iter_mut().chain(std::iter::once(&mut self.coordinator)) {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// CPU seconds (user + system over every thread) process `pid` has used: fields 14 and 15
/// of `/proc/PID/stat`, in clock ticks of 1/100 s (Linux's `USER_HZ` on every platform it
/// runs on).
fn cpu_seconds(pid: u32) -> Result<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).context("reading /proc/PID/stat (Linux only)")?;
    // The command name (field 2) is in parentheses and may hold spaces: count after it.
    let after = stat.rsplit_once(')').context("a /proc stat line without `)`")?.1;
    let fields: Vec<&str> = after.split_whitespace().collect();
    let ticks =
        |i: usize| -> Result<f64> { Ok(fields.get(i).context("a short /proc stat line")?.parse::<u64>()? as f64) };
    // Field 3 (the state) is fields[0], so field n is fields[n - 3].
    Ok((ticks(11)? + ticks(12)?) / 100.0)
}

/// Where a server's log goes: `$TROVE_BENCH_LOGS/NAME-PID.log` when that variable names a
/// folder (with `RUST_LOG` to choose what is logged), else nowhere.
fn server_log(program: &Path) -> Result<Stdio> {
    let Some(dir) = std::env::var_os("TROVE_BENCH_LOGS") else { return Ok(Stdio::null()) };
    static NEXT: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let name = program.file_name().map_or("server".into(), |n| n.to_string_lossy().into_owned());
    let path = Path::new(&dir).join(format!("{name}-{n}.log"));
    Ok(std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?.into())
}

/// Starts a server and reads the address it bound from its first line of stdout.
fn spawn_server(program: &Path, args: &[&str]) -> Result<(Child, String)> {
    trove_tests::farm::spawn_server(program, args, server_log(program)?)
        .with_context(|| format!("starting {}", program.display()))
}
