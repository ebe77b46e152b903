//! `trove render` end to end, run as a user runs it (SPEC §5): bad input exits non-zero with
//! a one-paragraph message naming the file and key, never a panic; good input writes a PNG,
//! a PFM that agrees with it, and `--stats` JSON with the documented keys.
//!
//! Cargo builds the `trove` binary for this package's integration tests and names it in
//! `CARGO_BIN_EXE_trove`, with the same features as the test run, so no rebuild happens here.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use trove_tests::{read_pfm, scratch, Header, Scratch};

/// The `trove` binary that cargo built for these tests.
fn trove() -> &'static Path {
    Path::new(env!("CARGO_BIN_EXE_trove"))
}

/// Runs `trove` with `args`, with backtraces enabled so that a panic could not hide, and
/// without the caller's `TROVE_DATA`, which would move every relative key.
fn run(args: &[&dyn AsRef<std::ffi::OsStr>]) -> Output {
    run_with_data(args, None)
}

/// [`run`] with `TROVE_DATA` set to `data` when given.
fn run_with_data(args: &[&dyn AsRef<std::ffi::OsStr>], data: Option<&Path>) -> Output {
    let mut cmd = Command::new(trove());
    for a in args {
        cmd.arg(a);
    }
    cmd.env("RUST_BACKTRACE", "1").env_remove("RUST_LOG").env_remove("TROVE_DATA");
    if let Some(data) = data {
        cmd.env("TROVE_DATA", data);
    }
    cmd.output().expect("run trove")
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A failed run: non-zero exit, and stderr one paragraph that contains every `needle`, with
/// no panic or backtrace.
#[track_caller]
fn failed(out: &Output, needles: &[&str]) -> String {
    let err = stderr(out);
    assert!(!out.status.success(), "expected failure, got {:?}; stderr: {err}", out.status);
    assert!(out.status.code().is_some_and(|c| c != 0), "killed by a signal? {:?}; stderr: {err}", out.status);
    assert!(!err.contains("panicked") && !err.contains("backtrace"), "a panic, not an error message: {err}");
    let text = err.trim();
    assert!(!text.is_empty(), "no message on stderr");
    assert!(!text.contains("\n\n"), "more than one paragraph: {err}");
    assert!(text.starts_with("error: "), "{err}");
    for n in needles {
        assert!(err.contains(n), "stderr lacks {n:?}: {err}");
    }
    err
}

const SIZE: (u32, u32) = (7, 5);

/// A tiny valid scene from generators: an opaque-ish graded sphere over a coloured background.
fn tiny_scene() -> String {
    let header =
        Header::new(SIZE.0, [0.5, 0.5, 3.0], [0.5, 0.5, 0.5], 25.0).size(SIZE.0, SIZE.1).background([0.2, 0.4, 0.6]);
    format!(
        r#"{header}
[[datasets]]
name = "ball"
dims = [8, 8, 8]
[datasets.channels.voxel]
generator = {{ kind = "sphere", radius = 0.5, profile = "radial", value = 1.0, type = "f32" }}

[[objects]]
name = "ball"
dataset = "ball"
colour = {{ type = "linear", red = [0.1, 0.9], green = [0.7, -0.3], blue = [0.05, 0.2] }}
opacity = {{ type = "ramp", points = [[0.0, 0.0], [1.0, 0.4]] }}
"#
    )
}

/// Writes `text` as `dir/name` and returns its path.
fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, text).expect("write scene");
    path
}

#[test]
fn malformed_scenes_exit_non_zero_naming_the_file_and_key() {
    let dir = scratch("cli-malformed");
    let good = tiny_scene();
    let cases = [
        (
            "bounds.toml",
            good.replace("[[0.0, 0.0], [1.0, 0.4]]", "[[1.0, 0.0], [0.0, 0.4]]"),
            "objects[0].opacity.points[1]",
        ),
        ("unknown.toml", good.replace("fov_y = 25.0", "fov_y = 25.0\nzoom = 2"), "camera.zoom"),
        ("fov.toml", good.replace("fov_y = 25.0", "fov_y = 180.0"), "camera.fov_y"),
        ("missing.toml", good.replace("dataset = \"ball\"\n", ""), "objects[0].dataset"),
        ("syntax.toml", good.replace("height = 5", "height = = 5"), "not valid TOML at line 3"),
        (
            "raw.toml",
            good.replace("generator = {", "raw = \"absent.raw\"\ntype = \"f32\"\n# {"),
            "datasets[0].channels.voxel.raw",
        ),
        ("dims.toml", good.replace("dims = [8, 8, 8]", "dims = [8, 0, 8]"), "datasets[0].dims"),
    ];
    for (name, text, key) in &cases {
        assert_ne!(text, &good, "{name}: the edit must change the scene");
        let scene = write(&dir, name, text);
        let png = dir.join(format!("{name}.png"));
        let out = run(&[&"render", &scene, &"-o", &png]);
        failed(&out, &[&scene.display().to_string(), key]);
        assert!(!png.exists(), "{name}: no image may be written for a refused scene");
    }
}

#[test]
fn a_missing_scene_file_is_named() {
    let dir = scratch("cli-missing-scene");
    let scene = dir.join("no-such-scene.toml");
    let out = run(&[&"render", &scene, &"-o", &dir.join("out.png")]);
    // The file, then what went wrong and why, with no pseudo key in between.
    let err = failed(&out, &[]);
    let want = format!("error: {}: cannot read the scene file: ", scene.display());
    assert!(err.starts_with(&want) && err.trim().len() > want.len(), "{err}");
}

#[test]
fn an_unwritable_output_path_is_a_clear_error() {
    let dir = scratch("cli-unwritable");
    let scene = write(&dir, "scene.toml", &tiny_scene());
    for name in ["out.png", "out.pfm"] {
        let output = dir.join("no-such-folder").join(name);
        let out = run(&[&"render", &scene, &"-o", &output]);
        failed(&out, &["cannot write", &output.display().to_string()]);
    }
    // Statistics to a folder that does not exist: the image is written, the error names the file.
    let stats = dir.join("no-such-folder").join("stats.json");
    let out = run(&[&"render", &scene, &"-o", &dir.join("ok.png"), &"--stats", &stats]);
    failed(&out, &[&stats.display().to_string()]);
}

#[test]
fn stats_json_has_the_documented_keys() {
    let dir = scratch("cli-stats");
    let scene = write(&dir, "scene.toml", &tiny_scene());
    let stats = dir.join("stats.json");
    let out = run(&[&"render", &scene, &"-o", &dir.join("out.png"), &"--stats", &stats]);
    assert!(out.status.success(), "{}", stderr(&out));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&stats).expect("stats written")).expect("stats are JSON");
    assert_eq!(json["algorithm"], "grouped");
    assert_eq!(json["width"], SIZE.0);
    assert_eq!(json["height"], SIZE.1);
    assert_eq!(json["objects"], 1);
    assert_eq!(json["datasets"], 1);
    for key in ["segments", "samples", "dataset_loads", "bytes_loaded"] {
        assert!(json[key].is_u64(), "`{key}` must be a count: {json}");
    }
    assert!(json["segments"].as_u64().unwrap() > 0 && json["samples"].as_u64().unwrap() > 0, "{json}");
    assert!(json["dataset_loads"].as_u64().unwrap() >= 1, "{json}");
    // 8³ f32 voxels.
    assert!(json["bytes_loaded"].as_u64().unwrap() >= 8 * 8 * 8 * 4, "{json}");
    let seconds = &json["seconds"];
    for key in ["intersection", "volume_rendering", "composition", "loading", "other", "total"] {
        let s = seconds[key].as_f64().unwrap_or_else(|| panic!("`seconds.{key}` must be a number: {json}"));
        assert!(s >= 0.0 && s.is_finite(), "seconds.{key} = {s}");
    }
}

#[test]
fn png_and_pfm_agree_to_rounding() {
    let dir = scratch("cli-png-pfm");
    let scene = write(&dir, "scene.toml", &tiny_scene());
    let (png, pfm) = (dir.join("out.png"), dir.join("out.pfm"));
    for output in [&png, &pfm] {
        let out = run(&[&"render", &scene, &"-o", output]);
        assert!(out.status.success(), "{}", stderr(&out));
    }
    let bytes = image::open(&png).expect("a readable PNG").to_rgb8();
    assert_eq!(bytes.dimensions(), SIZE);
    let float = read_pfm(&pfm);
    assert_eq!((float.width(), float.height()), SIZE);
    let mut object_seen = false;
    for row in 0..SIZE.1 {
        for col in 0..SIZE.0 {
            let c = float.pixel(col, row);
            let b = bytes.get_pixel(col, row).0;
            for i in 0..3 {
                let expected = (255.0 * c[i].clamp(0.0, 1.0)).round() as u8;
                assert_eq!(b[i], expected, "pixel ({col}, {row}) channel {i}: PFM {} vs PNG {}", c[i], b[i]);
            }
            object_seen |= (c[0] - 0.2).abs() > 1e-3;
        }
    }
    assert!(object_seen, "the sphere must be visible, or this compares only background");
}

/// The tiny scene reading its voxels from the key `ball.raw` (8³ u8) instead of a generator.
fn keyed_scene() -> String {
    let text = tiny_scene().replace(
        r#"generator = { kind = "sphere", radius = 0.5, profile = "radial", value = 1.0, type = "f32" }"#,
        "raw = \"ball.raw\"\ntype = \"u8\"",
    );
    assert!(text.contains("ball.raw"), "the edit must change the scene");
    text
}

/// 8³ u8 voxels: a bright ball in a dark box.
fn ball_raw() -> Vec<u8> {
    let at = |i: usize| (i as f64 + 0.5) / 8.0 - 0.5;
    (0..512).map(|i| if at(i % 8).hypot(at(i / 8 % 8)).hypot(at(i / 64)) < 0.4 { 250 } else { 10 }).collect()
}

/// A scene in `DIR/scenes` whose key `ball.raw` is in `DIR/data`, and the PNG it renders to
/// when the file lies beside it instead (the scene-folder default, SPEC §1).
fn data_root_fixture(name: &str) -> (Scratch, PathBuf, PathBuf, Vec<u8>) {
    let dir = scratch(name);
    let (scenes, data, beside) = (dir.join("scenes"), dir.join("data"), dir.join("beside"));
    for d in [&scenes, &data, &beside] {
        std::fs::create_dir_all(d).unwrap();
    }
    std::fs::write(data.join("ball.raw"), ball_raw()).unwrap();
    std::fs::write(beside.join("ball.raw"), ball_raw()).unwrap();
    let reference = dir.join("reference.png");
    let out = run(&[&"render", &write(&beside, "scene.toml", &keyed_scene()), &"-o", &reference]);
    assert!(out.status.success(), "{}", stderr(&out));
    let scene = write(&scenes, "scene.toml", &keyed_scene());
    (dir, scene, data, std::fs::read(reference).unwrap())
}

#[test]
fn keys_resolve_under_data_root_then_trove_data_then_the_scene_folder() {
    let (dir, scene, data, reference) = data_root_fixture("cli-data-root");
    let png = dir.join("out.png");
    let renders = |args: &[&dyn AsRef<std::ffi::OsStr>], env: Option<&Path>| {
        let _ = std::fs::remove_file(&png);
        let out = run_with_data(args, env);
        assert!(out.status.success(), "{}", stderr(&out));
        std::fs::read(&png).unwrap()
    };
    let nowhere = dir.join("nowhere");
    assert!(renders(&[&"render", &scene, &"-o", &png, &"--data-root", &data], None) == reference);
    assert!(renders(&[&"render", &scene, &"-o", &png], Some(&data)) == reference, "TROVE_DATA");
    // The option overrides the variable.
    assert!(renders(&[&"render", &scene, &"-o", &png, &"--data-root", &data], Some(&nowhere)) == reference);
    // An empty variable counts as unset; the scene's folder does not hold the file.
    let looked = dir.join("scenes").join("ball.raw");
    let out = run_with_data(&[&"render", &scene, &"-o", &png], Some(Path::new("")));
    failed(&out, &[&looked.display().to_string()]);
}

#[test]
fn a_key_that_names_no_file_says_where_it_looked_and_how_to_look_elsewhere() {
    let (dir, scene, _, _) = data_root_fixture("cli-no-data");
    let png = dir.join("out.png");
    let (file, key) = (scene.display().to_string(), "datasets[0].channels.voxel.raw");
    let looked = dir.join("scenes").join("ball.raw").display().to_string();
    let out = run(&[&"render", &scene, &"-o", &png]);
    failed(&out, &[&file, key, "\"ball.raw\"", &looked, "--data-root DIR", "TROVE_DATA=DIR", "docs/data.md"]);
    let elsewhere = dir.join("elsewhere");
    let looked = elsewhere.join("ball.raw").display().to_string();
    let out = run_with_data(&[&"render", &scene, &"-o", &png], Some(&elsewhere));
    failed(&out, &[&file, key, &looked, "from TROVE_DATA"]);
    let out = run(&[&"render", &scene, &"-o", &png, &"--data-root", &elsewhere]);
    failed(&out, &[&file, key, &looked, "(--data-root)"]);
    assert!(!png.exists(), "no image may be written");
}

#[test]
fn a_farm_render_refuses_a_data_root() {
    let (dir, scene, data, _) = data_root_fixture("cli-farm-data-root");
    // Refused before connecting: nothing listens at this address.
    let out = run(&[
        &"render",
        &scene,
        &"-o",
        &dir.join("out.png"),
        &"--coordinator",
        &"http://127.0.0.1:9",
        &"--data-root",
        &data,
    ]);
    failed(&out, &["--data-root", "applies to local renders", "its own --data-root"]);
}

#[test]
fn trove_data_verify_takes_the_same_data_root() {
    let dir = scratch("cli-data-verify");
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let out = run(&[&"data", &"verify", &"--data-root", &empty]);
    failed(&out, &[&empty.display().to_string(), "missing", "trove data fetch --data-root"]);
    let out = run_with_data(&[&"data", &"verify"], Some(&empty));
    failed(&out, &[&empty.display().to_string(), "missing"]);
}

#[test]
fn renders_over_a_limit_exit_non_zero_naming_it_and_write_nothing() {
    let dir = scratch("cli-limits");
    // A 16384² PFM, refused before rendering (a PNG of that size is allowed).
    let big = tiny_scene().replace("width = 7", "width = 16384").replace("height = 5", "height = 16384");
    assert_ne!(big, tiny_scene());
    let scene = write(&dir, "big.toml", &big);
    let pfm = dir.join("big.pfm");
    failed(&run(&[&"render", &scene, &"-o", &pfm]), &["big.pfm", "limit on PFM pixels is 16777216"]);
    assert!(!pfm.exists());
    // 300 nested boxes over one 2³ dataset at a huge step: about 90 000 piece tasks per ray.
    let mut nested = String::from(
        "[image]\nwidth = 512\nheight = 512\nbackground = [0, 0, 0]\n\
         [camera]\neye = [0, 0, 4]\ntarget = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 30.0\n\
         [[datasets]]\nname = \"d\"\ndims = [2, 2, 2]\n[datasets.channels.voxel]\n\
         generator = { kind = \"constant\", value = 0.5 }\n",
    );
    for i in 0..300 {
        let half = 1.0 - i as f64 / 301.0;
        let (s, t) = (2.0 * half, -half);
        nested += &format!(
            "[[objects]]\nname = \"o{i}\"\ndataset = \"d\"\nsampling_distance = 1e9\n\
             transform = {{ matrix = [[{s}, 0, 0, {t}], [0, {s}, 0, {t}], [0, 0, {s}, {t}], [0, 0, 0, 1]] }}\n\
             colour = {{ type = \"ramp\", points = [[0, 1, 1, 1], [1, 1, 1, 1]] }}\n\
             opacity = {{ type = \"ramp\", points = [[0, 0.01], [1, 0.01]] }}\n"
        );
    }
    let scene = write(&dir, "nested.toml", &nested);
    let png = dir.join("nested.png");
    failed(&run(&[&"render", &scene, &"-o", &png]), &["nested.toml", "limit on piece tasks per render is 536870912"]);
    assert!(!png.exists());
}
