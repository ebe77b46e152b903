//! Helpers shared by the integration tests: scratch folders, rendering scene text, and the
//! location of the shared real data (tests that need it skip with a message when absent).

use std::path::{Path, PathBuf};

use trove_core::render::{render, Algorithm, Image, RenderOptions, Rendered};
use trove_core::scene::Scene;

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

/// Renders scene text with the default algorithm and returns the image.
pub fn render_text(dir: &Path, toml: &str) -> Image {
    render_in(dir, toml, Algorithm::default()).image
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
