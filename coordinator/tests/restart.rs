//! The coordinator killed and restarted mid-queue, as an operator would see it: the real
//! `trove coordinator --state-dir` (one job at a time) and three `trove-worker` processes
//! with their own ids; jobs submitted through the library client and through a `trove
//! render --coordinator` process; the coordinator SIGKILLed while one job runs and others
//! wait, then started again on the same port over the same state folder. Every job
//! completes with the image local mode renders, byte for byte; every worker is registered
//! again under its id; job ids go on; a result finished before the kill is still served.
//! The recovery times are printed (BENCHMARKS.md, "Coordinator restart").

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use trove_coordinator::client::{FarmClient, JobFiles};
use trove_proto::v1 as pb;
use trove_tests::farm::spawn_server;
use trove_tests::process::{trove_worker_beside, Server};
use trove_tests::scratch;

fn trove() -> &'static Path {
    Path::new(env!("CARGO_BIN_EXE_trove"))
}

/// `trove-worker`, built beside `trove`.
fn trove_worker() -> PathBuf {
    trove_worker_beside(trove())
}

/// The longest any one wait in this test may take.
const WAIT: Duration = Duration::from_secs(40);

/// A scene over a file dataset (which only the workers hold) and a generated one; each job
/// its own size and background, so that no job's image could pass for another's.
fn scene(width: u32, height: u32, red: f64) -> String {
    generated(width, height, red) + SLAB
}

/// A dataset file and its object, added to [`generated`]'s.
const SLAB: &str = r#"
[[datasets]]
name = "slab"
dims = [4, 4, 2]
[datasets.channels.voxel]
raw = "slab.raw"
type = "u8"
[[objects]]
name = "slab"
dataset = "slab"
colour = { type = "ramp", points = [[0, 0.2, 0.3, 0.9], [255, 1, 1, 1]] }
opacity = { type = "ramp", points = [[0, 0.05], [255, 0.5]] }
transform = { matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0.1, 0.9], [0, 0, 0, 1]] }
"#;

/// A scene over a generated dataset only: any worker casts it.
fn generated(width: u32, height: u32, red: f64) -> String {
    format!(
        r#"
[image]
width = {width}
height = {height}
background = [{red}, 0.15, 0.2]
[camera]
eye = [0.5, 0.6, 3.2]
target = [0.5, 0.5, 0.5]
up = [0, 1, 0]
fov_y = 35.0
[[datasets]]
name = "ball"
dims = [20, 20, 20]
[datasets.channels.voxel]
generator = {{ kind = "sphere", radius = 0.5, profile = "radial", value = 1.0, type = "f32" }}
[[objects]]
name = "ball"
dataset = "ball"
colour = {{ type = "ramp", points = [[0.0, 0.9, 0.3, 0.1], [1.0, 0.2, 0.5, 1.0]] }}
opacity = {{ type = "ramp", points = [[0.0, 0.0], [1.0, 0.4]] }}
"#
    )
}

/// The jobs: (name, width, height, background red, tasks per batch). `slow` runs while the
/// coordinator is killed: tiny batches make it many round trips long without changing its
/// image; `process` is rendered by a `trove render --coordinator` process.
const JOBS: [(&str, u32, u32, f64, u32); 6] = [
    ("before", 40, 30, 0.10, 0),
    ("slow", 400, 300, 0.11, 4),
    ("process", 64, 48, 0.12, 0),
    ("queued-c", 48, 36, 0.13, 0),
    ("queued-d", 56, 42, 0.14, 0),
    ("after", 44, 33, 0.15, 0),
];

const WORKER_IDS: [&str; 3] = ["restart-w0", "restart-w1", "restart-w2"];

/// `job-<prefix>-<n>` split into its prefix and number.
fn id_parts(id: &str) -> (String, u64) {
    let (prefix, n) = id.rsplit_once('-').unwrap_or_else(|| panic!("job id {id} has no number"));
    (prefix.to_string(), n.parse().unwrap_or_else(|_| panic!("job id {id} does not end in a number")))
}

/// Starts the coordinator over `state` on `listen`; retried while the port is still taken
/// by the killed one's sockets.
fn start_coordinator(listen: &str, state: &Path) -> (Server, String) {
    let args = [
        "coordinator",
        "--listen",
        listen,
        "--heartbeat-ms",
        "100",
        "--max-jobs",
        "1",
        "--state-dir",
        state.to_str().unwrap(),
    ];
    let started = Instant::now();
    loop {
        match spawn_server(trove(), &args, Stdio::inherit()) {
            Ok((child, address)) => return (Server(child), address),
            Err(e) => assert!(started.elapsed() < WAIT, "the coordinator does not start on {listen}: {e}"),
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Waits until the coordinator lists exactly the workers `ids`, all alive.
async fn wait_for_workers(client: &mut FarmClient, ids: &[&str]) -> Vec<pb::WorkerInfo> {
    let started = Instant::now();
    loop {
        if let Ok(workers) = client.workers().await {
            let mut alive: Vec<&str> = workers.iter().filter(|w| w.alive).map(|w| w.worker_id.as_str()).collect();
            alive.sort_unstable();
            if alive == ids {
                return workers;
            }
            assert!(started.elapsed() < WAIT, "workers registered: {alive:?}, expected {ids:?}");
        }
        assert!(started.elapsed() < WAIT, "the coordinator does not answer ListWorkers");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// `f`, or a panic naming `what` if it takes longer than [`WAIT`].
async fn within<F: std::future::Future>(what: &str, f: F) -> F::Output {
    tokio::time::timeout(WAIT, f).await.unwrap_or_else(|_| panic!("{what}: nothing within {WAIT:?}"))
}

#[test]
fn a_coordinator_killed_mid_queue_and_restarted_loses_no_job_and_no_worker() {
    let dir = scratch("restart");
    let voxels: Vec<u8> = (0..32u8).map(|i| i * 8).collect();
    for w in 0..3 {
        std::fs::create_dir_all(dir.join(format!("w{w}"))).unwrap();
        std::fs::write(dir.join(format!("w{w}/slab.raw")), &voxels).unwrap();
    }
    for (name, w, h, red, _) in JOBS {
        std::fs::write(dir.join(format!("{name}.toml")), scene(w, h, red)).unwrap();
    }
    // The references: local mode, every scene at once.
    let locals: Vec<Child> = JOBS
        .iter()
        .map(|(name, ..)| {
            Command::new(trove())
                .args(["render", &format!("{name}.toml"), "-o", &format!("local-{name}.png"), "--data-root", "w0"])
                .current_dir(&dir)
                .env_remove("TROVE_DATA")
                .stdout(Stdio::null())
                .spawn()
                .unwrap()
        })
        .collect();
    let local = |name: &str| std::fs::read(dir.join(format!("local-{name}.png"))).unwrap();

    let state = dir.join("state");
    let (coordinator, address) = start_coordinator("127.0.0.1:0", &state);
    let url = format!("http://{address}");
    let _workers: Vec<Server> = WORKER_IDS
        .iter()
        .enumerate()
        .map(|(w, id)| {
            let root = dir.join(format!("w{w}"));
            let args = [
                "--coordinator",
                &url,
                "--listen",
                "127.0.0.1:0",
                "--data-root",
                root.to_str().unwrap(),
                "--worker-id",
                id,
            ];
            let (child, _) = spawn_server(&trove_worker(), &args, Stdio::inherit()).expect("start a worker");
            Server(child)
        })
        .collect();
    for mut child in locals {
        assert!(child.wait().unwrap().success(), "a local reference render failed");
    }

    let runtime = tokio::runtime::Runtime::new().unwrap();
    let options = |batch_tasks: u32| pb::JobOptions { batch_tasks, ..Default::default() };
    let scene_text = |name: &str| std::fs::read_to_string(dir.join(format!("{name}.toml"))).unwrap();

    let mut client = runtime.block_on(async {
        let mut client = FarmClient::connect(&url).await.expect("connect");
        wait_for_workers(&mut client, &WORKER_IDS).await;
        client
    });

    // A job that finishes before the kill: its result must outlive the coordinator.
    let (before_id, before) = runtime.block_on(async {
        let id = client.submit(scene_text("before"), "before.toml".into(), options(0)).await.expect("submit");
        let files = within("the first job", client.follow(&id, |_| {})).await;
        (id, files.expect("the first job renders"))
    });
    assert_eq!(before.png, local("before"), "{before_id}: farm and local PNGs differ");
    let (prefix, first) = id_parts(&before_id);

    // The slow job runs; then a `trove render` process's job and two more wait behind it.
    let follow = |client: &FarmClient, id: String| {
        let mut client = client.clone();
        runtime.spawn(async move {
            let files = client.follow(&id, |_| {}).await.unwrap_or_else(|e| panic!("{id}: {e}"));
            (id, files, Instant::now())
        })
    };
    let slow_id = runtime.block_on(client.submit(scene_text("slow"), "slow.toml".into(), options(4))).unwrap();
    let slow = follow(&client, slow_id.clone());
    let slow_submitted = Instant::now();
    let process_out = dir.join("farm-process.png");
    let mut process = Server(
        Command::new(trove())
            .args(["render", "process.toml", "-o", process_out.to_str().unwrap(), "--coordinator", &url])
            .current_dir(&dir)
            .env_remove("TROVE_DATA")
            .spawn()
            .unwrap(),
    );
    // Only this test submits, so the process's job is the next number.
    let process_id = format!("{prefix}-{}", first + 2);
    runtime.block_on(async {
        let started = Instant::now();
        while client.status(&process_id).await.is_err() {
            assert!(started.elapsed() < WAIT, "the render process's job {process_id} never appeared");
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    });
    let mut queued = Vec::new();
    for name in ["queued-c", "queued-d"] {
        let id = runtime.block_on(client.submit(scene_text(name), format!("{name}.toml"), options(0))).unwrap();
        queued.push((name, id.clone(), follow(&client, id)));
    }

    // Kill it while the slow job runs and the others wait.
    let statuses: Vec<pb::JobStatus> = runtime.block_on(async {
        let mut all = Vec::new();
        for id in [&slow_id, &process_id, &queued[0].1, &queued[1].1] {
            all.push(client.status(id).await.unwrap());
        }
        all
    });
    let mut coordinator = coordinator;
    coordinator.0.kill().unwrap();
    let killed = Instant::now();
    coordinator.0.wait().unwrap();
    eprintln!("killed {:.2?} after the slow job was submitted", killed.duration_since(slow_submitted));
    assert!(!slow.is_finished(), "the slow job finished before the kill");
    let states: Vec<pb::JobState> = statuses.iter().map(|s| s.state()).collect();
    assert_eq!(
        states,
        [pb::JobState::Running, pb::JobState::Queued, pb::JobState::Queued, pb::JobState::Queued],
        "the kill must find one job running and three waiting (the slow job finished too soon?)"
    );

    let (_coordinator, again) = start_coordinator(&address, &state);
    let up = killed.elapsed();
    assert_eq!(again, address);
    let running_again = runtime.block_on(within("the resumed job running", async {
        while !client.status(&slow_id).await.is_ok_and(|s| s.state() == pb::JobState::Running) {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        killed.elapsed()
    }));
    let workers = runtime.block_on(wait_for_workers(&mut client, &WORKER_IDS));
    let registered = killed.elapsed();
    assert_eq!(workers.len(), 3, "no stale entries: {workers:?}");

    // Every job completes with its local image: the followers re-attached.
    let mut finished = Vec::new();
    let (id, files, at) = runtime.block_on(within("the slow job", slow)).unwrap();
    assert_eq!(files.png, local("slow"), "{id}: the resumed job's image differs from local mode");
    finished.push(at);
    for (name, id, follower) in queued {
        let (_, files, at) = runtime.block_on(within(name, follower)).unwrap();
        assert_eq!(files.png, local(name), "{id}: the resumed job's image differs from local mode");
        finished.push(at);
    }
    let started = Instant::now();
    let exit = loop {
        if let Some(status) = process.0.try_wait().unwrap() {
            break status;
        }
        assert!(started.elapsed() < WAIT, "the trove render process did not finish");
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(exit.success(), "trove render --coordinator across the restart failed");
    assert_eq!(std::fs::read(&process_out).unwrap(), local("process"), "the render process's image differs");

    runtime.block_on(async {
        // A result from before the kill is still served, and the ids go on.
        let kept: JobFiles = client.result(&before_id).await.expect("the result from before the kill");
        assert_eq!(kept, before);
        let id = client.submit(scene_text("after"), "after.toml".into(), options(0)).await.expect("submit after");
        let (new_prefix, n) = id_parts(&id);
        assert!(new_prefix != prefix && n > first + 4, "{id} after {before_id}: ids restarted");
        let files = within("the job after the restart", client.follow(&id, |_| {})).await;
        assert_eq!(files.unwrap().png, local("after"));
    });

    let first_done = finished.iter().min().unwrap().duration_since(killed);
    let all_done = finished.iter().max().unwrap().duration_since(killed);
    eprintln!(
        "restart recovery: coordinator up {up:.2?}, 3 workers registered {registered:.2?}, resumed job running \
         {running_again:.2?}, first resumed job finished {first_done:.2?}, all 4 finished {all_done:.2?} after the kill"
    );
}

/// Jobs a store holds unfinished are resumed in order; one whose dataset no worker comes
/// back with waits out the grace (not less: workers re-register within heartbeats) and then
/// fails as its submission would have, with a typed failure the client does not retry, and
/// leaves the queue to the next, which renders what a fresh submission does.
#[test]
fn a_resumed_job_whose_dataset_never_returns_fails_after_the_grace_and_the_next_runs() {
    use trove_coordinator::farm::state::{JobRecord, StateStore};
    use trove_coordinator::farm::FarmConfig;
    use trove_tests::farm::{TestFarm, TEST_HEARTBEAT};

    let dir = scratch("resume-grace");
    let state = dir.join("state");
    let missing = scene(24, 18, 0.3);
    let generated = generated(24, 18, 0.4);
    {
        let store = StateStore::open(&state).unwrap();
        for (seq, (id, text)) in [("job-old-1", &missing), ("job-old-2", &generated)].into_iter().enumerate() {
            let status = pb::JobStatus { job_id: id.into(), state: pb::JobState::Running as i32, ..Default::default() };
            store
                .put_job(&JobRecord {
                    job_id: id.into(),
                    seq: seq as u64 + 1,
                    scene_toml: text.clone(),
                    scene_name: format!("{id}.toml"),
                    options: Some(pb::JobOptions::default()),
                    status: Some(status),
                    submitted_unix_ms: 1,
                    finished_unix_ms: 0,
                })
                .unwrap();
        }
    }
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let config = FarmConfig { heartbeat: TEST_HEARTBEAT, max_jobs: 1, state_dir: Some(state), ..FarmConfig::default() };
    let started = Instant::now();
    let farm = TestFarm::start_with(&[empty], config, None);
    farm.block_on(async {
        let mut client = farm.client().await;
        let refused = within("the resumed job", client.follow("job-old-1", |_| {})).await.unwrap_err();
        let waited = started.elapsed();
        let failure = refused.failure().unwrap_or_else(|| panic!("an untyped error: {refused}"));
        assert_eq!(failure.reason(), pb::Reason::DatasetNotHeld, "{}", failure.message);
        assert!(failure.message.contains("slab"), "{}", failure.message);
        assert!(waited >= Duration::from_millis(4500), "failed after {waited:?}, before the grace");
        let resumed = within("the next resumed job", client.follow("job-old-2", |_| {})).await.unwrap();
        let id = client.submit(generated.clone(), "fresh.toml".into(), pb::JobOptions::default()).await.unwrap();
        assert!(id.starts_with("job-") && id.ends_with("-3"), "{id}: numbers go on from the store's");
        let fresh = within("a fresh job", client.follow(&id, |_| {})).await.unwrap();
        assert_eq!(resumed.png, fresh.png, "a resumed job renders what a fresh submission does");
        // The failure was written down: a restart would not resume it again.
        assert_eq!(client.status("job-old-1").await.unwrap().state(), pb::JobState::Failed);
    });
}
