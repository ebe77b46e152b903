//! Every example scene in `scenes/` loads and renders (at a reduced size). Scenes that read
//! `../shared/data` are skipped, with a message, where that folder is absent.

use trove_core::render::{render, RenderOptions};
use trove_tests::{example_scenes, repo_root};

#[test]
fn every_example_scene_renders_at_reduced_size() {
    let count = std::fs::read_dir(repo_root().join("scenes")).expect("scenes/").count();
    assert!(count >= 9, "expected the example and figure scenes, found {count} files");
    for (path, scene) in example_scenes(48) {
        let out = render(&scene, &RenderOptions::default()).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let background = scene.image().background;
        let px = out.image.pixels();
        assert!(px.iter().flatten().all(|c| c.is_finite()), "{}: non-finite pixel", path.display());
        let covered = px.iter().filter(|p| **p != background).count();
        assert!(covered * 20 > px.len(), "{}: only {covered} of {} pixels show an object", path.display(), px.len());
    }
}
