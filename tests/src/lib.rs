//! Helpers shared by the integration tests: scratch folders, rendering scene text, and the
//! location of the shared real data; [`reference`](mod@reference) holds the scenes with closed-form ray
//! integrals that the accuracy tests and `trove-bench accuracy` measure the renderer against.
//! None of this belongs in `trove-core`: the library ships only what renders.
//!
//! Tests that need the real data (`../shared/data`, see `docs/data.md`) run only where it is.
//! Where it is absent they report the skip on the terminal — past cargo's output capture, which
//! would otherwise hide it behind an `ok` — and pass; with `TROVE_REQUIRE_DATA=1` (set by
//! `.ci/run`, since CI always has the data) a skip is a failure instead, so a broken data path
//! can never turn the data tests into silent passes.

pub mod reference;

pub mod farm;

pub mod fuzzing;

pub mod scenes;

pub mod process;

pub mod standin;

pub mod tls;

use std::io::Write;
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use trove_core::geometry::{split_into_pieces, PieceScratch, Segment};
use trove_core::render::{render, Algorithm, Image, RenderOptions, Rendered};
use trove_core::scene::{DataRoot, Scene, SceneError, SceneErrorKind};
use trove_core::RenderError;
use trove_core::Rgba;
use trove_core::{CastOptions, ObjectCaster};

/// A fresh scratch folder under the system temp dir, unique to this test.
pub fn scratch(name: &str) -> Scratch {
    let dir = std::env::temp_dir().join(format!("trove-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("create scratch folder");
    Scratch(dir)
}

/// A test's scratch folder ([`scratch`]), removed when the test is done with it, so that
/// test runs do not pile folders up in the temp dir; a failing test's folder (dropped
/// while its thread panics) stays, for looking at what it wrote.
#[must_use = "the folder is removed when this is dropped"]
#[derive(Debug)]
pub struct Scratch(PathBuf);

impl Scratch {
    /// The folder's path.
    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl std::ops::Deref for Scratch {
    type Target = Path;

    fn deref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<Path> for Scratch {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// The `[image]` and `[camera]` tables a test scene starts with. [`Header::new`] fixes
/// what every test states (size, eye, target, field of view) and defaults the rest (black
/// background, +y up); the builder methods change those where a test depends on them.
/// `Display` writes the two tables as TOML, numbers in Rust's round-trip form (`25.0`).
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Linear RGB background.
    pub background: [f64; 3],
    /// The camera's position.
    pub eye: [f64; 3],
    /// The point the camera looks at.
    pub target: [f64; 3],
    /// The camera's up direction.
    pub up: [f64; 3],
    /// Vertical field of view in degrees.
    pub fov_y: f64,
}

impl Header {
    /// A `side`×`side` image on black, seen from `eye` looking at `target` with +y up.
    pub fn new(side: u32, eye: [f64; 3], target: [f64; 3], fov_y: f64) -> Header {
        Header { width: side, height: side, background: [0.0; 3], eye, target, up: [0.0, 1.0, 0.0], fov_y }
    }

    /// The same with another image size.
    pub fn size(self, width: u32, height: u32) -> Header {
        Header { width, height, ..self }
    }

    /// The same on another background.
    pub fn background(self, background: [f64; 3]) -> Header {
        Header { background, ..self }
    }

    /// The same with another up direction.
    pub fn up(self, up: [f64; 3]) -> Header {
        Header { up, ..self }
    }
}

impl std::fmt::Display for Header {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let v = |p: [f64; 3]| format!("[{:?}, {:?}, {:?}]", p[0], p[1], p[2]);
        write!(
            f,
            "[image]\nwidth = {}\nheight = {}\nbackground = {}\n\n\
             [camera]\neye = {}\ntarget = {}\nup = {}\nfov_y = {:?}\n\n",
            self.width,
            self.height,
            v(self.background),
            v(self.eye),
            v(self.target),
            v(self.up),
            self.fov_y
        )
    }
}

/// Parses `toml` as if it were `dir/scene.toml` and renders it with `algorithm` (checking
/// on the way that every sampler path renders it alike, [`assert_sampler_paths_agree`]).
pub fn render_in(dir: &Path, toml: &str, algorithm: Algorithm) -> Rendered {
    let scene = Scene::parse(toml, dir.join("scene.toml")).unwrap_or_else(|e| panic!("scene: {e}"));
    assert_sampler_paths_agree(&scene);
    render(&scene, &RenderOptions { algorithm, ..Default::default() }).unwrap_or_else(|e| panic!("render: {e}"))
}

/// The ways an object can be bound to its volume: the default (specialised loop, empty
/// space skipped) first, the general loop without skipping last; skipping with the cells
/// classified at bind (as Algorithm 2 and the farm bind) in between.
pub const SAMPLER_PATHS: [CastOptions; 6] = [
    CastOptions { specialise: true, skip_empty_space: true, classify_upfront: false },
    CastOptions { specialise: true, skip_empty_space: true, classify_upfront: true },
    CastOptions { specialise: true, skip_empty_space: false, classify_upfront: false },
    CastOptions { specialise: false, skip_empty_space: true, classify_upfront: true },
    CastOptions { specialise: false, skip_empty_space: true, classify_upfront: false },
    CastOptions { specialise: false, skip_empty_space: false, classify_upfront: false },
];

/// Renders `scene` ray by ray as Algorithm 1 does (f64 throughout), binding every object
/// with `options`; returns the image and the samples cast. The sampler's oracle: every
/// [`SAMPLER_PATHS`] entry must give the same image.
pub fn render_with_cast_options(scene: &Scene, options: CastOptions) -> (Image, u64) {
    // Shadows' other-object shares first (SPEC §6), as every renderer computes them.
    let (scene, _) = trove_core::render::shadow::attach(scene, &trove_core::render::VolumeStore::new(None))
        .unwrap_or_else(|e| panic!("shadow pass: {e}"));
    let scene = &scene;
    let (w, h) = (scene.image().width, scene.image().height);
    let volumes: Vec<_> = scene.datasets().iter().map(|d| d.load().unwrap_or_else(|e| panic!("load: {e}"))).collect();
    let casters: Vec<ObjectCaster<'_>> = scene
        .objects()
        .iter()
        .map(|o| {
            ObjectCaster::with_options(o, &volumes[o.dataset()], scene.render().opacity_correction, options)
                .unwrap_or_else(|e| panic!("bind `{}`: {e}", o.name()))
        })
        .collect();
    let termination = scene.render().termination;
    let rows: Vec<(Vec<[f64; 3]>, u64)> = (0..h)
        .into_par_iter()
        .map(|row| {
            let (mut segments, mut scratch, mut pieces, mut cover) =
                (Vec::new(), PieceScratch::default(), Vec::new(), Vec::new());
            let mut samples = 0;
            let pixels = (0..w)
                .map(|col| {
                    let ray = scene.camera().ray(col, row, w, h);
                    segments.clear();
                    for (i, o) in scene.objects().iter().enumerate() {
                        if let Some((t_near, t_far)) = o.placement().segment(&ray) {
                            if t_far > t_near {
                                segments.push(Segment { object: i as u32, t_near, t_far });
                            }
                        }
                    }
                    split_into_pieces(&segments, &mut scratch, &mut pieces, &mut cover);
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
                    acc.with_background(scene.image().background)
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
            scene.path().display(),
            image.max_abs_difference(reference),
            image.max_byte_difference(reference)
        );
        assert!(
            samples <= all_samples,
            "{}: {options:?} cast {samples} > {all_samples} samples",
            scene.path().display()
        );
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
    let slack = 1e-6 + (1.0 - scene.render().termination);
    let diff = max_abs_difference(&reference, &grouped);
    assert!(diff <= slack, "grouped differs from per-ray by {diff} (allowed {slack})");
    reference
}

/// Largest per-channel difference between two images' linear values.
pub fn max_abs_difference(a: &Image, b: &Image) -> f64 {
    a.max_abs_difference(b)
}

/// Every example scene in `scenes/`, sorted, loaded with [`shared_data_dir`] as the data
/// root (given explicitly, as `--data-root` would give it: tests never read `TROVE_DATA`) and
/// shrunk so that its longer side is `max_side` pixels (aspect kept). A scene whose data is
/// not there is skipped where that folder is absent, with a line on the terminal (see
/// [`skip`]); anywhere else a missing file is a failure.
pub fn example_scenes(max_side: u32) -> Vec<(PathBuf, Scene)> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(repo_root().join("scenes"))
        .expect("scenes/ exists")
        .map(|e| e.expect("dir entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    files.sort();
    let data = shared_data_dir();
    let root = DataRoot::Given(data.clone());
    let mut scenes = Vec::new();
    for path in files {
        let scene = match Scene::load_in(&path, &root) {
            Ok(scene) => scene,
            Err(SceneError { kind: SceneErrorKind::DataNotFound { .. }, .. }) if !data.is_dir() => {
                let name = path.file_name().unwrap_or_default().to_string_lossy();
                skip(&format!("scenes/{name} reads ../shared/data, which is absent"));
                continue;
            }
            Err(e) => panic!("{e}"),
        };
        let (width, height) = shrunk(scene.image().width, scene.image().height, max_side);
        let scene = scene.with_image_size(width, height).unwrap_or_else(|e| panic!("{e}"));
        scenes.push((path, scene));
    }
    scenes
}

/// An image size scaled so that its longer side is `max_side` (aspect kept, at least 1).
fn shrunk(width: u32, height: u32, max_side: u32) -> (u32, u32) {
    let scale = max_side as f64 / width.max(height) as f64;
    let shrink = |side: u32| ((side as f64 * scale).round() as u32).max(1);
    (shrink(width), shrink(height))
}

/// Renders `scene` with `algorithm` under an optional memory budget; without one, checks
/// on the way that every sampler path renders it alike ([`assert_sampler_paths_agree`]).
pub fn render_with(scene: &Scene, algorithm: Algorithm, memory_budget: Option<u64>) -> Result<Rendered, RenderError> {
    if memory_budget.is_none() {
        assert_sampler_paths_agree(scene);
    }
    render(scene, &RenderOptions { algorithm, memory_budget, ..Default::default() })
}

/// `../shared/data` beside the repository: the data root of the example scenes, present or
/// not.
pub fn shared_data_dir() -> PathBuf {
    repo_root().join("../shared/data")
}

/// `../shared/data` seen from the repository root, if present; otherwise the calling test
/// should return early, and this reports the skip (see [`skip`]).
pub fn shared_data() -> Option<PathBuf> {
    let dir = shared_data_dir();
    if dir.is_dir() {
        Some(dir)
    } else {
        skip("../shared/data, the real datasets, is absent");
        None
    }
}

/// The variable that turns every skip into a failure (`.ci/run` sets it).
pub const REQUIRE_DATA: &str = "TROVE_REQUIRE_DATA";

/// Whether skips are failures: `TROVE_REQUIRE_DATA` is set to anything but empty or `0`.
pub fn data_required() -> bool {
    std::env::var_os(REQUIRE_DATA).is_some_and(|v| !v.is_empty() && v != "0")
}

/// Reports that the running test skips part or all of its work for `reason`, or fails it
/// when [`data_required`].
///
/// libtest captures `print!`/`eprint!` and shows them only for failing tests, so a skipped
/// test would look like any other pass. This writes to the standard error handle itself,
/// which the capture does not intercept, so the line appears in the run's output next to
/// the test's `ok`, naming the test (libtest names each test's thread after it).
pub fn skip(reason: &str) {
    let test = std::thread::current().name().unwrap_or("a test").to_string();
    if data_required() {
        panic!("{test}: {reason}, and {REQUIRE_DATA} is set, so this is a failure, not a skip (docs/data.md)");
    }
    let _ = writeln!(
        std::io::stderr().lock(),
        "SKIPPED in {test}: {reason}; see docs/data.md, or set {REQUIRE_DATA}=1 to fail instead"
    );
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

/// Reads an RGB Portable FloatMap (as `Image::save` writes for `.pfm`), for comparing the
/// unquantised output with expectations. Panics, naming the file, on anything malformed: a
/// test that reads a broken PFM has failed.
pub fn read_pfm(path: &Path) -> Image {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let bad = |what: &str| -> ! { panic!("{}: PFM {what}", path.display()) };
    // Four whitespace-separated header fields, then exactly one whitespace byte.
    let mut fields = Vec::new();
    let mut pos = 0;
    while fields.len() < 4 {
        pos += bytes[pos..].iter().take_while(|b| b.is_ascii_whitespace()).count();
        let len = bytes[pos..].iter().take_while(|b| !b.is_ascii_whitespace()).count();
        if len == 0 {
            bad("header is truncated");
        }
        fields.push(String::from_utf8_lossy(&bytes[pos..pos + len]).into_owned());
        pos += len;
    }
    if fields[0] != "PF" {
        bad("magic is not PF (only RGB PFM is read)");
    }
    let w: usize = fields[1].parse().unwrap_or_else(|_| bad("width"));
    let h: usize = fields[2].parse().unwrap_or_else(|_| bad("height"));
    let scale: f64 = fields[3].parse().unwrap_or_else(|_| bad("scale"));
    let data = bytes.get(pos + 1..pos + 1 + w * h * 12).unwrap_or_else(|| bad("data is truncated"));
    let value = |i: usize| {
        let b: [u8; 4] = data[i * 4..i * 4 + 4].try_into().expect("4 bytes");
        (if scale < 0.0 { f32::from_le_bytes(b) } else { f32::from_be_bytes(b) }) as f64
    };
    // Rows are stored bottom to top.
    let pixels = (0..w * h)
        .map(|i| {
            let (row, col) = (i / w, i % w);
            let src = 3 * ((h - 1 - row) * w + col);
            [value(src), value(src + 1), value(src + 2)]
        })
        .collect();
    Image::new(w as u32, h as u32, pixels)
}

/// The text of example scene `path` as a farm job: its dataset keys as written (a farm's
/// workers resolve them under their own data roots) and its image shrunk so that its longer
/// side is `max_side` pixels, as [`example_scenes`] shrinks it.
pub fn shrunk_scene_text(path: &Path, max_side: u32) -> String {
    let text = std::fs::read_to_string(path).expect("read scene");
    let mut table: toml::Table = text.parse().unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let image = table.get_mut("image").and_then(|v| v.as_table_mut()).expect("[image]");
    let side = |key: &str| u32::try_from(image[key].as_integer().expect("an integer")).expect("a pixel count");
    let (width, height) = shrunk(side("width"), side("height"), max_side);
    image.insert("width".into(), toml::Value::Integer(width.into()));
    image.insert("height".into(), toml::Value::Integer(height.into()));
    toml::to_string(&table).expect("serialise scene")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_header_is_the_scene_format_s_image_and_camera() {
        let h = Header::new(7, [0.5, 0.5, 3.0], [0.5, 0.5, 0.5], 25.0).size(7, 5).background([0.2, 0.4, 0.6]);
        let text = h.to_string();
        assert!(text.contains("width = 7\nheight = 5\n") && text.contains("fov_y = 25.0\n"), "{text}");
        let scene = trove_core::scene::Scene::parse(&text, "header.toml").unwrap_or_else(|e| panic!("{e}\n{text}"));
        assert_eq!((scene.image().width, scene.image().height, scene.image().background), (7, 5, [0.2, 0.4, 0.6]));
        let ray = scene.camera().ray(3, 2, 7, 5);
        assert_eq!(ray.origin.to_array(), [0.5, 0.5, 3.0]);
        assert!((ray.dir.to_array()[2] + 1.0).abs() < 1e-12, "the centre ray looks down −z: {:?}", ray.dir);
    }

    #[test]
    fn a_scratch_folder_is_removed_when_dropped_and_kept_when_its_test_fails() {
        let done = scratch("scratch-done");
        std::fs::write(done.join("file"), b"x").unwrap();
        let path = done.to_path_buf();
        drop(done);
        assert!(!path.exists(), "a finished test's folder is left behind");

        let failed = std::thread::spawn(|| {
            let dir = scratch("scratch-failed");
            std::fs::write(dir.join("file"), b"x").unwrap();
            let path = dir.to_path_buf();
            std::panic::panic_any(path);
        })
        .join()
        .expect_err("the thread panics");
        let path = failed.downcast::<PathBuf>().expect("the folder's path");
        assert!(path.join("file").exists(), "a failed test's folder is gone");
        std::fs::remove_dir_all(*path).unwrap();
    }

    #[test]
    fn a_saved_pfm_reads_back_to_f32_precision_with_row_zero_on_top() {
        let img = Image::new(
            2,
            3,
            vec![[0.1, 0.2, 0.3], [0.4, 0.5, 0.6], [0.7, 0.8, 0.9], [1.5, -0.5, 0.0], [0.0; 3], [1.0; 3]],
        );
        let dir = scratch("pfm");
        let path = dir.join("img.pfm");
        img.save(&path).expect("save");
        let back = read_pfm(&path);
        assert_eq!((back.width(), back.height()), (2, 3));
        for (a, b) in img.pixels().iter().zip(back.pixels()) {
            for i in 0..3 {
                assert!((a[i] - b[i]).abs() < 1e-7, "{a:?} vs {b:?}");
            }
        }
    }

    /// The complete scenes in the user documentation load: the reference must not teach a
    /// scene that TROVE refuses.
    #[test]
    fn the_scenes_in_docs_scene_format_load() {
        let doc = std::fs::read_to_string(repo_root().join("docs/scene-format.md")).expect("docs/scene-format.md");
        let blocks: Vec<&str> = doc.split("```toml\n").skip(1).filter_map(|b| b.split("```").next()).collect();
        let scenes: Vec<&&str> = blocks.iter().filter(|b| b.contains("[image]")).collect();
        assert!(!scenes.is_empty(), "no complete scene in docs/scene-format.md");
        let dir = scratch("doc-scenes");
        for text in scenes {
            Scene::parse(text, dir.join("scene.toml")).unwrap_or_else(|e| panic!("{e}\n{text}"));
        }
    }
}
