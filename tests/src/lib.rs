//! Helpers shared by the integration tests: scratch folders, rendering scene text, and the
//! location of the shared real data (tests that need it skip with a message when absent).

use std::path::{Path, PathBuf};

use trove_core::render::{render, Algorithm, Image, RenderOptions, Rendered};
use trove_core::scene::Scene;
use trove_core::RenderError;

/// A fresh scratch folder under the system temp dir, unique to this test.
pub fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("trove-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("create scratch folder");
    dir
}

/// Parses `toml` as if it were `dir/scene.toml` and renders it with `algorithm`.
pub fn render_in(dir: &Path, toml: &str, algorithm: Algorithm) -> Rendered {
    let scene = Scene::parse(toml, dir.join("scene.toml")).unwrap_or_else(|e| panic!("scene: {e}"));
    render(&scene, &RenderOptions { algorithm, ..Default::default() }).unwrap_or_else(|e| panic!("render: {e}"))
}

/// Renders scene text with both algorithms, checks that they agree, and returns
/// Algorithm 1's image.
///
/// Algorithm 1 is f64 end to end, so closed forms can be checked against its image to
/// 1e-9. The grouped algorithm (the default) carries each piece's colour and opacity as f32
/// (16-byte results, see `trove_core::render::workunit`), so it must agree to 1e-6, plus
/// `1 − termination` where the two may stop a ray at different samples (SPEC §4.4).
pub fn render_text(dir: &Path, toml: &str) -> Image {
    let scene = Scene::parse(toml, dir.join("scene.toml")).unwrap_or_else(|e| panic!("scene: {e}"));
    let run = |algorithm| {
        render(&scene, &RenderOptions { algorithm, ..Default::default() }).unwrap_or_else(|e| panic!("render: {e}"))
    };
    let reference = run(Algorithm::PerRay).image;
    let grouped = run(Algorithm::Grouped).image;
    let slack = 1e-6 + (1.0 - scene.render().termination);
    let diff = max_abs_difference(&reference, &grouped);
    assert!(diff <= slack, "grouped differs from per-ray by {diff} (allowed {slack})");
    reference
}

/// Largest per-channel difference between two images' linear values.
pub fn max_abs_difference(a: &Image, b: &Image) -> f64 {
    a.max_abs_difference(b)
}

/// Every example scene in `scenes/`, sorted, loaded and shrunk so that its longer side is
/// `max_side` pixels (aspect kept). Scenes that read `../shared/data` are skipped, with a
/// message, where that folder is absent.
pub fn example_scenes(max_side: u32) -> Vec<(PathBuf, Scene)> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(repo_root().join("scenes"))
        .expect("scenes/ exists")
        .map(|e| e.expect("dir entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    files.sort();
    let shared = repo_root().join("../shared/data").is_dir();
    let mut scenes = Vec::new();
    for path in files {
        let text = std::fs::read_to_string(&path).expect("read scene");
        if text.contains("shared/data") && !shared {
            eprintln!("skipping {}: it reads ../shared/data, which is absent", path.display());
            continue;
        }
        let scene = Scene::load(&path).unwrap_or_else(|e| panic!("{e}"));
        let (width, height) = (scene.image().width, scene.image().height);
        let scale = max_side as f64 / width.max(height) as f64;
        let shrink = |side: u32| ((side as f64 * scale).round() as u32).max(1);
        let scene = scene.with_image_size(shrink(width), shrink(height)).unwrap_or_else(|e| panic!("{e}"));
        scenes.push((path, scene));
    }
    scenes
}

/// Renders `scene` with `algorithm` under an optional memory budget.
pub fn render_with(scene: &Scene, algorithm: Algorithm, memory_budget: Option<u64>) -> Result<Rendered, RenderError> {
    render(scene, &RenderOptions { algorithm, memory_budget, progress: None })
}

/// `../shared/data` seen from the repository root, if present.
pub fn shared_data() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    if dir.is_dir() {
        Some(dir)
    } else {
        eprintln!("skipping: ../shared/data not found (this test reads the shared real datasets)");
        None
    }
}

/// The repository root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Writes little-endian f32 voxels to `path`.
pub fn write_f32(path: &Path, values: &[f32]) {
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(path, bytes).expect("write raw file");
}
