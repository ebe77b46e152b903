//! The stand-in worker (`trove_tests::standin`): a coordinator fed by two stand-ins that
//! answer from recorded results composites local mode's image byte for byte — on the render
//! that records the answers and on the next, answered from the table alone; whatever order
//! the answers come back in; and with several jobs sharing one worker, each taking the room
//! the others' answers free as it frees, without waiting for the driver's tick.

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::oneshot;
use trove_coordinator::farm::{DriverConfig, FarmConfig};
use trove_core::render::{render, RenderOptions};
use trove_core::scene::Scene;
use trove_proto::v1 as pb;
use trove_tests::farm::{TestFarm, TEST_HEARTBEAT};
use trove_tests::scratch;
use trove_tests::standin::{self, Answers, Order};

/// Two generated datasets, translucent (no ray terminates, so nothing is culled and the
/// second render sends exactly the tasks of the first).
fn scene(size: u32) -> String {
    scene_with_opacity(size, 0.2)
}

/// [`scene`] with the ball's opacity ramping to `ball`: at 1 its rays terminate inside it,
/// so the slab behind is culled by fronts that depend on which answers came first.
fn scene_with_opacity(size: u32, ball: f64) -> String {
    format!(
        "[image]\nwidth = {size}\nheight = {size}\nbackground = [0.1, 0.1, 0.2]\n\
         [camera]\neye = [0.5, 0.6, 3.0]\ntarget = [0.5, 0.5, 0.5]\nup = [0, 1, 0]\nfov_y = 40.0\n\
         [[datasets]]\nname = \"ball\"\ndims = [20, 20, 20]\n[datasets.channels.voxel]\n\
         generator = {{ kind = \"sphere\", radius = 0.5, profile = \"radial\", value = 1.0, type = \"f32\" }}\n\
         [[datasets]]\nname = \"ramp\"\ndims = [16, 16, 16]\n[datasets.channels.voxel]\n\
         generator = {{ kind = \"ramp\", axis = \"x\" }}\n\
         [[objects]]\nname = \"ball\"\ndataset = \"ball\"\n\
         colour = {{ type = \"ramp\", points = [[0.0, 0.9, 0.3, 0.1], [1.0, 0.2, 0.5, 1.0]] }}\n\
         opacity = {{ type = \"ramp\", points = [[0.0, 0.0], [1.0, {ball}]] }}\n\
         [[objects]]\nname = \"slab\"\ndataset = \"ramp\"\n\
         transform = {{ matrix = [[1.2, 0, 0, -0.1], [0, 1.2, 0, -0.1], [0, 0, 0.3, 0.2], [0, 0, 0, 1]] }}\n\
         colour = {{ type = \"ramp\", points = [[0.0, 0.0, 0.0, 1.0], [1.0, 1.0, 1.0, 0.0]] }}\n\
         opacity = {{ type = \"ramp\", points = [[0.0, 0.05], [1.0, 0.1]] }}\n"
    )
}

#[test]
fn stand_ins_answer_what_real_workers_would() {
    let dir = scratch("standin");
    let text = scene(40);
    let local = {
        let scene = Scene::parse(&text, dir.join("standin.toml")).unwrap_or_else(|e| panic!("{e}"));
        render(&scene, &RenderOptions::default()).unwrap().image.encode_png().unwrap()
    };
    let farm = TestFarm::start(&[]);
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap());
    let answers = Arc::new(Answers::new(&dir, pool).unwrap());
    let mut stops = Vec::new();
    for _ in 0..2 {
        let (stop, stopped) = oneshot::channel::<()>();
        let (url, answers) = (farm.url.clone(), answers.clone());
        farm.block_on(async move {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
            tokio::spawn(async move {
                let shutdown = async {
                    let _ = stopped.await;
                };
                standin::serve(listener, shutdown, &url, 2, answers).await.unwrap();
            });
        });
        stops.push(stop);
    }
    farm.wait_for_workers(2);
    // Small bands and batches, so that both datasets go through several batches per band.
    let options = pb::JobOptions { band_rows: 7, batch_tasks: 50, ..Default::default() };
    let first = farm.render_with(&text, "standin.toml", options).unwrap();
    assert!(first.png == local, "recording: the farm's PNG differs from local mode's");
    let (answered, cast) = answers.counts();
    assert!(cast > 0 && answered == cast, "the first render casts every task: {answered} answered, {cast} cast");
    let second = farm.render_with(&text, "standin.toml", options).unwrap();
    assert!(second.png == local, "from the table: the farm's PNG differs from local mode's");
    let (again, cast_again) = answers.counts();
    assert_eq!(cast_again, cast, "the second render is answered from the table alone");
    assert_eq!(again, 2 * answered);
    let stats: serde_json::Value = serde_json::from_slice(&second.stats_json).unwrap();
    assert!(stats["coordinator_seconds"]["event_loop"].as_f64().unwrap() > 0.0, "{stats}");
    assert_eq!(stats["samples"], serde_json::from_slice::<serde_json::Value>(&first.stats_json).unwrap()["samples"]);
    for stop in stops {
        let _ = stop.send(());
    }
    std::thread::sleep(Duration::from_millis(10));
}

fn local_png(text: &str, name: &str) -> Vec<u8> {
    let scene = Scene::parse(text, std::path::Path::new(name)).unwrap_or_else(|e| panic!("{e}"));
    render(&scene, &RenderOptions::default()).unwrap().image.encode_png().unwrap()
}

/// Starts `n` stand-ins of `threads` threads each, over one table, answering in `order`;
/// returns what stops them.
fn stand_ins(
    farm: &TestFarm,
    answers: &Arc<Answers>,
    n: usize,
    threads: u32,
    order: Order,
) -> Vec<oneshot::Sender<()>> {
    let mut stops = Vec::new();
    for _ in 0..n {
        let (stop, stopped) = oneshot::channel::<()>();
        let (url, answers) = (farm.url.clone(), answers.clone());
        farm.block_on(async move {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
            tokio::spawn(async move {
                let shutdown = async {
                    let _ = stopped.await;
                };
                standin::serve_in_order(listener, shutdown, &url, threads, answers, order).await.unwrap();
            });
        });
        stops.push(stop);
    }
    farm.wait_for_workers(n);
    stops
}

#[test]
fn answers_in_any_order_composite_the_local_image_byte_for_byte() {
    let dir = scratch("standin-shuffled");
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap());
    let answers = Arc::new(Answers::new(&dir, pool).unwrap());
    // Translucent (nothing culled) and opaque (the slab behind the ball culled by fronts).
    let scenes = [("translucent.toml", scene_with_opacity(36, 0.2)), ("opaque.toml", scene_with_opacity(36, 1.0))];
    for seed in [1, 7, 1234] {
        let farm = TestFarm::start(&[]);
        let stops = stand_ins(&farm, &answers, 2, 2, Order::Shuffled { seed, hold: 3 });
        for (name, text) in &scenes {
            let options = pb::JobOptions { band_rows: 5, batch_tasks: 40, ..Default::default() };
            let got = farm.render_with(text, name, options).unwrap();
            assert!(got.png == local_png(text, name), "{name}, seed {seed}: the farm's PNG differs from local mode's");
        }
        for stop in stops {
            let _ = stop.send(());
        }
    }
    assert!(answers.overtaken() > 0, "no answer came back out of order: the test tested nothing");
}

#[test]
fn jobs_sharing_one_worker_take_the_room_each_other_frees_without_waiting_for_a_tick() {
    let dir = scratch("standin-sharing");
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap());
    let answers = Arc::new(Answers::new(&dir, pool).unwrap());
    // The tick never comes during the test: a job whose worker is full of another job's
    // batches goes on only if that job's answers wake it. Without that wake-up the test
    // fails (its jobs stop), it never merely slows down.
    let driver = DriverConfig { tick: Duration::from_secs(3600), ..DriverConfig::default() };
    let config = FarmConfig { heartbeat: TEST_HEARTBEAT, driver, max_jobs: 3, ..FarmConfig::default() };
    let farm = TestFarm::start_with(&[], config, None);
    // One worker of one thread: room for four batches, over every job.
    let stops = stand_ins(&farm, &answers, 1, 1, Order::AsReceived);
    let jobs: Vec<(String, String)> = (0..3)
        .map(|i| (format!("shared-{i}.toml"), scene_with_opacity(30 + 2 * i, if i == 1 { 1.0 } else { 0.3 })))
        .collect();
    let got = farm.block_on(async {
        let mut running = Vec::new();
        for (name, text) in jobs.clone() {
            let mut client = farm.client().await;
            running.push(tokio::spawn(async move {
                let options = pb::JobOptions { band_rows: 4, batch_tasks: 30, ..Default::default() };
                client.render(text, name, options, |_| {}).await
            }));
        }
        let mut got = Vec::new();
        for job in running {
            let files = tokio::time::timeout(Duration::from_secs(60), job)
                .await
                .expect("a job stopped: a worker was left idle while it had work ready");
            got.push(files.expect("the job's task").expect("the job"));
        }
        got
    });
    for ((name, text), files) in jobs.iter().zip(got) {
        assert!(files.png == local_png(text, name), "{name}: the farm's PNG differs from local mode's");
    }
    for stop in stops {
        let _ = stop.send(());
    }
}

#[test]
fn a_worker_that_no_longer_holds_the_scene_is_sent_it_again_and_the_image_is_unchanged() {
    let dir = scratch("standin-forgetful");
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap());
    let answers = Arc::new(Answers::new(&dir, pool).unwrap());
    let farm = TestFarm::start(&[]);
    let stops = stand_ins(&farm, &answers, 1, 2, Order::AsReceived);
    let (name, text) = ("forgetful.toml", scene(32));
    let options = pb::JobOptions { band_rows: 6, batch_tasks: 40, ..Default::default() };
    // Remembered: the scene goes on the first stream only, the second names it by digest.
    let files = farm.render_with(&text, name, options).unwrap();
    assert!(files.png == local_png(&text, name), "the farm's PNG differs from local mode's");
    let stats: serde_json::Value = serde_json::from_slice(&files.stats_json).unwrap();
    assert_eq!((stats["streams_opened"].as_u64(), stats["scenes_sent"].as_u64()), (Some(2), Some(1)), "{stats}");
    assert_eq!(answers.scenes_unknown(), 0);
    // Forgotten as soon as opened (a worker restarted between streams): the stream that
    // names the scene by digest is refused as unknown, and opens again carrying it.
    answers.forget_scenes();
    let files = farm.render_with(&text, name, options).unwrap();
    assert!(files.png == local_png(&text, name), "the farm's PNG differs from local mode's");
    let stats: serde_json::Value = serde_json::from_slice(&files.stats_json).unwrap();
    assert_eq!(answers.scenes_unknown(), 1, "{stats}");
    assert_eq!((stats["streams_opened"].as_u64(), stats["scenes_sent"].as_u64()), (Some(3), Some(2)), "{stats}");
    for stop in stops {
        let _ = stop.send(());
    }
}

#[test]
fn a_holder_that_never_accepts_a_stream_holds_no_dataset_up_while_the_scene_is_on_its_way_to_it() {
    let dir = scratch("standin-stalled");
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap());
    let answers = Arc::new(Answers::new(&dir, pool).unwrap());
    // Streams that never open are given up only after an hour: the job finishes in time only
    // if the stalled worker's scene on its way does not keep the other holder from its
    // datasets.
    let driver = DriverConfig { batch_deadline: Duration::from_secs(3600), ..DriverConfig::default() };
    let config = FarmConfig { heartbeat: TEST_HEARTBEAT, driver, ..FarmConfig::default() };
    let farm = TestFarm::start_with(&[], config, None);
    // The stalled stand-in registers first, so that it is first among equals for every
    // dataset: its stream for the first dataset (carrying the scene) never opens, and the
    // second dataset must go to the other stand-in, not wait for the scene to arrive there.
    let mut stops = stand_ins(&farm, &answers, 1, 2, Order::Never);
    stops.extend(stand_ins(&farm, &answers, 1, 2, Order::AsReceived));
    farm.wait_for_workers(2);
    let (name, text) = ("stalled.toml", scene(30));
    let got = farm.block_on(async {
        let mut client = farm.client().await;
        let options = pb::JobOptions { band_rows: 6, batch_tasks: 40, ..Default::default() };
        let job = client.render(text.clone(), name.to_string(), options, |_| {});
        tokio::time::timeout(Duration::from_secs(60), job)
            .await
            .expect("the job stopped: a dataset waited for a worker that never accepts its stream")
            .expect("the job")
    });
    assert!(got.png == local_png(&text, name), "the farm's PNG differs from local mode's");
    for stop in stops {
        let _ = stop.send(());
    }
}
