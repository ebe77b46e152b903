//! A whole farm in this process: a coordinator and workers on `127.0.0.1:0`, each worker
//! over its own data root, driven through the same client a user's `trove render
//! --coordinator` uses. Dropping the farm shuts every server down. [`FarmOptions`] give it
//! tokens, TLS and a stream cap, as an operator's flags would. [`SharedFarm`] is several
//! coordinators sharing one pool of workers.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::oneshot;
use trove_coordinator::client::{ClientError, FarmClient, JobFiles};
use trove_coordinator::farm::{self, DriverConfig, FarmConfig, FarmSecurity};
use trove_proto::auth::Token;
use trove_proto::connect::Connector;
use trove_proto::tls::{CaCert, ServerTls};
use trove_proto::v1 as pb;
use trove_worker::metrics::WorkerMetrics;
use trove_worker::{WorkerConfig, WorkerSecurity};

/// A running in-process farm.
pub struct TestFarm {
    /// The coordinator's URL (`https://` with TLS).
    pub url: String,
    runtime: tokio::runtime::Runtime,
    coordinator: Option<oneshot::Sender<()>>,
    workers: Vec<Option<oneshot::Sender<()>>>,
    /// How [`TestFarm::client`] connects: the CA and the client token.
    connector: Connector,
    /// What [`TestFarm::add_worker`] gives each worker.
    worker_security: WorkerSecurity,
    max_streams: usize,
    /// A scratch folder the farm's data roots lie in, removed after the farm (the last
    /// field, so dropped after the runtime has stopped every server).
    scratch: Option<crate::Scratch>,
}

/// TLS for a test farm: one certificate (for `127.0.0.1`) that the coordinator and every
/// worker serve, and the CA that signed it, which every side trusts.
#[derive(Clone, Debug)]
pub struct TestTls {
    /// The CA.
    pub ca: CaCert,
    /// The servers' certificate and key.
    pub server: ServerTls,
}

/// How a test farm runs, beyond its data roots.
#[derive(Clone, Debug)]
pub struct FarmOptions {
    /// The coordinator's configuration (its `security` is set from the fields below).
    pub config: FarmConfig,
    /// Every worker's memory budget.
    pub budget: Option<u64>,
    /// Required by the coordinator's job API; the farm's client presents it.
    pub client_token: Option<Token>,
    /// Required by the coordinator's membership and every worker's casts; the workers and
    /// the coordinator present it.
    pub worker_token: Option<Token>,
    /// TLS on every connection.
    pub tls: Option<TestTls>,
    /// Every worker's stream cap.
    pub max_streams: usize,
}

impl Default for FarmOptions {
    fn default() -> Self {
        FarmOptions {
            config: FarmConfig { heartbeat: TEST_HEARTBEAT, ..FarmConfig::default() },
            budget: None,
            client_token: None,
            worker_token: None,
            tls: None,
            max_streams: trove_worker::cast::DEFAULT_MAX_STREAMS,
        }
    }
}

/// The longest a test waits for one render through the farm.
pub const RENDER_DEADLINE: Duration = Duration::from_secs(120);

/// Heartbeats in tests: fast, so a stopped worker is noticed within a second.
pub const TEST_HEARTBEAT: Duration = Duration::from_millis(100);

impl TestFarm {
    /// This farm, holding `scratch` (where its data roots lie) until it is dropped.
    pub fn holding(mut self, scratch: crate::Scratch) -> TestFarm {
        self.scratch = Some(scratch);
        self
    }

    /// A coordinator and one worker per data root; returns once every worker is registered.
    pub fn start(roots: &[PathBuf]) -> TestFarm {
        TestFarm::start_with(roots, FarmConfig { heartbeat: TEST_HEARTBEAT, ..FarmConfig::default() }, None)
    }

    /// As [`TestFarm::start`], with a coordinator configuration and a worker memory budget.
    pub fn start_with(roots: &[PathBuf], config: FarmConfig, budget: Option<u64>) -> TestFarm {
        TestFarm::start_opts(roots, FarmOptions { config, budget, ..FarmOptions::default() })
    }

    /// As [`TestFarm::start`], with every option.
    pub fn start_opts(roots: &[PathBuf], options: FarmOptions) -> TestFarm {
        let FarmOptions { mut config, budget, client_token, worker_token, tls, max_streams } = options;
        config.security = FarmSecurity {
            tls: tls.as_ref().map(|t| t.server.clone()),
            worker_ca: tls.as_ref().map(|t| t.ca.clone()),
            client_token: client_token.clone(),
            worker_token: worker_token.clone(),
        };
        let connector = Connector::new(tls.as_ref().map(|t| t.ca.clone()), client_token);
        let worker_security = WorkerSecurity {
            token: worker_token,
            tls: tls.as_ref().map(|t| t.server.clone()),
            coordinator_ca: tls.as_ref().map(|t| t.ca.clone()),
        };
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .expect("a tokio runtime");
        let (url, coordinator) = runtime.block_on(async {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind the coordinator");
            let url = connector.url_for(&listener.local_addr().expect("address").to_string());
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
        let mut farm = TestFarm {
            url,
            runtime,
            coordinator: Some(coordinator),
            workers: Vec::new(),
            connector,
            worker_security,
            max_streams,
            scratch: None,
        };
        for root in roots {
            farm.add_worker(root, budget);
        }
        farm.wait_for_workers(roots.len());
        farm
    }

    /// What [`TestFarm::add_worker`] runs a worker over `root` with: this farm's
    /// coordinator, credentials and stream cap.
    pub fn worker_config(&self, root: &Path, memory_budget: Option<u64>) -> WorkerConfig {
        WorkerConfig {
            memory_budget,
            security: self.worker_security.clone(),
            max_streams: self.max_streams,
            ..WorkerConfig::new(self.url.clone(), root)
        }
    }

    /// Starts another worker over `root`.
    pub fn add_worker(&mut self, root: &Path, memory_budget: Option<u64>) {
        let config = self.worker_config(root, memory_budget);
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

    /// The addresses of the workers the coordinator lists.
    pub fn worker_addresses(&self) -> Vec<String> {
        let workers = self.block_on(async { self.client().await.workers().await }).expect("list the workers");
        workers.into_iter().map(|w| w.address).collect()
    }

    /// A client of this farm, with its CA and client token.
    pub async fn client(&self) -> FarmClient {
        FarmClient::connect_with(&self.url, &self.connector).await.expect("connect to the test coordinator")
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
    spawn_server_with_env(program, args, &[], stderr)
}

/// As [`spawn_server`], with `env` added to the server's environment (e.g. `RUST_LOG`).
pub fn spawn_server_with_env(
    program: &Path,
    args: &[&str],
    env: &[(&str, &str)],
    stderr: std::process::Stdio,
) -> std::io::Result<(std::process::Child, String)> {
    use std::io::BufRead;
    let mut child = std::process::Command::new(program)
        .args(args)
        .envs(env.iter().copied())
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

/// Several coordinators sharing one pool of workers, each worker registered with all of them
/// (`trove-worker --coordinator A --coordinator B`): each coordinator owns the jobs
/// submitted to it, and every worker casts for all of them. A coordinator can be stopped and
/// started again on its address while the others go on. Dropping the farm shuts every
/// server down.
pub struct SharedFarm {
    /// Each coordinator's URL.
    pub urls: Vec<String>,
    /// Each worker's metrics (batches answered, batches refused as busy).
    pub worker_metrics: Vec<Arc<WorkerMetrics>>,
    runtime: tokio::runtime::Runtime,
    config: FarmConfig,
    coordinators: Vec<Option<RunningCoordinator>>,
    workers: Vec<Option<oneshot::Sender<()>>>,
}

/// A coordinator of a [`SharedFarm`]: what stops it, and its task.
struct RunningCoordinator {
    stop: oneshot::Sender<()>,
    task: tokio::task::JoinHandle<()>,
}

impl SharedFarm {
    /// `coordinators` coordinators and one worker per data root, each worker registered with
    /// every coordinator and holding at most `max_batches` batches (`None`: the default);
    /// returns once every coordinator lists every worker alive.
    pub fn start(coordinators: usize, roots: &[PathBuf], max_batches: Option<usize>) -> SharedFarm {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .expect("a tokio runtime");
        // A worker that refused a job's batch as busy counts as full for that job until it
        // answers one of the job's batches or the driver's next tick: a tick shorter than the
        // tests' jobs (a few hundred milliseconds) lets a refused worker back in within them.
        let driver = DriverConfig { tick: Duration::from_millis(20), ..DriverConfig::default() };
        let config = FarmConfig { heartbeat: TEST_HEARTBEAT, driver, ..FarmConfig::default() };
        let mut farm = SharedFarm {
            urls: Vec::new(),
            worker_metrics: Vec::new(),
            runtime,
            config,
            coordinators: Vec::new(),
            workers: Vec::new(),
        };
        for _ in 0..coordinators {
            let listener = farm.runtime.block_on(tokio::net::TcpListener::bind("127.0.0.1:0")).expect("bind");
            farm.urls.push(format!("http://{}", listener.local_addr().expect("address")));
            let running = farm.run_coordinator(listener);
            farm.coordinators.push(Some(running));
        }
        for root in roots {
            let mut config = WorkerConfig::new(farm.urls[0].clone(), root);
            config.coordinators = farm.urls.clone();
            if let Some(n) = max_batches {
                config.max_batches = n;
            }
            farm.worker_metrics.push(config.metrics.clone());
            let tx = farm.runtime.block_on(async {
                let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind a worker");
                let (tx, rx) = oneshot::channel::<()>();
                tokio::spawn(async move {
                    let stopped = async {
                        let _ = rx.await;
                    };
                    if let Err(e) = trove_worker::run(listener, stopped, config).await {
                        eprintln!("worker stopped: {e}");
                    }
                });
                tx
            });
            farm.workers.push(Some(tx));
        }
        for i in 0..coordinators {
            farm.wait_for_workers(i, roots.len());
        }
        farm
    }

    fn run_coordinator(&self, listener: tokio::net::TcpListener) -> RunningCoordinator {
        let config = self.config.clone();
        let (stop, stopped) = oneshot::channel::<()>();
        let task = self.runtime.spawn(async move {
            let stopped = async {
                let _ = stopped.await;
            };
            if let Err(e) = farm::run(listener, stopped, config).await {
                eprintln!("coordinator stopped: {e}");
            }
        });
        RunningCoordinator { stop, task }
    }

    /// Stops coordinator `i` and waits until it has (it holds no job: its drain is at once);
    /// its workers go on serving the others and keep trying to reach it.
    pub fn stop_coordinator(&mut self, i: usize) {
        let running = self.coordinators[i].take().expect("coordinator running");
        let _ = running.stop.send(());
        self.runtime
            .block_on(async { tokio::time::timeout(Duration::from_secs(30), running.task).await })
            .expect("the coordinator stops within 30 s")
            .expect("the coordinator's task");
    }

    /// Starts coordinator `i` again on its address, empty: its workers register again when
    /// their next heartbeat is answered "unknown".
    pub fn restart_coordinator(&mut self, i: usize) {
        assert!(self.coordinators[i].is_none(), "coordinator {i} is running");
        let address = self.urls[i].trim_start_matches("http://").to_string();
        let listener = self.runtime.block_on(tokio::net::TcpListener::bind(&address)).expect("bind the same address");
        self.coordinators[i] = Some(self.run_coordinator(listener));
    }

    /// Waits until coordinator `i` lists `n` alive workers (at most ten seconds).
    pub fn wait_for_workers(&self, i: usize, n: usize) {
        let started = Instant::now();
        loop {
            let alive = self.workers(i).map(|w| w.iter().filter(|w| w.alive).count()).unwrap_or(0);
            if alive >= n {
                return;
            }
            assert!(
                started.elapsed() < Duration::from_secs(10),
                "coordinator {i}: only {alive} of {n} workers registered"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// The workers coordinator `i` lists, with its counts of their batches.
    pub fn workers(&self, i: usize) -> Result<Vec<pb::WorkerInfo>, ClientError> {
        self.block_on(async { self.client(i).await?.workers().await })
    }

    /// A client of coordinator `i`.
    pub async fn client(&self, i: usize) -> Result<FarmClient, ClientError> {
        FarmClient::connect(&self.urls[i]).await
    }

    /// Runs a future on the farm's runtime.
    pub fn block_on<F: std::future::Future>(&self, f: F) -> F::Output {
        self.runtime.block_on(f)
    }

    /// Renders each (coordinator, scene text, name) at once, each through its coordinator, as
    /// `trove render --coordinator` does; every job must end within [`RENDER_DEADLINE`].
    pub fn render_at_once(
        &self,
        jobs: &[(usize, String, String, pb::JobOptions)],
    ) -> Vec<Result<JobFiles, ClientError>> {
        self.block_on(async {
            let renders = jobs.iter().map(|(i, text, name, options)| {
                let (text, name, options) = (text.clone(), name.clone(), *options);
                let url = self.urls[*i].clone();
                tokio::spawn(async move {
                    let mut client = FarmClient::connect(&url).await?;
                    client.render(text, name, options, |_| {}).await
                })
            });
            let handles: Vec<_> = renders.collect();
            let mut out = Vec::with_capacity(handles.len());
            for handle in handles {
                let files = tokio::time::timeout(RENDER_DEADLINE, handle)
                    .await
                    .unwrap_or_else(|_| panic!("no result within {RENDER_DEADLINE:?}"))
                    .expect("the render task");
                out.push(files);
            }
            out
        })
    }
}

impl Drop for SharedFarm {
    fn drop(&mut self) {
        for w in self.workers.iter_mut() {
            if let Some(tx) = w.take() {
                let _ = tx.send(());
            }
        }
        for c in self.coordinators.iter_mut() {
            if let Some(running) = c.take() {
                let _ = running.stop.send(());
            }
        }
    }
}
