//! Issue 10: the sampler's specialised loops and empty-space skipping change no image.
//! Every example scene (and the peers' benchmark scenes, where their data is present), every
//! closed-form reference scene and — through the test-support render helpers — every scene
//! the other suites render, renders bit for bit alike on every sampler path
//! ([`trove_tests::SAMPLER_PATHS`]). The skipping logic itself is unit-tested beside it, in
//! `trove-core/src/sampling/tests.rs`.

use trove_core::scene::{DataRoot, Scene, SceneError, SceneErrorKind};
use trove_core::Interpolation;
use trove_core::ObjectCaster;
use trove_tests::reference::{Reference, Setup};
use trove_tests::{
    assert_sampler_paths_agree, example_scenes, render_with_cast_options, repo_root, shared_data_dir, skip,
    SAMPLER_PATHS,
};

#[test]
fn every_example_scene_renders_alike_on_every_sampler_path() {
    for (path, scene) in example_scenes(64) {
        eprintln!("{}", path.display());
        assert_sampler_paths_agree(&scene);
    }
}

#[test]
fn the_peers_benchmark_scenes_render_alike_and_skip_empty_space() {
    let dir = repo_root().join("scenes/peers");
    let mut rendered = 0;
    // Each scene's data root (its comment says how to get or make the data). The synthetic
    // volume and the f32 head are made by scripts, not part of the shared data, so their
    // absence is never a failure, even where missing shared data is.
    for (name, data, shared) in [
        ("cthead.toml", shared_data_dir(), true),
        ("synthetic-u8.toml", dir.join("data"), false),
        ("cthead-f32.toml", dir.join("data"), false),
    ] {
        let path = dir.join(name);
        let scene = match Scene::load_in(&path, &DataRoot::Given(data.clone())) {
            Ok(scene) => scene,
            Err(SceneError { kind: SceneErrorKind::DataNotFound { .. }, .. }) => {
                let reason = format!("scenes/peers/{name}: its data is absent under {}", data.display());
                if shared {
                    skip(&reason);
                } else {
                    eprintln!("SKIPPED: {reason} (made by a script, see the scene's comment)");
                }
                continue;
            }
            Err(e) => panic!("{e}"),
        };
        let scene = scene.with_image_size(48, 48).unwrap_or_else(|e| panic!("{e}"));
        assert_sampler_paths_agree(&scene);
        let (_, with_skipping) = render_with_cast_options(&scene, SAMPLER_PATHS[0]);
        let (_, without) = render_with_cast_options(&scene, SAMPLER_PATHS[SAMPLER_PATHS.len() - 1]);
        assert!(with_skipping < without, "{name}: {with_skipping} samples with skipping, {without} without");
        rendered += 1;
    }
    eprintln!("{rendered} peers scenes checked");
}

#[test]
fn every_reference_scene_renders_alike_on_every_sampler_path() {
    for r in Reference::ALL {
        for interpolation in [
            Interpolation::Nearest,
            Interpolation::Trilinear,
            Interpolation::Nonlinear { omega: [0.0, 0.5, 0.5] },
            Interpolation::Cubic,
        ] {
            for opacity_correction in [true, false] {
                let setup = Setup { dims: 12, image_side: 20, interpolation, step_voxels: 0.37, opacity_correction };
                let scene = r.scene(&setup).unwrap_or_else(|e| panic!("{}: {e}", r.name()));
                assert_sampler_paths_agree(&scene);
            }
        }
    }
}

#[test]
fn example_scenes_use_specialised_loops() {
    // Every object of the example scenes has a specialised loop except the combinations the
    // general loop keeps (bit voxels, mixed raw and voxel maps).
    let (mut specialised, mut objects) = (0, 0);
    for (path, scene) in example_scenes(8) {
        // A scene with shadows binds once the other objects' shares are computed.
        let (scene, _) = trove_core::render::shadow::attach(&scene, &trove_core::render::VolumeStore::new(None))
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let volumes: Vec<_> = scene.datasets().iter().map(|d| d.load().expect("load")).collect();
        for o in scene.objects() {
            let caster = ObjectCaster::new(o, &volumes[o.dataset()], scene.render().opacity_correction)
                .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            objects += 1;
            specialised += usize::from(caster.is_specialised());
        }
    }
    eprintln!("{specialised} of {objects} example objects run specialised loops");
    assert!(objects == 0 || specialised * 4 >= objects * 3, "{specialised} of {objects}");
}
