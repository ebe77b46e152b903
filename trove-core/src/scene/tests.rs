//! Bad input (SPEC §1, §1.1, §2, §3.2, §3.3, §4.5): one test per rule a user can break.
//!
//! Every test starts from [`base`], a small valid scene whose datasets are generated (no
//! files needed), changes one thing, and checks through [`refused`] that the scene is
//! refused, that the error's key is the exact TOML path of the offending key, that the
//! message names the scene file, and that it says what was expected. Tests that need files
//! (raw size mismatches, missing files) write them to a scratch folder first.

use std::path::{Path, PathBuf};

use super::{Scene, MAX_IMAGE_SIDE, MAX_OBJECTS};
use crate::SceneError;

/// The scene file's name in every message checked here.
const NAME: &str = "bad-input-scene.toml";

/// The first dataset's body: a generated u8 sphere, channel `voxel` only.
const BALL: &str = r#"dims = [4, 4, 4]
[datasets.channels.voxel]
generator = { kind = "sphere", radius = 0.4 }
"#;

/// The second dataset's body: generated u8 red, green, blue and alpha, no `voxel`.
const RGBA: &str = r#"dims = [2, 2, 2]
[datasets.channels.red]
generator = { kind = "constant", value = 200, type = "u8" }
[datasets.channels.green]
generator = { kind = "constant", value = 100, type = "u8" }
[datasets.channels.blue]
generator = { kind = "constant", value = 50, type = "u8" }
[datasets.channels.alpha]
generator = { kind = "constant", value = 128, type = "u8" }
"#;

/// A small valid scene: every key below is edited by some test.
fn base() -> String {
    format!(
        r#"
[image]
width = 8
height = 6
background = [0.1, 0.2, 0.3]

[camera]
eye = [0.5, 0.5, 3.0]
target = [0.5, 0.5, 0.5]
up = [0.0, 1.0, 0.0]
fov_y = 30.0

[render]
termination = 0.99

[[datasets]]
name = "ball"
{BALL}
[[datasets]]
name = "rgba"
{RGBA}
[[objects]]
name = "skull"
dataset = "ball"
colour = {{ type = "lut", bounds = [100.0], colours = [[0, 0, 0], [1, 1, 1]] }}
opacity = {{ type = "lut", bounds = [100.0], values = [0.0, 0.5] }}

[[objects]]
name = "photo"
dataset = "rgba"
colour = {{ type = "raw" }}
opacity = {{ type = "raw" }}
transform = {{ matrix = [[1, 0, 0, 1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]] }}
"#
    )
}

/// The base scene with each `(old, new)` applied; `old` must occur exactly once, so an edit
/// cannot silently miss or hit the wrong key.
fn with(edits: &[(&str, &str)]) -> String {
    edits.iter().fold(base(), |text, (old, new)| {
        assert_eq!(text.matches(old).count(), 1, "{old:?} must occur exactly once in the scene:\n{text}");
        text.replacen(old, new, 1)
    })
}

/// A folder that holds no files: scenes parsed "in" it reference none.
fn nowhere() -> PathBuf {
    std::env::temp_dir().join("trove-scene-tests-no-files")
}

/// A fresh scratch folder for a test that writes dataset files.
fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("trove-scene-tests-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("create scratch folder");
    dir
}

/// Parses `text` as `dir/NAME`; it must be valid.
#[track_caller]
fn accepted_in(dir: &Path, text: &str) -> Scene {
    Scene::parse(text, dir.join(NAME)).unwrap_or_else(|e| panic!("refused: {e}\n{text}"))
}

#[track_caller]
fn accepted(text: &str) -> Scene {
    accepted_in(&nowhere(), text)
}

/// Parses `text` as `dir/NAME` and checks the refusal: exactly `key`, the file and key in
/// the displayed message, and every `expected` fragment in the message.
#[track_caller]
fn refused_in(dir: &Path, text: &str, key: &str, expected: &[&str]) -> SceneError {
    let path = dir.join(NAME);
    let err = match Scene::parse(text, &path) {
        Ok(_) => panic!("accepted; expected a refusal at `{key}`:\n{text}"),
        Err(e) => e,
    };
    let shown = err.to_string();
    assert_eq!(err.key, key, "wrong key path in: {shown}");
    assert_eq!(err.file, path, "{shown}");
    assert!(shown.contains(&path.display().to_string()), "the message does not name the file: {shown}");
    assert!(shown.contains(key), "the message does not name the key: {shown}");
    for e in expected {
        assert!(err.message.contains(e), "the message lacks {e:?}: {shown}");
    }
    assert!(!err.message.trim().is_empty() && !err.message.contains('\n'), "one-line message: {shown:?}");
    err
}

#[track_caller]
fn refused(text: &str, key: &str, expected: &[&str]) -> SceneError {
    refused_in(&nowhere(), text, key, expected)
}

/// `n` more objects named `extra{i}`, appended to the base scene.
fn with_extra_objects(n: usize) -> String {
    let mut text = base();
    for i in 0..n {
        text += &format!(
            "[[objects]]\nname = \"extra{i}\"\ndataset = \"ball\"\n\
             colour = {{ type = \"constant\", red = [1], green = [1], blue = [1] }}\n\
             opacity = {{ type = \"constant\", coefficients = [0.1] }}\n"
        );
    }
    text
}

// ---------------------------------------------------------------------------------------
// The base scene itself, so that no refusal below is an accident of a broken base.

#[test]
fn the_base_scene_is_valid() {
    let s = accepted(&base());
    assert_eq!((s.image.width, s.image.height), (8, 6));
    assert_eq!(s.datasets.len(), 2);
    assert_eq!(s.objects.len(), 2);
    assert_eq!(s.path, nowhere().join(NAME));
}

// ---------------------------------------------------------------------------------------
// SPEC §1: TOML syntax, unknown keys, wrong types.

#[test]
fn toml_syntax_errors_are_refused_with_their_line() {
    let e = refused(&with(&[("height = 6", "height = ")]), "(syntax)", &["not valid TOML", "line 4"]);
    assert!(e.to_string().contains(NAME));
    refused(&with(&[("fov_y = 30.0", "fov_y = 30.0\nfov_y = 40.0")]), "(syntax)", &["not valid TOML"]);
    refused(&with(&[("[camera]", "[camera")]), "(syntax)", &["not valid TOML"]);
}

#[test]
fn unknown_keys_are_refused_at_every_level() {
    let cases: &[(&[(&str, &str)], &str)] = &[
        (&[("\n[image]", "colour_space = \"srgb\"\n[image]")], "colour_space"),
        (&[("[image]", "[image]\ndepth = 3")], "image.depth"),
        (&[("fov_y = 30.0", "fov_y = 30.0\nfov_x = 30.0")], "camera.fov_x"),
        (&[("termination = 0.99", "termination = 0.99\nopacity_corection = false")], "render.opacity_corection"),
        (&[("name = \"ball\"", "name = \"ball\"\nspacing = [1, 1, 1]")], "datasets[0].spacing"),
        (&[("radius = 0.4 }", "radius = 0.4 }\nscale = 2")], "datasets[0].channels.voxel.scale"),
        (&[("name = \"photo\"", "name = \"photo\"\nvisible = true")], "objects[1].visible"),
        (&[("values = [0.0, 0.5] }", "values = [0.0, 0.5], gamma = 2 }")], "objects[0].opacity.gamma"),
        (&[("colour = { type = \"raw\" }", "colour = { type = \"raw\", foo = 1 }")], "objects[1].colour.foo"),
        (&[("[0, 0, 0, 1]] }", "[0, 0, 0, 1]], scale = 2 }")], "objects[1].transform.scale"),
        (
            &[("name = \"skull\"", "name = \"skull\"\nextent = { min = [0, 0, 0], centre = [0.5, 0.5, 0.5] }")],
            "objects[0].extent.centre",
        ),
        (
            &[("name = \"skull\"", "name = \"skull\"\ninterpolation = { type = \"nearest\", omega = [0, 1, 0] }")],
            "objects[0].interpolation.omega",
        ),
    ];
    for (edits, key) in cases {
        refused(&with(edits), key, &["unknown key", "expected"]);
    }
}

#[test]
fn generator_keys_are_checked_by_name() {
    let key = |k: &str| format!("datasets[0].channels.voxel.generator.{k}");
    // An unknown key, a key of another kind, a key of the wrong type, a missing required key.
    refused(&with(&[("radius = 0.4", "radious = 0.4")]), &key("radious"), &["unknown key", "radius"]);
    refused(&with(&[("radius = 0.4", "radius = 0.4, squares = [2, 2, 2]")]), &key("squares"), &["sphere"]);
    refused(&with(&[("radius = 0.4", "radius = \"big\"")]), &key("radius"), &["expected a number", "string"]);
    refused(&with(&[("kind = \"sphere\", radius = 0.4", "kind = \"constant\"")]), &key("value"), &["constant"]);
    refused(&with(&[("kind = \"sphere\"", "kind = \"cube\"")]), &key("kind"), &["cube", "sphere"]);
    // Values the generator refuses (documented in dataset::generator).
    refused(&with(&[("radius = 0.4", "radius = 0.0")]), &key("radius"), &["greater than 0"]);
    refused(&with(&[("radius = 0.4", "radius = 0.4, value = 300")]), &key("value"), &["u8"]);
    refused(&with(&[("radius = 0.4", "radius = nan")]), &key("radius"), &["finite"]);
}

#[test]
fn wrong_types_are_refused_with_what_was_expected() {
    let cases: &[(&str, &str, &str, &[&str])] = &[
        ("width = 8", "width = \"8\"", "image.width", &["expected a whole number", "string"]),
        ("width = 8", "width = 8.5", "image.width", &["expected a whole number", "8.5"]),
        ("fov_y = 30.0", "fov_y = \"wide\"", "camera.fov_y", &["expected a number", "string"]),
        ("background = [0.1, 0.2, 0.3]", "background = [0.1, 0.2]", "image.background", &["3"]),
        ("background = [0.1, 0.2, 0.3]", "background = 0.5", "image.background", &["expected", "array"]),
        ("eye = [0.5, 0.5, 3.0]", "eye = [0.5, \"a\", 3.0]", "camera.eye[1]", &["expected a number"]),
        ("termination = 0.99", "opacity_correction = \"yes\"", "render.opacity_correction", &["boolean"]),
        ("dims = [4, 4, 4]", "dims = [4, 4]", "datasets[0].dims", &["3"]),
        ("dims = [4, 4, 4]", "dims = [4, 4, 4.5]", "datasets[0].dims[2]", &["expected a whole number"]),
        ("name = \"ball\"", "name = 7", "datasets[0].name", &["expected a string"]),
        ("dataset = \"ball\"", "dataset = [\"ball\"]", "objects[0].dataset", &["expected a string"]),
        (
            "name = \"skull\"",
            "name = \"skull\"\nsampling_distance = \"fine\"",
            "objects[0].sampling_distance",
            &["expected a number"],
        ),
        ("colour = { type = \"raw\" }", "colour = \"raw\"", "objects[1].colour", &["expected a table"]),
        ("values = [0.0, 0.5]", "values = [0.0, \"half\"]", "objects[0].opacity.values[1]", &["expected a number"]),
        ("bounds = [100.0], values", "bounds = 100.0, values", "objects[0].opacity.bounds", &["expected an array"]),
        ("colour = { type = \"raw\" }", "colour = { type = 3 }", "objects[1].colour.type", &["expected a string"]),
        ("[0, 0, 0, 1]] }", "[0, 0, \"0\", 1]] }", "objects[1].transform.matrix[3][2]", &["expected a number"]),
        ("name = \"skull\"", "name = \"skull\"\ninterpolation = 3", "objects[0].interpolation", &["\"trilinear\""]),
    ];
    for (old, new, key, expected) in cases {
        refused(&with(&[(old, new)]), key, expected);
    }
    let render = with(&[("\n[image]", "render = 3\n[image]"), ("[render]\ntermination = 0.99\n", "")]);
    refused(&render, "render", &["expected a table", "integer `3`"]);
    let image = with(&[
        ("\n[image]", "image = [8, 6]\n[image]"),
        ("[image]\nwidth = 8\nheight = 6\nbackground = [0.1, 0.2, 0.3]\n", ""),
    ]);
    refused(&image, "image", &["expected a table"]);
    let mut objects = base();
    objects.truncate(objects.find("[[objects]]").expect("objects"));
    refused(
        &objects.replacen("\n[image]", "objects = 3\n[image]", 1),
        "objects",
        &["expected an array", "integer `3`"],
    );
}

// ---------------------------------------------------------------------------------------
// SPEC §4.5: required keys.

#[test]
fn every_required_key_is_named_when_missing() {
    let cases = [
        ("width = 8\n", "image.width"),
        ("height = 6\n", "image.height"),
        ("background = [0.1, 0.2, 0.3]\n", "image.background"),
        ("eye = [0.5, 0.5, 3.0]\n", "camera.eye"),
        ("target = [0.5, 0.5, 0.5]\n", "camera.target"),
        ("up = [0.0, 1.0, 0.0]\n", "camera.up"),
        ("fov_y = 30.0\n", "camera.fov_y"),
        ("name = \"rgba\"\n", "datasets[1].name"),
        ("name = \"skull\"\n", "objects[0].name"),
        ("dataset = \"rgba\"\n", "objects[1].dataset"),
        ("colour = { type = \"lut\", bounds = [100.0], colours = [[0, 0, 0], [1, 1, 1]] }\n", "objects[0].colour"),
        ("opacity = { type = \"raw\" }\n", "objects[1].opacity"),
    ];
    for (line, key) in cases {
        refused(&with(&[(line, "")]), key, &["missing", "required"]);
    }
    // Whole tables.
    let no_image = with(&[("[image]\nwidth = 8\nheight = 6\nbackground = [0.1, 0.2, 0.3]\n", "")]);
    refused(&no_image, "image", &["missing", "required"]);
    let no_camera = with(&[(
        "[camera]\neye = [0.5, 0.5, 3.0]\ntarget = [0.5, 0.5, 0.5]\nup = [0.0, 1.0, 0.0]\nfov_y = 30.0\n",
        "",
    )]);
    refused(&no_camera, "camera", &["missing", "required"]);
    // Inside mapping tables.
    refused(&with(&[("colour = { type = \"raw\" }", "colour = { }")]), "objects[1].colour.type", &["missing"]);
    refused(&with(&[("bounds = [100.0], values", "values")]), "objects[0].opacity.bounds", &["missing"]);
    refused(
        &with(&[("colour = { type = \"raw\" }", "colour = { type = \"linear\", red = [0, 1], green = [0, 1] }")]),
        "objects[1].colour.blue",
        &["missing"],
    );
}

#[test]
fn render_defaults_hold_when_the_table_is_absent() {
    let s = accepted(&with(&[("[render]\ntermination = 0.99\n", "")]));
    assert_eq!(s.render.termination, 0.999);
    assert!(s.render.opacity_correction);
}

// ---------------------------------------------------------------------------------------
// SPEC §4.5 refusals and the documented limits of [image].

#[test]
fn image_size_is_within_the_documented_limits() {
    refused(&with(&[("width = 8", "width = 0")]), "image.width", &["1 to 16384", "got 0"]);
    refused(&with(&[("width = 8", "width = -3")]), "image.width", &["1 to 16384"]);
    let over = format!("height = {}", MAX_IMAGE_SIDE as u64 + 1);
    refused(&with(&[("height = 6", &over)]), "image.height", &["1 to 16384", "16385"]);
    let huge = with(&[("height = 6", "height = 4294967297")]);
    refused(&huge, "image.height", &["1 to 16384"]);
    let at_limit = format!("width = {MAX_IMAGE_SIDE}");
    assert_eq!(accepted(&with(&[("width = 8", &at_limit)])).image.width, MAX_IMAGE_SIDE);
}

#[test]
fn background_outside_the_unit_range_is_refused() {
    for bad in ["[1.5, 0.2, 0.3]", "[0.1, -0.01, 0.3]", "[0.1, 0.2, nan]", "[0.1, 0.2, inf]"] {
        let edit = format!("background = {bad}");
        refused(&with(&[("background = [0.1, 0.2, 0.3]", &edit)]), "image.background", &["[0, 1]"]);
    }
    accepted(&with(&[("background = [0.1, 0.2, 0.3]", "background = [0, 1, 1.0]")]));
}

#[test]
fn fov_outside_the_open_range_is_refused() {
    for bad in ["0.0", "180.0", "-30", "200", "nan", "inf"] {
        let edit = format!("fov_y = {bad}");
        refused(&with(&[("fov_y = 30.0", &edit)]), "camera.fov_y", &["(0, 180)"]);
    }
    accepted(&with(&[("fov_y = 30.0", "fov_y = 179.5")]));
    accepted(&with(&[("fov_y = 30.0", "fov_y = 1")]));
}

#[test]
fn termination_outside_the_half_open_range_is_refused() {
    for bad in ["0.0", "1.5", "-0.5", "nan"] {
        let edit = format!("termination = {bad}");
        refused(&with(&[("termination = 0.99", &edit)]), "render.termination", &["(0, 1]"]);
    }
    assert_eq!(accepted(&with(&[("termination = 0.99", "termination = 1.0")])).render.termination, 1.0);
}

#[test]
fn up_parallel_to_the_view_direction_is_refused() {
    for up in ["[0, 0, 1]", "[0, 0, -2.5]", "[0, 0, 0]"] {
        let edit = format!("up = {up}");
        refused(&with(&[("up = [0.0, 1.0, 0.0]", &edit)]), "camera.up", &["not parallel to the view direction"]);
    }
    // Not parallel, merely oblique: fine.
    accepted(&with(&[("up = [0.0, 1.0, 0.0]", "up = [0, 1, 5]")]));
}

#[test]
fn eye_equal_to_target_is_refused() {
    refused(&with(&[("eye = [0.5, 0.5, 3.0]", "eye = [0.5, 0.5, 0.5]")]), "camera.target", &["different from the eye"]);
}

#[test]
fn non_finite_camera_vectors_are_refused() {
    refused(&with(&[("eye = [0.5, 0.5, 3.0]", "eye = [0.5, nan, 3.0]")]), "camera.eye", &["finite"]);
    refused(&with(&[("target = [0.5, 0.5, 0.5]", "target = [inf, 0.5, 0.5]")]), "camera.target", &["finite"]);
    refused(&with(&[("up = [0.0, 1.0, 0.0]", "up = [0.0, -inf, 0.0]")]), "camera.up", &["finite"]);
}

#[test]
fn unknown_distorted_sampling_mode_is_refused() {
    let text = with(&[("termination = 0.99", "termination = 0.99\ndistorted_sampling = \"fast\"")]);
    refused(&text, "render.distorted_sampling", &["\"exact\" or \"straight\"", "fast"]);
}

// ---------------------------------------------------------------------------------------
// SPEC §1: names, references and counts.

#[test]
fn duplicate_dataset_names_are_refused() {
    refused(
        &with(&[("name = \"rgba\"", "name = \"ball\"")]),
        "datasets[1].name",
        &["duplicate", "ball", "datasets[0]"],
    );
}

#[test]
fn duplicate_object_names_are_refused() {
    refused(
        &with(&[("name = \"photo\"", "name = \"skull\"")]),
        "objects[1].name",
        &["duplicate", "skull", "objects[0]"],
    );
}

#[test]
fn an_object_naming_a_missing_dataset_is_refused() {
    refused(
        &with(&[("dataset = \"rgba\"", "dataset = \"rgb\"")]),
        "objects[1].dataset",
        &["no dataset named \"rgb\"", "ball"],
    );
}

#[test]
fn object_count_is_within_the_documented_limit() {
    // The base has two objects; at the limit the scene loads, one more is refused.
    assert_eq!(accepted(&with_extra_objects(MAX_OBJECTS - 2)).objects.len(), MAX_OBJECTS);
    refused(&with_extra_objects(MAX_OBJECTS - 1), "objects", &["at most 4096 objects", "4097"]);
}

#[test]
fn dataset_count_is_within_the_documented_limit() {
    let mut text = base();
    for i in 0..MAX_OBJECTS - 1 {
        text += &format!("[[datasets]]\nname = \"d{i}\"\n{BALL}");
    }
    refused(&text, "datasets", &["at most 4096 datasets", "4097"]);
}

// ---------------------------------------------------------------------------------------
// SPEC §1.1: datasets and channels.

#[test]
fn a_dataset_without_any_source_is_refused() {
    refused(&with(&[(BALL, "")]), "datasets[0]", &["`file`", "`image`", "`channels`"]);
}

#[test]
fn explicit_channels_without_dims_are_refused() {
    refused(&with(&[("dims = [4, 4, 4]\n", "")]), "datasets[0].dims", &["missing", "dims"]);
}

#[test]
fn dims_below_one_are_refused() {
    for bad in ["[0, 4, 4]", "[4, -1, 4]", "[4, 4, 0]"] {
        let edit = format!("dims = {bad}");
        refused(&with(&[("dims = [4, 4, 4]", &edit)]), "datasets[0].dims", &["≥ 1"]);
    }
}

#[test]
fn dims_whose_byte_size_overflows_are_refused() {
    let cases = [
        ("[2147483647, 2147483647, 2147483647]", "more than"),
        ("[1048576, 1048576, 2]", "more than"),
        ("[4294967296, 1, 1]", "exceeds"),
        ("[9223372036854775807, 9223372036854775807, 2]", "exceeds"),
    ];
    for (bad, needle) in cases {
        let edit = format!("dims = {bad}");
        refused(&with(&[("dims = [4, 4, 4]", &edit)]), "datasets[0].dims", &[needle]);
    }
}

#[test]
fn unknown_channel_names_are_refused() {
    let text = with(&[("[datasets.channels.voxel]", "[datasets.channels.density]")]);
    refused(&text, "datasets[0].channels.density", &["unknown channel", "voxel", "user4"]);
}

#[test]
fn a_channel_needs_exactly_one_source() {
    let both = with(&[("radius = 0.4 }", "radius = 0.4 }\nraw = \"ball.raw\"\ntype = \"u8\"")]);
    refused(&both, "datasets[0].channels.voxel", &["exactly one of `raw`, `nrrd` or `generator`"]);
    let none = with(&[("generator = { kind = \"sphere\", radius = 0.4 }", "")]);
    refused(&none, "datasets[0].channels.voxel", &["exactly one of `raw`, `nrrd` or `generator`"]);
}

#[test]
fn raw_only_keys_on_other_channels_are_refused() {
    let text = with(&[("radius = 0.4 }", "radius = 0.4 }\nendian = \"big\"")]);
    refused(&text, "datasets[0].channels.voxel.endian", &["only a `raw` channel"]);
    let text = with(&[("radius = 0.4 }", "radius = 0.4 }\ntype = \"u8\"")]);
    refused(&text, "datasets[0].channels.voxel.type", &["only a `raw` channel"]);
}

#[test]
fn raw_channel_type_and_endian_are_checked() {
    let dir = scratch("raw-type");
    std::fs::write(dir.join("ball.raw"), [0u8; 64]).unwrap();
    let gen = "generator = { kind = \"sphere\", radius = 0.4 }";
    let k = "datasets[0].channels.voxel";
    refused_in(&dir, &with(&[(gen, "raw = \"ball.raw\"")]), &format!("{k}.type"), &["missing", "u16"]);
    let text = with(&[(gen, "raw = \"ball.raw\"\ntype = \"i16\"")]);
    refused_in(&dir, &text, &format!("{k}.type"), &["bit, u8, u16, u32 or f32", "i16"]);
    let text = with(&[(gen, "raw = \"ball.raw\"\ntype = \"u8\"\nendian = \"middle\"")]);
    refused_in(&dir, &text, &format!("{k}.endian"), &["\"little\" or \"big\"", "middle"]);
    accepted_in(&dir, &with(&[(gen, "raw = \"ball.raw\"\ntype = \"u8\"\nendian = \"big\"")]));
}

#[test]
fn a_channel_type_the_channel_does_not_allow_is_refused() {
    // `red` must be u8 (SPEC §1.1); from a raw file the key is the `type` that says u16.
    let dir = scratch("channel-type");
    std::fs::write(dir.join("red.raw"), [0u8; 16]).unwrap();
    let red = "[datasets.channels.red]\ngenerator = { kind = \"constant\", value = 200, type = \"u8\" }";
    let text = with(&[(red, "[datasets.channels.red]\nraw = \"red.raw\"\ntype = \"u16\"")]);
    refused_in(&dir, &text, "datasets[1].channels.red.type", &["`red` must be u8", "u16"]);
    // From a generator, the generator.
    let text = with(&[("value = 200, type = \"u8\"", "value = 200, type = \"f32\"")]);
    refused(&text, "datasets[1].channels.red.generator", &["`red` must be u8", "f32"]);
    // `bit` must be bit.
    let text = with(&[(
        "[datasets.channels.alpha]",
        "[datasets.channels.bit]\ngenerator = { kind = \"ramp\" }\n[datasets.channels.alpha]",
    )]);
    refused(&text, "datasets[1].channels.bit.generator", &["`bit` must be bit", "f32"]);
}

#[test]
fn raw_file_size_must_match_dims_exactly() {
    let dir = scratch("raw-size");
    std::fs::write(dir.join("ball.raw"), [0u8; 100]).unwrap();
    let text = with(&[("generator = { kind = \"sphere\", radius = 0.4 }", "raw = \"ball.raw\"\ntype = \"u16\"")]);
    // dims [4, 4, 4] of u16 need 128 bytes; the file has 100.
    refused_in(&dir, &text, "datasets[0].channels.voxel.raw", &["100 bytes", "128 bytes", "ball.raw"]);
    // One byte too many is as wrong as too few.
    std::fs::write(dir.join("ball.raw"), [0u8; 129]).unwrap();
    refused_in(&dir, &text, "datasets[0].channels.voxel.raw", &["129 bytes", "128 bytes"]);
    std::fs::write(dir.join("ball.raw"), [0u8; 128]).unwrap();
    accepted_in(&dir, &text);
}

#[test]
fn nrrd_size_and_dims_must_agree() {
    let dir = scratch("nrrd-size");
    let header = "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 4 4 4\nencoding: raw\n\n";
    let mut bytes = header.as_bytes().to_vec();
    bytes.extend([0u8; 60]);
    std::fs::write(dir.join("short.nrrd"), &bytes).unwrap();
    let text = with(&[(BALL, "file = \"short.nrrd\"\n")]);
    refused_in(&dir, &text, "datasets[0].file", &["60 bytes", "64 bytes", "short.nrrd"]);

    let mut bytes = header.as_bytes().to_vec();
    bytes.extend([0u8; 64]);
    std::fs::write(dir.join("ok.nrrd"), &bytes).unwrap();
    accepted_in(&dir, &with(&[(BALL, "file = \"ok.nrrd\"\n")]));
    // Dims in the scene that disagree with the header.
    let text = with(&[(BALL, "file = \"ok.nrrd\"\ndims = [4, 4, 5]\n")]);
    refused_in(&dir, &text, "datasets[0].file", &["[4, 4, 4]", "[4, 4, 5]"]);
    let gen = "generator = { kind = \"sphere\", radius = 0.4 }";
    let text = with(&[("dims = [4, 4, 4]", "dims = [4, 4, 5]"), (gen, "nrrd = \"ok.nrrd\"")]);
    refused_in(&dir, &text, "datasets[0].channels.voxel.nrrd", &["[4, 4, 4]", "[4, 4, 5]"]);
}

#[test]
fn nonexistent_files_are_refused_naming_the_path() {
    let dir = scratch("missing-files");
    let gen = "generator = { kind = \"sphere\", radius = 0.4 }";
    let named = |f: &str| dir.join(f).display().to_string();

    let text = with(&[(gen, "raw = \"absent.raw\"\ntype = \"u8\"")]);
    refused_in(&dir, &text, "datasets[0].channels.voxel.raw", &[&named("absent.raw"), "cannot read"]);
    let text = with(&[(gen, "nrrd = \"absent.nrrd\"")]);
    refused_in(&dir, &text, "datasets[0].channels.voxel.nrrd", &[&named("absent.nrrd")]);
    let text = with(&[(BALL, "file = \"absent.nhdr\"\n")]);
    refused_in(&dir, &text, "datasets[0].file", &[&named("absent.nhdr")]);
    let text = with(&[(BALL, "file = \"absent.nii.gz\"\n")]);
    refused_in(&dir, &text, "datasets[0].file", &[&named("absent.nii.gz")]);
    let text = with(&[(RGBA, "image = \"absent.png\"\n")]);
    refused_in(&dir, &text, "datasets[1].image", &[&named("absent.png"), "cannot read"]);
    // Relative paths resolve against the scene's folder, not the working directory.
    let text = with(&[(RGBA, "image = \"sub/absent.png\"\n")]);
    refused_in(&dir, &text, "datasets[1].image", &[&named("sub/absent.png")]);
}

#[test]
fn a_file_with_an_unsupported_extension_is_refused() {
    let dir = scratch("extension");
    std::fs::write(dir.join("head.mha"), b"not read").unwrap();
    let text = with(&[(BALL, "file = \"head.mha\"\n")]);
    refused_in(&dir, &text, "datasets[0].file", &["head.mha", ".nrrd, .nhdr, .nii or .nii.gz"]);
}

#[test]
fn an_image_that_is_not_an_image_is_refused() {
    let dir = scratch("not-an-image");
    std::fs::write(dir.join("photo.png"), b"plain text, not a PNG").unwrap();
    let text = with(&[(RGBA, "image = \"photo.png\"\n")]);
    refused_in(&dir, &text, "datasets[1].image", &["photo.png", "PNG or JPEG"]);
}

#[test]
fn file_and_image_together_are_refused() {
    let text = with(&[(BALL, "file = \"a.nrrd\"\nimage = \"a.png\"\n")]);
    refused(&text, "datasets[0].image", &["either `file` or `image`"]);
}

/// A 3×2 RGB PNG in `dir` (no alpha channel).
fn write_png(dir: &Path, name: &str) {
    let rgb: Vec<u8> = (0..18).map(|i| (i * 14) as u8).collect();
    image::save_buffer(dir.join(name), &rgb, 3, 2, image::ExtendedColorType::Rgb8).unwrap();
}

#[test]
fn image_datasets_bring_their_channels_and_dims() {
    let dir = scratch("image-dataset");
    write_png(&dir, "photo.png");
    // An RGB image: raw colour is fine, raw opacity needs alpha, which it lacks.
    let text = with(&[(RGBA, "image = \"photo.png\"\n")]);
    refused_in(&dir, &text, "objects[1].opacity", &["alpha"]);
    let opaque = "opacity = { type = \"constant\", coefficients = [0.5] }";
    let s = accepted_in(&dir, &with(&[(RGBA, "image = \"photo.png\"\n"), ("opacity = { type = \"raw\" }", opaque)]));
    assert_eq!(s.datasets[1].dims.as_array(), [3, 2, 1]);
    // Declared dims must agree with the image.
    let text = with(&[(RGBA, "image = \"photo.png\"\ndims = [3, 3, 1]\n"), ("opacity = { type = \"raw\" }", opaque)]);
    refused_in(&dir, &text, "datasets[1].image", &["[3, 2, 1]", "[3, 3, 1]"]);
    // A channel the image already gives cannot be given again.
    let text = with(&[
        (RGBA, "image = \"photo.png\"\n[datasets.channels.red]\ngenerator = { kind = \"constant\", value = 1, type = \"u8\" }\n"),
        ("opacity = { type = \"raw\" }", opaque),
    ]);
    refused_in(&dir, &text, "datasets[1].channels.red", &["already given"]);
}

// ---------------------------------------------------------------------------------------
// SPEC §3.2: mappings and the channels they need.

#[test]
fn raw_colour_needs_colour_channels() {
    // `ball` has only a voxel channel.
    let text = with(&[(
        "colour = { type = \"lut\", bounds = [100.0], colours = [[0, 0, 0], [1, 1, 1]] }",
        "colour = { type = \"raw\" }",
    )]);
    refused(&text, "objects[0].colour", &["red, green and blue", "grey", "bit"]);
    // Two of three colour channels are not enough either.
    let text =
        with(&[("[datasets.channels.blue]\ngenerator = { kind = \"constant\", value = 50, type = \"u8\" }\n", "")]);
    refused(&text, "objects[1].colour", &["red, green and blue"]);
}

#[test]
fn raw_opacity_needs_alpha() {
    let text = with(&[(
        "opacity = { type = \"lut\", bounds = [100.0], values = [0.0, 0.5] }",
        "opacity = { type = \"raw\" }",
    )]);
    refused(&text, "objects[0].opacity", &["alpha"]);
    let text =
        with(&[("[datasets.channels.alpha]\ngenerator = { kind = \"constant\", value = 128, type = \"u8\" }\n", "")]);
    refused(&text, "objects[1].opacity", &["alpha"]);
}

#[test]
fn voxel_reading_maps_need_a_voxel_channel() {
    // `rgba` has no voxel channel: a lut, ramp or non-constant polynomial cannot read it.
    let lut = "colour = { type = \"lut\", bounds = [1.0], colours = [[0, 0, 0], [1, 1, 1]] }";
    refused(
        &with(&[("colour = { type = \"raw\" }", lut)]),
        "objects[1].colour",
        &["`voxel`", "\"rgba\"", "raw or constant"],
    );
    let ramp = "opacity = { type = \"ramp\", points = [[0, 0], [1, 1]] }";
    refused(&with(&[("opacity = { type = \"raw\" }", ramp)]), "objects[1].opacity", &["`voxel`"]);
    let linear = "opacity = { type = \"linear\", coefficients = [0, 1] }";
    refused(&with(&[("opacity = { type = \"raw\" }", linear)]), "objects[1].opacity", &["`voxel`"]);
    // Constants read nothing.
    let constant = "opacity = { type = \"constant\", coefficients = [0.3] }";
    accepted(&with(&[("opacity = { type = \"raw\" }", constant)]));
}

#[test]
fn lut_on_an_image_dataset_is_refused() {
    let dir = scratch("image-lut");
    write_png(&dir, "photo.png");
    let lut = "colour = { type = \"lut\", bounds = [0.5], colours = [[0, 0, 0], [1, 1, 1]] }";
    let text = with(&[
        (RGBA, "image = \"photo.png\"\n"),
        ("colour = { type = \"raw\" }", lut),
        ("opacity = { type = \"raw\" }", "opacity = { type = \"constant\", coefficients = [1] }"),
    ]);
    refused_in(&dir, &text, "objects[1].colour", &["`voxel`"]);
}

#[test]
fn lut_bounds_must_strictly_increase() {
    let text = with(&[("bounds = [100.0], values = [0.0, 0.5]", "bounds = [100.0, 100.0], values = [0.0, 0.5, 1.0]")]);
    refused(&text, "objects[0].opacity.bounds", &["strictly increasing"]);
    let text = with(&[(
        "bounds = [100.0], colours = [[0, 0, 0], [1, 1, 1]]",
        "bounds = [5, 3], colours = [[0, 0, 0], [1, 1, 1], [0, 1, 0]]",
    )]);
    refused(&text, "objects[0].colour.bounds", &["strictly increasing", "[1] = 3 follows 5"]);
    let text = with(&[("bounds = [100.0], values", "bounds = [nan], values")]);
    refused(&text, "objects[0].opacity.bounds[0]", &["finite"]);
}

#[test]
fn lut_entries_must_be_one_more_than_bounds() {
    let text = with(&[("colours = [[0, 0, 0], [1, 1, 1]]", "colours = [[0, 0, 0], [1, 1, 1], [0, 1, 0]]")]);
    refused(&text, "objects[0].colour.colours", &["expected 2 entries", "got 3"]);
    let text = with(&[("values = [0.0, 0.5]", "values = [0.5]")]);
    refused(&text, "objects[0].opacity.values", &["expected 2 entries", "got 1"]);
    let text = with(&[("colours = [[0, 0, 0], [1, 1, 1]]", "colours = [[0, 0, 0], [1, 1]]")]);
    refused(&text, "objects[0].colour.colours[1]", &["expected 3 numbers", "got 2"]);
    let text = with(&[("values = [0.0, 0.5]", "values = [0.0, inf]")]);
    refused(&text, "objects[0].opacity.values[1]", &["finite"]);
}

#[test]
fn polynomial_coefficient_counts_are_checked() {
    let op = "opacity = { type = \"lut\", bounds = [100.0], values = [0.0, 0.5] }";
    let cases = [
        ("linear", "[0, 1, 2]", "exactly 2 coefficients, got 3"),
        ("constant", "[0, 1]", "exactly 1 coefficient, got 2"),
        ("quadratic", "[0, 1]", "exactly 3 coefficients, got 2"),
        ("cubic", "[0, 1, 2]", "exactly 4 coefficients, got 3"),
        ("polynomial", "[]", "1 to 32 coefficients"),
    ];
    for (ty, coefficients, needle) in cases {
        let edit = format!("opacity = {{ type = \"{ty}\", coefficients = {coefficients} }}");
        refused(&with(&[(op, &edit)]), "objects[0].opacity.coefficients", &[needle]);
    }
    let many = format!("opacity = {{ type = \"polynomial\", coefficients = {:?} }}", vec![0.0; 33]);
    refused(&with(&[(op, &many)]), "objects[0].opacity.coefficients", &["1 to 32 coefficients", "got 33"]);
    // Colour: each list on its own, named by its key.
    let col = "colour = { type = \"lut\", bounds = [100.0], colours = [[0, 0, 0], [1, 1, 1]] }";
    let edit = "colour = { type = \"linear\", red = [0, 1], green = [0, 1, 2], blue = [0, 1] }";
    refused(&with(&[(col, edit)]), "objects[0].colour.green", &["exactly 2 coefficients, got 3"]);
    let edit = "colour = { type = \"polynomial\", red = [0, 1], green = [0.5], blue = [] }";
    refused(&with(&[(col, edit)]), "objects[0].colour.blue", &["1 to 32 coefficients", "got 0"]);
}

#[test]
fn ramp_points_must_be_ordered() {
    let op = "opacity = { type = \"lut\", bounds = [100.0], values = [0.0, 0.5] }";
    let edit = "opacity = { type = \"ramp\", points = [[0, 0], [200, 1], [100, 0.5]] }";
    refused(&with(&[(op, edit)]), "objects[0].opacity.points[2]", &["ordered", "100 follows 200"]);
    let edit = "opacity = { type = \"ramp\", points = [] }";
    refused(&with(&[(op, edit)]), "objects[0].opacity.points", &["1 to 65536 points"]);
    let col = "colour = { type = \"lut\", bounds = [100.0], colours = [[0, 0, 0], [1, 1, 1]] }";
    let edit = "colour = { type = \"ramp\", points = [[0, 0, 0, 0], [255, 1, 1]] }";
    refused(&with(&[(col, edit)]), "objects[0].colour.points[1]", &["expected 4 numbers [value, r, g, b]"]);
    // Equal values make a step, which is allowed.
    let edit = "opacity = { type = \"ramp\", points = [[0, 0], [100, 0], [100, 1]] }";
    accepted(&with(&[(op, edit)]));
}

#[test]
fn unknown_map_types_are_refused() {
    let op = "opacity = { type = \"lut\", bounds = [100.0], values = [0.0, 0.5] }";
    refused(&with(&[(op, "opacity = { type = \"sigmoid\" }")]), "objects[0].opacity.type", &["sigmoid", "ramp"]);
    refused(
        &with(&[("colour = { type = \"raw\" }", "colour = { type = \"hsv\" }")]),
        "objects[1].colour.type",
        &["hsv", "lut"],
    );
}

// ---------------------------------------------------------------------------------------
// SPEC §3.3: interpolation.

fn with_interpolation(value: &str) -> String {
    with(&[("name = \"skull\"", &format!("name = \"skull\"\ninterpolation = {value}"))])
}

#[test]
fn interpolation_names_are_checked() {
    refused(
        &with_interpolation("\"bicubic\""),
        "objects[0].interpolation",
        &["unknown interpolation \"bicubic\"", "\"nearest\""],
    );
    refused(&with_interpolation("{ type = \"tricubic\" }"), "objects[0].interpolation", &["unknown interpolation"]);
    for ok in [
        "\"nearest\"",
        "\"trilinear\"",
        "\"cubic\"",
        "{ type = \"cubic\" }",
        "{ type = \"nonlinear\", omega = [0, 1, 0] }",
    ] {
        accepted(&with_interpolation(ok));
    }
}

#[test]
fn nonlinear_interpolation_needs_omega_of_three() {
    refused(&with_interpolation("\"nonlinear\""), "objects[0].interpolation", &["omega = [w0, w1, w2]"]);
    refused(&with_interpolation("{ type = \"nonlinear\" }"), "objects[0].interpolation.omega", &["missing"]);
    refused(
        &with_interpolation("{ type = \"nonlinear\", omega = [0, 1] }"),
        "objects[0].interpolation.omega",
        &["expected 3 numbers", "got 2"],
    );
    refused(
        &with_interpolation("{ type = \"nonlinear\", omega = [0, 1, 0, 0] }"),
        "objects[0].interpolation.omega",
        &["got 4"],
    );
    refused(
        &with_interpolation("{ type = \"nonlinear\", omega = [0, nan, 0] }"),
        "objects[0].interpolation.omega[1]",
        &["finite"],
    );
}

// ---------------------------------------------------------------------------------------
// SPEC §2: transforms and extents.

fn with_transform(value: &str) -> String {
    with(&[(
        "transform = { matrix = [[1, 0, 0, 1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]] }",
        &format!("transform = {value}"),
    )])
}

const MATRIX_KEY: &str = "objects[1].transform.matrix";

#[test]
fn matrix_must_be_four_by_four() {
    refused(&with_transform("{ matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]] }"), MATRIX_KEY, &["4×4"]);
    refused(&with_transform("{ matrix = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]] }"), MATRIX_KEY, &["4×4"]);
    refused(
        &with_transform("{ matrix = [[1, 0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]] }"),
        MATRIX_KEY,
        &["4×4"],
    );
}

#[test]
fn matrix_must_be_affine() {
    let m = "{ matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.5, 1]] }";
    refused(&with_transform(m), MATRIX_KEY, &["affine", "last row 0 0 0 1"]);
    let m = "{ matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 2]] }";
    refused(&with_transform(m), MATRIX_KEY, &["affine"]);
}

#[test]
fn matrix_must_be_finite() {
    for bad in ["nan", "inf", "-inf"] {
        let m = format!("{{ matrix = [[1, 0, 0, 0], [0, {bad}, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]] }}");
        refused(&with_transform(&m), MATRIX_KEY, &["finite"]);
    }
    let m = "{ matrix = [[1, 0, 0, 1e308], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]] }";
    accepted(&with_transform(m));
}

#[test]
fn matrix_must_be_non_singular() {
    let cases = [
        "{ matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]] }",
        "{ matrix = [[1, 2, 3, 0], [2, 4, 6, 0], [0, 0, 1, 0], [0, 0, 0, 1]] }",
        "{ matrix = [[0, 0, 0, 5], [0, 0, 0, 5], [0, 0, 0, 5], [0, 0, 0, 1]] }",
    ];
    for m in cases {
        refused(&with_transform(m), MATRIX_KEY, &["singular"]);
    }
    // Tiny but non-singular is a valid (small) box.
    accepted(&with_transform("{ matrix = [[1e-3, 0, 0, 0], [0, 1e-3, 0, 0], [0, 0, 1e-3, 0], [0, 0, 0, 1]] }"));
}

#[test]
fn matrix_and_corners_are_exclusive() {
    let both = "{ matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], corners = [] }";
    refused(&with_transform(both), "objects[1].transform", &["exactly one of `matrix` or `corners`"]);
    refused(&with_transform("{ }"), "objects[1].transform", &["exactly one of `matrix` or `corners`"]);
}

const UNIT_CORNERS: &str = "[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1]";

#[test]
fn corners_must_be_eight_points() {
    let k = "objects[1].transform.corners";
    refused(&with_transform(&format!("{{ corners = [{UNIT_CORNERS}] }}")), k, &["eight [x, y, z] corners"]);
    refused(&with_transform(&format!("{{ corners = [{UNIT_CORNERS}, [1, 1]] }}")), k, &["eight [x, y, z] corners"]);
    let nine = format!("{{ corners = [{UNIT_CORNERS}, [1, 1, 1], [2, 2, 2]] }}");
    refused(&with_transform(&nine), k, &["eight"]);
    refused(&with_transform(&format!("{{ corners = [{UNIT_CORNERS}, [1, nan, 1]] }}")), k, &["finite"]);
    accepted(&with_transform(&format!("{{ corners = [{UNIT_CORNERS}, [1, 1, 1]] }}")));
}

#[test]
fn folded_corners_are_refused() {
    // Corner 7 pulled through the box: the map's Jacobian changes sign (SPEC §2).
    let folded = format!("{{ corners = [{UNIT_CORNERS}, [-2, -2, -2]] }}");
    refused(&with_transform(&folded), "objects[1].transform.corners", &["folds over itself"]);
    // All eight corners at one point.
    let point = format!("{{ corners = [{}] }}", ["[1, 1, 1]"; 8].join(", "));
    refused(&with_transform(&point), "objects[1].transform.corners", &["degenerate"]);
}

fn with_extent(value: &str) -> String {
    with(&[("name = \"skull\"", &format!("name = \"skull\"\nextent = {value}"))])
}

#[test]
fn extent_min_must_be_below_max() {
    let e = refused(
        &with_extent("{ min = [0, 0.5, 0], max = [1, 0.5, 1] }"),
        "objects[0].extent",
        &["0 ≤ min < max ≤ 1", "axis 1"],
    );
    assert!(e.message.contains("0.5"), "{e}");
    refused(&with_extent("{ min = [0, 0, 0.8], max = [1, 1, 0.2] }"), "objects[0].extent", &["min < max", "axis 2"]);
    // An omitted max is 1.
    refused(&with_extent("{ min = [1, 0, 0] }"), "objects[0].extent", &["min < max", "axis 0"]);
}

#[test]
fn extent_must_lie_within_the_unit_cube() {
    refused(&with_extent("{ min = [-0.1, 0, 0] }"), "objects[0].extent", &["0 ≤ min"]);
    refused(&with_extent("{ max = [1, 1.5, 1] }"), "objects[0].extent", &["max ≤ 1"]);
    refused(&with_extent("{ max = [1, 1, nan] }"), "objects[0].extent", &["0 ≤ min < max ≤ 1"]);
    let s = accepted(&with_extent("{ min = [0, 0.25, 0], max = [1, 0.75, 1] }"));
    assert_eq!(s.objects[0].placement.extent().min.y, 0.25);
}

// ---------------------------------------------------------------------------------------
// SPEC §4.2: sampling distance.

fn with_sampling(value: &str) -> String {
    with(&[("name = \"skull\"", &format!("name = \"skull\"\nsampling_distance = {value}"))])
}

#[test]
fn sampling_distance_must_be_finite_and_not_negative() {
    for bad in ["-0.1", "nan", "inf", "-inf"] {
        refused(&with_sampling(bad), "objects[0].sampling_distance", &["finite world distance ≥ 0"]);
    }
    assert_eq!(accepted(&with_sampling("0")).objects[0].sampling_distance, 0.0);
    assert_eq!(accepted(&with_sampling("0.01")).objects[0].sampling_distance, 0.01);
}

#[test]
fn absurdly_small_sampling_distance_is_refused() {
    // The unit box is √3 across: 1e-9 would take ~1.7e9 samples per ray, over the cap.
    refused(&with_sampling("1e-9"), "objects[0].sampling_distance", &["samples per ray", "at most"]);
    refused(&with_sampling("5e-324"), "objects[0].sampling_distance", &["at most"]);
    // √3 / 2^24 ≈ 1.03e-7 is the smallest accepted for this box.
    accepted(&with_sampling("1.1e-7"));
}

// ---------------------------------------------------------------------------------------
// Scene::load.

#[test]
fn a_missing_scene_file_is_named() {
    let path = nowhere().join("no-such-scene.toml");
    let e = Scene::load(&path).unwrap_err();
    assert_eq!(e.key, "(file)");
    assert!(e.to_string().contains(&path.display().to_string()), "{e}");
    assert!(e.message.contains("cannot read the scene file"), "{e}");
}

#[test]
fn positional_arrays_are_refused_where_tables_are_expected() {
    let text = "image = [8, 6, [0, 0, 0]]\n[camera]\neye = [0, 0, 4]\ntarget = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 40\n";
    let err = Scene::parse(text, "pos.toml").unwrap_err();
    assert_eq!(err.key, "image");
    assert!(err.message.contains("table"), "{err}");
    let text = format!("{}\n[[objects]]\nname = \"x\"\ndataset = \"d\"\ncolour = {{ type = \"raw\" }}\nopacity = {{ type = \"raw\" }}\ntransform = [[1, 0, 0, 0]]\n", "[image]\nwidth = 2\nheight = 2\nbackground = [0, 0, 0]\n[camera]\neye = [0, 0, 4]\ntarget = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 40");
    let err = Scene::parse(&text, "pos.toml").unwrap_err();
    assert_eq!(err.key, "objects[0].transform");
}
