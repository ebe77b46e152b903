//! Faults injected into a farm of real processes, as an operator would meet them: the real
//! `trove coordinator` and three `trove-worker`s on loopback, every dataset file held by two
//! of the three workers.
//!
//! * A worker SIGKILLed while a job is half cast, twenty times: every job completes with the
//!   image local mode renders, byte for byte (a fresh worker takes the dead one's place
//!   before the next repetition, so three are always up).
//! * Fifty jobs submitted at once: all complete with their local images, the ones beyond
//!   `--max-jobs` report their place in the queue, and the coordinator's peak resident
//!   memory stays under a bound that follows from its configuration.
//! * Hostile scenes through `trove render --coordinator`: refused with a non-zero exit and a
//!   message naming the limit, and the same coordinator renders the next scene.
//!
//! The tests here share the machine's cores with each other's processes, so they run one
//! at a time ([`serial`]); each bounds every wait.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tokio::sync::mpsc;
use trove_coordinator::client::FarmClient;
use trove_core::dataset::FsCatalog;
use trove_core::render::{render, RenderOptions};
use trove_core::scene::Scene;
use trove_proto::v1 as pb;
use trove_tests::farm::{data_root, spawn_server};
use trove_tests::process::trove_worker_beside;
use trove_tests::scenes::{many_objects, nested_boxes};
use trove_tests::{scratch, Scratch};

fn trove() -> &'static Path {
    Path::new(env!("CARGO_BIN_EXE_trove"))
}

/// `trove-worker`, built beside `trove`.
fn trove_worker() -> PathBuf {
    trove_worker_beside(trove())
}

/// One test at a time: each starts four processes on a machine of two cores, and the kill
/// test's job must still be mid-way when its kill lands.
fn serial() -> MutexGuard<'static, ()> {
    static LOCK: Mutex<()> = Mutex::new(());
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}

/// A child process killed (SIGKILL) when dropped.
struct Server {
    child: Child,
    address: String,
}

impl Server {
    /// Starts `program args`, its log on this test's stderr.
    fn start(program: &Path, args: &[&str]) -> Server {
        let (child, address) = spawn_server(program, args, Stdio::inherit())
            .unwrap_or_else(|e| panic!("start {}: {e}", program.display()));
        Server { child, address }
    }

    /// SIGKILL, and reap it.
    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.kill();
    }
}

/// Heartbeats every 50 ms: a killed worker counts as lost after five missed (250 ms), though
/// its streams usually break first.
const HEARTBEAT_MS: &str = "50";

/// The longest any one wait in these tests lasts (a job, a registration).
const WAIT: Duration = Duration::from_secs(60);

/// The three dataset files, each `N`³ u8 voxels, and which two workers hold each.
const N: usize = 20;
const FILES: [&str; 3] = ["a.raw", "b.raw", "c.raw"];
const HELD_BY: [[&str; 2]; 3] = [["a.raw", "b.raw"], ["b.raw", "c.raw"], ["c.raw", "a.raw"]];

/// Writes the dataset files under `dir`: a ball, a ramp along x, and a shell.
fn write_datasets(dir: &Path) {
    let voxels = |f: &dyn Fn(f64, f64, f64) -> f64| -> Vec<u8> {
        let mut out = Vec::with_capacity(N * N * N);
        for z in 0..N {
            for y in 0..N {
                for x in 0..N {
                    let c = |i: usize| (i as f64 + 0.5) / N as f64 - 0.5;
                    out.push((f(c(x), c(y), c(z)).clamp(0.0, 1.0) * 255.0).round() as u8);
                }
            }
        }
        out
    };
    let r = |x: f64, y: f64, z: f64| (x * x + y * y + z * z).sqrt();
    std::fs::write(dir.join("a.raw"), voxels(&|x, y, z| 1.0 - 2.0 * r(x, y, z))).unwrap();
    std::fs::write(dir.join("b.raw"), voxels(&|x, _, _| x + 0.5)).unwrap();
    std::fs::write(dir.join("c.raw"), voxels(&|x, y, z| 1.0 - 8.0 * (r(x, y, z) - 0.35).abs())).unwrap();
}

/// A scene of the three datasets side by side on a `size`² image; `extra` goes into every
/// object (an interpolation, a step) and `hue` tints the colour maps, so that scenes differ.
fn scene(size: u32, extra: &str, hue: f64) -> String {
    let mut text = format!(
        "[image]\nwidth = {size}\nheight = {size}\nbackground = [0.1, 0.1, 0.2]\n\
         [camera]\neye = [0.5, 0.6, 3.0]\ntarget = [0.5, 0.5, 0.5]\nup = [0, 1, 0]\nfov_y = 35.0\n"
    );
    for (i, file) in FILES.iter().enumerate() {
        let x = 0.02 + 0.33 * i as f64;
        text += &format!(
            "[[datasets]]\nname = \"d{i}\"\ndims = [{N}, {N}, {N}]\n[datasets.channels.voxel]\nraw = \"{file}\"\n\
             type = \"u8\"\n\
             [[objects]]\nname = \"o{i}\"\ndataset = \"d{i}\"\n{extra}\n\
             transform = {{ matrix = [[0.3, 0, 0, {x}], [0, 0.3, 0, 0.35], [0, 0, 0.3, 0.35], [0, 0, 0, 1]] }}\n\
             colour = {{ type = \"ramp\", points = [[0, {hue}, 0.3, 0.1], [255, 0.2, 0.5, 1.0]] }}\n\
             opacity = {{ type = \"ramp\", points = [[0, 0.0], [255, 0.4]] }}\n"
        );
    }
    text
}

/// Local mode's PNG of `text`, its keys resolved under `dir`.
fn local_png(text: &str, dir: &Path) -> Vec<u8> {
    let scene = Scene::parse_with(text, "scene.toml", &FsCatalog::trusting(dir)).unwrap_or_else(|e| panic!("{e}"));
    render(&scene, &RenderOptions::default()).unwrap().image.encode_png().unwrap()
}

/// A coordinator and three workers over data roots that each hold two of the three files.
struct Farm {
    coordinator: Server,
    url: String,
    workers: Vec<Server>,
    runtime: tokio::runtime::Runtime,
    /// Removed last, once the processes that write into it are gone.
    dir: Scratch,
}

impl Farm {
    fn start(name: &str, coordinator_args: &[&str]) -> Farm {
        let dir = scratch(name);
        write_datasets(&dir);
        let mut args = vec!["coordinator", "--listen", "127.0.0.1:0", "--heartbeat-ms", HEARTBEAT_MS];
        args.extend_from_slice(coordinator_args);
        let coordinator = Server::start(trove(), &args);
        let url = format!("http://{}", coordinator.address);
        let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
        let mut farm = Farm { dir, coordinator, url, workers: Vec::new(), runtime };
        for i in 0..3 {
            let worker = farm.start_worker(i);
            farm.workers.push(worker);
        }
        let addresses: Vec<String> = farm.workers.iter().map(|w| w.address.clone()).collect();
        farm.wait_for_alive(&addresses);
        farm
    }

    /// Starts worker `i` over its data root (the same root on a restart).
    fn start_worker(&self, i: usize) -> Server {
        let root = data_root(&self.dir.join(format!("w{i}")), &self.dir, &HELD_BY[i]);
        let args = ["--coordinator", &self.url, "--listen", "127.0.0.1:0", "--data-root", root.to_str().unwrap()];
        Server::start(&trove_worker(), &args)
    }

    fn client(&self) -> FarmClient {
        self.runtime.block_on(FarmClient::connect(&self.url)).expect("connect to the coordinator")
    }

    /// The coordinator's workers by address, alive ones only.
    fn alive(&self) -> HashMap<String, pb::WorkerInfo> {
        let mut client = self.client();
        let workers = self.runtime.block_on(client.workers()).unwrap_or_default();
        workers.into_iter().filter(|w| w.alive).map(|w| (w.address.clone(), w)).collect()
    }

    /// Waits until exactly the workers at `addresses` are alive.
    fn wait_for_alive(&self, addresses: &[String]) {
        let started = Instant::now();
        loop {
            let alive = self.alive();
            if alive.len() == addresses.len() && addresses.iter().all(|a| alive.contains_key(a)) {
                return;
            }
            assert!(started.elapsed() < WAIT, "workers {addresses:?} not all alive (alive: {:?})", alive.keys());
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// The coordinator's peak resident memory so far (`VmHWM`), in bytes.
    fn coordinator_peak_rss(&self) -> u64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.coordinator.child.id())).unwrap();
        let line = status.lines().find(|l| l.starts_with("VmHWM:")).expect("VmHWM in /proc/PID/status");
        let kib: u64 = line.split_whitespace().nth(1).and_then(|n| n.parse().ok()).expect("VmHWM in kB");
        kib * 1024
    }
}

/// Submits `text` and follows it on its own task; every status comes back on the channel,
/// the stream's end as `None`.
fn follow(farm: &Farm, text: &str) -> (String, mpsc::UnboundedReceiver<Option<pb::JobStatus>>) {
    let mut client = farm.client();
    // Small batches in bands of four rows: the job's progress is published as each band is
    // composited (and every 250 ms), so it comes in many steps and a kill lands between them.
    let options = pb::JobOptions { batch_tasks: 4, band_rows: 4, ..Default::default() };
    let id = farm
        .runtime
        .block_on(client.submit(text.to_string(), "scene.toml".into(), options))
        .unwrap_or_else(|e| panic!("submit: {e}"));
    let (tx, rx) = mpsc::unbounded_channel();
    let watched = id.clone();
    farm.runtime.spawn(async move {
        let status_tx = tx.clone();
        let result = client
            .watch(&watched, |s| {
                let _ = status_tx.send(Some(s.clone()));
            })
            .await;
        if let Err(e) = result {
            eprintln!("watching {watched}: {e}");
        }
        let _ = tx.send(None);
    });
    (id, rx)
}

/// The next status of a followed job, within [`WAIT`]; `None` once its stream ended.
fn next_status(farm: &Farm, rx: &mut mpsc::UnboundedReceiver<Option<pb::JobStatus>>) -> Option<pb::JobStatus> {
    farm.runtime
        .block_on(async { tokio::time::timeout(WAIT, rx.recv()).await })
        .expect("a job's status within the wait")
        .flatten()
}

fn is_final(state: pb::JobState) -> bool {
    matches!(state, pb::JobState::Succeeded | pb::JobState::Failed | pb::JobState::Cancelled)
}

/// Follows a job to its end: its last status.
fn finish(farm: &Farm, rx: &mut mpsc::UnboundedReceiver<Option<pb::JobStatus>>) -> pb::JobStatus {
    let mut last = None;
    while let Some(status) = next_status(farm, rx) {
        last = Some(status);
    }
    last.expect("the job reported a status")
}

/// Cubic interpolation at a fine step: about 0.3 s a job over three workers in batches of
/// four tasks (measured with the workers' sockets sending at once, `TCP_NODELAY`), so a
/// kill lands while batches are out.
const SLOW: &str = "interpolation = \"cubic\"\nsampling_distance = 0.00007";

#[test]
fn a_worker_killed_mid_job_twenty_times_costs_no_job_and_changes_no_pixel() {
    let _serial = serial();
    let mut farm = Farm::start("faults-kill", &[]);
    let texts = [scene(56, SLOW, 0.9), scene(52, SLOW, 0.4)];
    let expected: Vec<Vec<u8>> = texts.iter().map(|t| local_png(t, &farm.dir)).collect();

    // Each scene once (loading the workers' datasets), then four jobs without a kill for
    // the time a kill costs.
    let mut unharmed = Vec::new();
    for rep in 0..6 {
        let started = Instant::now();
        let (id, mut rx) = follow(&farm, &texts[rep % texts.len()]);
        assert_eq!(finish(&farm, &mut rx).state(), pb::JobState::Succeeded);
        unharmed.push(started.elapsed());
        let png = farm.runtime.block_on(farm.client().result(&id)).unwrap().png;
        assert!(png == expected[rep % texts.len()], "unharmed job {rep}: the image differs from local mode's");
    }
    let mut unharmed = unharmed.split_off(texts.len());
    unharmed.sort();

    let (mut with_kill, mut done_at_kill) = (Vec::new(), Vec::new());
    // Twenty kills that land mid-job. A job that ends before one could land (its progress
    // is published in steps, so the last steps may come together) is checked all the same
    // and does not count; at most ten such are allowed.
    let mut rep = 0;
    while with_kill.len() < 20 {
        assert!(rep < 30, "only {} of {rep} jobs were still running when a kill could land", with_kill.len());
        let text = &texts[rep % texts.len()];
        let started = Instant::now();
        let (id, mut rx) = follow(&farm, text);
        // Wait until the job is part cast, then kill a worker that has cast some of it.
        let kill = loop {
            let status = next_status(&farm, &mut rx).unwrap_or_else(|| panic!("rep {rep}: the stream ended early"));
            if is_final(status.state()) {
                assert_eq!(status.state(), pb::JobState::Succeeded, "rep {rep}: {:?}", status.failure);
                break None;
            }
            if status.state() != pb::JobState::Running || status.pieces_done == 0 {
                continue;
            }
            let casting: Vec<&str> =
                status.workers.iter().filter(|w| w.batches > 0).map(|w| w.worker_id.as_str()).collect();
            let alive = farm.alive();
            let found = farm
                .workers
                .iter()
                .position(|w| alive.get(&w.address).is_some_and(|info| casting.contains(&info.worker_id.as_str())));
            if let Some(i) = found {
                break Some((i, status.pieces_done as f64 / status.pieces_total as f64));
            }
        };
        let Some((victim, done)) = kill else {
            let png = farm.runtime.block_on(farm.client().result(&id)).unwrap().png;
            assert!(png == expected[rep % texts.len()], "rep {rep}: the image differs from local mode's");
            eprintln!("rep {rep}: the job ended before a kill could land");
            rep += 1;
            continue;
        };
        farm.workers[victim].kill();
        done_at_kill.push(done);
        let last = finish(&farm, &mut rx);
        assert_eq!(last.state(), pb::JobState::Succeeded, "rep {rep}: {:?}", last.failure);
        with_kill.push(started.elapsed());
        let files = farm.runtime.block_on(farm.client().result(&id)).unwrap();
        assert!(files.png == expected[rep % texts.len()], "rep {rep}: the image differs from local mode's");

        // A fresh worker over the dead one's data root, so three are up for the next kill.
        farm.workers[victim] = farm.start_worker(victim);
        let addresses: Vec<String> = farm.workers.iter().map(|w| w.address.clone()).collect();
        farm.wait_for_alive(&addresses);
        rep += 1;
    }
    with_kill.sort();
    done_at_kill.sort_by(f64::total_cmp);
    eprintln!(
        "kills survived: 20 of 20 ({rep} jobs); a job took {:?} median unharmed ({:?} .. {:?}), {:?} median with a kill \
         ({:?} .. {:?}); the kill landed with {:.0}% .. {:.0}% of the pieces done (median {:.0}%)",
        unharmed[2],
        unharmed[0],
        unharmed[3],
        with_kill[10],
        with_kill[0],
        with_kill[19],
        100.0 * done_at_kill[0],
        100.0 * done_at_kill[19],
        100.0 * done_at_kill[10]
    );
}

/// Bands a coordinator holds per job here (`--band-memory`), and jobs at once
/// (`--max-jobs`): with them its memory is bounded by configuration, not by the jobs queued.
const BAND_MEMORY: &str = "16MiB";
const MAX_JOBS: usize = 4;

/// The bound on the coordinator's peak resident memory running fifty jobs, from its
/// configuration: 32 MiB for its code, runtime and the fifty jobs' scenes, plans and
/// results (a few KiB each at these sizes; it measures ~16 MiB in all here), plus the bands
/// of the four jobs running at once (4 × 16 MiB, whatever the scenes). Memory that grew by
/// a band's worth per submitted job, or a leak of a megabyte per job, would pass it. (Before
/// admission control, twenty concurrent jobs peaked at 131 MiB.)
const PEAK_RSS_BOUND: u64 = (32 << 20) + MAX_JOBS as u64 * (16 << 20);

#[test]
fn fifty_concurrent_jobs_complete_in_queue_order_within_bounded_coordinator_memory() {
    let _serial = serial();
    let max_jobs = MAX_JOBS.to_string();
    let farm = Farm::start("faults-fifty", &["--max-jobs", &max_jobs, "--band-memory", BAND_MEMORY]);
    let texts: Vec<String> = (0..5).map(|i| scene(24 + 4 * i, "", 0.1 + 0.2 * i as f64)).collect();
    let expected: Vec<Vec<u8>> = texts.iter().map(|t| local_png(t, &farm.dir)).collect();
    let client = farm.client();

    let outcomes = farm.runtime.block_on(async {
        let tasks: Vec<_> = (0..50)
            .map(|i| {
                let (mut client, text) = (client.clone(), texts[i % texts.len()].clone());
                tokio::spawn(async move {
                    let id = client.submit(text, format!("job{i}.toml"), Default::default()).await?;
                    let mut places = Vec::new();
                    let last = client
                        .watch(&id, |s| {
                            if s.state() == pb::JobState::Queued {
                                places.push(s.queue_position);
                            }
                        })
                        .await?;
                    let png = match last.state() {
                        pb::JobState::Succeeded => client.result(&id).await?.png,
                        _ => Vec::new(),
                    };
                    Ok::<_, trove_coordinator::client::ClientError>((last, places, png))
                })
            })
            .collect();
        let mut out = Vec::new();
        for task in tasks {
            out.push(tokio::time::timeout(WAIT, task).await.expect("every job within the wait"));
        }
        out
    });

    let (mut queued, mut furthest) = (0, 0);
    for (i, outcome) in outcomes.into_iter().enumerate() {
        let (last, places, png) = outcome.expect("a job's task").unwrap_or_else(|e| panic!("job {i}: {e}"));
        assert_eq!(last.state(), pb::JobState::Succeeded, "job {i}: {:?}", last.failure);
        assert!(png == expected[i % texts.len()], "job {i}: the image differs from local mode's");
        // A queued job's place is 1 (next) or more, and it only moves forward.
        assert!(places.iter().all(|&p| (1..50).contains(&p)), "job {i}: places {places:?}");
        assert!(places.windows(2).all(|w| w[1] <= w[0]), "job {i}: places went back: {places:?}");
        queued += !places.is_empty() as usize;
        furthest = furthest.max(places.first().copied().unwrap_or(0));
    }
    // Fifty at once against four slots: most of them waited, and said where (how many, and
    // how far back, depends on how fast the first ones finish while the rest are submitted).
    assert!(queued >= 25, "only {queued} of 50 jobs reported a place in the queue");
    assert!(furthest > 2 * MAX_JOBS as u32, "no job waited further back than place {furthest}");
    let peak = farm.coordinator_peak_rss();
    eprintln!(
        "50 concurrent jobs completed; {queued} reported queue places, the furthest back {furthest}; coordinator \
         VmHWM {} MiB",
        peak >> 20
    );
    assert!(peak < PEAK_RSS_BOUND, "the coordinator peaked at {} MiB", peak >> 20);
}

/// `trove render --coordinator` of `text` (written as `name` in `dir`) to `output`.
fn cli_render(dir: &Path, url: &str, name: &str, text: &str, output: &str) -> std::process::Output {
    std::fs::write(dir.join(name), text).unwrap();
    Command::new(trove())
        .args(["render", name, "-o", output, "--coordinator", url])
        .current_dir(dir)
        .env_remove("TROVE_DATA")
        .output()
        .unwrap()
}

#[test]
fn hostile_scenes_through_the_cli_are_refused_naming_the_limit_and_the_coordinator_serves_on() {
    let _serial = serial();
    let farm = Farm::start("faults-hostile", &[]);
    let dir = farm.dir.to_path_buf();
    let huge_pfm = scene(16384, "", 0.5);
    let hostile: [(&str, String, &str, &str); 4] = [
        ("nested.toml", nested_boxes(300, 512, "1e9"), "out.png", "limit on piece tasks per render is 536870912"),
        ("many.toml", many_objects(4096, 8192), "out.png", "limit on ray–object tests per render"),
        ("tiny.toml", scene(64, "sampling_distance = 1e-9", 0.5), "out.png", "objects[0].sampling_distance"),
        ("pfm.toml", huge_pfm, "out.pfm", "limit on PFM pixels"),
    ];
    let good = scene(24, "", 0.7);
    let expected = local_png(&good, &dir);
    for (name, text, output, limit) in &hostile {
        let started = Instant::now();
        let out = cli_render(&dir, &farm.url, name, text, output);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{name} rendered");
        assert!(stderr.contains(limit) && stderr.contains(name), "{name}: the message names no limit: {stderr}");
        assert!(started.elapsed() < WAIT, "{name}: refusing took {:?}", started.elapsed());
        assert!(!dir.join(output).exists(), "{name}: an output was written");
        // The coordinator is up, and renders the next scene as local mode does.
        let out = cli_render(&dir, &farm.url, "good.toml", &good, "good.png");
        assert!(out.status.success(), "after {name}: {}", String::from_utf8_lossy(&out.stderr));
        assert!(std::fs::read(dir.join("good.png")).unwrap() == expected, "after {name}: the image differs");
        std::fs::remove_file(dir.join("good.png")).unwrap();
    }
    assert_eq!(farm.alive().len(), 3, "every worker still registered");
}
