//! Every example scene in `scenes/` loads and renders (at a reduced size). Scenes that read
//! `../shared/data` are skipped, with a message, where that folder is absent.

use std::path::PathBuf;

use trove_core::render::{render, RenderOptions};
use trove_core::scene::Scene;
use trove_tests::repo_root;

/// Every `.toml` under `scenes/`, sorted.
pub fn scene_files() -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(repo_root().join("scenes"))
        .expect("scenes/ exists")
        .map(|e| e.expect("dir entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    files.sort();
    files
}

#[test]
fn every_example_scene_renders_at_reduced_size() {
    let files = scene_files();
    assert!(files.len() >= 9, "expected the example and figure scenes, found {files:?}");
    let shared = repo_root().join("../shared/data").is_dir();
    let mut rendered = 0;
    for path in files {
        let text = std::fs::read_to_string(&path).unwrap();
        if text.contains("shared/data") && !shared {
            eprintln!("skipping {}: ../shared/data not found", path.display());
            continue;
        }
        let mut scene = Scene::load(&path).unwrap_or_else(|e| panic!("{e}"));
        let scale = 48.0 / scene.image.width.max(scene.image.height) as f64;
        scene.image.width = ((scene.image.width as f64 * scale).round() as u32).max(1);
        scene.image.height = ((scene.image.height as f64 * scale).round() as u32).max(1);
        let out = render(&scene, &RenderOptions::default()).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let background = scene.image.background;
        let px = out.image.pixels();
        assert!(px.iter().flatten().all(|c| c.is_finite()), "{}: non-finite pixel", path.display());
        let covered = px.iter().filter(|p| **p != background).count();
        assert!(covered * 20 > px.len(), "{}: only {covered} of {} pixels show an object", path.display(), px.len());
        rendered += 1;
    }
    eprintln!("rendered {rendered} scenes");
}
