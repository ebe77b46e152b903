//! Operating a farm: the real `trove jobs`, `trove jobs result`, `trove workers` and `trove
//! cancel` against an in-process farm (their text, their `--json`, their errors for an
//! unknown job and an unreachable coordinator); the Prometheus page after a render; gRPC
//! health, a worker NOT_SERVING until it has registered; and server reflection.

use std::io::{Read, Write};
use std::path::Path;
use std::process::{Command, Output};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;
use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
use tonic_reflection::pb::v1::ServerReflectionRequest;
use trove_coordinator::farm::metrics::FarmMetrics;
use trove_coordinator::farm::{self, DriverConfig, FarmConfig};
use trove_proto::v1 as pb;
use trove_tests::farm::{data_root, TestFarm, TEST_HEARTBEAT};
use trove_tests::scenes::ball;
use trove_tests::scratch;
use trove_worker::metrics::WorkerMetrics;
use trove_worker::WorkerConfig;

fn trove() -> &'static Path {
    Path::new(env!("CARGO_BIN_EXE_trove"))
}

/// Runs `trove args`, bounded: a command that hangs fails the test instead.
fn run(args: &[&str]) -> Output {
    let mut child = Command::new(trove())
        .args(args)
        .env("RUST_BACKTRACE", "1")
        .env_remove("RUST_LOG")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("run trove");
    let started = Instant::now();
    while child.try_wait().expect("wait for trove").is_none() {
        if started.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            panic!("trove {args:?} ran past a minute");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    child.wait_with_output().expect("trove's output")
}

fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// A successful run's standard output.
#[track_caller]
fn ok(out: Output) -> String {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "expected success, got {:?}; stderr: {err}", out.status);
    stdout(&out)
}

/// A failed run: non-zero exit, one `error:` paragraph on stderr containing every needle.
#[track_caller]
fn failed(out: Output, needles: &[&str]) -> String {
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(1), "expected a clean failure; stderr: {err}");
    assert!(err.starts_with("error: ") && !err.contains("panicked"), "{err}");
    for n in needles {
        assert!(err.contains(n), "stderr lacks {n:?}: {err}");
    }
    err
}

fn config() -> FarmConfig {
    FarmConfig { heartbeat: TEST_HEARTBEAT, ..FarmConfig::default() }
}

/// A farm of one worker over an empty root.
fn one_worker_farm(name: &str, config: FarmConfig) -> TestFarm {
    let dir = scratch(name);
    TestFarm::start_with(&[data_root(&dir.join("w0"), &dir, &[])], config, None).holding(dir)
}

/// A loopback URL nothing listens on (a port bound, then let go).
fn dead_url() -> String {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    let url = format!("http://{}", listener.local_addr().unwrap());
    drop(listener);
    url
}

#[test]
fn jobs_workers_and_results_are_listed_and_fetched_and_unknown_jobs_named() {
    let dir = scratch("ops-cli");
    let farm = one_worker_farm("ops-cli-farm", config());
    let url = farm.url.clone();
    let text = ball(16, "");
    let files = farm.render(&text, "scenes/ball.toml", false).expect("render");
    let id = ok(run(&["jobs", "--coordinator", &url, "--json"]));
    let jobs: serde_json::Value = serde_json::from_str(&id).expect("jobs --json is JSON");
    let jobs = jobs.as_array().expect("an array");
    assert_eq!(jobs.len(), 1, "{jobs:?}");
    let job = &jobs[0];
    let id = job["job_id"].as_str().expect("an id").to_string();
    assert_eq!(job["state"], "succeeded");
    assert_eq!(job["scene_name"], "scenes/ball.toml");
    assert_eq!(job["queue_position"], 0);
    let (done, total) = (job["pieces_done"].as_u64().unwrap(), job["pieces_total"].as_u64().unwrap());
    assert!(total > 0 && done == total, "{job}");
    assert!(job["age_s"].as_f64().is_some_and(|a| (0.0..60.0).contains(&a)), "{job}");

    // The table: a header and the job's line, its columns aligned under it.
    let table = ok(run(&["jobs", "--coordinator", &url]));
    let lines: Vec<&str> = table.lines().collect();
    assert_eq!(lines.len(), 2, "{table}");
    for column in ["ID", "STATE", "SCENE", "PROGRESS", "QUEUE", "AGE"] {
        assert!(lines[0].contains(column), "{table}");
    }
    assert!(lines[1].starts_with(&id) && lines[1].contains("succeeded") && lines[1].contains("scenes/ball.toml"));
    assert!(lines[1].contains(&format!("{total}/{total} (100%)")), "{table}");
    assert_eq!(lines[0].find("STATE"), lines[1].find("succeeded"), "{table}");

    let workers = ok(run(&["workers", "--coordinator", &url, "--json"]));
    let workers: serde_json::Value = serde_json::from_str(&workers).expect("workers --json is JSON");
    assert_eq!(workers.as_array().map(Vec::len), Some(1), "{workers}");
    assert_eq!(workers[0]["alive"], true);
    assert!(workers[0]["batches_done"].as_u64().unwrap() > 0, "{workers}");
    let table = ok(run(&["workers", "--coordinator", &url]));
    assert!(table.lines().next().unwrap().starts_with("ID") && table.contains("alive"), "{table}");

    // The result, fetched later, is the render's, byte for byte.
    let (png, stats) = (dir.join("again.png"), dir.join("again.json"));
    let (png_s, stats_s) = (png.to_str().unwrap(), stats.to_str().unwrap());
    ok(run(&["jobs", "result", &id, "-o", png_s, "--stats", stats_s, "--coordinator", &url]));
    assert!(std::fs::read(&png).unwrap() == files.png, "the fetched PNG differs");
    assert_eq!(std::fs::read(&stats).unwrap(), files.stats_json);
    // It kept no PFM, and says so naming the job.
    let pfm = dir.join("again.pfm");
    failed(run(&["jobs", "result", &id, "-o", pfm.to_str().unwrap(), "--coordinator", &url]), &[&id, "kept no PFM"]);
    assert!(!pfm.exists());

    // Unknown jobs are named.
    failed(run(&["jobs", "result", "job-nope", "-o", png_s, "--coordinator", &url]), &["no job `job-nope`"]);
    failed(run(&["cancel", "job-nope", "--coordinator", &url]), &["no job `job-nope`"]);
    // A finished job is left as it was.
    let said = ok(run(&["cancel", &id, "--coordinator", &url]));
    assert!(said.contains("already succeeded"), "{said}");
}

#[test]
fn an_unreachable_coordinator_fails_every_command_naming_its_url() {
    let url = dead_url();
    let out = std::env::temp_dir().join("trove-ops-unreachable.png");
    let out = out.to_str().unwrap();
    for args in [
        vec!["jobs", "--coordinator", &url],
        vec!["jobs", "--coordinator", &url, "--json"],
        vec!["workers", "--coordinator", &url],
        vec!["cancel", "job-1", "--coordinator", &url],
        vec!["jobs", "result", "job-1", "-o", out, "--coordinator", &url],
    ] {
        let err = failed(run(&args), &["cannot reach", &url]);
        assert!(!err.contains("\n\n"), "{err}");
    }
    // Without a URL, the command is refused naming the flag.
    let missing = run(&["workers"]);
    assert!(!missing.status.success());
    assert!(String::from_utf8_lossy(&missing.stderr).contains("--coordinator"));
}

#[test]
fn a_queued_and_a_running_job_are_listed_in_order_and_cancelled() {
    let farm = one_worker_farm("ops-cancel", FarmConfig { max_jobs: 1, ..config() });
    let url = farm.url.clone();
    // Slow enough to be running while the commands below run (cubic at a fine step).
    let slow = ball(160, "interpolation = \"cubic\"\nsampling_distance = 0.002");
    let ids = farm.block_on(async {
        let mut client = farm.client().await;
        let first = client.submit(slow, "slow.toml".into(), Default::default()).await.unwrap();
        let second = client.submit(ball(8, ""), "waiting.toml".into(), Default::default()).await.unwrap();
        [first, second]
    });
    let listed: serde_json::Value = serde_json::from_str(&ok(run(&["jobs", "--coordinator", &url, "--json"]))).unwrap();
    let listed: Vec<(&str, &str, u64)> = listed
        .as_array()
        .unwrap()
        .iter()
        .map(|j| (j["job_id"].as_str().unwrap(), j["state"].as_str().unwrap(), j["queue_position"].as_u64().unwrap()))
        .collect();
    assert_eq!(listed, [(ids[0].as_str(), "running", 0), (ids[1].as_str(), "queued", 1)]);
    let said = ok(run(&["cancel", &ids[1], "--coordinator", &url]));
    assert!(said.starts_with(&format!("{}: cancel requested", ids[1])), "{said}");
    let said = ok(run(&["cancel", &ids[0], "--coordinator", &url, "--json"]));
    let said: serde_json::Value = serde_json::from_str(&said).unwrap();
    assert_eq!(said["job_id"], ids[0].as_str());
    // Both end cancelled, the running one within a batch.
    farm.block_on(async {
        let mut client = farm.client().await;
        for id in &ids {
            let last = tokio::time::timeout(Duration::from_secs(60), client.watch(id, |_| {}))
                .await
                .expect("the job ends")
                .unwrap();
            assert_eq!(last.state(), pb::JobState::Cancelled, "{id}");
        }
    });
    let table = ok(run(&["jobs", "--coordinator", &url]));
    assert_eq!(table.matches("cancelled").count(), 2, "{table}");
}

/// `GET /metrics` from `address`, over one plain HTTP/1.1 connection.
fn scrape(address: std::net::SocketAddr) -> String {
    let mut stream = std::net::TcpStream::connect(address).expect("connect to the metrics port");
    stream.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    stream.write_all(b"GET /metrics HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n").unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).expect("read the page");
    let (head, body) = response.split_once("\r\n\r\n").expect("a header and a body");
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    assert!(head.to_ascii_lowercase().contains("content-type: application/openmetrics-text"), "{head}");
    body.to_string()
}

/// The value of the sample `name` (with its labels, as written) on `page`.
fn sample(page: &str, name: &str) -> f64 {
    page.lines()
        .find_map(|l| l.strip_prefix(name).and_then(|rest| rest.strip_prefix(' ')))
        .unwrap_or_else(|| panic!("no `{name}` on the page:\n{page}"))
        .trim()
        .parse()
        .unwrap_or_else(|e| panic!("`{name}`: {e}"))
}

#[test]
fn metrics_count_a_renders_pieces_and_jobs_and_the_workers_cast() {
    let metrics = Arc::new(FarmMetrics::new());
    let config =
        FarmConfig { driver: DriverConfig { metrics: metrics.clone(), ..DriverConfig::default() }, ..config() };
    let farm = TestFarm::start_with(&[], config, None);
    let dir = scratch("ops-metrics");
    let worker_metrics = Arc::new(WorkerMetrics::new());
    let (address, worker_address) = farm.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap();
        tokio::spawn(farm::metrics::serve(listener, std::future::pending(), metrics.clone()));
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let worker_address = listener.local_addr().unwrap();
        tokio::spawn(trove_worker::metrics::serve(listener, std::future::pending(), worker_metrics.clone()));
        (address, worker_address)
    });
    let before = scrape(address);
    assert_eq!(sample(&before, "trove_jobs{state=\"succeeded\"}"), 0.0);
    assert_eq!(sample(&before, "trove_pieces_cast_total"), 0.0);
    assert_eq!(sample(&before, "trove_workers_registered"), 0.0);
    let worker = start_worker(&farm, &dir.join("w0"), worker_metrics.clone());
    farm.wait_for_workers(1);

    let files = farm.render(&ball(24, ""), "ball.toml", false).expect("render");
    let stats: serde_json::Value = serde_json::from_slice(&files.stats_json).unwrap();
    let cast: u64 = stats["workers"].as_array().unwrap().iter().map(|w| w["tasks"].as_u64().unwrap()).sum();
    assert!(cast > 0);
    let page = scrape(address);
    assert_eq!(sample(&page, "trove_pieces_cast_total"), cast as f64, "{page}");
    assert_eq!(sample(&page, "trove_batches_total"), stats["batches"].as_f64().unwrap());
    assert_eq!(sample(&page, "trove_batch_latency_seconds_count"), stats["batches"].as_f64().unwrap());
    assert_eq!(sample(&page, "trove_jobs{state=\"succeeded\"}"), 1.0);
    assert_eq!(sample(&page, "trove_jobs{state=\"running\"}"), 0.0);
    assert_eq!(sample(&page, "trove_workers_registered"), 1.0);
    assert_eq!(sample(&page, "trove_workers_alive"), 1.0);
    let to = stats["wire_bytes_to_workers"].as_f64().unwrap();
    assert_eq!(sample(&page, "trove_wire_bytes_total{direction=\"to_workers\"}"), to);
    let from = stats["wire_bytes_from_workers"].as_f64().unwrap();
    assert_eq!(sample(&page, "trove_wire_bytes_total{direction=\"from_workers\"}"), from);
    assert!(sample(&page, "trove_dispatch_busy_seconds_total") > 0.0, "{page}");

    // The worker counted the same pieces, and holds the ball's voxels.
    let page = scrape(worker_address);
    assert_eq!(sample(&page, "trove_worker_pieces_cast_total"), cast as f64, "{page}");
    assert_eq!(sample(&page, "trove_worker_batches_total"), stats["batches"].as_f64().unwrap());
    assert!(sample(&page, "trove_worker_casting_seconds_total") > 0.0);
    assert!(sample(&page, "trove_worker_resident_bytes") >= (24 * 24 * 24 * 4) as f64, "{page}");
    // The job's streams closed with it.
    let open = wait_until(|| sample(&scrape(worker_address), "trove_worker_streams_open") == 0.0);
    assert!(open, "a stream still open after the job");
    drop(worker);
}

/// Polls `f` every 20 ms for up to ten seconds.
fn wait_until(mut f: impl FnMut() -> bool) -> bool {
    let started = Instant::now();
    while started.elapsed() < Duration::from_secs(10) {
        if f() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    false
}

/// A worker of `farm`'s coordinator over an empty root, counting into `metrics`; it stops
/// when the sender is dropped. Returns the sender and the worker's URL.
fn start_worker(
    farm: &TestFarm,
    root: &Path,
    metrics: Arc<WorkerMetrics>,
) -> (tokio::sync::oneshot::Sender<()>, String) {
    start_worker_of(farm, &farm.url, root, metrics)
}

fn start_worker_of(
    farm: &TestFarm,
    coordinator: &str,
    root: &Path,
    metrics: Arc<WorkerMetrics>,
) -> (tokio::sync::oneshot::Sender<()>, String) {
    std::fs::create_dir_all(root).unwrap();
    let config = WorkerConfig { metrics, ..WorkerConfig::new(coordinator, root) };
    farm.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        tokio::spawn(trove_worker::run(
            listener,
            async {
                let _ = rx.await;
            },
            config,
        ));
        (tx, url)
    })
}

/// A channel to the server at `url`.
async fn channel(url: &str) -> tonic::transport::Channel {
    let endpoint = tonic::transport::Endpoint::from_shared(url.to_string()).expect("a URL");
    endpoint.timeout(Duration::from_secs(10)).connect().await.unwrap_or_else(|e| panic!("connect to {url}: {e}"))
}

/// The health of `service` ("" for the server as a whole) at `url`.
async fn health(url: &str, service: &str) -> ServingStatus {
    let mut client = HealthClient::new(channel(url).await);
    let request = HealthCheckRequest { service: service.to_string() };
    client.check(request).await.expect("a health answer").into_inner().status()
}

#[test]
fn a_worker_is_not_serving_until_it_has_registered_and_the_coordinator_serves() {
    // A coordinator's port that takes connections but serves nothing yet: the worker cannot
    // register until the coordinator below starts on it.
    let farm = TestFarm::start_with(&[], config(), None);
    let (listener, coordinator) = farm.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        (listener, url)
    });
    let dir = scratch("ops-health");
    let (_stop, worker) = start_worker_of(&farm, &coordinator, &dir.join("w0"), Arc::default());
    let statuses = farm.block_on(async {
        let mut seen = Vec::new();
        // Answered throughout: the worker serves health before it is registered.
        for _ in 0..5 {
            seen.push((health(&worker, "").await, health(&worker, "trove.v1.Worker").await));
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        seen
    });
    assert!(statuses.iter().all(|s| *s == (ServingStatus::NotServing, ServingStatus::NotServing)), "{statuses:?}");

    let (stop_coordinator, stopped) = tokio::sync::oneshot::channel::<()>();
    farm.block_on(async {
        tokio::spawn(farm::run(
            listener,
            async {
                let _ = stopped.await;
            },
            config(),
        ));
    });
    let serving = farm.block_on(async {
        let started = Instant::now();
        while started.elapsed() < Duration::from_secs(20) {
            if health(&worker, "").await == ServingStatus::Serving {
                return true;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        false
    });
    assert!(serving, "the worker never reported SERVING after its coordinator came up");
    farm.block_on(async {
        assert_eq!(health(&worker, "trove.v1.Worker").await, ServingStatus::Serving);
        for service in ["", "trove.v1.Coordinator", "trove.v1.Membership"] {
            assert_eq!(health(&coordinator, service).await, ServingStatus::Serving, "coordinator `{service}`");
        }
        // The coordinator lists the worker it let in.
        let mut client = trove_coordinator::client::FarmClient::connect(&coordinator).await.unwrap();
        assert_eq!(client.workers().await.unwrap().len(), 1);
    });
    drop(stop_coordinator);
}

/// The services reflection lists at `url`, and the file it describes `symbol` with.
async fn reflect(url: &str, symbol: &str) -> (Vec<String>, Vec<u8>) {
    let mut client = ServerReflectionClient::new(channel(url).await);
    let requests = [MessageRequest::ListServices(String::new()), MessageRequest::FileContainingSymbol(symbol.into())]
        .map(|m| ServerReflectionRequest { host: String::new(), message_request: Some(m) });
    let mut answers = client.server_reflection_info(tokio_stream::iter(requests)).await.unwrap().into_inner();
    let (mut services, mut file) = (Vec::new(), Vec::new());
    while let Some(answer) = answers.message().await.unwrap() {
        match answer.message_response.expect("an answer") {
            MessageResponse::ListServicesResponse(list) => services.extend(list.service.into_iter().map(|s| s.name)),
            MessageResponse::FileDescriptorResponse(files) => file = files.file_descriptor_proto.concat(),
            other => panic!("unexpected reflection answer {other:?}"),
        }
    }
    (services, file)
}

#[test]
fn reflection_lists_and_describes_both_servers_services() {
    let dir = scratch("ops-reflection");
    let farm = TestFarm::start(&[]);
    let (_stop, worker) = start_worker(&farm, &dir.join("w0"), Arc::default());
    farm.wait_for_workers(1);
    let (services, file) = farm.block_on(reflect(&farm.url, "trove.v1.Coordinator"));
    for s in ["trove.v1.Coordinator", "trove.v1.Membership", "grpc.health.v1.Health"] {
        assert!(services.iter().any(|n| n == s), "{s} not in {services:?}");
    }
    // The descriptor is the compiled trove.proto, ListJobs and its messages included.
    let text = String::from_utf8_lossy(&file);
    for name in ["trove.proto", "ListJobs", "JobSummary", "submitted_unix_ms"] {
        assert!(text.contains(name), "the descriptor lacks {name}");
    }
    // The older protocol version, which some clients still ask for first, answers too.
    let listed: Vec<String> = farm.block_on(async {
        use tonic_reflection::pb::v1alpha::server_reflection_client::ServerReflectionClient as V1Alpha;
        use tonic_reflection::pb::v1alpha::server_reflection_request::MessageRequest as Ask;
        use tonic_reflection::pb::v1alpha::server_reflection_response::MessageResponse as Answer;
        use tonic_reflection::pb::v1alpha::ServerReflectionRequest as Request;
        let mut client = V1Alpha::new(channel(&farm.url).await);
        let ask = Request { host: String::new(), message_request: Some(Ask::ListServices(String::new())) };
        let mut answers = client.server_reflection_info(tokio_stream::iter([ask])).await.unwrap().into_inner();
        match answers.message().await.unwrap().and_then(|a| a.message_response) {
            Some(Answer::ListServicesResponse(list)) => list.service.into_iter().map(|s| s.name).collect(),
            other => panic!("unexpected v1alpha answer {other:?}"),
        }
    });
    assert!(listed.iter().any(|n| n == "trove.v1.Coordinator"), "{listed:?}");
    let (services, _) = farm.block_on(reflect(&worker, "trove.v1.Worker"));
    assert!(services.iter().any(|n| n == "trove.v1.Worker"), "{services:?}");
    assert!(services.iter().any(|n| n == "grpc.health.v1.Health"), "{services:?}");
}

/// A server binary killed when dropped, with the addresses it printed (its first lines).
struct Served {
    child: std::process::Child,
    lines: Vec<String>,
    /// Kept open: a server that wrote to a closed pipe would fail.
    _stdout: Option<std::io::BufReader<std::process::ChildStdout>>,
}

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Starts `program args` and reads the `lines` addresses it prints first (within ten
/// seconds: a server that prints fewer fails the test instead of hanging it).
fn serve(program: &Path, args: &[&str], lines: usize) -> Served {
    use std::io::BufRead;
    let child = Command::new(program)
        .args(args)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::inherit())
        .spawn()
        .unwrap_or_else(|e| panic!("start {}: {e}", program.display()));
    let mut served = Served { child, lines: Vec::new(), _stdout: None };
    let mut stdout = std::io::BufReader::new(served.child.stdout.take().expect("piped"));
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut read = Vec::new();
        for _ in 0..lines {
            let mut line = String::new();
            if stdout.read_line(&mut line).unwrap_or(0) == 0 {
                break;
            }
            read.push(line.trim().to_string());
        }
        let _ = tx.send((read, stdout));
    });
    let (read, stdout) = rx
        .recv_timeout(Duration::from_secs(10))
        .unwrap_or_else(|_| panic!("{} printed fewer than {lines} lines in 10 s", program.display()));
    assert_eq!(read.len(), lines, "{} printed only {read:?}", program.display());
    for line in &read {
        assert!(line.starts_with("127.0.0.1:"), "{} printed {line:?}", program.display());
    }
    served.lines = read;
    served._stdout = Some(stdout);
    served
}

#[test]
fn the_binaries_serve_metrics_health_and_reflection_on_the_ports_they_print() {
    let worker_binary = trove().with_file_name(format!("trove-worker{}", std::env::consts::EXE_SUFFIX));
    assert!(worker_binary.exists(), "{} is missing: run the workspace's tests", worker_binary.display());
    let dir = scratch("ops-binaries");
    std::fs::create_dir_all(dir.join("w0")).unwrap();
    let coordinator = serve(
        trove(),
        &["coordinator", "--listen", "127.0.0.1:0", "--heartbeat-ms", "100", "--metrics-listen", "127.0.0.1:0"],
        2,
    );
    let url = format!("http://{}", coordinator.lines[0]);
    let root = dir.join("w0");
    let worker = serve(
        &worker_binary,
        &[
            "--coordinator",
            &url,
            "--listen",
            "127.0.0.1:0",
            "--data-root",
            root.to_str().unwrap(),
            "--metrics-listen",
            "127.0.0.1:0",
        ],
        2,
    );
    let (metrics, worker_metrics) = (coordinator.lines[1].parse().unwrap(), worker.lines[1].parse().unwrap());
    assert!(wait_until(|| sample(&scrape(metrics), "trove_workers_alive") == 1.0), "the worker never registered");
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let worker_url = format!("http://{}", worker.lines[0]);
    let serving = runtime.block_on(async {
        let started = Instant::now();
        while started.elapsed() < Duration::from_secs(10) {
            if health(&worker_url, "").await == ServingStatus::Serving {
                return true;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        false
    });
    assert!(serving, "the registered worker never reported SERVING");
    let (services, _) = runtime.block_on(reflect(&url, "trove.v1.Coordinator"));
    assert!(services.iter().any(|s| s == "trove.v1.Coordinator"), "{services:?}");

    let scene = dir.join("ball.toml");
    std::fs::write(&scene, ball(16, "")).unwrap();
    let png = dir.join("ball.png");
    ok(run(&["render", scene.to_str().unwrap(), "-o", png.to_str().unwrap(), "--coordinator", &url]));
    let page = scrape(metrics);
    assert_eq!(sample(&page, "trove_jobs{state=\"succeeded\"}"), 1.0, "{page}");
    let cast = sample(&page, "trove_pieces_cast_total");
    assert!(cast > 0.0, "{page}");
    assert_eq!(sample(&scrape(worker_metrics), "trove_worker_pieces_cast_total"), cast);
}

/// A coordinator's `Membership` that the test makes forget its workers: while `forget` is
/// set, heartbeats are answered `known = false` and registrations refused.
struct Forgetful(Arc<std::sync::atomic::AtomicBool>);

#[tonic::async_trait]
impl pb::membership_server::Membership for Forgetful {
    async fn register(
        &self,
        _: tonic::Request<pb::RegisterRequest>,
    ) -> Result<tonic::Response<pb::RegisterResponse>, tonic::Status> {
        if self.0.load(std::sync::atomic::Ordering::SeqCst) {
            return Err(tonic::Status::unavailable("not taking workers"));
        }
        Ok(tonic::Response::new(pb::RegisterResponse { worker_id: "w1".into(), heartbeat_millis: 20 }))
    }

    async fn heartbeat(
        &self,
        _: tonic::Request<pb::HeartbeatRequest>,
    ) -> Result<tonic::Response<pb::HeartbeatResponse>, tonic::Status> {
        let known = !self.0.load(std::sync::atomic::Ordering::SeqCst);
        Ok(tonic::Response::new(pb::HeartbeatResponse { known }))
    }

    async fn deregister(
        &self,
        _: tonic::Request<pb::DeregisterRequest>,
    ) -> Result<tonic::Response<pb::DeregisterResponse>, tonic::Status> {
        Ok(tonic::Response::new(pb::DeregisterResponse {}))
    }
}

#[test]
fn a_worker_the_coordinator_forgets_is_not_serving_until_it_registers_again() {
    let farm = TestFarm::start_with(&[], config(), None);
    let forget = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let coordinator = farm.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let membership = pb::membership_server::MembershipServer::new(Forgetful(forget.clone()));
        let incoming = tokio_stream::wrappers::TcpListenerStream::new(listener);
        tokio::spawn(tonic::transport::Server::builder().add_service(membership).serve_with_incoming(incoming));
        url
    });
    let dir = scratch("ops-forgotten");
    let (_stop, worker) = start_worker_of(&farm, &coordinator, &dir.join("w0"), Arc::default());
    let becomes = |wanted: ServingStatus| {
        farm.block_on(async {
            let started = Instant::now();
            while started.elapsed() < Duration::from_secs(10) {
                if health(&worker, "").await == wanted {
                    return true;
                }
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
            false
        })
    };
    assert!(becomes(ServingStatus::Serving), "never SERVING after registering");
    forget.store(true, std::sync::atomic::Ordering::SeqCst);
    assert!(becomes(ServingStatus::NotServing), "still SERVING after the coordinator forgot it");
    // Refused registrations keep it out: it stays NOT_SERVING.
    std::thread::sleep(Duration::from_millis(200));
    assert_eq!(farm.block_on(health(&worker, "trove.v1.Worker")), ServingStatus::NotServing);
    forget.store(false, std::sync::atomic::Ordering::SeqCst);
    assert!(becomes(ServingStatus::Serving), "never SERVING again after registering again");
}
