//! A whole farm in this process: a coordinator and workers on `127.0.0.1:0`, each worker
//! over its own data root, driven through the same client a user's `trove render
//! --coordinator` uses. Dropping the farm shuts every server down.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use tokio::sync::oneshot;
use trove_coordinator::client::{ClientError, FarmClient, JobFiles};
use trove_coordinator::farm::{self, FarmConfig};
use trove_proto::v1 as pb;
use trove_worker::WorkerConfig;

/// A running in-process farm.
pub struct TestFarm {
    /// The coordinator's URL.
    pub url: String,
    runtime: tokio::runtime::Runtime,
    coordinator: Option<oneshot::Sender<()>>,
    workers: Vec<Option<oneshot::Sender<()>>>,
}

/// The longest a test waits for one render through the farm.
pub const RENDER_DEADLINE: Duration = Duration::from_secs(120);

/// Heartbeats in tests: fast, so a stopped worker is noticed within a second.
pub const TEST_HEARTBEAT: Duration = Duration::from_millis(100);

impl TestFarm {
    /// A coordinator and one worker per data root; returns once every worker is registered.
    pub fn start(roots: &[PathBuf]) -> TestFarm {
        TestFarm::start_with(roots, FarmConfig { heartbeat: TEST_HEARTBEAT, ..FarmConfig::default() }, None)
    }

    /// As [`TestFarm::start`], with a coordinator configuration and a worker memory budget.
    pub fn start_with(roots: &[PathBuf], config: FarmConfig, budget: Option<u64>) -> TestFarm {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .expect("a tokio runtime");
        let (url, coordinator) = runtime.block_on(async {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind the coordinator");
            let url = format!("http://{}", listener.local_addr().expect("address"));
            let (tx, rx) = oneshot::channel::<()>();
            tokio::spawn(async move {
                let _ = farm::run(
                    listener,
                    async {
                        let _ = rx.await;
                    },
                    config,
                )
                .await;
            });
            (url, tx)
        });
        let mut farm = TestFarm { url, runtime, coordinator: Some(coordinator), workers: Vec::new() };
        for root in roots {
            farm.add_worker(root, budget);
        }
        farm.wait_for_workers(roots.len());
        farm
    }

    /// Starts another worker over `root`.
    pub fn add_worker(&mut self, root: &Path, memory_budget: Option<u64>) {
        let config = WorkerConfig {
            coordinator: self.url.clone(),
            advertise: None,
            data_root: root.to_path_buf(),
            memory_budget,
            metrics: Default::default(),
        };
        let tx = self.runtime.block_on(async {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind a worker");
            let (tx, rx) = oneshot::channel::<()>();
            tokio::spawn(async move {
                if let Err(e) = trove_worker::run(
                    listener,
                    async {
                        let _ = rx.await;
                    },
                    config,
                )
                .await
                {
                    eprintln!("worker stopped: {e}");
                }
            });
            tx
        });
        self.workers.push(Some(tx));
    }

    /// Stops worker `i` (its server shuts down; the coordinator notices missed heartbeats).
    pub fn stop_worker(&mut self, i: usize) {
        if let Some(tx) = self.workers[i].take() {
            let _ = tx.send(());
        }
    }

    /// Waits until the coordinator lists `n` alive workers (at most ten seconds).
    pub fn wait_for_workers(&self, n: usize) {
        let started = Instant::now();
        loop {
            let alive = self.workers_alive();
            if alive >= n {
                return;
            }
            assert!(started.elapsed() < Duration::from_secs(10), "only {alive} of {n} workers registered");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// How many workers the coordinator counts as alive.
    pub fn workers_alive(&self) -> usize {
        self.block_on(async { self.client().await.workers().await.map(|w| w.iter().filter(|w| w.alive).count()) })
            .unwrap_or(0)
    }

    /// A client of this farm.
    pub async fn client(&self) -> FarmClient {
        FarmClient::connect(&self.url).await.expect("connect to the test coordinator")
    }

    /// Runs a future on the farm's runtime.
    pub fn block_on<F: std::future::Future>(&self, f: F) -> F::Output {
        self.runtime.block_on(f)
    }

    /// Renders scene text through the farm, as `trove render --coordinator` does. A test
    /// must end by itself: a job that has not finished within [`RENDER_DEADLINE`] fails it.
    pub fn render(&self, scene_toml: &str, name: &str, want_pfm: bool) -> Result<JobFiles, ClientError> {
        self.render_with(scene_toml, name, pb::JobOptions { want_pfm, ..Default::default() })
    }

    /// As [`TestFarm::render`], with the job's options (band rows, batch size).
    pub fn render_with(&self, scene_toml: &str, name: &str, options: pb::JobOptions) -> Result<JobFiles, ClientError> {
        self.block_on(async {
            let render =
                async { self.client().await.render(scene_toml.to_string(), name.to_string(), options, |_| {}).await };
            tokio::time::timeout(RENDER_DEADLINE, render)
                .await
                .unwrap_or_else(|_| panic!("{name}: no result within {RENDER_DEADLINE:?}"))
        })
    }
}

impl Drop for TestFarm {
    fn drop(&mut self) {
        for w in self.workers.iter_mut() {
            if let Some(tx) = w.take() {
                let _ = tx.send(());
            }
        }
        if let Some(tx) = self.coordinator.take() {
            let _ = tx.send(());
        }
    }
}

/// A data root holding `files` (names under `from`), hard-linked where the file system
/// allows and copied otherwise: never symlinked, since a worker refuses links that leave
/// its root.
pub fn data_root(dir: &Path, from: &Path, files: &[&str]) -> PathBuf {
    std::fs::create_dir_all(dir).expect("create a data root");
    for f in files {
        let (src, dst) = (from.join(f), dir.join(f));
        if dst.exists() {
            continue;
        }
        if std::fs::hard_link(&src, &dst).is_err() {
            std::fs::copy(&src, &dst).unwrap_or_else(|e| panic!("copy {}: {e}", src.display()));
        }
    }
    dir.to_path_buf()
}

/// Starts a server binary (`trove coordinator`, `trove-worker`) and reads the address it
/// bound from its first line of stdout, which must be on loopback. Its stdout stays open
/// (a server that later wrote to a closed pipe would fail); `stderr` is where its log goes.
pub fn spawn_server(
    program: &Path,
    args: &[&str],
    stderr: std::process::Stdio,
) -> std::io::Result<(std::process::Child, String)> {
    use std::io::BufRead;
    let mut child = std::process::Command::new(program)
        .args(args)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(stderr)
        .spawn()?;
    let mut line = String::new();
    let mut stdout = std::io::BufReader::new(child.stdout.take().expect("stdout is piped"));
    stdout.read_line(&mut line)?;
    child.stdout = Some(stdout.into_inner());
    let address = line.trim().to_string();
    if !address.starts_with("127.0.0.1:") {
        let _ = child.kill();
        let _ = child.wait();
        let message = format!("{} printed {address:?} instead of its address", program.display());
        return Err(std::io::Error::other(message));
    }
    Ok((child, address))
}
