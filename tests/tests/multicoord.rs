//! Several coordinators sharing one pool of workers (issue 21's layout: each coordinator
//! owns whole jobs, every worker registers with all of them): jobs submitted to different
//! coordinators at once render to local mode's bytes; a worker casts for every coordinator
//! that has work, refusing what is beyond its `--max-batches` as busy without losing a
//! batch; a coordinator that restarts gets its workers back while the others go on; and one
//! coordinator refusing the worker token leaves the worker serving the rest. Everything
//! runs in this process on `127.0.0.1:0`, and each check is on counts or bytes, never on
//! how long something took.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use tokio::sync::oneshot;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;
use trove_coordinator::client::FarmClient;
use trove_coordinator::farm::{self, FarmConfig, FarmSecurity};
use trove_core::render::{render, RenderOptions};
use trove_core::scene::{DataRoot, Scene};
use trove_proto::auth::Token;
use trove_proto::v1 as pb;
use trove_tests::farm::{SharedFarm, RENDER_DEADLINE, TEST_HEARTBEAT};
use trove_tests::scenes::random_scene;
use trove_tests::scratch;
use trove_worker::{WorkerConfig, WorkerError, WorkerSecurity};

/// Datasets per random scene.
const DATASETS: usize = 10;

/// Two random scenes of raw datasets under one data root, their keys apart (`a/…`, `b/…`),
/// so that the two coordinators' jobs need different datasets of the same workers.
fn two_scenes(root: &Path) -> [String; 2] {
    ["a", "b"].map(|sub| {
        let dir = root.join(sub);
        std::fs::create_dir_all(&dir).unwrap();
        let seed = if sub == "a" { 21 } else { 22 };
        random_scene(&dir, DATASETS, seed).replace("raw = \"d", &format!("raw = \"{sub}/d"))
    })
}

/// What local mode renders from `text` with its keys under `root`.
fn local_png(text: &str, root: &Path) -> Vec<u8> {
    let scene = Scene::parse_in(text, "scene.toml", &DataRoot::Given(root.to_path_buf())).unwrap();
    render(&scene, &RenderOptions::default()).unwrap().image.encode_png().unwrap()
}

/// Bands of a few rows and batches of a few tasks: many batches of each job in flight.
fn many_batches() -> pb::JobOptions {
    pb::JobOptions { band_rows: 3, batch_tasks: 7, ..Default::default() }
}

/// Each worker's batches in a job's statistics, by worker id.
fn batches_by_worker(stats_json: &[u8]) -> Vec<(String, u64)> {
    let stats: serde_json::Value = serde_json::from_slice(stats_json).unwrap();
    let workers = stats["workers"].as_array().expect("stats list the workers");
    workers.iter().map(|w| (w["worker_id"].as_str().unwrap().to_string(), w["batches"].as_u64().unwrap())).collect()
}

/// Worker folders that all hold the same files (hard links to `data`'s `a/` and `b/`).
fn roots(dir: &Path, data: &Path, workers: usize) -> Vec<PathBuf> {
    (0..workers)
        .map(|w| {
            let root = dir.join(format!("w{w}"));
            for sub in ["a", "b"] {
                std::fs::create_dir_all(root.join(sub)).unwrap();
                for entry in std::fs::read_dir(data.join(sub)).unwrap() {
                    let from = entry.unwrap().path();
                    let to = root.join(sub).join(from.file_name().unwrap());
                    if std::fs::hard_link(&from, &to).is_err() {
                        std::fs::copy(&from, &to).unwrap();
                    }
                }
            }
            root
        })
        .collect()
}

#[test]
fn two_coordinators_sharing_three_workers_render_their_jobs_at_once_as_in_local_mode() {
    let dir = scratch("multicoord-three");
    let data = dir.join("data");
    let scenes = two_scenes(&data);
    let expected = scenes.clone().map(|text| local_png(&text, &data));
    let farm = SharedFarm::start(2, &roots(&dir, &data, 3), None);
    for round in 0..2 {
        let jobs: Vec<_> = (0..2).map(|c| (c, scenes[c].clone(), format!("scene-{c}.toml"), many_batches())).collect();
        let files = farm.render_at_once(&jobs);
        for (c, files) in files.into_iter().enumerate() {
            let files = files.unwrap_or_else(|e| panic!("round {round}, coordinator {c}: {e}"));
            assert!(files.png == expected[c], "round {round}, coordinator {c}: the PNG differs from local mode's");
        }
    }
    // Each coordinator knows all three workers alive, and cast its jobs on them. Which of
    // them took batches depends on timing here (with answers back before the next send, the
    // least-loaded choice's tie goes to the first holder every time), so that every worker
    // is used is held by the contended test below, where a full worker forces it.
    for c in 0..2 {
        let workers = farm.workers(c).unwrap();
        assert_eq!(workers.len(), 3, "coordinator {c}: {workers:?}");
        assert!(workers.iter().all(|w| w.alive), "coordinator {c}: {workers:?}");
        assert!(workers.iter().map(|w| w.batches_done).sum::<u64>() > 0, "coordinator {c}: {workers:?}");
    }
    // Each worker parsed each of the two scenes at most once, over both rounds, both
    // coordinators and every dataset's stream: the others found it parsed.
    for (w, m) in farm.worker_metrics.iter().enumerate() {
        assert!(m.scenes_parsed() <= 2, "worker {w} parsed {} scenes", m.scenes_parsed());
    }
    let parsed: u64 = farm.worker_metrics.iter().map(|m| m.scenes_parsed()).sum();
    let reused: u64 = farm.worker_metrics.iter().map(|m| m.scenes_reused()).sum();
    assert!(parsed >= 2 && reused > parsed, "parsed {parsed}, reused {reused}");
}

#[test]
fn a_worker_shared_by_two_coordinators_casts_for_both_and_refuses_only_beyond_its_maximum() {
    let dir = scratch("multicoord-busy");
    let data = dir.join("data");
    let scenes = two_scenes(&data);
    let expected = scenes.clone().map(|text| local_png(&text, &data));
    // One batch at a time per worker, while each coordinator offers each worker several
    // (twice its threads): every worker is contended, within each job and between the two.
    let farm = SharedFarm::start(2, &roots(&dir, &data, 2), Some(1));
    let jobs: Vec<_> = (0..2).map(|c| (c, scenes[c].clone(), format!("scene-{c}.toml"), many_batches())).collect();
    let files = farm.render_at_once(&jobs);
    let refused_by_workers: u64 = farm.worker_metrics.iter().map(|m| m.refused()).sum();
    let answered_by_workers: u64 = farm.worker_metrics.iter().map(|m| m.batches()).sum();
    let mut answered_in_jobs = 0;
    let mut refused_in_jobs = 0;
    for (c, files) in files.into_iter().enumerate() {
        let files = files.unwrap_or_else(|e| panic!("coordinator {c}: {e}"));
        // Refused batches were sent again, none lost, none cast twice into the image.
        assert!(files.png == expected[c], "coordinator {c}: the PNG differs from local mode's");
        // Both workers cast batches of this coordinator's job: neither coordinator was
        // starved of either worker by the other keeping it full.
        let by_worker = batches_by_worker(&files.stats_json);
        assert_eq!(by_worker.len(), 2, "coordinator {c}: {by_worker:?}");
        assert!(by_worker.iter().all(|(_, n)| *n > 0), "coordinator {c}: {by_worker:?}");
        answered_in_jobs += by_worker.iter().map(|(_, n)| n).sum::<u64>();
        let stats: serde_json::Value = serde_json::from_slice(&files.stats_json).unwrap();
        refused_in_jobs += stats["batches_refused_busy"].as_u64().expect("batches_refused_busy");
    }
    // The workers refused batches, the jobs took those refusals and sent the batches again
    // (a refusal still on its way when its job ended is not counted by the job); the
    // workers answered each job's batches, some perhaps more than once, never fewer.
    assert!(refused_by_workers > 0, "no batch was refused: the contention this test needs did not happen");
    assert!(refused_in_jobs > 0 && refused_in_jobs <= refused_by_workers, "{refused_in_jobs} of {refused_by_workers}");
    assert!(answered_by_workers >= answered_in_jobs, "{answered_by_workers} < {answered_in_jobs}");
    // And the coordinators' own counts: each worker served each coordinator.
    for c in 0..2 {
        let workers = farm.workers(c).unwrap();
        assert!(workers.iter().all(|w| w.batches_done > 0 && w.batches_in_flight == 0), "coordinator {c}: {workers:?}");
    }
}

/// The health of the worker at `address`, as a Kubernetes gRPC probe asks it.
async fn health(address: &str) -> ServingStatus {
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{address}"))
        .unwrap()
        .timeout(Duration::from_secs(5))
        .connect()
        .await
        .unwrap();
    let request = HealthCheckRequest { service: String::new() };
    HealthClient::new(channel).check(request).await.unwrap().into_inner().status()
}

#[test]
fn a_coordinator_restarting_leaves_the_other_rendering_and_gets_its_workers_back() {
    let dir = scratch("multicoord-restart");
    let data = dir.join("data");
    let scenes = two_scenes(&data);
    let expected = scenes.clone().map(|text| local_png(&text, &data));
    let mut farm = SharedFarm::start(2, &roots(&dir, &data, 2), None);
    let addresses: Vec<String> = farm.workers(1).unwrap().into_iter().map(|w| w.address).collect();
    farm.stop_coordinator(0);
    // While coordinator 0 is down: coordinator 1 renders, and the workers, still registered
    // with it, stay ready.
    let files = farm.render_at_once(&[(1, scenes[1].clone(), "b.toml".into(), many_batches())]);
    let files = files.into_iter().next().unwrap().expect("coordinator 1 renders while coordinator 0 is down");
    assert!(files.png == expected[1], "coordinator 1's PNG differs from local mode's");
    assert!(batches_by_worker(&files.stats_json).iter().all(|(_, n)| *n > 0));
    for address in &addresses {
        assert_eq!(farm.block_on(health(address)), ServingStatus::Serving, "worker {address}");
    }
    // Coordinator 0 comes back empty on its address; the workers register again (their next
    // heartbeat is answered "unknown"), and both coordinators render at once.
    farm.restart_coordinator(0);
    farm.wait_for_workers(0, 2);
    let jobs: Vec<_> = (0..2).map(|c| (c, scenes[c].clone(), format!("scene-{c}.toml"), many_batches())).collect();
    for (c, files) in farm.render_at_once(&jobs).into_iter().enumerate() {
        let files = files.unwrap_or_else(|e| panic!("after the restart, coordinator {c}: {e}"));
        assert!(files.png == expected[c], "after the restart, coordinator {c}: the PNG differs");
    }
    let workers = farm.workers(0).unwrap();
    assert!(workers.iter().all(|w| w.alive && w.batches_done > 0), "{workers:?}");
}

/// A coordinator on `127.0.0.1:0` requiring `worker_token` of workers (and presenting it on
/// its cast streams); returns its URL and what stops it.
async fn coordinator_with(worker_token: &str) -> (String, oneshot::Sender<()>) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let security = FarmSecurity { worker_token: Some(Token::new(worker_token).unwrap()), ..Default::default() };
    let config = FarmConfig { heartbeat: TEST_HEARTBEAT, security, ..FarmConfig::default() };
    let (tx, rx) = oneshot::channel::<()>();
    tokio::spawn(farm::run(
        listener,
        async {
            let _ = rx.await;
        },
        config,
    ));
    (url, tx)
}

/// A worker over `root` with token `token`, serving `coordinators`; its task ends with
/// what `trove_worker::run` returned.
async fn worker_of(
    coordinators: &[&str],
    root: &Path,
    token: &str,
) -> (tokio::task::JoinHandle<Result<(), WorkerError>>, oneshot::Sender<()>) {
    let mut config = WorkerConfig::new(coordinators[0], root);
    config.coordinators = coordinators.iter().map(|c| c.to_string()).collect();
    config.security = WorkerSecurity { token: Some(Token::new(token).unwrap()), ..Default::default() };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let (tx, rx) = oneshot::channel::<()>();
    let task = tokio::spawn(trove_worker::run(
        listener,
        async {
            let _ = rx.await;
        },
        config,
    ));
    (task, tx)
}

#[test]
fn a_coordinator_refusing_the_token_leaves_the_worker_serving_the_others_and_all_refusing_stops_it() {
    let dir = scratch("multicoord-token");
    let data = dir.join("data");
    let [scene, _] = two_scenes(&data);
    let expected = local_png(&scene, &data);
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    runtime.block_on(async {
        let (good, _stop_good) = coordinator_with("the-worker-token").await;
        let (bad, _stop_bad) = coordinator_with("another-token").await;
        let (other_bad, _stop_other_bad) = coordinator_with("a-third-token").await;
        // Refused by one of its two coordinators: the worker serves the other.
        let (worker, _stop_worker) = worker_of(&[&bad, &good], &data, "the-worker-token").await;
        let mut client = FarmClient::connect(&good).await.unwrap();
        let started = Instant::now();
        while client.workers().await.unwrap().iter().filter(|w| w.alive).count() < 1 {
            assert!(started.elapsed() < Duration::from_secs(10), "the worker never registered with {good}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let render = client.render(scene.clone(), "a.toml".into(), many_batches(), |_| {});
        let files = tokio::time::timeout(RENDER_DEADLINE, render).await.expect("bounded").unwrap();
        assert!(files.png == expected, "the PNG differs from local mode's");
        // By now the refusing coordinator has answered (the worker registered with both at
        // once, and the render took many heartbeats): the worker still runs.
        let mut bad_client = FarmClient::connect(&bad).await.unwrap();
        assert!(bad_client.workers().await.unwrap().is_empty(), "the refusing coordinator registered the worker");
        assert!(!worker.is_finished(), "one refusal out of two coordinators stopped the worker");
        // Refused by every coordinator it serves: the worker stops and says so.
        let (refused, _stop) = worker_of(&[&bad, &other_bad], &data, "the-worker-token").await;
        let ended = tokio::time::timeout(Duration::from_secs(30), refused).await.expect("it stops by itself");
        match ended.unwrap() {
            Err(WorkerError::AllRefused { count: 2, first }) => {
                assert_eq!(first.code, tonic::Code::Unauthenticated, "{first}");
            }
            other => panic!("expected every coordinator's refusal, got {other:?}"),
        }
        // Refused by its only coordinator: as before, the refusal itself.
        let (alone, _stop) = worker_of(&[&bad], &data, "the-worker-token").await;
        let ended = tokio::time::timeout(Duration::from_secs(30), alone).await.expect("it stops by itself");
        assert!(matches!(ended.unwrap(), Err(WorkerError::Refused(_))));
    });
}

#[test]
fn a_worker_refuses_no_coordinator_and_one_listed_twice() {
    let dir = scratch("multicoord-config");
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    runtime.block_on(async {
        for coordinators in [vec![], vec!["http://127.0.0.1:9".to_string(), "http://127.0.0.1:9".to_string()]] {
            let mut config = WorkerConfig::new("http://127.0.0.1:9", dir.path());
            config.coordinators = coordinators.clone();
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
            let ended = tokio::time::timeout(Duration::from_secs(10), trove_worker::run(listener, async {}, config))
                .await
                .expect("refused at once");
            assert!(matches!(ended, Err(WorkerError::Coordinators(_))), "{coordinators:?}: {ended:?}");
        }
    });
}
