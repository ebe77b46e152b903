//! Algorithm 1 (per ray) and Algorithm 2 (grouped by dataset) render the same image
//! (SPEC §4.4), and the memory budget behaves as SPEC §5 says: datasets are evicted and
//! reloaded, every load is counted, resident bytes never exceed the budget, and a budget
//! that cannot hold a dataset is refused with a clear error.

use std::path::Path;

use trove_core::render::StoreError;
use trove_core::render::{Algorithm, Rendered};
use trove_core::scene::Scene;
use trove_core::RenderError;
use trove_tests::{example_scenes, max_abs_difference, render_with, scratch, write_f32, Header};

fn parse(dir: &Path, text: &str) -> Scene {
    Scene::parse(text, dir.join("scene.toml")).unwrap_or_else(|e| panic!("scene: {e}"))
}

fn both(scene: &Scene, budget: Option<u64>) -> (Rendered, Rendered) {
    let per_ray = render_with(scene, Algorithm::PerRay, budget).unwrap_or_else(|e| panic!("per-ray: {e}"));
    let grouped = render_with(scene, Algorithm::Grouped, budget).unwrap_or_else(|e| panic!("grouped: {e}"));
    (per_ray, grouped)
}

fn header(size: u32, termination: f64) -> String {
    let header = Header::new(size, [0.0, 0.6, 4.0], [0.0, 0.0, 0.0], 40.0).background([0.1, 0.2, 0.3]);
    format!("{header}[render]\ntermination = {termination}\n")
}

/// `count` generated datasets `d0..`, each `n`³ f32 (a radial sphere of a different size).
fn datasets(count: usize, n: u32) -> String {
    (0..count)
        .map(|i| {
            let radius = 0.35 + 0.04 * i as f64;
            format!(
                "[[datasets]]\nname = \"d{i}\"\ndims = [{n}, {n}, {n}]\n[datasets.channels.voxel]\n\
                 generator = {{ kind = \"sphere\", radius = {radius}, profile = \"radial\", value = 1.0, type = \"f32\" }}\n"
            )
        })
        .collect()
}

/// An object of dataset `d` in the box `min + [0, size]³`, translucent or opaque.
fn object(name: &str, d: usize, min: [f64; 3], size: f64, opaque: bool) -> String {
    let opacity = if opaque { "[[0.0, 0.0], [0.05, 0.9]]" } else { "[[0.0, 0.0], [0.3, 0.04], [1.0, 0.12]]" };
    let hue = [[0.9, 0.3, 0.2], [0.2, 0.8, 0.4], [0.3, 0.4, 1.0], [0.9, 0.9, 0.3]][d % 4];
    format!(
        "[[objects]]\nname = \"{name}\"\ndataset = \"d{d}\"\n\
         colour = {{ type = \"ramp\", points = [[0.0, {}, {}, {}], [1.0, 1.0, 1.0, 1.0]] }}\n\
         opacity = {{ type = \"ramp\", points = {opacity} }}\n\
         transform = {{ matrix = [[{size}, 0, 0, {}], [0, {size}, 0, {}], [0, 0, {size}, {}], [0, 0, 0, 1]] }}\n",
        hue[0], hue[1], hue[2], min[0], min[1], min[2]
    )
}

/// Translucent objects of three datasets overlapping in space: pieces shared by objects of
/// different datasets, composited as co-located media only once all are cast.
fn overlapping_translucent(size: u32, termination: f64) -> String {
    header(size, termination)
        + &datasets(3, 12)
        + &object("a", 0, [-1.0, -0.6, -0.5], 1.3, false)
        + &object("b", 1, [-0.4, -0.8, -0.9], 1.3, false)
        + &object("c", 2, [-0.1, -0.3, -0.2], 1.1, false)
        + &object("d", 0, [-0.8, -0.2, -1.4], 1.6, false)
        + &object("e", 1, [0.2, -0.9, 0.3], 0.8, false)
}

/// Two slabs crossing in an X seen from the front: on the left of the image rays meet
/// dataset 0 first, on the right dataset 1 first, so no dataset order follows every ray
/// and the grouped algorithm must cast some pieces before what lies in front is known.
fn crossed_slabs(size: u32) -> String {
    let slab = |name: &str, d: usize, angle: f64| {
        let (s, c) = angle.to_radians().sin_cos();
        // A 3 × 1.2 × 0.3 slab centred at the origin, turned about y.
        let (lx, ly, lz) = (3.0, 1.2, 0.3);
        let m = [[lx * c, 0.0, lz * s], [0.0, ly, 0.0], [-lx * s, 0.0, lz * c]];
        let centre = |r: [f64; 3]| -(r[0] + r[1] + r[2]) / 2.0;
        format!(
            "[[objects]]\nname = \"{name}\"\ndataset = \"d{d}\"\n\
             colour = {{ type = \"constant\", red = [{}], green = [0.5], blue = [{}] }}\n\
             opacity = {{ type = \"ramp\", points = [[0.0, 0.15], [1.0, 0.6]] }}\n\
             transform = {{ matrix = [[{}, {}, {}, {}], [{}, {}, {}, {}], [{}, {}, {}, {}], [0, 0, 0, 1]] }}\n",
            0.9 - 0.7 * d as f64,
            0.2 + 0.7 * d as f64,
            m[0][0],
            m[0][1],
            m[0][2],
            centre(m[0]),
            m[1][0],
            m[1][1],
            m[1][2],
            centre(m[1]),
            m[2][0],
            m[2][1],
            m[2][2],
            centre(m[2]),
        )
    };
    header(size, 0.999) + &datasets(2, 10) + &slab("left-front", 0, 35.0) + &slab("right-front", 1, -35.0)
}

/// A small Fig. 1: nine objects from one dataset in three rows, opaque ones in front of
/// translucent ones and the other way round.
fn rows_of_one_dataset(size: u32, datasets_count: usize) -> String {
    let mut text = header(size, 0.999) + &datasets(datasets_count, 12);
    let mut i = 0;
    for (z, y) in [(0.6, -0.5), (-0.3, -0.4), (-1.2, -0.3)] {
        for x in [-1.3, -0.45, 0.4] {
            text += &object(&format!("o{i}"), i % datasets_count, [x, y, z], 0.8, i % 3 != 1);
            i += 1;
        }
    }
    text
}

#[test]
fn per_ray_and_grouped_agree_on_every_scene_in_scenes() {
    let scenes = example_scenes(64);
    assert!(!scenes.is_empty(), "no scene files in scenes/");
    for (path, scene) in scenes {
        let (a, b) = both(&scene, None);
        let d = a.image.max_byte_difference(&b.image);
        assert!(d <= 1, "{}: per-ray and grouped differ by {d}/255", path.display());
        assert_eq!(a.stats.pieces, b.stats.pieces, "{}", path.display());
    }
}

#[test]
fn per_ray_and_grouped_agree_on_overlapping_translucent_objects() {
    let dir = scratch("alg-overlap");
    // Without early termination the only difference is f32 piece results.
    let (a, b) = both(&parse(&dir, &overlapping_translucent(48, 1.0)), None);
    assert!(max_abs_difference(&a.image, &b.image) < 1e-6, "{}", max_abs_difference(&a.image, &b.image));
    assert_eq!(a.stats.samples, b.stats.samples);
    assert!(a.image.pixels().iter().any(|p| p != &[0.1, 0.2, 0.3]), "the objects must be visible");
    // With it, within one 8-bit level.
    let (a, b) = both(&parse(&dir, &overlapping_translucent(48, 0.95)), None);
    assert!(a.image.max_byte_difference(&b.image) <= 1);
}

#[test]
fn grouped_is_right_when_no_dataset_order_follows_every_ray() {
    let dir = scratch("alg-crossed");
    let scene = parse(&dir, &crossed_slabs(64));
    let (a, b) = both(&scene, None);
    assert!(a.image.max_byte_difference(&b.image) <= 1, "{}", a.image.max_byte_difference(&b.image));
    assert!(max_abs_difference(&a.image, &b.image) <= 1e-6 + 0.001);
    // Both slabs are met first on some rays: each dataset had blind casts or culls.
    assert!(b.stats.samples_skipped > 0);
}

#[test]
fn grouped_early_termination_casts_about_as_many_samples_as_per_ray() {
    let dir = scratch("alg-early");
    for datasets_count in [1, 3] {
        let (a, b) = both(&parse(&dir, &rows_of_one_dataset(64, datasets_count)), None);
        assert!(a.image.max_byte_difference(&b.image) <= 1);
        let ratio = b.stats.samples as f64 / a.stats.samples as f64;
        assert!(ratio <= 1.15, "{datasets_count} datasets: grouped cast {ratio}× the per-ray samples");
        assert!(b.stats.samples_skipped > 0, "opaque objects hide others, so some pieces are skipped");
        // Without early termination the grouped algorithm would cast every piece.
        let total = b.stats.samples + b.stats.samples_skipped;
        assert!(total > a.stats.samples + a.stats.samples / 10, "{total} vs {}", a.stats.samples);
    }
}

/// A wide slab of `depth` in z from `z0`, covering x and y over [−1, 2], of a constant
/// dataset `dataset`, with constant opacity `opacity` and an explicit sampling distance.
fn constant_slab(name: &str, dataset: &str, z0: f64, depth: f64, opacity: f64, step: f64) -> String {
    format!(
        "[[datasets]]\nname = \"{dataset}\"\ndims = [2, 2, 2]\n[datasets.channels.voxel]\n\
         generator = {{ kind = \"constant\", value = 0.0 }}\n\
         [[objects]]\nname = \"{name}\"\ndataset = \"{dataset}\"\n\
         colour = {{ type = \"constant\", red = [1.0], green = [1.0], blue = [1.0] }}\n\
         opacity = {{ type = \"constant\", coefficients = [{opacity:?}] }}\nsampling_distance = {step:?}\n\
         transform = {{ matrix = [[3, 0, 0, -1], [0, 3, 0, -1], [0, 0, {depth:?}, {z0:?}], [0, 0, 0, 1]] }}\n"
    )
}

#[test]
fn samples_skipped_counts_every_sample_position_hidden_behind_an_opaque_object() {
    // Every ray meets an opaque slab (z in [1, 1.2]; its first sample makes the ray opaque)
    // and then a translucent one (z in [0, 0.5]) that it never casts. Each of those rays skips
    // exactly the back slab's SPEC §4.2 sample count, computed here from SPEC §4.1's rays.
    let (side, fov, step, depth) = (9u32, 20.0f64, 0.0173, 0.5);
    let text = Header::new(side, [0.5, 0.5, 3.0], [0.5, 0.5, 0.0], fov).to_string()
        + "[render]\ntermination = 0.999\n"
        + &constant_slab("front", "a", 1.0, 0.2, 1.0, 0.05)
        + &constant_slab("back", "b", 0.0, depth, 0.1, step);
    let dir = scratch("alg-skipped");
    let scene = parse(&dir, &text);
    let s = (fov.to_radians() / 2.0).tan();
    let mut expected = 0u64;
    for row in 0..side {
        for col in 0..side {
            // The camera looks down −z with +y up, so dir ∝ (x·s, y·s, −1).
            let x = (2.0 * (col as f64 + 0.5) / side as f64 - 1.0) * s;
            let y = (1.0 - 2.0 * (row as f64 + 0.5) / side as f64) * s;
            // The ray crosses the back slab through its front and back faces (|x|, |y| stay
            // far inside [−1, 2]), over a length depth / |dir.z|.
            let samples = depth * (1.0 + x * x + y * y).sqrt() / step;
            assert!(((samples.fract()) - 0.5).abs() > 1e-6, "pixel ({col}, {row}) sits on a rounding tie");
            expected += samples.round().max(1.0) as u64;
        }
    }
    let pixels = (side * side) as u64;
    for algorithm in [Algorithm::PerRay, Algorithm::Grouped] {
        let r = render_with(&scene, algorithm, None).unwrap_or_else(|e| panic!("{e}"));
        let name = algorithm.name();
        assert_eq!(r.stats.samples_skipped, expected, "{name}: samples skipped behind the opaque slab");
        if algorithm == Algorithm::PerRay {
            // One sample in the front slab per ray, and nothing cast behind it.
            assert_eq!(r.stats.samples, pixels, "{name}: samples cast");
        }
        assert!(r.image.pixels().iter().all(|p| *p == [1.0; 3]), "{name}: every pixel is the white front slab");
    }
}

/// Four datasets of 24³ f32 in rows, so rays alternate between them; with the total bytes
/// they occupy once loaded (55 296 voxel bytes each plus their macrocell ranges).
fn budget_scene(dir: &Path) -> (Scene, u64) {
    let mut text = header(48, 0.999) + &datasets(4, 24);
    // An unused dataset must never be loaded.
    text += "[[datasets]]\nname = \"unused\"\ndims = [30, 30, 30]\n[datasets.channels.voxel]\n\
             generator = { kind = \"constant\", value = 1.0 }\n";
    let mut i = 0;
    for z in [0.5, -0.1, -0.7, -1.3] {
        for x in [-1.0, -0.2] {
            text += &object(&format!("o{i}"), i % 4, [x + 0.15 * (i % 3) as f64, -0.5, z], 0.9, false);
            i += 1;
        }
    }
    let scene = parse(dir, &text);
    let total = scene.datasets()[..4].iter().map(|d| d.resident_bytes()).sum();
    assert!(total > 4 * 24u64.pow(3) * 4);
    (scene, total)
}

#[test]
fn with_no_budget_each_dataset_is_loaded_once() {
    let dir = scratch("alg-nobudget");
    let (scene, total) = budget_scene(&dir);
    let (a, b) = both(&scene, None);
    for r in [&a, &b] {
        assert_eq!(r.stats.dataset_loads, 4, "{}", r.stats.algorithm);
        assert_eq!(r.stats.bytes_loaded, total, "{}", r.stats.algorithm);
        assert_eq!(r.stats.memory_budget, None);
    }
    // Algorithm 2 unloads each dataset after its turn: one dataset at a time, with the
    // macrocell classification of its objects kept beside it (a few hundred bytes here).
    let one = total / 4;
    assert!((one..one + one / 16).contains(&b.stats.peak_resident_bytes), "{} of {one}", b.stats.peak_resident_bytes);
    assert_eq!(a.stats.peak_resident_bytes, total);
    assert!(a.image.max_byte_difference(&b.image) <= 1);
}

#[test]
fn a_short_budget_makes_per_ray_reload_while_grouped_loads_each_voxel_once() {
    let dir = scratch("alg-budget");
    let (scene, total) = budget_scene(&dir);
    let one = total / 4;
    let budget = one + one / 2; // one dataset and a half: never two at once
    let (a, b) = both(&scene, Some(budget));
    assert!(a.stats.dataset_loads > b.stats.dataset_loads, "{} vs {}", a.stats.dataset_loads, b.stats.dataset_loads);
    assert_eq!(b.stats.dataset_loads, 4);
    assert!(b.stats.bytes_loaded <= total);
    assert_eq!(a.stats.bytes_loaded, a.stats.dataset_loads * one);
    for r in [&a, &b] {
        assert!(r.stats.peak_resident_bytes <= budget, "{}: {}", r.stats.algorithm, r.stats.peak_resident_bytes);
        assert!(r.stats.peak_resident_bytes >= one);
        assert_eq!(r.stats.memory_budget, Some(budget));
    }
    assert!(a.image.max_byte_difference(&b.image) <= 1);
    // The budget changes when data is loaded, never the image.
    let unlimited = render_with(&scene, Algorithm::PerRay, None).unwrap();
    assert_eq!(unlimited.image, a.image);
}

#[test]
fn a_budget_of_exactly_one_dataset_renders_on_many_threads_without_deadlock() {
    // Loads run inside rayon jobs while other jobs wait for them; a loader that used rayon
    // itself once deadlocked here, so a watchdog turns a hang into a failure, and a few
    // repetitions give the thread interleavings a chance to show it.
    let (done_tx, done_rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let dir = scratch("alg-tight");
        let (scene, total) = budget_scene(&dir);
        let budget = total / 4;
        let pool = rayon::ThreadPoolBuilder::new().num_threads(4).build().unwrap();
        for _ in 0..5 {
            let (a, b) = pool.install(|| both(&scene, Some(budget)));
            for r in [&a, &b] {
                assert!(r.stats.peak_resident_bytes <= budget);
            }
            assert!(a.stats.dataset_loads > 4);
            assert!(a.image.max_byte_difference(&b.image) <= 1);
        }
        let _ = done_tx.send(());
    });
    match done_rx.recv_timeout(std::time::Duration::from_secs(120)) {
        Ok(()) => {}
        Err(std::sync::mpsc::RecvTimeoutError::Timeout) => panic!("rendering under a one-dataset budget deadlocked"),
        Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
            panic!("the render thread failed (see its panic above)")
        }
    }
}

/// Eight small objects of eight datasets side by side, in front of a translucent backdrop
/// of a ninth that every one of them covers a part of.
fn side_by_side(size: u32) -> (String, usize) {
    let mut text = header(size, 0.999) + &datasets(9, 12);
    for i in 0..8 {
        let (x, y) = (-1.5 + 0.75 * (i % 4) as f64, if i < 4 { 0.05 } else { -0.75 });
        text += &object(&format!("o{i}"), i, [x, y, 0.5], 0.6, i % 2 == 0);
    }
    text += &object("backdrop", 8, [-1.8, -1.2, -1.5], 2.6, false);
    (text, 9)
}

#[test]
fn a_kept_store_serves_a_second_render_of_many_datasets_on_many_threads() {
    use trove_core::render::{render, RenderOptions, VolumeStore};
    let (text, count) = side_by_side(40);
    let dir = scratch("alg-kept");
    let scene = parse(&dir, &text);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(4).build().unwrap();
    let store = VolumeStore::new(None);
    let kept = RenderOptions { store: Some(store.clone()), ..Default::default() };
    let first = pool.install(|| render(&scene, &kept)).unwrap();
    // Each dataset loaded once and each object's classification worked out once.
    assert_eq!(first.stats.dataset_loads, count as u64);
    assert_eq!(first.stats.classification_misses, count as u64);
    let all: u64 = scene.datasets().iter().map(|d| d.resident_bytes()).sum();
    assert!(store.resident_bytes() > all, "the datasets and their classifications stay resident");
    let second = pool.install(|| render(&scene, &kept)).unwrap();
    assert_eq!((second.stats.dataset_loads, second.stats.bytes_loaded), (0, 0));
    assert_eq!(second.stats.classification_misses, 0);
    assert!(second.stats.classification_hits >= count as u64);
    assert!(second.image.pixels() == first.image.pixels());
    assert_eq!(second.stats.samples, first.stats.samples);
    // Without a kept store the same render loads and classifies everything again.
    let own = pool.install(|| render(&scene, &RenderOptions::default())).unwrap();
    assert_eq!((own.stats.dataset_loads, own.stats.classification_misses), (count as u64, count as u64));
    assert!(own.image.pixels() == first.image.pixels());
}

#[test]
fn a_budget_smaller_than_a_dataset_is_a_clear_error() {
    let dir = scratch("alg-small");
    let (scene, total) = budget_scene(&dir);
    for algorithm in [Algorithm::PerRay, Algorithm::Grouped] {
        match render_with(&scene, algorithm, Some(total / 4 - 1)) {
            Err(RenderError::Store(StoreError::BudgetTooSmall { name, needed, budget })) => {
                assert_eq!((name.as_str(), needed, budget), ("d0", total / 4, total / 4 - 1));
            }
            Err(e) => panic!("{}: wrong error {e}", algorithm.name()),
            Ok(_) => panic!("{}: rendered under a budget smaller than a dataset", algorithm.name()),
        }
    }
}

#[test]
fn under_a_budget_a_mapped_raw_file_is_read_into_memory_and_counted() {
    let dir = scratch("alg-raw");
    let n = 16usize;
    let values: Vec<f32> = (0..n * n * n).map(|i| ((i * 7) % 13) as f32 / 13.0).collect();
    write_f32(&dir.join("v.raw"), &values);
    let text = header(32, 0.999)
        + &format!("[[datasets]]\nname = \"d0\"\ndims = [{n}, {n}, {n}]\n[datasets.channels.voxel]\nraw = \"v.raw\"\ntype = \"f32\"\n")
        + &object("o", 0, [-0.5, -0.5, -0.5], 1.0, false);
    let scene = parse(&dir, &text);
    // The voxels and their macrocell ranges.
    let bytes = scene.datasets()[0].resident_bytes();
    assert!(bytes > (n * n * n * 4) as u64);
    let mapped = render_with(&scene, Algorithm::Grouped, None).unwrap();
    let copied = render_with(&scene, Algorithm::Grouped, Some(bytes)).unwrap();
    assert_eq!(mapped.image, copied.image);
    assert_eq!((copied.stats.dataset_loads, copied.stats.bytes_loaded), (1, bytes));
    assert_eq!(copied.stats.peak_resident_bytes, bytes);
}

#[test]
fn stats_json_has_the_spec_keys_and_the_new_ones() {
    let dir = scratch("alg-json");
    let (scene, _) = budget_scene(&dir);
    let r = render_with(&scene, Algorithm::Grouped, None).unwrap();
    let json = serde_json::to_value(&r.stats).unwrap();
    for key in [
        "algorithm",
        "width",
        "height",
        "objects",
        "datasets",
        "segments",
        "samples",
        "dataset_loads",
        "bytes_loaded",
        "peak_resident_bytes",
        "samples_skipped",
        "memory_budget",
    ] {
        assert!(json.get(key).is_some(), "missing {key}");
    }
    for key in ["intersection", "volume_rendering", "composition", "loading", "other", "total"] {
        assert!(json["seconds"].get(key).is_some(), "missing seconds.{key}");
    }
    assert_eq!(json["algorithm"], "grouped");
}

#[test]
fn grouped_renders_in_bands_of_rows_give_the_image_of_one_band() {
    use trove_core::render::{render, RenderOptions};
    for (path, scene) in example_scenes(40) {
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        let whole = render(&scene, &RenderOptions::default()).unwrap_or_else(|e| panic!("{name}: {e}"));
        // A band memory of one byte: every band is one row, and the datasets stay resident
        // from band to band.
        let options = RenderOptions { band_memory: Some(1), ..Default::default() };
        let banded = render(&scene, &options).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(banded.image.pixels() == whole.image.pixels(), "{name}: banded pixels differ");
        assert_eq!((banded.stats.pieces, banded.stats.samples), (whole.stats.pieces, whole.stats.samples), "{name}");
        // Each band binds again; the classifications the first band kept serve the others.
        let s = &banded.stats;
        assert_eq!(s.classification_misses, whole.stats.classification_misses, "{name}: a later band classified");
        if s.classification_misses > 0 {
            assert!(s.classification_hits > 0, "{name}: no later band found the kept classification");
        }
    }
}
