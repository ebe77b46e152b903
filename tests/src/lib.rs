//! Helpers shared by the integration tests: scratch folders, rendering scene text, and the
//! location of the shared real data (tests that need it skip with a message when absent).

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use trove_core::composite::Rgba;
use trove_core::geometry::{split_into_pieces, Segment};
use trove_core::render::{render, Algorithm, Image, RenderOptions, Rendered};
use trove_core::sampling::{CastOptions, ObjectCaster};
use trove_core::scene::Scene;
use trove_core::RenderError;

/// A fresh scratch folder under the system temp dir, unique to this test.
pub fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("trove-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("create scratch folder");
    dir
}

/// Parses `toml` as if it were `dir/scene.toml` and renders it with `algorithm` (checking
/// on the way that every sampler path renders it alike, [`assert_sampler_paths_agree`]).
pub fn render_in(dir: &Path, toml: &str, algorithm: Algorithm) -> Rendered {
    let scene = Scene::parse(toml, dir.join("scene.toml")).unwrap_or_else(|e| panic!("scene: {e}"));
    assert_sampler_paths_agree(&scene);
    render(&scene, &RenderOptions { algorithm, ..Default::default() }).unwrap_or_else(|e| panic!("render: {e}"))
}

/// The ways an object can be bound to its volume: the default (specialised loop, empty
/// space skipped) first, the general loop without skipping last.
pub const SAMPLER_PATHS: [CastOptions; 4] = [
    CastOptions { specialise: true, skip_empty_space: true },
    CastOptions { specialise: true, skip_empty_space: false },
    CastOptions { specialise: false, skip_empty_space: true },
    CastOptions { specialise: false, skip_empty_space: false },
];

/// Renders `scene` ray by ray as Algorithm 1 does (f64 throughout), binding every object
/// with `options`; returns the image and the samples cast. The sampler's oracle: every
/// [`SAMPLER_PATHS`] entry must give the same image.
pub fn render_with_cast_options(scene: &Scene, options: CastOptions) -> (Image, u64) {
    let (w, h) = (scene.image.width, scene.image.height);
    let volumes: Vec<_> = scene.datasets.iter().map(|d| d.load().unwrap_or_else(|e| panic!("load: {e}"))).collect();
    let casters: Vec<ObjectCaster<'_>> = scene
        .objects
        .iter()
        .map(|o| {
            ObjectCaster::with_options(o, &volumes[o.dataset], scene.render.opacity_correction, options)
                .unwrap_or_else(|e| panic!("bind `{}`: {e}", o.name))
        })
        .collect();
    let termination = scene.render.termination;
    let rows: Vec<(Vec<[f64; 3]>, u64)> = (0..h)
        .into_par_iter()
        .map(|row| {
            let (mut segments, mut cuts, mut pieces, mut cover) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
            let mut samples = 0;
            let pixels = (0..w)
                .map(|col| {
                    let ray = scene.camera.ray(col, row, w, h);
                    segments.clear();
                    for (i, o) in scene.objects.iter().enumerate() {
                        if let Some((t_near, t_far)) = o.placement.segment(&ray) {
                            if t_far > t_near {
                                segments.push(Segment { object: i as u32, t_near, t_far });
                            }
                        }
                    }
                    split_into_pieces(&segments, &mut cuts, &mut pieces, &mut cover);
                    let mut acc = Rgba::CLEAR;
                    for piece in &pieces {
                        if acc.alpha >= termination {
                            break;
                        }
                        let objects = &cover[piece.cover.0 as usize..piece.cover.1 as usize];
                        if let [only] = objects {
                            let r = casters[*only as usize].cast(&ray, piece.t0, piece.t1, acc.alpha, termination);
                            samples += r.samples;
                            acc.over(r.rgba);
                        } else {
                            let parts: Vec<Rgba> = objects
                                .iter()
                                .map(|&o| {
                                    let r = casters[o as usize].cast(&ray, piece.t0, piece.t1, 0.0, f64::INFINITY);
                                    samples += r.samples;
                                    r.rgba
                                })
                                .collect();
                            acc.over(Rgba::colocated(parts));
                        }
                    }
                    acc.with_background(scene.image.background)
                })
                .collect();
            (pixels, samples)
        })
        .collect();
    let samples = rows.iter().map(|(_, s)| s).sum();
    (Image::new(w, h, rows.into_iter().flat_map(|(p, _)| p).collect()), samples)
}

/// Asserts that every way of binding the sampler ([`SAMPLER_PATHS`]) renders `scene` to the
/// same image, bit for bit: the specialised loops against the general one, empty-space
/// skipping against none. (Issue 10 asks for 1/255; the sampler promises identity, since
/// neither changes a sample's position or value.) Skipping casts no more samples.
pub fn assert_sampler_paths_agree(scene: &Scene) {
    let renders: Vec<(Image, u64)> = SAMPLER_PATHS.iter().map(|&o| render_with_cast_options(scene, o)).collect();
    let (reference, all_samples) = &renders[SAMPLER_PATHS.len() - 1];
    for ((image, samples), options) in renders.iter().zip(SAMPLER_PATHS) {
        assert!(
            image.pixels() == reference.pixels(),
            "{}: {options:?} differs from the general loop without skipping by {} (max byte {})",
            scene.path.display(),
            image.max_abs_difference(reference),
            image.max_byte_difference(reference)
        );
        assert!(samples <= all_samples, "{}: {options:?} cast {samples} > {all_samples} samples", scene.path.display());
    }
}

/// Renders scene text with both algorithms, checks that they agree, and returns
/// Algorithm 1's image. Every sampler path is checked to render it alike first
/// ([`assert_sampler_paths_agree`]).
///
/// Algorithm 1 is f64 end to end, so closed forms can be checked against its image to
/// 1e-9. The grouped algorithm (the default) carries each piece's colour and opacity as f32
/// (16-byte results, see `trove_core::render::workunit`), so it must agree to 1e-6, plus
/// `1 − termination` where the two may stop a ray at different samples (SPEC §4.4).
pub fn render_text(dir: &Path, toml: &str) -> Image {
    let scene = Scene::parse(toml, dir.join("scene.toml")).unwrap_or_else(|e| panic!("scene: {e}"));
    assert_sampler_paths_agree(&scene);
    let run = |algorithm| {
        render(&scene, &RenderOptions { algorithm, ..Default::default() }).unwrap_or_else(|e| panic!("render: {e}"))
    };
    let reference = run(Algorithm::PerRay).image;
    let grouped = run(Algorithm::Grouped).image;
    let slack = 1e-6 + (1.0 - scene.render.termination);
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
        let mut scene = Scene::load(&path).unwrap_or_else(|e| panic!("{e}"));
        let scale = max_side as f64 / scene.image.width.max(scene.image.height) as f64;
        scene.image.width = ((scene.image.width as f64 * scale).round() as u32).max(1);
        scene.image.height = ((scene.image.height as f64 * scale).round() as u32).max(1);
        scenes.push((path, scene));
    }
    scenes
}

/// Renders `scene` with `algorithm` under an optional memory budget; without one, checks
/// on the way that every sampler path renders it alike ([`assert_sampler_paths_agree`]).
pub fn render_with(scene: &Scene, algorithm: Algorithm, memory_budget: Option<u64>) -> Result<Rendered, RenderError> {
    if memory_budget.is_none() {
        assert_sampler_paths_agree(scene);
    }
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
