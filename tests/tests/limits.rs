//! Bounded work from any input: scenes whose geometry would make unbounded work (nested
//! boxes at a huge step, many objects, tiny steps, a 16384² PFM) are refused with errors
//! naming the limit, locally and on the farm, and the coordinator goes on serving; jobs
//! beyond `max_jobs` wait QUEUED in order with their places; a job past its deadline fails
//! with a typed reason; a panic in a job's step fails that job only.

use std::time::{Duration, Instant};

use trove_coordinator::farm::{DriverConfig, FarmConfig};
use trove_core::render::limits::LimitError;
use trove_core::render::{render, RenderError, RenderOptions};
use trove_core::scene::Scene;
use trove_proto::v1 as pb;
use trove_tests::farm::{data_root, TestFarm, TEST_HEARTBEAT};
use trove_tests::scenes::{ball, many_objects, nested_boxes, slow_ball};
use trove_tests::scratch;

fn local_png(text: &str, name: &str) -> Vec<u8> {
    let scene = Scene::parse(text, name).unwrap_or_else(|e| panic!("{e}"));
    render(&scene, &RenderOptions::default()).unwrap().image.encode_png().unwrap()
}

/// The local render's refusal, which must be a limit.
fn local_limit(text: &str) -> LimitError {
    let scene = Scene::parse(text, "limits.toml").unwrap_or_else(|e| panic!("valid scene expected: {e}"));
    match render(&scene, &RenderOptions::default()) {
        Err(RenderError::Limit(e)) => e,
        Err(e) => panic!("refused, but not for a limit: {e}"),
        Ok(_) => panic!("rendered"),
    }
}

/// A farm of one worker over an empty root (the scenes here are generated).
fn farm(name: &str, config: FarmConfig) -> TestFarm {
    let dir = scratch(name);
    TestFarm::start_with(&[data_root(&dir.join("w0"), &dir, &[])], config, None).holding(dir)
}

fn config() -> FarmConfig {
    FarmConfig { heartbeat: TEST_HEARTBEAT, ..FarmConfig::default() }
}

/// The farm's refusal of `text`, which must come at submission, quickly, as
/// INVALID_ARGUMENT with a typed failure.
fn farm_refusal(farm: &TestFarm, text: &str, options: pb::JobOptions) -> pb::Failure {
    let started = Instant::now();
    let refused = farm.block_on(async {
        let mut client = farm.client().await;
        client.submit(text.to_string(), "limits.toml".into(), options).await
    });
    assert!(started.elapsed() < Duration::from_secs(60), "refusing took {:?}", started.elapsed());
    let err = refused.expect_err("the farm accepted the job");
    err.failure().cloned().unwrap_or_else(|| panic!("untyped error: {err}"))
}

#[test]
fn three_hundred_nested_boxes_at_a_huge_step_are_refused_locally_and_on_the_farm_which_then_renders() {
    let text = nested_boxes(300, 512, "1e9");
    let e = local_limit(&text);
    assert!(matches!(e, LimitError::TasksPerRender { .. }), "{e}");
    assert!(e.to_string().contains("limit on piece tasks per render is 536870912"), "{e}");

    let farm = farm("limits-nested", config());
    let f = farm_refusal(&farm, &text, Default::default());
    assert_eq!((f.reason(), f.retryable, f.file.as_str()), (pb::Reason::LimitExceeded, false, "limits.toml"));
    assert!(f.message.contains("limit on piece tasks per render"), "{}", f.message);
    // The coordinator is up and serves the next job.
    let good = ball(16, "");
    assert_eq!(farm.render(&good, "good.toml", false).unwrap().png, local_png(&good, "good.toml"));
}

#[test]
fn many_objects_on_a_large_image_are_refused_before_counting() {
    let text = many_objects(4096, 8192);
    let e = local_limit(&text);
    assert!(e.to_string().contains("limit on ray–object tests per render"), "{e}");
    let farm = farm("limits-many", config());
    let f = farm_refusal(&farm, &text, Default::default());
    assert_eq!(f.reason(), pb::Reason::LimitExceeded);
    assert!(f.message.contains("4096 objects"), "{}", f.message);
    // The same objects on a small image are fine.
    let small = many_objects(4096, 24);
    assert_eq!(farm.render(&small, "small.toml", false).unwrap().png, local_png(&small, "small.toml"));
}

#[test]
fn tiny_steps_are_refused_and_a_huge_step_renders_as_locally() {
    let tiny = ball(64, "sampling_distance = 1e-9");
    let err = Scene::parse(&tiny, "tiny.toml").unwrap_err();
    assert!(err.to_string().contains("objects[0].sampling_distance"), "{err}");
    let farm = farm("limits-steps", config());
    let f = farm_refusal(&farm, &tiny, Default::default());
    assert_eq!((f.reason(), f.key.as_str()), (pb::Reason::SceneInvalid, "objects[0].sampling_distance"));
    // One sample per piece is a valid, cheap render.
    let huge = ball(16, "sampling_distance = 1e9");
    assert_eq!(farm.render(&huge, "huge.toml", false).unwrap().png, local_png(&huge, "huge.toml"));
}

#[test]
fn a_16384_square_pfm_is_refused_and_a_band_over_the_memory_bound_too() {
    let big = ball(16384, "").replace("fov_y = 35.0", "fov_y = 1.0");
    let farm = farm(
        "limits-pfm",
        FarmConfig { driver: DriverConfig { memory_bound: 1, ..DriverConfig::default() }, ..config() },
    );
    let f = farm_refusal(&farm, &big, pb::JobOptions { want_pfm: true, ..Default::default() });
    assert_eq!(f.reason(), pb::Reason::LimitExceeded);
    assert!(f.message.contains("16384×16384 PFM") && f.message.contains("limit on PFM pixels"), "{}", f.message);
    // A job that asks for one band of dense rows when the bound holds far fewer tasks.
    let dense = nested_boxes(40, 64, "0.1");
    let f = farm_refusal(&farm, &dense, pb::JobOptions { band_rows: 64, ..Default::default() });
    assert!(f.message.contains("limit on piece tasks per band"), "{}", f.message);
    // Left to size its own bands, the same job renders as local mode does.
    assert_eq!(farm.render(&dense, "dense.toml", false).unwrap().png, local_png(&dense, "dense.toml"));
}

#[test]
fn jobs_beyond_max_jobs_wait_in_order_with_their_places_and_all_finish() {
    let farm = farm("limits-queue", FarmConfig { max_jobs: 1, ..config() });
    let texts = [slow_ball(96), ball(20, ""), ball(12, "")];
    let statuses = farm.block_on(async {
        let mut client = farm.client().await;
        let mut ids = Vec::new();
        for (i, text) in texts.iter().enumerate() {
            ids.push(client.submit(text.clone(), format!("q{i}.toml"), Default::default()).await.unwrap());
        }
        // Watched at once, each on its own task, so that every queued status is seen.
        let watches = ids.iter().map(|id| {
            let (mut client, id) = (client.clone(), id.clone());
            tokio::spawn(async move {
                let mut places = Vec::new();
                let last = client
                    .watch(&id, |s| {
                        if s.state() == pb::JobState::Queued && places.last() != Some(&s.queue_position) {
                            places.push(s.queue_position);
                        }
                    })
                    .await
                    .unwrap();
                (last.state(), places)
            })
        });
        let watched = tokio::time::timeout(Duration::from_secs(120), futures_join(watches.collect())).await;
        let mut out = Vec::new();
        for (watch, id) in watched.expect("the queued jobs finish").into_iter().zip(&ids) {
            let (state, places) = watch.expect("a watch task");
            let files = client.result(id).await.unwrap();
            out.push((state, places, files.png));
        }
        out
    });
    for (i, (state, _, png)) in statuses.iter().enumerate() {
        assert_eq!(*state, pb::JobState::Succeeded, "job {i}");
        assert!(*png == local_png(&texts[i], "q.toml"), "job {i}'s image");
    }
    // The first ran at once; the others waited, the last second in line, then first.
    assert!(statuses[0].1.is_empty(), "{:?}", statuses[0].1);
    assert_eq!(statuses[1].1.first(), Some(&1), "{:?}", statuses[1].1);
    assert_eq!(statuses[2].1.first(), Some(&2), "{:?}", statuses[2].1);
}

/// Every spawned task's output, in order.
async fn futures_join<T>(tasks: Vec<tokio::task::JoinHandle<T>>) -> Vec<Result<T, tokio::task::JoinError>> {
    let mut out = Vec::new();
    for task in tasks {
        out.push(task.await);
    }
    out
}

#[test]
fn a_job_past_its_deadline_fails_with_a_typed_reason_and_the_next_one_runs() {
    // Far shorter than the slow job takes (seconds, even on a fast machine), so that the
    // deadline, not the job's speed, decides.
    let deadline = Duration::from_millis(500);
    let farm = farm(
        "limits-deadline",
        FarmConfig { driver: DriverConfig { job_deadline: deadline, ..DriverConfig::default() }, ..config() },
    );
    let started = Instant::now();
    let err = farm.render(&slow_ball(320), "slow.toml", false).unwrap_err();
    let f = err.failure().unwrap_or_else(|| panic!("untyped error: {err}"));
    assert_eq!((f.reason(), f.retryable), (pb::Reason::DeadlineExceeded, false), "{f:?}");
    assert!(f.message.contains("deadline of 0.5 s"), "{}", f.message);
    assert!(started.elapsed() < deadline + Duration::from_secs(10), "took {:?}", started.elapsed());
    let good = ball(8, "");
    assert_eq!(farm.render(&good, "good.toml", false).unwrap().png, local_png(&good, "good.toml"));
}

#[cfg(debug_assertions)]
#[test]
fn a_panic_in_a_step_fails_that_job_only() {
    use trove_coordinator::farm::Fault;
    for (fault, step) in
        [(Fault::Intersection, "intersection"), (Fault::Composition, "composition"), (Fault::Encoding, "encoding")]
    {
        let config = FarmConfig {
            driver: DriverConfig { fault: Some(fault), ..DriverConfig::default() },
            max_jobs: 1,
            ..config()
        };
        let farm = farm(&format!("limits-panic-{step}"), config);
        // Two jobs one after the other: each fails by itself (the first frees its room).
        for name in ["a.toml", "b.toml"] {
            let err = farm.render(&ball(8, ""), name, false).unwrap_err();
            let f = err.failure().unwrap_or_else(|| panic!("{step}: untyped error: {err}"));
            assert_eq!(f.reason(), pb::Reason::Internal, "{step}: {f:?}");
            assert!(f.message.contains(&format!("{step} step panicked")), "{}", f.message);
        }
        assert_eq!(farm.workers_alive(), 1, "the coordinator still serves");
    }
}
