//! The coordinator alone: the real coordinator (`trove_coordinator::farm::run`) in this
//! process, fed by stand-in workers (`trove_tests::standin`) that answer each batch at once
//! with results recorded from a real cast, so that what limits a job is the coordinator's
//! own work. Reports the pieces per second it sustains, its CPU per piece in all and by
//! stage, and how its throughput grows from one core to two.
//!
//! Each core count runs in a child process (`--one C`), since rayon's global pool — which
//! the coordinator's blocking steps use — is sized once per process. There the coordinator
//! gets a tokio runtime of C worker threads and a rayon pool of C threads, all pinned to the
//! first C processors this process may use; the stand-ins, their rayon pool and the client
//! run on threads of other names, pinned to the remaining processors (or, when none remain,
//! to all of them, shared: the output says which). The coordinator's CPU is the sum of its
//! own threads' run time (`/proc/self/task/TID/schedstat`, by thread name), so the
//! stand-ins' CPU is never counted in it, wherever they run. Per-stage times come from the
//! job's own statistics (`coordinator_seconds`, wall time on the thread doing each step).
//!
//! Every image is checked against local mode's byte for byte; a difference is an error.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, ensure, Context, Result};
use serde_json::{json, Value};
use tokio::sync::oneshot;
use trove_coordinator::client::FarmClient;
use trove_coordinator::farm::{self, FarmConfig};
use trove_core::render::{render, RenderOptions};
use trove_core::scene::{DataRoot, Scene};
use trove_proto::v1 as pb;
use trove_tests::standin::{self, Answers};

use crate::farm_sim::recorded::{self, place_of, CoordinatorRecord, RunsOn, SceneCosts, Stage, COORDINATOR_FORMAT};
use crate::stats::median;
use crate::table1::{table1_scene, write_dataset, Storage};

/// `trove-bench coordinator` options.
#[derive(clap::Args)]
pub struct Args {
    /// Image width and height (Fig. 1 keeps its aspect, its longer side this).
    #[arg(long, default_value_t = 1024)]
    size: u32,
    /// Measured renders of each scene and core count (after one that records the answers).
    #[arg(long, default_value_t = 3)]
    repeat: u32,
    /// Stand-in workers.
    #[arg(long, default_value_t = 2)]
    workers: u32,
    /// Coordinator core counts to measure.
    #[arg(long, value_delimiter = ',', default_value = "1,2")]
    cores: Vec<usize>,
    /// Voxels per axis of each Table-1 dataset.
    #[arg(long, default_value_t = 81)]
    dims: u32,
    /// The data folder that `scenes/fig01-fifteen-objects.toml` reads (Fig. 1 is skipped
    /// with a message where it is absent).
    #[arg(long, default_value = "../shared/data")]
    data_root: PathBuf,
    /// Also write what the 1-core runs measured to this file, for `farm-sim` to read (the
    /// repository keeps one: `bench/recorded/coordinator.json`). Needs 1 in `--cores`.
    #[arg(long)]
    record: Option<PathBuf>,
    /// With 1 coordinator core: the runtime's one worker thread (the job's event loop and the
    /// transport) runs on a processor of its own (the last allowed) and the stand-ins share
    /// the first with the coordinator's other threads, so that the loop's timer counts no
    /// waits behind the bands' threads. Those rows' throughput is then not one core's.
    #[arg(long)]
    loop_apart: bool,
    /// (Internal) measure with this many coordinator cores in this process, printing one
    /// JSON line per scene; `--dir` holds the scenes.
    #[arg(long, hide = true)]
    one: Option<usize>,
    #[arg(long, hide = true)]
    dir: Option<PathBuf>,
}

/// A scene to measure: its name for the table, its file, all under one data root.
struct Case {
    name: String,
    scene: PathBuf,
}

/// Runs the benchmark and prints its table.
pub fn run(args: Args) -> Result<()> {
    if let Some(cores) = args.one {
        let dir = args.dir.clone().context("--one needs --dir")?;
        return measure_in_this_process(&args, cores, &dir);
    }
    let dir = std::env::temp_dir().join(format!("trove-bench-coordinator-{}", std::process::id()));
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let result = run_in(&args, &dir);
    let _ = std::fs::remove_dir_all(&dir);
    result
}

fn run_in(args: &Args, dir: &Path) -> Result<()> {
    if args.record.is_some() {
        ensure!(args.cores.contains(&1), "--record writes the 1-core runs: put 1 in --cores");
    }
    write_cases(args, dir)?;
    println!("processor: {}; sampler: {}", processor(), simd_path());
    println!("load average before: {}", load_average());
    let mut rows = Vec::new();
    for &cores in &args.cores {
        let me = std::env::current_exe()?;
        let output = Command::new(me)
            .arg("coordinator")
            .args(["--one", &cores.to_string(), "--dir", path_str(dir)?])
            .args(["--size", &args.size.to_string(), "--repeat", &args.repeat.to_string()])
            .args(["--workers", &args.workers.to_string()])
            .args(if args.loop_apart { &["--loop-apart"][..] } else { &[] })
            .stdin(Stdio::null())
            .stderr(Stdio::inherit())
            .output()?;
        ensure!(output.status.success(), "the measurement with {cores} coordinator cores failed");
        for line in String::from_utf8_lossy(&output.stdout).lines().filter(|l| l.starts_with('{')) {
            rows.push(serde_json::from_str::<Value>(line)?);
        }
    }
    println!("load average after: {}", load_average());
    print_table(&rows);
    if let Some(file) = &args.record {
        let record = record_of(args, &rows)?;
        record.write(file)?;
        println!("recorded the 1-core runs in {}", file.display());
    }
    Ok(())
}

/// The 1-core rows as a [`CoordinatorRecord`]: each stage's CPU per piece estimated as
/// `recorded::SceneCosts` describes, from the measured CPU of the coordinator's threads and
/// of the runtime's one worker thread (which runs the job's event loop and the transport).
fn record_of(args: &Args, rows: &[Value]) -> Result<CoordinatorRecord> {
    let f = |v: &Value| v.as_f64().unwrap_or(0.0);
    let mut scenes = Vec::new();
    for r in rows.iter().filter(|r| r["cores"] == 1) {
        let name = r["scene"].as_str().unwrap_or("?").to_string();
        let pieces = r["pieces"].as_u64().context("a row without pieces")?;
        let per = |seconds: f64| seconds * 1e9 / pieces.max(1) as f64;
        let st = r["stages"].as_object().context("a row without stages")?;
        let wall = |k: &str| st.get(k).map_or(0.0, f);
        // The loop's own timer counts every step of the job's task; what it also times
        // apart (stages placed on it: none since bands have threads of their own) is taken
        // out, and the rest is `loop_rest`.
        let on_loop = |k: &str| place_of(k).is_some_and(|(runs_on, _)| runs_on == RunsOn::EventLoop);
        let timed_loop = st.keys().filter(|k| on_loop(k)).map(|k| wall(k)).sum::<f64>();
        let loop_wall = wall("event_loop");
        let mut walls: Vec<(String, f64)> = Vec::new();
        for (key, seconds) in st {
            if key != "event_loop" {
                walls.push((key.clone(), f(seconds)));
            }
        }
        walls.push(("loop_rest".into(), (loop_wall - timed_loop).max(0.0)));
        let cpu = f(&r["coordinator_cpu"]);
        let worker_cpu = r["loop_thread_cpu"].as_f64().context("a 1-core row without its worker thread's CPU")?;
        let worker_wait = r["loop_thread_wait"].as_f64().unwrap_or(0.0);
        // The loop's CPU: its timed steps never block, so their wall time is CPU and waits
        // for the core, which on one core shared with the bands' threads and rayon's are
        // many. Their CPU is taken as that wall time less its share of the thread's waits
        // (the thread's CPU over its CPU and waits), capped by the CPU of the thread.
        let loop_cpu = (loop_wall * worker_cpu / (worker_cpu + worker_wait).max(1e-12)).min(worker_cpu).min(cpu);
        let blocking_cpu = (cpu - worker_cpu).max(0.0);
        // Two groups: the event loop's stages, and those of blocking threads (the bands'
        // threads, rayon's, the image's encoding).
        let mut groups = [0.0, 0.0];
        let mut placed = Vec::new();
        for (key, seconds) in walls {
            let (runs_on, at) = place_of(&key).with_context(|| {
                format!(
                    "the job's statistics have a stage `{key}` that farm_sim::recorded::place_of does not place: \
                     say where it runs and bump COORDINATOR_FORMAT"
                )
            })?;
            let group = if runs_on == RunsOn::EventLoop { 0 } else { 1 };
            groups[group] += seconds;
            placed.push((key, seconds, runs_on, at, group));
        }
        let scale = [loop_cpu / groups[0].max(1e-12), blocking_cpu / groups[1].max(1e-12)];
        let mut stages: Vec<Stage> = placed
            .into_iter()
            .map(|(name, seconds, runs_on, at, group)| Stage {
                name,
                cpu_ns_per_piece: per(seconds * scale[group]),
                wall_ns_per_piece: Some(per(seconds)),
                runs_on,
                at,
            })
            .collect();
        let (runs_on, at) = place_of("transport").expect("transport is placed");
        stages.push(Stage {
            name: "transport".into(),
            cpu_ns_per_piece: per((worker_cpu - loop_cpu).max(0.0)),
            wall_ns_per_piece: None,
            runs_on,
            at,
        });
        scenes.push(SceneCosts {
            scene: name,
            pixels: r["pixels"].as_u64().context("a row without pixels")?,
            pieces,
            tasks_sent: r["tasks_sent"].as_u64().unwrap_or(0),
            cpu_ns_per_piece: per(cpu),
            stages,
        });
    }
    ensure!(!scenes.is_empty(), "no 1-core rows to record");
    let cores: Vec<String> = args.cores.iter().map(|c| c.to_string()).collect();
    let file = args.record.as_ref().map(|p| p.display().to_string()).unwrap_or_default();
    Ok(CoordinatorRecord {
        format: COORDINATOR_FORMAT,
        processor: recorded::processor(),
        simd: simd_path().to_string(),
        commit: recorded::commit(),
        command: format!(
            "trove-bench coordinator --size {} --repeat {} --workers {} --cores {} --dims {}{} --record {file}",
            args.size,
            args.repeat,
            args.workers,
            cores.join(","),
            args.dims,
            if args.loop_apart { " --loop-apart" } else { "" }
        ),
        cores: 1,
        scenes,
    })
}

/// The Table-1 scene (15 raw datasets) and Fig. 1, in one data root: `dir/root`.
fn write_cases(args: &Args, dir: &Path) -> Result<()> {
    let root = dir.join("root");
    std::fs::create_dir_all(&root)?;
    for v in 0..15 {
        write_dataset(&root.join(format!("head{v:02}.raw")), v, args.dims, Storage::Raw)?;
    }
    std::fs::write(root.join("table1.toml"), table1_scene(args.size, args.dims, Storage::Raw, false))?;
    let fig01 = trove_tests::repo_root().join("scenes/fig01-fifteen-objects.toml");
    if !args.data_root.is_dir() {
        eprintln!("SKIPPED Fig. 1: {} is not a folder (pass --data-root)", args.data_root.display());
        return Ok(());
    }
    crate::farm::copy_files(&args.data_root, &root)?;
    let mut table: toml::Table = std::fs::read_to_string(&fig01)?.parse()?;
    let image = table.get_mut("image").and_then(|v| v.as_table_mut()).context("fig01: no [image]")?;
    let side = |key: &str| image[key].as_integer().unwrap_or(1).max(1);
    let (w, h) = (side("width"), side("height"));
    let long = w.max(h);
    let size = i64::from(args.size);
    image.insert("width".into(), toml::Value::Integer((w * size + long / 2) / long));
    image.insert("height".into(), toml::Value::Integer((h * size + long / 2) / long));
    std::fs::write(root.join("fig01.toml"), toml::to_string(&table)?)?;
    Ok(())
}

fn cases(dir: &Path, size: u32) -> Vec<Case> {
    let root = dir.join("root");
    let mut cases = vec![Case { name: format!("Table 1, 15 datasets, {size}²"), scene: root.join("table1.toml") }];
    if root.join("fig01.toml").exists() {
        cases.push(Case { name: format!("Fig. 1, {size}²"), scene: root.join("fig01.toml") });
    }
    cases
}

/// One measured render: its wall time, the coordinator's and the stand-ins' CPU, the job's
/// statistics, and the run and wait times of the coordinator's worker thread (with 1 core).
type Run = (f64, f64, f64, Value, (f64, f64));

/// One core count, in this process: see the module's doc.
fn measure_in_this_process(args: &Args, cores: usize, dir: &Path) -> Result<()> {
    let cpus = allowed_cpus();
    ensure!(cores >= 1 && cores <= cpus.len(), "{cores} coordinator cores asked for, {} available", cpus.len());
    let coordinator_cpus: Vec<usize> = cpus[..cores].to_vec();
    let loop_apart = args.loop_apart && cores == 1;
    ensure!(!loop_apart || cpus.len() >= 2, "--loop-apart needs two processors");
    let (standin_cpus, separated) = if loop_apart {
        (coordinator_cpus.clone(), false)
    } else if cpus.len() > cores {
        (cpus[cores..].to_vec(), true)
    } else {
        (cpus.clone(), false)
    };
    let (c, s) = (coordinator_cpus.clone(), standin_cpus.clone());
    rayon::ThreadPoolBuilder::new()
        .num_threads(cores)
        .thread_name(|i| format!("coord-rayon-{i}"))
        .start_handler(move |_| pin(&c))
        .build_global()
        .context("rayon's global pool")?;
    let c = coordinator_cpus.clone();
    let coordinator_rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(cores)
        .thread_name("coord-tokio")
        .thread_keep_alive(Duration::from_secs(3600))
        .on_thread_start(move || pin(&c))
        .enable_all()
        .build()?;
    let s2 = s.clone();
    let standin_rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(s.len())
        .thread_name("standin-tokio")
        .on_thread_start(move || pin(&s2))
        .enable_all()
        .build()?;
    let s3 = s.clone();
    let pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .num_threads(s.len())
            .thread_name(|i| format!("standin-rayon-{i}"))
            .start_handler(move |_| pin(&s3))
            .build()?,
    );
    pin(&standin_cpus);
    eprintln!(
        "{cores} coordinator core(s): coordinator on processors {coordinator_cpus:?}, stand-ins and client on {standin_cpus:?}{}",
        if separated { "" } else { " (shared with the coordinator: no processor left)" }
    );

    let (url, stop_coordinator) = coordinator_rt.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let url = format!("http://{}", listener.local_addr()?);
        let (tx, rx) = oneshot::channel::<()>();
        tokio::spawn(async move {
            let shutdown = async {
                let _ = rx.await;
            };
            if let Err(e) = farm::run(listener, shutdown, FarmConfig::default()).await {
                eprintln!("coordinator stopped: {e}");
            }
        });
        anyhow::Ok((url, tx))
    })?;
    // With one worker thread, every task of the coordinator's runtime — the job's event
    // loop and the transport — runs on it: its CPU is theirs (its blocking threads are
    // others).
    let loop_thread = if cores == 1 {
        // SAFETY: gettid has no preconditions.
        Some(coordinator_rt.block_on(async { tokio::spawn(async { unsafe { libc::gettid() } }).await })?)
    } else {
        None
    };
    if let (true, Some(tid), Some(&apart)) = (loop_apart, loop_thread, cpus.last()) {
        pin_thread(tid, &[apart]).context("pinning the loop's thread apart")?;
        eprintln!("the runtime's worker thread (event loop, transport) apart on processor {apart}");
    }
    let root = dir.join("root");
    let answers = Arc::new(Answers::new(&root, pool)?);
    let mut stops = Vec::new();
    for _ in 0..args.workers {
        let (stop, stopped) = oneshot::channel::<()>();
        let (url, answers) = (url.clone(), answers.clone());
        standin_rt.block_on(async move {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
            tokio::spawn(async move {
                let shutdown = async {
                    let _ = stopped.await;
                };
                if let Err(e) = standin::serve(listener, shutdown, &url, 2, answers).await {
                    eprintln!("stand-in stopped: {e}");
                }
            });
            anyhow::Ok(())
        })?;
        stops.push(stop);
    }
    let mut client = standin_rt.block_on(FarmClient::connect(&url))?;
    let started = Instant::now();
    while standin_rt.block_on(client.workers())?.iter().filter(|w| w.alive).count() < args.workers as usize {
        ensure!(started.elapsed() < Duration::from_secs(10), "the stand-ins did not register within 10 s");
        std::thread::sleep(Duration::from_millis(20));
    }

    for case in cases(dir, args.size) {
        let text = std::fs::read_to_string(&case.scene)?;
        let name = case.scene.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let scene = Scene::parse_in(&text, &case.scene, &DataRoot::Given(root.clone()))?;
        let local = render(&scene, &RenderOptions::default())?.image.encode_png()?;
        let loop_cpu = || loop_thread.map_or(Ok((0.0, 0.0)), tid_cpu);
        let mut farm_render = || -> Result<Run> {
            let (cpu, standins, on_loop) = (thread_cpu("coord-")?, thread_cpu("standin-")?, loop_cpu()?);
            let started = Instant::now();
            let files =
                standin_rt.block_on(client.render(text.clone(), name.clone(), pb::JobOptions::default(), |_| {}))?;
            let wall = started.elapsed().as_secs_f64();
            let (cpu, standins) = (thread_cpu("coord-")? - cpu, thread_cpu("standin-")? - standins);
            let after = loop_cpu()?;
            let on_loop = (after.0 - on_loop.0, after.1 - on_loop.1);
            ensure!(files.png == local, "{}: the coordinator's image differs from local mode's", case.name);
            Ok((wall, cpu, standins, serde_json::from_slice(&files.stats_json)?, on_loop))
        };
        let recording = Instant::now();
        farm_render()?;
        eprintln!("{} / {cores} core(s): answers recorded in {:.1} s", case.name, recording.elapsed().as_secs_f64());
        let cast_before = answers.counts().1;
        let mut runs = Vec::new();
        for _ in 0..args.repeat.max(1) {
            let run = farm_render()?;
            eprintln!("{} / {cores} core(s): {:.3} s, coordinator CPU {:.3} s", case.name, run.0, run.1);
            runs.push(run);
        }
        let cast_during = answers.counts().1 - cast_before;
        let stats = &runs[0].3;
        let pieces = stats["pieces"].as_u64().context("no `pieces` in the job's statistics")?;
        let sent: u64 = stats["workers"].as_array().map_or(0, |w| w.iter().filter_map(|w| w["tasks"].as_u64()).sum());
        let n = runs.len() as f64;
        let mut stages = json!({});
        for key in stats["coordinator_seconds"].as_object().context("no `coordinator_seconds`")?.keys() {
            let sum: f64 = runs.iter().map(|r| r.3["coordinator_seconds"][key].as_f64().unwrap_or(0.0)).sum();
            stages[key] = json!(sum / n);
        }
        let row = json!({
            "scene": case.name,
            "cores": cores,
            "separated": separated,
            "loop_apart": loop_apart,
            "pieces": pieces,
            "tasks_sent": sent,
            "batches": stats["batches"],
            "seconds": median(runs.iter().map(|r| r.0)),
            "coordinator_cpu": runs.iter().map(|r| r.1).sum::<f64>() / n,
            "standin_cpu": runs.iter().map(|r| r.2).sum::<f64>() / n,
            "loop_thread_cpu": loop_thread.map(|_| runs.iter().map(|r| r.4 .0).sum::<f64>() / n),
            "loop_thread_wait": loop_thread.map(|_| runs.iter().map(|r| r.4 .1).sum::<f64>() / n),
            "pixels": u64::from(scene.image().width) * u64::from(scene.image().height),
            "stages": stages,
            "cast_during_measurement": cast_during,
        });
        println!("{row}");
    }
    for stop in stops {
        let _ = stop.send(());
    }
    let _ = stop_coordinator.send(());
    Ok(())
}

fn print_table(rows: &[Value]) {
    let f = |v: &Value| v.as_f64().unwrap_or(f64::NAN);
    println!(
        "\n| scene | coordinator cores | pieces | tasks sent | job s (median) | pieces/s | coordinator CPU ns/piece | intersection | planning | dispatch | encoding | decoding + recording | event loop | composition | PNG | stand-ins' CPU ns/piece |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in rows {
        let pieces = f(&r["pieces"]).max(1.0);
        let ns = |s: f64| s * 1e9 / pieces;
        let st = &r["stages"];
        println!(
            "| {} | {}{} | {} | {} | {:.3} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} |",
            r["scene"].as_str().unwrap_or("?"),
            r["cores"],
            match (r["loop_apart"].as_bool(), r["separated"].as_bool()) {
                (Some(true), _) => " (shared; loop apart)",
                (_, Some(true)) => "",
                _ => " (shared)",
            },
            r["pieces"],
            r["tasks_sent"],
            f(&r["seconds"]),
            pieces / f(&r["seconds"]),
            ns(f(&r["coordinator_cpu"])),
            ns(f(&st["intersection"])),
            ns(f(&st["planning"])),
            ns(f(&st["dispatch"])),
            ns(f(&st["encoding"])),
            ns(f(&st["decoding"]) + f(&st["recording"])),
            ns(f(&st["event_loop"])),
            ns(f(&st["composition"])),
            ns(f(&st["image_encoding"])),
            ns(f(&r["standin_cpu"])),
        );
    }
    println!(
        "\nStage columns: wall time per piece on the thread doing the step (the job's statistics). Planning, dispatch, \
         encoding, decoding and recording run on each band's own thread, intersection and composition there with \
         rayon within, several bands at once, so theirs add up waits for a processor and can exceed the CPU column; \
         the event loop (per-batch work only: the stock of batches, sending, asking bands, forwarding answers) is \
         one task whose steps never block, so its column is CPU time and waits for a core (on one core shared \
         with the bands' threads, many: the lines below give its thread's; the record takes the loop's CPU as its \
         timer less its share of those waits)."
    );
    for r1 in rows.iter().filter(|r| r["cores"] == 1 && r["loop_apart"] != true) {
        for r2 in rows.iter().filter(|r| r["cores"] == 2 && r["scene"] == r1["scene"]) {
            println!(
                "{}: throughput on 2 cores / 1 core = {:.2}",
                r1["scene"].as_str().unwrap_or("?"),
                f(&r1["seconds"]) / f(&r2["seconds"])
            );
        }
    }
    for r in rows.iter().filter(|r| r["loop_thread_cpu"].is_number()) {
        let ns = |v: &Value| f(v) * 1e9 / f(&r["pieces"]).max(1.0);
        println!(
            "{}, 1 core: the runtime's one worker thread (event loop and transport) ran {:.0} ns a piece and waited \
             {:.0} ns a piece for the core; the loop's own timer counted {:.0} ns a piece",
            r["scene"].as_str().unwrap_or("?"),
            ns(&r["loop_thread_cpu"]),
            ns(&r["loop_thread_wait"]),
            ns(&r["stages"]["event_loop"])
        );
    }
    let cast: u64 = rows.iter().filter_map(|r| r["cast_during_measurement"].as_u64()).sum();
    println!("tasks the stand-ins had to cast during the measured renders: {cast}");
}

/// The processors this process may run on.
fn allowed_cpus() -> Vec<usize> {
    // SAFETY: a zeroed `cpu_set_t` is a valid empty set, and `sched_getaffinity` writes at
    // most `size_of::<cpu_set_t>()` bytes into it.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        if libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set) != 0 {
            return (0..std::thread::available_parallelism().map_or(1, |n| n.get())).collect();
        }
        (0..libc::CPU_SETSIZE as usize).filter(|&c| libc::CPU_ISSET(c, &set)).collect()
    }
}

/// Pins the calling thread to `cpus` (best effort: a refusal leaves it unpinned).
fn pin(cpus: &[usize]) {
    // SAFETY: as in `allowed_cpus`; pid 0 is the calling thread.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        for &c in cpus {
            libc::CPU_SET(c, &mut set);
        }
        let _ = libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set);
    }
}

/// CPU seconds run so far by this process's threads whose name starts with `prefix`:
/// `/proc/self/task/TID/schedstat`'s first field (nanoseconds on a processor).
fn thread_cpu(prefix: &str) -> Result<f64> {
    let mut ns = 0u64;
    for entry in std::fs::read_dir("/proc/self/task").context("reading /proc/self/task (Linux only)")? {
        let dir = entry?.path();
        let Ok(comm) = std::fs::read_to_string(dir.join("comm")) else { continue };
        if !comm.starts_with(prefix) {
            continue;
        }
        let Ok(sched) = std::fs::read_to_string(dir.join("schedstat")) else {
            bail!("{}: no schedstat (a kernel without CONFIG_SCHED_INFO)", dir.display())
        };
        ns += sched.split_whitespace().next().and_then(|v| v.parse::<u64>().ok()).unwrap_or(0);
    }
    Ok(ns as f64 * 1e-9)
}

fn processor() -> String {
    format!("{} ({} processors allowed)", recorded::processor(), allowed_cpus().len())
}

fn simd_path() -> &'static str {
    recorded::simd_path()
}

/// Pins thread `tid` of this process to `cpus`.
fn pin_thread(tid: libc::pid_t, cpus: &[usize]) -> Result<()> {
    // SAFETY: as in `allowed_cpus`; `tid` is a thread of this process.
    let rc = unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        for &c in cpus {
            libc::CPU_SET(c, &mut set);
        }
        libc::sched_setaffinity(tid, std::mem::size_of::<libc::cpu_set_t>(), &set)
    };
    ensure!(rc == 0, "sched_setaffinity: {}", std::io::Error::last_os_error());
    Ok(())
}

/// Seconds thread `tid` of this process has run so far, and waited runnable for a
/// processor (its schedstat's first two fields).
fn tid_cpu(tid: libc::pid_t) -> Result<(f64, f64)> {
    let file = format!("/proc/self/task/{tid}/schedstat");
    let text = std::fs::read_to_string(&file).with_context(|| format!("reading {file}"))?;
    let mut fields = text.split_whitespace().map(|v| v.parse::<u64>().ok());
    let (Some(Some(run)), Some(Some(wait))) = (fields.next(), fields.next()) else {
        bail!("{file}: expected its run and wait times")
    };
    Ok((run as f64 * 1e-9, wait as f64 * 1e-9))
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|l| l.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}

fn path_str(path: &Path) -> Result<&str> {
    path.to_str().with_context(|| format!("{} is not UTF-8", path.display()))
}
