//! The stand-in worker (`trove_tests::standin`): a coordinator fed by two stand-ins that
//! answer from recorded results composites local mode's image byte for byte — on the render
//! that records the answers and on the next, answered from the table alone.

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::oneshot;
use trove_core::render::{render, RenderOptions};
use trove_core::scene::Scene;
use trove_proto::v1 as pb;
use trove_tests::farm::TestFarm;
use trove_tests::scratch;
use trove_tests::standin::{self, Answers};

/// Two generated datasets, translucent (no ray terminates, so nothing is culled and the
/// second render sends exactly the tasks of the first).
fn scene(size: u32) -> String {
    format!(
        "[image]\nwidth = {size}\nheight = {size}\nbackground = [0.1, 0.1, 0.2]\n\
         [camera]\neye = [0.5, 0.6, 3.0]\ntarget = [0.5, 0.5, 0.5]\nup = [0, 1, 0]\nfov_y = 40.0\n\
         [[datasets]]\nname = \"ball\"\ndims = [20, 20, 20]\n[datasets.channels.voxel]\n\
         generator = {{ kind = \"sphere\", radius = 0.5, profile = \"radial\", value = 1.0, type = \"f32\" }}\n\
         [[datasets]]\nname = \"ramp\"\ndims = [16, 16, 16]\n[datasets.channels.voxel]\n\
         generator = {{ kind = \"ramp\", axis = \"x\" }}\n\
         [[objects]]\nname = \"ball\"\ndataset = \"ball\"\n\
         colour = {{ type = \"ramp\", points = [[0.0, 0.9, 0.3, 0.1], [1.0, 0.2, 0.5, 1.0]] }}\n\
         opacity = {{ type = \"ramp\", points = [[0.0, 0.0], [1.0, 0.2]] }}\n\
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
