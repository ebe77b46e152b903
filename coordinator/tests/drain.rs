//! Stopping a farm's processes as Kubernetes does, with SIGTERM, against the real binaries
//! with tokens (and, for the workers' test, TLS everywhere, certificates made at run time):
//!
//! * a coordinator with a running job finishes it, refuses a job submitted meanwhile with
//!   `UNAVAILABLE`, and exits 0 within its grace;
//! * a worker mid-job deregisters, finishes what it holds and exits 0, and the job completes
//!   on the other holder with the local image.
//!
//! Jobs are held running without timing luck: a worker frozen with SIGSTOP (still alive in
//! the coordinator's eyes for a few heartbeats) keeps its part of the job waiting until it
//! is thawed with SIGCONT.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use tokio::sync::mpsc;
use trove_coordinator::client::{ClientError, FarmClient};
use trove_core::render::{render, RenderOptions};
use trove_core::scene::{DataRoot, Scene};
use trove_proto::auth::Token;
use trove_proto::connect::Connector;
use trove_proto::tls::CaCert;
use trove_proto::v1 as pb;
use trove_tests::farm::spawn_server_with_env;
use trove_tests::process::{trove_worker_beside, Server};
use trove_tests::scenes::{self, SLAB_AND_BALL as SCENE};
use trove_tests::scratch;
use trove_tests::tls::TestPki;

fn trove() -> &'static Path {
    Path::new(env!("CARGO_BIN_EXE_trove"))
}

/// `trove-worker`, built beside `trove`.
fn trove_worker() -> PathBuf {
    trove_worker_beside(trove())
}

/// Starts `program args` with its log (at `info`) in `log`; the bound address with it.
fn start(program: &Path, args: &[&str], log: &Path) -> (Server, String) {
    let file = std::fs::File::create(log).unwrap();
    let started = spawn_server_with_env(program, args, &[("RUST_LOG", "info")], Stdio::from(file));
    let (child, address) = started.unwrap_or_else(|e| panic!("start {}: {e}", program.display()));
    (Server(child), address)
}

/// The slab's data root, `dir/name`.
fn slab_root(dir: &Path, name: &str) -> PathBuf {
    scenes::slab_root(&dir.join(name))
}

fn local_png(data: &Path) -> Vec<u8> {
    let scene = Scene::parse_in(SCENE, "scene.toml", &DataRoot::Given(data.to_path_buf())).unwrap();
    render(&scene, &RenderOptions::default()).unwrap().image.encode_png().unwrap()
}

/// Writes the two token files; returns their paths (client, worker).
fn token_files(dir: &Path) -> (PathBuf, PathBuf) {
    let (client, worker) = (dir.join("client.token"), dir.join("worker.token"));
    std::fs::write(&client, "client-secret\n").unwrap();
    std::fs::write(&worker, "worker-secret\n").unwrap();
    (client, worker)
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap()
}

/// Waits until the coordinator lists `n` workers, at most 20 seconds.
async fn wait_for_workers(client: &mut FarmClient, n: usize) -> Vec<pb::WorkerInfo> {
    let started = Instant::now();
    loop {
        let workers = client.workers().await.unwrap();
        if workers.iter().filter(|w| w.alive).count() >= n {
            return workers;
        }
        assert!(started.elapsed() < Duration::from_secs(20), "only {} of {n} workers registered", workers.len());
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Submits `SCENE` and follows it from a task of its own; statuses arrive on the receiver.
async fn submit_and_follow(
    client: &FarmClient,
) -> (String, mpsc::UnboundedReceiver<pb::JobStatus>, tokio::task::JoinHandle<Result<pb::JobStatus, ClientError>>) {
    let mut client = client.clone();
    let id = client.submit(SCENE.into(), "scene.toml".into(), pb::JobOptions::default()).await.unwrap();
    let (tx, rx) = mpsc::unbounded_channel();
    let job = id.clone();
    let watch = tokio::spawn(async move {
        client
            .watch(&job, |s| {
                let _ = tx.send(s.clone());
            })
            .await
    });
    (id, rx, watch)
}

/// Waits for a status for which `ok` holds, at most 20 seconds.
async fn wait_status(statuses: &mut mpsc::UnboundedReceiver<pb::JobStatus>, ok: impl Fn(&pb::JobStatus) -> bool) {
    let wait = async {
        while let Some(s) = statuses.recv().await {
            assert!(!matches!(s.state(), pb::JobState::Failed | pb::JobState::Cancelled), "the job ended: {s:?}");
            if ok(&s) {
                return;
            }
        }
        panic!("the job's watch ended");
    };
    tokio::time::timeout(Duration::from_secs(20), wait).await.expect("the job reached the state asked for");
}

#[test]
fn sigterm_lets_the_coordinators_running_job_finish_refuses_new_ones_and_exits_zero() {
    let dir = scratch("drain-coordinator");
    let root = slab_root(&dir, "w0");
    let (client_token, worker_token) = token_files(&dir);
    // Heartbeats every 2 s: a frozen worker stays alive in the coordinator's eyes for 10 s.
    let (mut coordinator, address) = start(
        trove(),
        &[
            "coordinator",
            "--listen",
            "127.0.0.1:0",
            "--heartbeat-ms",
            "2000",
            "--drain-grace-s",
            "60",
            "--client-token-file",
            client_token.to_str().unwrap(),
            "--worker-token-file",
            worker_token.to_str().unwrap(),
        ],
        &dir.join("coordinator.log"),
    );
    let url = format!("http://{address}");
    let worker_args =
        ["--coordinator", &url, "--data-root", root.to_str().unwrap(), "--token-file", worker_token.to_str().unwrap()];
    let (worker, _) = start(&trove_worker(), &worker_args, &dir.join("worker.log"));

    // `trove render` without the token is refused with a message that says so.
    std::fs::write(dir.join("scene.toml"), SCENE).unwrap();
    let out = Command::new(trove())
        .args(["render", "scene.toml", "-o", "farm.png", "--coordinator", &url])
        .current_dir(&dir)
        .env_remove("TROVE_DATA")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "a render without the client token succeeded");
    assert!(stderr.contains("refused") && stderr.contains("--token-file"), "{stderr}");

    let rt = runtime();
    rt.block_on(async {
        let connector = Connector::new(None, Some(Token::from_file(&client_token).unwrap()));
        let mut client = FarmClient::connect_with(&url, &connector).await.unwrap();
        wait_for_workers(&mut client, 1).await;
        // The worker freezes: the job's batches wait for it, so the job is running when
        // the coordinator is told to stop.
        worker.signal("-STOP");
        let (id, mut statuses, watch) = submit_and_follow(&client).await;
        wait_status(&mut statuses, |s| s.state() == pb::JobState::Running).await;
        let told = Instant::now();
        coordinator.signal("-TERM");
        // New jobs are refused once the drain began (a malformed scene tells the two apart
        // without adding a job: it is refused as malformed before, as unavailable after).
        let refused = loop {
            match client.submit(String::new(), "probe.toml".into(), pb::JobOptions::default()).await {
                Err(ClientError::Failed(f)) if f.reason() == pb::Reason::Unavailable => break f,
                Err(ClientError::Failed(f)) if f.reason() == pb::Reason::SceneInvalid => {}
                other => panic!("unexpected answer while draining: {other:?}"),
            }
            assert!(told.elapsed() < Duration::from_secs(5), "the coordinator did not start draining");
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        assert!(refused.retryable, "{refused:?}");
        let e = client.submit(SCENE.into(), "scene.toml".into(), pb::JobOptions::default()).await.unwrap_err();
        assert_eq!(e.failure().map(|f| f.reason()), Some(pb::Reason::Unavailable), "{e:?}");
        worker.signal("-CONT");
        let last = tokio::time::timeout(Duration::from_secs(60), watch).await.expect("the job ends").unwrap().unwrap();
        assert_eq!(last.state(), pb::JobState::Succeeded, "{:?}", last.failure);
        let files = client.result(&id).await.unwrap();
        assert!(files.png == local_png(&root), "the drained job's PNG differs from local mode's");
    });
    let status = coordinator.exit_within(Duration::from_secs(60));
    assert!(status.success(), "the coordinator exited with {status}");
    let log = std::fs::read_to_string(dir.join("coordinator.log")).unwrap();
    assert!(log.contains("draining") && log.contains("drained"), "{log}");
}

/// A CA, and a certificate it signed for 127.0.0.1, written as PEM files under `dir`:
/// (ca, cert, key).
fn tls_files(dir: &Path) -> (PathBuf, PathBuf, PathBuf) {
    let pki = TestPki::new();
    let paths = (dir.join("ca.pem"), dir.join("server.pem"), dir.join("server.key"));
    std::fs::write(&paths.0, pki.ca).unwrap();
    std::fs::write(&paths.1, pki.cert).unwrap();
    std::fs::write(&paths.2, pki.key).unwrap();
    paths
}

#[test]
fn sigterm_to_a_worker_mid_job_deregisters_it_and_the_job_completes_on_the_other_holder() {
    let dir = scratch("drain-worker");
    // The generated ball can be cast by either worker; only `b` holds the slab, which lies
    // in front of the ball: while `b` is frozen, the ball's tasks behind the slab wait.
    let (root_a, root_b) = (dir.join("a"), slab_root(&dir, "b"));
    std::fs::create_dir_all(&root_a).unwrap();
    let (_, worker_token) = token_files(&dir);
    let (ca, cert, key) = tls_files(&dir);
    let (ca, cert, key, token) =
        (ca.to_str().unwrap(), cert.to_str().unwrap(), key.to_str().unwrap(), worker_token.to_str().unwrap());
    let tls = ["--tls-cert", cert, "--tls-key", key, "--tls-ca", ca];
    let mut args =
        vec!["coordinator", "--listen", "127.0.0.1:0", "--heartbeat-ms", "2000", "--worker-token-file", token];
    args.extend(tls);
    let (_coordinator, address) = start(trove(), &args, &dir.join("coordinator.log"));
    let url = format!("https://{address}");
    let start_worker = |root: &Path, log: &str| {
        let mut args = vec!["--coordinator", &url, "--data-root", root.to_str().unwrap(), "--token-file", token];
        args.extend(tls);
        start(&trove_worker(), &args, &dir.join(log))
    };
    let (mut a, address_a) = start_worker(&root_a, "a.log");
    let (b, address_b) = start_worker(&root_b, "b.log");

    let rt = runtime();
    rt.block_on(async {
        let connector = Connector::new(Some(CaCert::from_file(Path::new(ca)).unwrap()), None);
        let mut client = FarmClient::connect_with(&url, &connector).await.unwrap();
        wait_for_workers(&mut client, 2).await;
        b.signal("-STOP");
        let (id, mut statuses, watch) = submit_and_follow(&client).await;
        // `a` has cast part of the job: the job is mid-way and `a` holds a stream of it.
        let started = Instant::now();
        loop {
            let workers = client.workers().await.unwrap();
            if workers.iter().any(|w| w.address == address_a && w.batches_done > 0) {
                break;
            }
            assert!(started.elapsed() < Duration::from_secs(5), "worker a cast nothing: {workers:?}");
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        wait_status(&mut statuses, |s| s.state() == pb::JobState::Running).await;
        a.signal("-TERM");
        let status = a.exit_within(Duration::from_secs(5));
        assert!(status.success(), "worker a exited with {status}");
        let workers = client.workers().await.unwrap();
        let listed: Vec<&str> = workers.iter().map(|w| w.address.as_str()).collect();
        assert_eq!(listed, [address_b.as_str()], "the coordinator still lists the worker that left");
        b.signal("-CONT");
        let last = tokio::time::timeout(Duration::from_secs(60), watch).await.expect("the job ends").unwrap().unwrap();
        assert_eq!(last.state(), pb::JobState::Succeeded, "{:?}", last.failure);
        let files = client.result(&id).await.unwrap();
        assert!(files.png == local_png(&root_b), "the job's PNG differs from local mode's");
    });
    let log = std::fs::read_to_string(dir.join("a.log")).unwrap();
    assert!(log.contains("deregistered") && log.contains("stopped"), "{log}");
}
