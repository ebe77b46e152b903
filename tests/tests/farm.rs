//! The render farm in one process (SPEC §5): a coordinator and workers on `127.0.0.1:0`,
//! the shared datasets split among the workers (one held by two), driven through the
//! client that `trove render --coordinator` uses. Every example scene renders through the
//! farm to the very PNG local mode writes; bad jobs fail with typed reasons and leave the
//! coordinator serving.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use trove_core::render::{render, RenderOptions};
use trove_core::scene::{DataRoot, Scene};
use trove_proto::v1 as pb;
use trove_tests::farm::{data_root, TestFarm};
use trove_tests::scenes::random_scene;
use trove_tests::{example_scenes, scratch, shared_data, shrunk_scene_text};

/// The files the example scenes read, split over three workers; the CT head (used by four
/// scenes) is held by two of them.
fn three_roots(dir: &Path, data: &Path) -> Vec<PathBuf> {
    let ct = ["cthead_256x256x113_uint16_le.nhdr", "cthead_256x256x113_uint16_le.raw"];
    vec![
        data_root(&dir.join("w0"), data, &[ct[0], ct[1], "photo_astronaut.png"]),
        data_root(
            &dir.join("w1"),
            data,
            &[ct[0], ct[1], "engine_256x256x128_uint8.nhdr", "engine_256x256x128_uint8.raw.gz", "photo_chelsea.png"],
        ),
        data_root(&dir.join("w2"), data, &["photo_coffee.png"]),
    ]
}

/// A generated-data scene small enough to render in a moment.
fn generated_scene(size: u32) -> String {
    format!(
        "[image]\nwidth = {size}\nheight = {size}\nbackground = [0.1, 0.1, 0.2]\n\
         [camera]\neye = [0.5, 0.6, 3.0]\ntarget = [0.5, 0.5, 0.5]\nup = [0, 1, 0]\nfov_y = 35.0\n\
         [[datasets]]\nname = \"ball\"\ndims = [24, 24, 24]\n[datasets.channels.voxel]\n\
         generator = {{ kind = \"sphere\", radius = 0.5, profile = \"radial\", value = 1.0, type = \"f32\" }}\n\
         [[objects]]\nname = \"ball\"\ndataset = \"ball\"\n\
         colour = {{ type = \"ramp\", points = [[0.0, 0.9, 0.3, 0.1], [1.0, 0.2, 0.5, 1.0]] }}\n\
         opacity = {{ type = \"ramp\", points = [[0.0, 0.0], [1.0, 0.3]] }}\n"
    )
}

/// The PNG local mode renders from `text` with its keys under `data` (`--data-root data`).
fn local_png(text: &str, name: &str, data: &Path) -> Vec<u8> {
    let scene = Scene::parse_in(text, name, &DataRoot::Given(data.to_path_buf())).unwrap_or_else(|e| panic!("{e}"));
    render(&scene, &RenderOptions::default()).unwrap().image.encode_png().unwrap()
}

#[test]
fn every_example_scene_renders_through_the_farm_as_in_local_mode() {
    let Some(data) = shared_data() else { return };
    let dir = scratch("farm-scenes");
    let farm = TestFarm::start(&three_roots(&dir, &data));
    for (path, _) in example_scenes(48) {
        let text = shrunk_scene_text(&path, 48);
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        let expected = local_png(&text, &name, &data);
        let files = farm.render(&text, &name, false).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(files.png == expected, "{name}: the farm's PNG differs from local mode's");
        let stats: serde_json::Value = serde_json::from_slice(&files.stats_json).unwrap();
        for key in
            ["algorithm", "samples", "pieces", "effects", "wire_bytes_to_workers", "wire_bytes_from_workers", "workers"]
        {
            assert!(stats.get(key).is_some(), "{name}: stats lack `{key}`");
        }
        // The workers count the samples they shade, object by object.
        let shaded: u64 = stats["effects"]
            .as_array()
            .expect("effects")
            .iter()
            .map(|e| e["shading_evaluations"].as_u64().expect("counted"))
            .sum();
        let lit = text.contains("[[lights]]");
        assert_eq!(shaded > 0, lit, "{name}: {shaded} samples shaded");
    }
}

#[test]
fn a_scene_with_shadows_renders_through_the_farm_as_in_local_mode() {
    // Generators only: runs without the shared data. One worker, and three, each holding
    // every dataset, so the shadow pass and the casting spread over them.
    let dir = scratch("farm-shadows");
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/shadows.toml");
    let text = shrunk_scene_text(&path, 40);
    let expected = local_png(&text, "shadows.toml", &dir);
    for workers in [1, 3] {
        let roots: Vec<PathBuf> =
            (0..workers).map(|i| data_root(&dir.join(format!("w{workers}-{i}")), &dir, &[])).collect();
        let farm = TestFarm::start(&roots);
        let files = farm.render(&text, "shadows.toml", false).unwrap_or_else(|e| panic!("{workers} workers: {e}"));
        assert!(files.png == expected, "{workers} workers: the farm's PNG differs from local mode's");
        let stats: serde_json::Value = serde_json::from_slice(&files.stats_json).unwrap();
        assert!(stats["seconds"]["shadows"].as_f64().is_some_and(|s| s > 0.0), "{}", stats["seconds"]);
        for e in stats["effects"].as_array().expect("effects") {
            assert_eq!(e["ran"], serde_json::json!(["shading", "shadows"]), "{e}");
            assert!(e["shadow_lookups"].as_u64().is_some_and(|n| n > 0), "{e}");
        }
        // One lit object alone: its shadow pass finds nothing else between it and the
        // light, so no map goes with the scene, and its own share still renders.
        let lone = generated_scene(16)
            + "shading = {}\n[[lights]]\ntype = \"directional\"\ndirection = [0.3, -1.0, -0.5]\nshadows = true\n";
        let files = farm.render(&lone, "lone.toml", false).unwrap_or_else(|e| panic!("{workers} workers, lone: {e}"));
        assert!(files.png == local_png(&lone, "lone.toml", &dir), "{workers} workers: the lone object differs");
    }
}

/// The shadow pass's second round derives its points from the first round's maps, so a
/// worker asked to refine without them refuses by reason instead of answering nothing.
#[test]
fn a_worker_refuses_to_refine_shadows_without_the_first_rounds_maps() {
    let dir = scratch("farm-refine");
    let root = dir.join("root");
    std::fs::create_dir_all(&root).unwrap();
    let farm = TestFarm::start(std::slice::from_ref(&root));
    let text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/shadows.toml")).unwrap();
    let address = farm.worker_addresses().remove(0);
    let open = pb::CastOpen {
        job_id: "refine-test".into(),
        scene_digest: trove_proto::convert::scene_digest(&text, "shadows.toml", &[], None).to_vec(),
        scene_toml: text,
        scene_name: "shadows.toml".into(),
        dataset: 0,
        ..Default::default()
    };
    let asked = |refine: bool| {
        let open = open.clone();
        farm.block_on(async {
            let channel = tonic::transport::Endpoint::from_shared(format!("http://{address}"))
                .unwrap()
                .connect()
                .await
                .expect("connect to the worker");
            let mut worker = pb::worker_client::WorkerClient::new(channel);
            worker.shadow(pb::ShadowRequest { open: Some(open), refine }).await
        })
    };
    let status = asked(true).expect_err("refused");
    let failure = trove_proto::convert::status_failure(&status).expect("a typed failure");
    assert_eq!(failure.reason(), pb::Reason::BadBatch, "{failure:?}");
    assert!(failure.message.contains("first pass"), "{}", failure.message);
    // The first round itself is answered (the floor's dataset shades the others' lattices).
    assert!(asked(false).is_ok());
}

#[test]
fn the_farm_writes_the_same_pfm_as_local_mode() {
    let dir = scratch("farm-pfm");
    let farm = TestFarm::start(&[data_root(&dir.join("w0"), &dir, &[])]);
    let text = generated_scene(20);
    let files = farm.render(&text, "pfm.toml", true).unwrap();
    let scene = Scene::parse(&text, dir.join("pfm.toml")).unwrap();
    let image = render(&scene, &RenderOptions::default()).unwrap().image;
    let expected = trove_core::render::encode_pfm(image.width(), image.height(), &image.to_rgb32f());
    assert!(files.pfm.as_deref() == Some(&expected[..]), "PFM differs");
    assert_eq!(files.png, image.encode_png().unwrap());
}

#[test]
fn a_job_naming_a_dataset_no_worker_holds_fails_at_once_naming_it() {
    let dir = scratch("farm-missing");
    let farm = TestFarm::start(&[data_root(&dir.join("w0"), &dir, &[])]);
    let text = generated_scene(8).replace(
        "[[datasets]]\nname = \"ball\"",
        "[[datasets]]\nname = \"ct\"\nfile = \"nowhere/cthead.nhdr\"\n[[datasets]]\nname = \"ball\"",
    );
    let started = Instant::now();
    let err = farm.render(&text, "missing.toml", false).unwrap_err();
    assert!(started.elapsed() < Duration::from_secs(5), "took {:?}", started.elapsed());
    let f = err.failure().unwrap_or_else(|| panic!("untyped error: {err}"));
    assert_eq!(f.reason(), pb::Reason::DatasetNotHeld, "{f:?}");
    assert_eq!(f.key, "datasets[0].file");
    assert!(f.message.contains("nowhere/cthead.nhdr"), "{}", f.message);
}

#[test]
fn a_malformed_scene_is_refused_naming_file_and_key_and_the_coordinator_keeps_serving() {
    let dir = scratch("farm-malformed");
    let farm = TestFarm::start(&[data_root(&dir.join("w0"), &dir, &[])]);
    let bad = generated_scene(8).replace("fov_y = 35.0", "fov_y = 235.0");
    let err = farm.render(&bad, "scenes/bad.toml", false).unwrap_err();
    let f = err.failure().unwrap_or_else(|| panic!("untyped error: {err}"));
    assert_eq!(
        (f.reason(), f.file.as_str(), f.key.as_str()),
        (pb::Reason::SceneInvalid, "scenes/bad.toml", "camera.fov_y")
    );
    let status = farm.block_on(async {
        let mut client = farm.client().await;
        client.submit(bad.clone(), "bad.toml".into(), Default::default()).await
    });
    assert!(status.is_err());
    // The coordinator still serves good jobs.
    let good = generated_scene(8);
    assert_eq!(farm.render(&good, "good.toml", false).unwrap().png, local_png(&good, "good.toml", &dir));
}

#[test]
fn two_jobs_submitted_together_both_finish_correctly() {
    let dir = scratch("farm-two");
    let farm = TestFarm::start(&[data_root(&dir.join("w0"), &dir, &[]), data_root(&dir.join("w1"), &dir, &[])]);
    let (a, b) = (generated_scene(24), generated_scene(17).replace("0.3]]", "0.8]]"));
    let (ra, rb) = farm.block_on(async {
        let (mut ca, mut cb) = (farm.client().await, farm.client().await);
        tokio::join!(
            ca.render(a.clone(), "a.toml".into(), Default::default(), |_| {}),
            cb.render(b.clone(), "b.toml".into(), Default::default(), |_| {})
        )
    });
    assert_eq!(ra.unwrap().png, local_png(&a, "a.toml", &dir));
    assert_eq!(rb.unwrap().png, local_png(&b, "b.toml", &dir));
}

#[test]
fn a_cancelled_job_stops_casting_within_a_batch() {
    let dir = scratch("farm-cancel");
    let farm = TestFarm::start(&[data_root(&dir.join("w0"), &dir, &[])]);
    // Many small batches of expensive pieces: cubic interpolation at a fine step.
    let text = generated_scene(160).replace(
        "[[objects]]\nname = \"ball\"",
        "[[objects]]\nname = \"ball\"\ninterpolation = \"cubic\"\nsampling_distance = 0.002",
    );
    let (state, done_at_cancel, done_after) = farm.block_on(async {
        let mut client = farm.client().await;
        let options = pb::JobOptions { batch_tasks: 64, ..Default::default() };
        let id = client.submit(text.clone(), "slow.toml".into(), options).await.unwrap();
        // Wait until casting has started, then cancel.
        let mut watcher = client.clone();
        let id2 = id.clone();
        let started = tokio::spawn(async move {
            let mut seen = 0;
            let _ = watcher
                .watch(&id2, |s| {
                    if s.pieces_done > 0 && seen == 0 {
                        seen = s.pieces_done;
                    }
                })
                .await;
        });
        let t0 = Instant::now();
        loop {
            let workers = client.workers().await.unwrap();
            if workers.iter().any(|w| w.batches_done > 0) || t0.elapsed() > Duration::from_secs(30) {
                break;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        let done_at_cancel: u64 = client.workers().await.unwrap().iter().map(|w| w.batches_done).sum();
        client.cancel(&id).await.unwrap();
        let last = client.watch(&id, |_| {}).await.unwrap();
        let _ = started.await;
        // Give the workers a moment to drop what was queued, then count again.
        tokio::time::sleep(Duration::from_millis(300)).await;
        let a: u64 = client.workers().await.unwrap().iter().map(|w| w.batches_done + w.batches_in_flight).sum();
        tokio::time::sleep(Duration::from_millis(500)).await;
        let b: u64 = client.workers().await.unwrap().iter().map(|w| w.batches_done + w.batches_in_flight).sum();
        assert_eq!(a, b, "batches still being answered after the cancel settled");
        // What the cancelled job had out no longer counts against its workers' capacity.
        let out: u64 = client.workers().await.unwrap().iter().map(|w| w.batches_in_flight).sum();
        assert_eq!(out, 0, "the cancelled job's batches still count as in flight");
        (last.state(), done_at_cancel, b)
    });
    assert_eq!(state, pb::JobState::Cancelled);
    // At most the batches in flight at the cancel (a few per worker) were answered after it.
    assert!(done_after <= done_at_cancel + 16, "{done_at_cancel} → {done_after}");
    // And the farm goes on serving: the next job on the same worker finishes.
    farm.render(&generated_scene(40), "after.toml", false).expect("a job after the cancelled one");
}

#[test]
fn a_worker_refuses_keys_that_leave_its_root() {
    let dir = scratch("farm-sandbox");
    let root = dir.join("root");
    std::fs::create_dir_all(&root).unwrap();
    let outside = dir.join("secret.raw");
    std::fs::write(&outside, [7u8; 8]).unwrap();
    std::fs::write(root.join("inside.raw"), [1u8; 8]).unwrap();
    #[cfg(unix)]
    std::os::unix::fs::symlink(&outside, root.join("link.raw")).unwrap();
    let farm = TestFarm::start(std::slice::from_ref(&root));
    let scene = |key: &str| {
        generated_scene(4).replace(
            "[[objects]]",
            &format!(
                "[[datasets]]\nname = \"r\"\ndims = [2, 2, 2]\n[datasets.channels.voxel]\nraw = \"{key}\"\ntype = \"u8\"\n[[objects]]"
            ),
        )
    };
    let outside_key = outside.display().to_string();
    let mut keys = vec!["../secret.raw", "./../secret.raw", outside_key.as_str()];
    if cfg!(unix) {
        keys.push("link.raw");
    }
    for key in keys {
        let err = farm.render(&scene(key), "s.toml", false).unwrap_err();
        let f = err.failure().unwrap_or_else(|| panic!("{key}: untyped error {err}"));
        assert_eq!(f.reason(), pb::Reason::DatasetNotHeld, "{key}: {f:?}");
    }
    // The file inside the root is held and casts.
    assert!(farm.render(&scene("inside.raw"), "s.toml", false).is_ok());
}

#[test]
fn random_scenes_of_many_datasets_render_as_in_local_mode_on_any_number_of_workers_with_replicas() {
    let dir = scratch("farm-random");
    let datasets = 12;
    for (seed, workers) in [(1, 1), (2, 2), (3, 3), (4, 5)] {
        let data = dir.join(format!("seed{seed}"));
        std::fs::create_dir_all(&data).unwrap();
        let text = random_scene(&data, datasets, seed);
        let name = format!("random-{seed}.toml");
        let expected = local_png(&text, &name, &data);
        // Dataset i on worker i mod n, and every third one also on the next worker.
        let roots: Vec<PathBuf> = (0..workers)
            .map(|w| {
                let files: Vec<String> = (0..datasets)
                    .filter(|i| i % workers == w || (i.is_multiple_of(3) && (i + 1) % workers == w))
                    .map(|i| format!("d{i}.raw"))
                    .collect();
                let files: Vec<&str> = files.iter().map(String::as_str).collect();
                data_root(&dir.join(format!("seed{seed}-w{w}")), &data, &files)
            })
            .collect();
        let farm = TestFarm::start(&roots);
        // Bands of a few rows and batches of a few tasks: many bands and batches in flight at
        // once, answered in whatever order the workers' threads finish them.
        for (band_rows, batch_tasks) in [(0, 0), (3, 7), (1, 1)] {
            let options = pb::JobOptions { band_rows, batch_tasks, ..Default::default() };
            let files = farm.render_with(&text, &name, options).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert!(
                files.png == expected,
                "seed {seed}, {workers} workers, bands of {band_rows} rows, batches of {batch_tasks}: the farm's PNG differs"
            );
            // The scene goes once to each worker; its other streams name it by digest.
            let stats: serde_json::Value = serde_json::from_slice(&files.stats_json).unwrap();
            let (opened, sent) = (stats["streams_opened"].as_u64().unwrap(), stats["scenes_sent"].as_u64().unwrap());
            assert!(
                (1..=workers as u64).contains(&sent) && sent < opened,
                "seed {seed}, {workers} workers: the scene was sent {sent} times on {opened} streams"
            );
        }
    }
}
