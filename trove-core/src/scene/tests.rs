//! Bad input (SPEC §1, §1.1, §2, §3.2, §3.3, §4.5): one test per rule a user can break.
//!
//! Every test starts from [`base`], a small valid scene whose datasets are generated (no
//! files needed), changes one thing, and checks through [`refused!`] that the scene is
//! refused, that the error's key is the exact TOML path of the offending key, that it names
//! the scene file, and that its kind is the rule that was broken. The wording users see is
//! checked separately, in `messages_name_the_file_the_key_and_what_was_expected`. Tests that
//! need files (raw size mismatches, missing files) write them to a scratch folder first.

use std::path::{Path, PathBuf};

use glam::DVec3;

use super::{DataRoot, Scene, SceneError, SceneErrorKind as Kind, MAX_IMAGE_SIDE, MAX_OBJECTS};
use crate::dataset::generator::GeneratorError;
use crate::dataset::{
    ChannelName, DataFile, DatasetError, DimsError, FileInfo, FileKind, FsCatalog, KeyProblem, VoxelType,
};
use crate::geometry::hexahedron::HexahedronError;
use crate::geometry::{CameraError, CameraField};
use crate::testing::TempDir;

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

/// A fresh scratch folder for a test that writes dataset files, removed when dropped.
fn scratch(name: &str) -> TempDir {
    TempDir::new(&format!("scene-{name}"))
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

/// The error and its causes on one line, as the command line prints them.
fn shown(err: &SceneError) -> String {
    crate::error::with_causes(err)
}

/// Parses `text` as `dir/NAME` and checks the refusal: exactly `key` (`None`: the file as a
/// whole), the file, a kind `is` accepts, and one line of text that starts with file and key.
#[track_caller]
fn refusal(dir: &Path, text: &str, key: Option<&str>, is: impl Fn(&Kind) -> bool) -> SceneError {
    let path = dir.join(NAME);
    let err = match Scene::parse(text, &path) {
        Ok(_) => panic!("accepted; expected a refusal at {key:?}:\n{text}"),
        Err(e) => e,
    };
    let shown = shown(&err);
    assert_eq!(err.key.as_deref(), key, "wrong key path in: {shown}");
    assert_eq!(err.file, path, "{shown}");
    assert!(is(&err.kind), "unexpected kind {:?} in: {shown}", err.kind);
    let start = match key {
        Some(key) => format!("{}: {key}: ", path.display()),
        None => format!("{}: ", path.display()),
    };
    assert!(shown.starts_with(&start) && shown.len() > start.len(), "not `{start}...`: {shown}");
    assert!(!shown.contains('\n'), "one-line message: {shown:?}");
    err
}

/// `refused!(text, key, pattern)`: the scene is refused at `key` with a kind matching the
/// pattern (guards allowed); `refused!(in dir, ...)` parses it in `dir`.
macro_rules! refused {
    (in $dir:expr, $text:expr, $key:expr, $($kind:tt)+) => {
        refusal(&$dir, &$text, Some(AsRef::<str>::as_ref(&$key)), |k| matches!(k, $($kind)+))
    };
    ($text:expr, $key:expr, $($kind:tt)+) => {
        refusal(&nowhere(), &$text, Some(AsRef::<str>::as_ref(&$key)), |k| matches!(k, $($kind)+))
    };
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
    let syntax = |k: &Kind| matches!(k, Kind::Syntax { .. });
    let e = refusal(&nowhere(), &with(&[("height = 6", "height = ")]), None, syntax);
    assert!(matches!(e.kind, Kind::Syntax { position: Some((4, _)), .. }), "{e:?}");
    refusal(&nowhere(), &with(&[("fov_y = 30.0", "fov_y = 30.0\nfov_y = 40.0")]), None, syntax);
    refusal(&nowhere(), &with(&[("[camera]", "[camera")]), None, syntax);
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
        let field = key.rsplit('.').next().unwrap_or(key);
        let e = refused!(with(edits), key, Kind::UnknownKey { .. } | Kind::UnknownMapKey { .. });
        if let Kind::UnknownKey { field: f, expected } = &e.kind {
            assert_eq!((f.as_str(), expected.is_some()), (field, true), "{e}");
        }
    }
}

#[test]
fn generator_keys_are_checked_by_name() {
    let key = |k: &str| format!("datasets[0].channels.voxel.generator.{k}");
    // An unknown key, a key of another kind, a key of the wrong type, a missing required key.
    refused!(with(&[("radius = 0.4", "radious = 0.4")]), key("radious"), Kind::UnknownKey { field, .. } if field == "radious");
    refused!(
        with(&[("radius = 0.4", "radius = 0.4, squares = [2, 2, 2]")]),
        key("squares"),
        Kind::Generator(GeneratorError::KeyNotForKind { key: "squares", kind: "sphere", .. })
    );
    refused!(
        with(&[("radius = 0.4", "radius = \"big\"")]),
        key("radius"),
        Kind::WrongType { expected, got } if expected == "a number" && got.starts_with("string")
    );
    refused!(
        with(&[("kind = \"sphere\", radius = 0.4", "kind = \"constant\"")]),
        key("value"),
        Kind::Generator(GeneratorError::MissingKey { kind: "constant", key: "value" })
    );
    let e = refused!(with(&[("kind = \"sphere\"", "kind = \"cube\"")]), key("kind"), Kind::Deserialize(_));
    assert!(shown(&e).contains("cube") && shown(&e).contains("sphere"), "{e}");
    refused!(
        with(&[("radius = 0.4", "radius = 0.4, type = \"i16\"")]),
        key("type"),
        Kind::Generator(GeneratorError::UnknownType { got }) if got == "i16"
    );
    // Values the generator refuses (documented in dataset::generator).
    refused!(
        with(&[("radius = 0.4", "radius = 0.0")]),
        key("radius"),
        Kind::Generator(GeneratorError::NotPositive { key: "radius", .. })
    );
    refused!(
        with(&[("radius = 0.4", "radius = 0.4, value = 300")]),
        key("value"),
        Kind::Generator(GeneratorError::DoesNotFit { key: "value", ty: VoxelType::U8, .. })
    );
    refused!(
        with(&[("radius = 0.4", "radius = nan")]),
        key("radius"),
        Kind::Generator(GeneratorError::NotFinite { key: "radius", .. })
    );
}

#[test]
fn wrong_types_are_refused_with_what_was_expected() {
    // (edit, key, what was expected, a fragment of what was found); `None`: a wrong length.
    let cases: &[(&str, &str, &str, &str, Option<&str>)] = &[
        ("width = 8", "width = \"8\"", "image.width", "a whole number", Some("string")),
        ("width = 8", "width = 8.5", "image.width", "a whole number", Some("8.5")),
        ("fov_y = 30.0", "fov_y = \"wide\"", "camera.fov_y", "a number", Some("string")),
        ("background = [0.1, 0.2, 0.3]", "background = [0.1, 0.2]", "image.background", "an array of length 3", None),
        ("background = [0.1, 0.2, 0.3]", "background = 0.5", "image.background", "an array of length 3", Some("0.5")),
        ("eye = [0.5, 0.5, 3.0]", "eye = [0.5, \"a\", 3.0]", "camera.eye[1]", "a number", Some("string")),
        ("termination = 0.99", "opacity_correction = \"yes\"", "render.opacity_correction", "a boolean", Some("yes")),
        ("dims = [4, 4, 4]", "dims = [4, 4]", "datasets[0].dims", "an array of length 3", None),
        ("dims = [4, 4, 4]", "dims = [4, 4, 4.5]", "datasets[0].dims[2]", "a whole number", Some("4.5")),
        ("name = \"ball\"", "name = 7", "datasets[0].name", "a string", Some("7")),
        ("dataset = \"ball\"", "dataset = [\"ball\"]", "objects[0].dataset", "a string", Some("sequence")),
        (
            "name = \"skull\"",
            "name = \"skull\"\nsampling_distance = \"fine\"",
            "objects[0].sampling_distance",
            "a number",
            Some("string"),
        ),
        ("values = [0.0, 0.5]", "values = [0.0, \"half\"]", "objects[0].opacity.values[1]", "a number", Some("string")),
        (
            "bounds = [100.0], values",
            "bounds = 100.0, values",
            "objects[0].opacity.bounds",
            "an array of numbers",
            Some("float"),
        ),
        (
            "colour = { type = \"raw\" }",
            "colour = { type = 3 }",
            "objects[1].colour.type",
            "a string (raw, lut",
            Some("integer"),
        ),
        ("[0, 0, 0, 1]] }", "[0, 0, \"0\", 1]] }", "objects[1].transform.matrix[3][2]", "a number", Some("string")),
        (
            "name = \"skull\"",
            "name = \"skull\"\ninterpolation = 3",
            "objects[0].interpolation",
            "\"nearest\", \"trilinear\"",
            Some("integer"),
        ),
    ];
    for &(old, new, key, want, found) in cases {
        refusal(&nowhere(), &with(&[(old, new)]), Some(key), |k| match (k, found) {
            (Kind::WrongType { expected, got }, Some(found)) => expected.starts_with(want) && got.contains(found),
            (Kind::WrongLength { expected, got: 2 }, None) => expected == want,
            _ => false,
        });
    }
    refused!(
        with(&[("colour = { type = \"raw\" }", "colour = \"raw\"")]),
        "objects[1].colour",
        Kind::NotAMap { got: "string" }
    );
    let table = |got: &'static str| move |k: &Kind| matches!(k, Kind::WrongType { expected, got: g } if expected == "a table of named keys" && g == got);
    let render = with(&[("\n[image]", "render = 3\n[image]"), ("[render]\ntermination = 0.99\n", "")]);
    refusal(&nowhere(), &render, Some("render"), table("integer `3`"));
    let image = with(&[
        ("\n[image]", "image = [8, 6]\n[image]"),
        ("[image]\nwidth = 8\nheight = 6\nbackground = [0.1, 0.2, 0.3]\n", ""),
    ]);
    refusal(&nowhere(), &image, Some("image"), table("array `[8, 6]`"));
    let mut objects = base();
    objects.truncate(objects.find("[[objects]]").expect("objects"));
    refused!(
        objects.replacen("\n[image]", "objects = 3\n[image]", 1),
        "objects",
        Kind::NotAnArrayOfTables { table, got } if table == "objects" && got == "integer `3`"
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
        let field = key.rsplit('.').next().unwrap_or(key);
        refused!(with(&[(line, "")]), key, Kind::MissingKey { field: f } if f == field);
    }
    // Whole tables.
    let no_image = with(&[("[image]\nwidth = 8\nheight = 6\nbackground = [0.1, 0.2, 0.3]\n", "")]);
    refused!(no_image, "image", Kind::MissingKey { field } if field == "image");
    let no_camera = with(&[(
        "[camera]\neye = [0.5, 0.5, 3.0]\ntarget = [0.5, 0.5, 0.5]\nup = [0.0, 1.0, 0.0]\nfov_y = 30.0\n",
        "",
    )]);
    refused!(no_camera, "camera", Kind::MissingKey { field } if field == "camera");
    // Inside mapping tables.
    refused!(
        with(&[("colour = { type = \"raw\" }", "colour = { }")]),
        "objects[1].colour.type",
        Kind::MissingMapType { .. }
    );
    refused!(with(&[("bounds = [100.0], values", "values")]), "objects[0].opacity.bounds", Kind::MissingMapKey);
    refused!(
        with(&[("colour = { type = \"raw\" }", "colour = { type = \"linear\", red = [0, 1], green = [0, 1] }")]),
        "objects[1].colour.blue",
        Kind::MissingMapKey
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
    refused!(with(&[("width = 8", "width = 0")]), "image.width", Kind::ImageSide { got: 0 });
    refused!(with(&[("width = 8", "width = -3")]), "image.width", Kind::ImageSide { got: -3 });
    let over = format!("height = {}", MAX_IMAGE_SIDE as u64 + 1);
    refused!(with(&[("height = 6", &over)]), "image.height", Kind::ImageSide { got: 16385 });
    let huge = with(&[("height = 6", "height = 4294967297")]);
    refused!(huge, "image.height", Kind::ImageSide { got: 4294967297 });
    let at_limit = format!("width = {MAX_IMAGE_SIDE}");
    assert_eq!(accepted(&with(&[("width = 8", &at_limit)])).image.width, MAX_IMAGE_SIDE);
}

#[test]
fn background_outside_the_unit_range_is_refused() {
    for bad in ["[1.5, 0.2, 0.3]", "[0.1, -0.01, 0.3]", "[0.1, 0.2, nan]", "[0.1, 0.2, inf]"] {
        let edit = format!("background = {bad}");
        refused!(with(&[("background = [0.1, 0.2, 0.3]", &edit)]), "image.background", Kind::Background { .. });
    }
    accepted(&with(&[("background = [0.1, 0.2, 0.3]", "background = [0, 1, 1.0]")]));
}

#[test]
fn fov_outside_the_open_range_is_refused() {
    for bad in ["0.0", "180.0", "-30", "200", "nan", "inf"] {
        let edit = format!("fov_y = {bad}");
        refused!(with(&[("fov_y = 30.0", &edit)]), "camera.fov_y", Kind::Camera(CameraError::FovOutOfRange { .. }));
    }
    accepted(&with(&[("fov_y = 30.0", "fov_y = 179.5")]));
    accepted(&with(&[("fov_y = 30.0", "fov_y = 1")]));
}

#[test]
fn termination_outside_the_half_open_range_is_refused() {
    for bad in ["0.0", "1.5", "-0.5", "nan"] {
        let edit = format!("termination = {bad}");
        refused!(with(&[("termination = 0.99", &edit)]), "render.termination", Kind::Termination { .. });
    }
    assert_eq!(accepted(&with(&[("termination = 0.99", "termination = 1.0")])).render.termination, 1.0);
}

#[test]
fn up_parallel_to_the_view_direction_is_refused() {
    for up in ["[0, 0, 1]", "[0, 0, -2.5]", "[0, 0, 0]"] {
        let edit = format!("up = {up}");
        refused!(
            with(&[("up = [0.0, 1.0, 0.0]", &edit)]),
            "camera.up",
            Kind::Camera(CameraError::UpParallelToView { .. })
        );
    }
    // Not parallel, merely oblique: fine.
    accepted(&with(&[("up = [0.0, 1.0, 0.0]", "up = [0, 1, 5]")]));
}

#[test]
fn eye_equal_to_target_is_refused() {
    refused!(
        with(&[("eye = [0.5, 0.5, 3.0]", "eye = [0.5, 0.5, 0.5]")]),
        "camera.target",
        Kind::Camera(CameraError::TargetIsEye)
    );
}

#[test]
fn non_finite_camera_vectors_are_refused() {
    let not_finite =
        |field| move |k: &Kind| matches!(k, Kind::Camera(CameraError::NotFinite { field: f, .. }) if *f == field);
    let text = with(&[("eye = [0.5, 0.5, 3.0]", "eye = [0.5, nan, 3.0]")]);
    refusal(&nowhere(), &text, Some("camera.eye"), not_finite(CameraField::Eye));
    let text = with(&[("target = [0.5, 0.5, 0.5]", "target = [inf, 0.5, 0.5]")]);
    refusal(&nowhere(), &text, Some("camera.target"), not_finite(CameraField::Target));
    let text = with(&[("up = [0.0, 1.0, 0.0]", "up = [0.0, -inf, 0.0]")]);
    refusal(&nowhere(), &text, Some("camera.up"), not_finite(CameraField::Up));
}

#[test]
fn unknown_distorted_sampling_mode_is_refused() {
    let text = with(&[("termination = 0.99", "termination = 0.99\ndistorted_sampling = \"fast\"")]);
    refused!(text, "render.distorted_sampling", Kind::DistortedSampling { got } if got == "fast");
}

// ---------------------------------------------------------------------------------------
// SPEC §1: names, references and counts.

#[test]
fn duplicate_dataset_names_are_refused() {
    refused!(
        with(&[("name = \"rgba\"", "name = \"ball\"")]),
        "datasets[1].name",
        Kind::DuplicateName { what: "dataset", name, first } if name == "ball" && first == "datasets[0]"
    );
}

#[test]
fn duplicate_object_names_are_refused() {
    refused!(
        with(&[("name = \"photo\"", "name = \"skull\"")]),
        "objects[1].name",
        Kind::DuplicateName { what: "object", name, first } if name == "skull" && first == "objects[0]"
    );
}

#[test]
fn an_object_naming_a_missing_dataset_is_refused() {
    refused!(
        with(&[("dataset = \"rgba\"", "dataset = \"rgb\"")]),
        "objects[1].dataset",
        Kind::UnknownDataset { name, known } if name == "rgb" && *known == ["ball", "rgba"]
    );
}

#[test]
fn object_count_is_within_the_documented_limit() {
    // The base has two objects; at the limit the scene loads, one more is refused.
    assert_eq!(accepted(&with_extra_objects(MAX_OBJECTS - 2)).objects.len(), MAX_OBJECTS);
    refused!(with_extra_objects(MAX_OBJECTS - 1), "objects", Kind::TooMany { what: "objects", max: 4096, got: 4097 });
}

#[test]
fn dataset_count_is_within_the_documented_limit() {
    let mut text = base();
    for i in 0..MAX_OBJECTS - 1 {
        text += &format!("[[datasets]]\nname = \"d{i}\"\n{BALL}");
    }
    refused!(text, "datasets", Kind::TooMany { what: "datasets", max: 4096, got: 4097 });
}

// ---------------------------------------------------------------------------------------
// SPEC §1.1: datasets and channels.

#[test]
fn a_dataset_without_any_source_is_refused() {
    refused!(with(&[(BALL, "")]), "datasets[0]", Kind::NoSource);
}

#[test]
fn explicit_channels_without_dims_are_refused() {
    refused!(with(&[("dims = [4, 4, 4]\n", "")]), "datasets[0].dims", Kind::MissingDims);
}

#[test]
fn dims_below_one_are_refused() {
    for bad in ["[0, 4, 4]", "[4, -1, 4]", "[4, 4, 0]"] {
        let edit = format!("dims = {bad}");
        refused!(with(&[("dims = [4, 4, 4]", &edit)]), "datasets[0].dims", Kind::DimsBelowOne { .. });
    }
}

#[test]
fn dims_whose_byte_size_overflows_are_refused() {
    let cases = [
        ("[2147483647, 2147483647, 2147483647]", false),
        ("[1048576, 1048576, 2]", false),
        ("[4294967296, 1, 1]", true),
        ("[9223372036854775807, 9223372036854775807, 2]", true),
    ];
    for (bad, axis_too_large) in cases {
        let edit = format!("dims = {bad}");
        refusal(&nowhere(), &with(&[("dims = [4, 4, 4]", &edit)]), Some("datasets[0].dims"), |k| match k {
            Kind::Dims(DimsError::AxisTooLarge { .. }) => axis_too_large,
            Kind::Dims(DimsError::TooManyVoxels { .. }) => !axis_too_large,
            _ => false,
        });
    }
}

#[test]
fn unknown_channel_names_are_refused() {
    let text = with(&[("[datasets.channels.voxel]", "[datasets.channels.density]")]);
    refused!(text, "datasets[0].channels.density", Kind::UnknownChannel);
}

#[test]
fn a_channel_needs_exactly_one_source() {
    let both = with(&[("radius = 0.4 }", "radius = 0.4 }\nraw = \"ball.raw\"\ntype = \"u8\"")]);
    refused!(both, "datasets[0].channels.voxel", Kind::ChannelSources);
    let none = with(&[("generator = { kind = \"sphere\", radius = 0.4 }", "")]);
    refused!(none, "datasets[0].channels.voxel", Kind::ChannelSources);
}

#[test]
fn raw_only_keys_on_other_channels_are_refused() {
    let text = with(&[("radius = 0.4 }", "radius = 0.4 }\nendian = \"big\"")]);
    refused!(text, "datasets[0].channels.voxel.endian", Kind::RawOnlyKey);
    let text = with(&[("radius = 0.4 }", "radius = 0.4 }\ntype = \"u8\"")]);
    refused!(text, "datasets[0].channels.voxel.type", Kind::RawOnlyKey);
}

#[test]
fn raw_channel_type_and_endian_are_checked() {
    let dir = scratch("raw-type");
    std::fs::write(dir.join("ball.raw"), [0u8; 64]).unwrap();
    let gen = "generator = { kind = \"sphere\", radius = 0.4 }";
    let k = "datasets[0].channels.voxel";
    refused!(in dir, with(&[(gen, "raw = \"ball.raw\"")]), format!("{k}.type"), Kind::MissingRawType);
    let text = with(&[(gen, "raw = \"ball.raw\"\ntype = \"i16\"")]);
    refused!(in dir, text, format!("{k}.type"), Kind::UnknownVoxelType { got } if got == "i16");
    let text = with(&[(gen, "raw = \"ball.raw\"\ntype = \"u8\"\nendian = \"middle\"")]);
    refused!(in dir, text, format!("{k}.endian"), Kind::UnknownEndian { got } if got == "middle");
    accepted_in(&dir, &with(&[(gen, "raw = \"ball.raw\"\ntype = \"u8\"\nendian = \"big\"")]));
}

#[test]
fn a_channel_type_the_channel_does_not_allow_is_refused() {
    // `red` must be u8 (SPEC §1.1); from a raw file the key is the `type` that says u16.
    let dir = scratch("channel-type");
    std::fs::write(dir.join("red.raw"), [0u8; 16]).unwrap();
    let red = "[datasets.channels.red]\ngenerator = { kind = \"constant\", value = 200, type = \"u8\" }";
    let text = with(&[(red, "[datasets.channels.red]\nraw = \"red.raw\"\ntype = \"u16\"")]);
    refused!(
        in dir,
        text,
        "datasets[1].channels.red.type",
        Kind::ChannelType { channel: ChannelName::Red, got: VoxelType::U16 }
    );
    // From a generator, the generator.
    let text = with(&[("value = 200, type = \"u8\"", "value = 200, type = \"f32\"")]);
    refused!(
        text,
        "datasets[1].channels.red.generator",
        Kind::ChannelType { channel: ChannelName::Red, got: VoxelType::F32 }
    );
    // `bit` must be bit.
    let text = with(&[(
        "[datasets.channels.alpha]",
        "[datasets.channels.bit]\ngenerator = { kind = \"ramp\" }\n[datasets.channels.alpha]",
    )]);
    refused!(
        text,
        "datasets[1].channels.bit.generator",
        Kind::ChannelType { channel: ChannelName::Bit, got: VoxelType::F32 }
    );
}

#[test]
fn raw_file_size_must_match_dims_exactly() {
    let dir = scratch("raw-size");
    std::fs::write(dir.join("ball.raw"), [0u8; 100]).unwrap();
    let text = with(&[("generator = { kind = \"sphere\", radius = 0.4 }", "raw = \"ball.raw\"\ntype = \"u16\"")]);
    // dims [4, 4, 4] of u16 need 128 bytes; the file has 100.
    let file = dir.join("ball.raw");
    refused!(
        in dir,
        text,
        "datasets[0].channels.voxel.raw",
        Kind::Dataset(DatasetError::SizeMismatch { path, expected: 128, actual: 100, .. }) if *path == file
    );
    // One byte too many is as wrong as too few.
    std::fs::write(dir.join("ball.raw"), [0u8; 129]).unwrap();
    refused!(
        in dir,
        text,
        "datasets[0].channels.voxel.raw",
        Kind::Dataset(DatasetError::SizeMismatch { expected: 128, actual: 129, .. })
    );
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
    let file = dir.join("short.nrrd");
    refused!(
        in dir,
        text,
        "datasets[0].file",
        Kind::Dataset(DatasetError::SizeMismatch { path, expected: 64, actual: 60, .. }) if *path == file
    );

    let mut bytes = header.as_bytes().to_vec();
    bytes.extend([0u8; 64]);
    std::fs::write(dir.join("ok.nrrd"), &bytes).unwrap();
    accepted_in(&dir, &with(&[(BALL, "file = \"ok.nrrd\"\n")]));
    // Dims in the scene that disagree with the header.
    let text = with(&[(BALL, "file = \"ok.nrrd\"\ndims = [4, 4, 5]\n")]);
    let disagree = |k: &Kind| matches!(k, Kind::DimsDisagree { found, declared } if found.as_array() == [4, 4, 4] && declared.as_array() == [4, 4, 5]);
    refusal(&dir, &text, Some("datasets[0].file"), disagree);
    let gen = "generator = { kind = \"sphere\", radius = 0.4 }";
    let text = with(&[("dims = [4, 4, 4]", "dims = [4, 4, 5]"), (gen, "nrrd = \"ok.nrrd\"")]);
    refusal(&dir, &text, Some("datasets[0].channels.voxel.nrrd"), disagree);
}

#[test]
fn nonexistent_files_are_refused_naming_the_path() {
    let dir = scratch("missing-files");
    let gen = "generator = { kind = \"sphere\", radius = 0.4 }";
    // The error names the key and the file it looked for (resolved against the scene's
    // folder, not the working directory), and the data root it looked in.
    let missing = |name: &str| {
        let file = dir.join(name);
        let name = name.to_string();
        move |k: &Kind| {
            matches!(k, Kind::DataNotFound { key, looked_for, root }
                if *key == name && *looked_for == file && **root == DataRoot::SceneFolder)
        }
    };
    let text = with(&[(gen, "raw = \"absent.raw\"\ntype = \"u8\"")]);
    refusal(&dir, &text, Some("datasets[0].channels.voxel.raw"), missing("absent.raw"));
    let text = with(&[(gen, "nrrd = \"absent.nrrd\"")]);
    refusal(&dir, &text, Some("datasets[0].channels.voxel.nrrd"), missing("absent.nrrd"));
    let text = with(&[(BALL, "file = \"absent.nhdr\"\n")]);
    refusal(&dir, &text, Some("datasets[0].file"), missing("absent.nhdr"));
    let text = with(&[(BALL, "file = \"absent.nii.gz\"\n")]);
    refusal(&dir, &text, Some("datasets[0].file"), missing("absent.nii.gz"));
    let text = with(&[(RGBA, "image = \"absent.png\"\n")]);
    refusal(&dir, &text, Some("datasets[1].image"), missing("absent.png"));
    let text = with(&[(RGBA, "image = \"sub/absent.png\"\n")]);
    refusal(&dir, &text, Some("datasets[1].image"), missing("sub/absent.png"));

    // A header found under the data root whose own data file is missing is a fault of that
    // header, not of the data root: the error names the data file and keeps the OS's kind.
    std::fs::write(
        dir.join("lost.nhdr"),
        "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 4 4 4\nencoding: raw\ndata file: lost.raw\n",
    )
    .unwrap();
    let lost = dir.join("lost.raw");
    let text = with(&[(BALL, "file = \"lost.nhdr\"\n")]);
    refusal(&dir, &text, Some("datasets[0].file"), |k| {
        matches!(k, Kind::Dataset(e @ DatasetError::Io { path, source })
            if *path == lost && source.kind() == std::io::ErrorKind::NotFound && !e.is_retryable())
    });
}

#[test]
fn keys_resolve_under_the_data_root_given() {
    let data = scratch("data-root");
    let scenes = scratch("data-root-scenes");
    std::fs::write(data.join("ball.raw"), [7u8; 64]).unwrap();
    let gen = "generator = { kind = \"sphere\", radius = 0.4 }";
    let text = with(&[(gen, "raw = \"ball.raw\"\ntype = \"u8\"")]);
    let path = scenes.join(NAME);
    for root in [DataRoot::Given(data.to_path_buf()), DataRoot::Environment(data.to_path_buf())] {
        let scene = Scene::parse_in(&text, &path, &root).unwrap_or_else(|e| panic!("{root:?}: {e}"));
        assert_eq!(scene.path(), path, "messages still name the scene file");
    }
    std::fs::write(&path, &text).unwrap();
    assert!(Scene::load_in(&path, &DataRoot::Given(data.to_path_buf())).is_ok());
    // The scene's folder does not hold it, and a root given replaces that folder.
    let e = Scene::load(&path).unwrap_err();
    let looked = scenes.join("ball.raw");
    assert!(
        matches!(&e.kind, Kind::DataNotFound { key, looked_for, root }
            if key == "ball.raw" && *looked_for == looked && **root == DataRoot::SceneFolder),
        "{e:?}"
    );
    let elsewhere = DataRoot::Environment(scenes.join("elsewhere"));
    let e = Scene::load_in(&path, &elsewhere).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("datasets[0].channels.voxel.raw"));
    assert!(matches!(&e.kind, Kind::DataNotFound { root, .. } if **root == elsewhere), "{e:?}");
}

#[test]
fn a_file_with_an_unsupported_extension_is_refused() {
    let dir = scratch("extension");
    std::fs::write(dir.join("head.mha"), b"not read").unwrap();
    let text = with(&[(BALL, "file = \"head.mha\"\n")]);
    refused!(in dir, text, "datasets[0].file", Kind::VolumeExtension { file, .. } if file == "head.mha");
}

#[test]
fn an_image_that_is_not_an_image_is_refused() {
    let dir = scratch("not-an-image");
    std::fs::write(dir.join("photo.png"), b"plain text, not a PNG").unwrap();
    let text = with(&[(RGBA, "image = \"photo.png\"\n")]);
    let file = dir.join("photo.png");
    let e =
        refused!(in dir, text, "datasets[1].image", Kind::Dataset(DatasetError::Format { path, .. }) if *path == file);
    assert!(shown(&e).contains("not a readable PNG or JPEG image"), "{e}");
}

#[test]
fn file_and_image_together_are_refused() {
    let text = with(&[(BALL, "file = \"a.nrrd\"\nimage = \"a.png\"\n")]);
    refused!(text, "datasets[0].image", Kind::FileAndImage);
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
    refused!(in dir, text, "objects[1].opacity", Kind::RawOpacityAlpha);
    let opaque = "opacity = { type = \"constant\", coefficients = [0.5] }";
    let s = accepted_in(&dir, &with(&[(RGBA, "image = \"photo.png\"\n"), ("opacity = { type = \"raw\" }", opaque)]));
    assert_eq!(s.datasets()[1].dims().as_array(), [3, 2, 1]);
    // Declared dims must agree with the image.
    let text = with(&[(RGBA, "image = \"photo.png\"\ndims = [3, 3, 1]\n"), ("opacity = { type = \"raw\" }", opaque)]);
    refused!(
        in dir,
        text,
        "datasets[1].image",
        Kind::DimsDisagree { found, declared } if found.as_array() == [3, 2, 1] && declared.as_array() == [3, 3, 1]
    );
    // A channel the image already gives cannot be given again.
    let text = with(&[
        (RGBA, "image = \"photo.png\"\n[datasets.channels.red]\ngenerator = { kind = \"constant\", value = 1, type = \"u8\" }\n"),
        ("opacity = { type = \"raw\" }", opaque),
    ]);
    refused!(in dir, text, "datasets[1].channels.red", Kind::ChannelGivenTwice { channel: ChannelName::Red });
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
    refused!(text, "objects[0].colour", Kind::RawColourChannels);
    // Two of three colour channels are not enough either.
    let text =
        with(&[("[datasets.channels.blue]\ngenerator = { kind = \"constant\", value = 50, type = \"u8\" }\n", "")]);
    refused!(text, "objects[1].colour", Kind::RawColourChannels);
}

#[test]
fn raw_opacity_needs_alpha() {
    let text = with(&[(
        "opacity = { type = \"lut\", bounds = [100.0], values = [0.0, 0.5] }",
        "opacity = { type = \"raw\" }",
    )]);
    refused!(text, "objects[0].opacity", Kind::RawOpacityAlpha);
    let text =
        with(&[("[datasets.channels.alpha]\ngenerator = { kind = \"constant\", value = 128, type = \"u8\" }\n", "")]);
    refused!(text, "objects[1].opacity", Kind::RawOpacityAlpha);
}

#[test]
fn voxel_reading_maps_need_a_voxel_channel() {
    // `rgba` has no voxel channel: a lut, ramp or non-constant polynomial cannot read it.
    let lut = "colour = { type = \"lut\", bounds = [1.0], colours = [[0, 0, 0], [1, 1, 1]] }";
    let rgba = |k: &Kind| matches!(k, Kind::MapNeedsVoxel { dataset } if dataset == "rgba");
    refusal(&nowhere(), &with(&[("colour = { type = \"raw\" }", lut)]), Some("objects[1].colour"), rgba);
    let ramp = "opacity = { type = \"ramp\", points = [[0, 0], [1, 1]] }";
    refusal(&nowhere(), &with(&[("opacity = { type = \"raw\" }", ramp)]), Some("objects[1].opacity"), rgba);
    let linear = "opacity = { type = \"linear\", coefficients = [0, 1] }";
    refusal(&nowhere(), &with(&[("opacity = { type = \"raw\" }", linear)]), Some("objects[1].opacity"), rgba);
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
    refused!(in dir, text, "objects[1].colour", Kind::MapNeedsVoxel { .. });
}

#[test]
fn lut_bounds_must_strictly_increase() {
    let text = with(&[("bounds = [100.0], values = [0.0, 0.5]", "bounds = [100.0, 100.0], values = [0.0, 0.5, 1.0]")]);
    refused!(text, "objects[0].opacity.bounds", Kind::BoundsNotIncreasing { index: 1, .. });
    let text = with(&[(
        "bounds = [100.0], colours = [[0, 0, 0], [1, 1, 1]]",
        "bounds = [5, 3], colours = [[0, 0, 0], [1, 1, 1], [0, 1, 0]]",
    )]);
    refused!(text, "objects[0].colour.bounds", Kind::BoundsNotIncreasing { index: 1, value: 3.0, previous: 5.0 });
    let text = with(&[("bounds = [100.0], values", "bounds = [nan], values")]);
    refused!(text, "objects[0].opacity.bounds[0]", Kind::NotFinite { got } if got.is_nan());
}

#[test]
fn lut_entries_must_be_one_more_than_bounds() {
    let text = with(&[("colours = [[0, 0, 0], [1, 1, 1]]", "colours = [[0, 0, 0], [1, 1, 1], [0, 1, 0]]")]);
    refused!(text, "objects[0].colour.colours", Kind::LutEntries { bounds: 1, got: 3 });
    let text = with(&[("values = [0.0, 0.5]", "values = [0.5]")]);
    refused!(text, "objects[0].opacity.values", Kind::LutEntries { bounds: 1, got: 1 });
    let text = with(&[("colours = [[0, 0, 0], [1, 1, 1]]", "colours = [[0, 0, 0], [1, 1]]")]);
    refused!(text, "objects[0].colour.colours[1]", Kind::NumberCount { expected: 3, layout: None, got: 2 });
    let text = with(&[("values = [0.0, 0.5]", "values = [0.0, inf]")]);
    refused!(text, "objects[0].opacity.values[1]", Kind::NotFinite { got } if got.is_infinite());
}

#[test]
fn polynomial_coefficient_counts_are_checked() {
    let op = "opacity = { type = \"lut\", bounds = [100.0], values = [0.0, 0.5] }";
    let cases = [
        ("linear", "[0, 1, 2]", 2, 3),
        ("constant", "[0, 1]", 1, 2),
        ("quadratic", "[0, 1]", 3, 2),
        ("cubic", "[0, 1, 2]", 4, 3),
    ];
    for (ty, coefficients, n, given) in cases {
        let edit = format!("opacity = {{ type = \"{ty}\", coefficients = {coefficients} }}");
        refused!(
            with(&[(op, &edit)]),
            "objects[0].opacity.coefficients",
            Kind::CoefficientCount { ty: t, expected, got } if *t == ty && *expected == n && *got == given
        );
    }
    let edit = "opacity = { type = \"polynomial\", coefficients = [] }";
    refused!(with(&[(op, edit)]), "objects[0].opacity.coefficients", Kind::PolynomialTerms { got: 0 });
    let many = format!("opacity = {{ type = \"polynomial\", coefficients = {:?} }}", vec![0.0; 33]);
    refused!(with(&[(op, &many)]), "objects[0].opacity.coefficients", Kind::PolynomialTerms { got: 33 });
    // Colour: each list on its own, named by its key.
    let col = "colour = { type = \"lut\", bounds = [100.0], colours = [[0, 0, 0], [1, 1, 1]] }";
    let edit = "colour = { type = \"linear\", red = [0, 1], green = [0, 1, 2], blue = [0, 1] }";
    refused!(
        with(&[(col, edit)]),
        "objects[0].colour.green",
        Kind::CoefficientCount { ty: "linear", expected: 2, got: 3 }
    );
    let edit = "colour = { type = \"polynomial\", red = [0, 1], green = [0.5], blue = [] }";
    refused!(with(&[(col, edit)]), "objects[0].colour.blue", Kind::PolynomialTerms { got: 0 });
}

#[test]
fn ramp_points_must_be_ordered() {
    let op = "opacity = { type = \"lut\", bounds = [100.0], values = [0.0, 0.5] }";
    let edit = "opacity = { type = \"ramp\", points = [[0, 0], [200, 1], [100, 0.5]] }";
    refused!(
        with(&[(op, edit)]),
        "objects[0].opacity.points[2]",
        Kind::RampNotOrdered { value: 100.0, previous: 200.0 }
    );
    let edit = "opacity = { type = \"ramp\", points = [] }";
    refused!(with(&[(op, edit)]), "objects[0].opacity.points", Kind::RampPointCount { got: 0 });
    let col = "colour = { type = \"lut\", bounds = [100.0], colours = [[0, 0, 0], [1, 1, 1]] }";
    let edit = "colour = { type = \"ramp\", points = [[0, 0, 0, 0], [255, 1, 1]] }";
    refused!(
        with(&[(col, edit)]),
        "objects[0].colour.points[1]",
        Kind::NumberCount { expected: 4, layout: Some("[value, r, g, b]"), got: 3 }
    );
    // Equal values make a step, which is allowed.
    let edit = "opacity = { type = \"ramp\", points = [[0, 0], [100, 0], [100, 1]] }";
    accepted(&with(&[(op, edit)]));
}

#[test]
fn unknown_map_types_are_refused() {
    let op = "opacity = { type = \"lut\", bounds = [100.0], values = [0.0, 0.5] }";
    refused!(
        with(&[(op, "opacity = { type = \"sigmoid\" }")]),
        "objects[0].opacity.type",
        Kind::UnknownMapType { map: "opacity", got, .. } if got == "sigmoid"
    );
    refused!(
        with(&[("colour = { type = \"raw\" }", "colour = { type = \"hsv\" }")]),
        "objects[1].colour.type",
        Kind::UnknownMapType { map: "colour", got, .. } if got == "hsv"
    );
}

// ---------------------------------------------------------------------------------------
// SPEC §3.3: interpolation.

fn with_interpolation(value: &str) -> String {
    with(&[("name = \"skull\"", &format!("name = \"skull\"\ninterpolation = {value}"))])
}

#[test]
fn interpolation_names_are_checked() {
    refused!(
        with_interpolation("\"bicubic\""),
        "objects[0].interpolation",
        Kind::UnknownInterpolation { got } if got == "bicubic"
    );
    refused!(
        with_interpolation("{ type = \"tricubic\" }"),
        "objects[0].interpolation",
        Kind::UnknownInterpolation { got } if got == "tricubic"
    );
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
    refused!(with_interpolation("\"nonlinear\""), "objects[0].interpolation", Kind::NonlinearNeedsOmega);
    refused!(with_interpolation("{ type = \"nonlinear\" }"), "objects[0].interpolation.omega", Kind::MissingMapKey);
    refused!(
        with_interpolation("{ type = \"nonlinear\", omega = [0, 1] }"),
        "objects[0].interpolation.omega",
        Kind::NumberCount { expected: 3, layout: Some("[w0, w1, w2]"), got: 2 }
    );
    refused!(
        with_interpolation("{ type = \"nonlinear\", omega = [0, 1, 0, 0] }"),
        "objects[0].interpolation.omega",
        Kind::NumberCount { expected: 3, got: 4, .. }
    );
    refused!(
        with_interpolation("{ type = \"nonlinear\", omega = [0, nan, 0] }"),
        "objects[0].interpolation.omega[1]",
        Kind::NotFinite { .. }
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
    refused!(with_transform("{ matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]] }"), MATRIX_KEY, Kind::MatrixShape);
    refused!(
        with_transform("{ matrix = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]] }"),
        MATRIX_KEY,
        Kind::MatrixShape
    );
    refused!(
        with_transform("{ matrix = [[1, 0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]] }"),
        MATRIX_KEY,
        Kind::MatrixShape
    );
}

#[test]
fn matrix_must_be_affine() {
    let m = "{ matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.5, 1]] }";
    refused!(with_transform(m), MATRIX_KEY, Kind::NotAffine { last_row } if *last_row == [0.0, 0.0, 0.5, 1.0]);
    let m = "{ matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 2]] }";
    refused!(with_transform(m), MATRIX_KEY, Kind::NotAffine { .. });
}

#[test]
fn matrix_must_be_finite() {
    for bad in ["nan", "inf", "-inf"] {
        let m = format!("{{ matrix = [[1, 0, 0, 0], [0, {bad}, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]] }}");
        refused!(with_transform(&m), MATRIX_KEY, Kind::MatrixNotFinite);
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
        refused!(with_transform(m), MATRIX_KEY, Kind::SingularMatrix);
    }
    // Tiny but non-singular is a valid (small) box.
    accepted(&with_transform("{ matrix = [[1e-3, 0, 0, 0], [0, 1e-3, 0, 0], [0, 0, 1e-3, 0], [0, 0, 0, 1]] }"));
}

#[test]
fn matrix_and_corners_are_exclusive() {
    let both = "{ matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], corners = [] }";
    refused!(with_transform(both), "objects[1].transform", Kind::TransformSources);
    refused!(with_transform("{ }"), "objects[1].transform", Kind::TransformSources);
}

const UNIT_CORNERS: &str = "[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1]";

#[test]
fn corners_must_be_eight_points() {
    let k = "objects[1].transform.corners";
    refused!(with_transform(&format!("{{ corners = [{UNIT_CORNERS}] }}")), k, Kind::CornerCount);
    refused!(with_transform(&format!("{{ corners = [{UNIT_CORNERS}, [1, 1]] }}")), k, Kind::CornerCount);
    let nine = format!("{{ corners = [{UNIT_CORNERS}, [1, 1, 1], [2, 2, 2]] }}");
    refused!(with_transform(&nine), k, Kind::CornerCount);
    refused!(
        with_transform(&format!("{{ corners = [{UNIT_CORNERS}, [1, nan, 1]] }}")),
        k,
        Kind::Hexahedron(HexahedronError::NonFiniteCorner { index: 7, .. })
    );
    accepted(&with_transform(&format!("{{ corners = [{UNIT_CORNERS}, [1, 1, 1]] }}")));
}

#[test]
fn folded_corners_are_refused() {
    // Corner 7 pulled through the box: the map's Jacobian changes sign (SPEC §2).
    let folded = format!("{{ corners = [{UNIT_CORNERS}, [-2, -2, -2]] }}");
    refused!(with_transform(&folded), "objects[1].transform.corners", Kind::Hexahedron(HexahedronError::Folds { .. }));
    // All eight corners at one point.
    let point = format!("{{ corners = [{}] }}", ["[1, 1, 1]"; 8].join(", "));
    refused!(with_transform(&point), "objects[1].transform.corners", Kind::Hexahedron(HexahedronError::SinglePoint));
}

fn with_extent(value: &str) -> String {
    with(&[("name = \"skull\"", &format!("name = \"skull\"\nextent = {value}"))])
}

#[test]
fn extent_min_must_be_below_max() {
    refused!(
        with_extent("{ min = [0, 0.5, 0], max = [1, 0.5, 1] }"),
        "objects[0].extent",
        Kind::Extent { min: [0.0, 0.5, 0.0], max: [1.0, 0.5, 1.0], axis: 1 }
    );
    refused!(
        with_extent("{ min = [0, 0, 0.8], max = [1, 1, 0.2] }"),
        "objects[0].extent",
        Kind::Extent { axis: 2, .. }
    );
    // An omitted max is 1.
    refused!(
        with_extent("{ min = [1, 0, 0] }"),
        "objects[0].extent",
        Kind::Extent { max: [1.0, 1.0, 1.0], axis: 0, .. }
    );
}

#[test]
fn extent_must_lie_within_the_unit_cube() {
    refused!(with_extent("{ min = [-0.1, 0, 0] }"), "objects[0].extent", Kind::Extent { axis: 0, .. });
    refused!(with_extent("{ max = [1, 1.5, 1] }"), "objects[0].extent", Kind::Extent { axis: 1, .. });
    refused!(with_extent("{ max = [1, 1, nan] }"), "objects[0].extent", Kind::Extent { axis: 2, .. });
    let s = accepted(&with_extent("{ min = [0, 0.25, 0], max = [1, 0.75, 1] }"));
    assert_eq!(s.objects()[0].placement.extent().min.y, 0.25);
}

// ---------------------------------------------------------------------------------------
// SPEC §4.2: sampling distance.

fn with_sampling(value: &str) -> String {
    with(&[("name = \"skull\"", &format!("name = \"skull\"\nsampling_distance = {value}"))])
}

#[test]
fn sampling_distance_must_be_finite_and_not_negative() {
    for bad in ["-0.1", "nan", "inf", "-inf"] {
        refused!(with_sampling(bad), "objects[0].sampling_distance", Kind::SamplingDistance { .. });
    }
    assert_eq!(accepted(&with_sampling("0")).objects[0].sampling_distance, 0.0);
    assert_eq!(accepted(&with_sampling("0.01")).objects[0].sampling_distance, 0.01);
}

#[test]
fn absurdly_small_sampling_distance_is_refused() {
    // The unit box is √3 across: 1e-9 would take ~1.7e9 samples per ray, over the cap.
    refused!(with_sampling("1e-9"), "objects[0].sampling_distance", Kind::TooManySamplesPerRay { distance, .. } if *distance == 1e-9);
    refused!(with_sampling("5e-324"), "objects[0].sampling_distance", Kind::TooManySamplesPerRay { .. });
    // √3 / 2^24 ≈ 1.03e-7 is the smallest accepted for this box.
    accepted(&with_sampling("1.1e-7"));
}

// ---------------------------------------------------------------------------------------
// Scene::load.

#[test]
fn a_missing_scene_file_is_named() {
    let path = nowhere().join("no-such-scene.toml");
    let e = Scene::load(&path).unwrap_err();
    assert_eq!((e.file.as_path(), e.key.as_deref()), (path.as_path(), None));
    assert!(matches!(&e.kind, Kind::Read(io) if io.kind() == std::io::ErrorKind::NotFound), "{e:?}");
}

#[test]
fn positional_arrays_are_refused_where_tables_are_expected() {
    let text = "image = [8, 6, [0, 0, 0]]\n[camera]\neye = [0, 0, 4]\ntarget = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 40\n";
    let err = Scene::parse(text, "pos.toml").unwrap_err();
    assert_eq!(err.key.as_deref(), Some("image"));
    assert!(matches!(&err.kind, Kind::WrongType { expected, .. } if expected == "a table of named keys"), "{err}");
    let text = format!("{}\n[[objects]]\nname = \"x\"\ndataset = \"d\"\ncolour = {{ type = \"raw\" }}\nopacity = {{ type = \"raw\" }}\ntransform = [[1, 0, 0, 0]]\n", "[image]\nwidth = 2\nheight = 2\nbackground = [0, 0, 0]\n[camera]\neye = [0, 0, 4]\ntarget = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 40");
    let err = Scene::parse(&text, "pos.toml").unwrap_err();
    assert_eq!(err.key.as_deref(), Some("objects[0].transform"));
}

// ---------------------------------------------------------------------------------------
// The wording users see (SPEC §1): file, key path, what was expected, and the cause found by
// a lower layer, on one line, as `trove render` prints it.

#[test]
fn messages_name_the_file_the_key_and_what_was_expected() {
    let path = nowhere().join(NAME);
    let file = path.display();
    let message = |text: &str| shown(&Scene::parse(text, &path).unwrap_err());
    let text = with(&[("bounds = [100.0], values = [0.0, 0.5]", "bounds = [9, 5], values = [0.0, 0.5, 1]")]);
    assert_eq!(
        message(&text),
        format!("{file}: objects[0].opacity.bounds: bounds must be strictly increasing, but [1] = 5 follows 9")
    );
    assert_eq!(
        message(&with(&[("radius = 0.4", "radius = 0.0")])),
        format!("{file}: datasets[0].channels.voxel.generator.radius: `radius` = 0: must be greater than 0")
    );
    assert_eq!(
        message(&with(&[("up = [0.0, 1.0, 0.0]", "up = [0, 0, 1]")])),
        format!("{file}: camera.up: expected a direction not parallel to the view direction, got [0.0, 0.0, 1.0]")
    );
    assert_eq!(
        message(&with(&[("width = 8", "width = \"8\"")])),
        format!("{file}: image.width: expected a whole number, got string \"8\"")
    );
    let syntax = message(&with(&[("height = 6", "height = ")]));
    assert!(syntax.starts_with(&format!("{file}: not valid TOML at line 4, column ")), "{syntax}");

    let dir = scratch("messages");
    let scene = dir.join(NAME);
    let in_dir = |text: &str| shown(&Scene::parse(text, &scene).unwrap_err());
    let gen = "generator = { kind = \"sphere\", radius = 0.4 }";
    let absent = dir.join("absent.raw");
    let text = with(&[(gen, "raw = \"absent.raw\"\ntype = \"u8\"")]);
    assert_eq!(
        in_dir(&text),
        format!(
            "{}: datasets[0].channels.voxel.raw: dataset key \"absent.raw\" names no file: looked for {}; keys \
             resolve in the scene file's folder when no data root is given; pass --data-root DIR or set \
             TROVE_DATA=DIR to name the folder that holds the data (docs/data.md)",
            scene.display(),
            absent.display()
        )
    );
    let under = |root: &DataRoot| shown(&Scene::parse_in(&text, &scene, root).unwrap_err());
    let data = Path::new("/data/trove");
    let looked = data.join("absent.raw");
    assert_eq!(
        under(&DataRoot::Given(data.into())),
        format!(
            "{}: datasets[0].channels.voxel.raw: dataset key \"absent.raw\" names no file: looked for {}; the \
             data root is {} (--data-root)",
            scene.display(),
            looked.display(),
            data.display()
        )
    );
    let env = under(&DataRoot::Environment(data.into()));
    assert!(
        env.ends_with(&format!("the data root is {} (from TROVE_DATA; --data-root overrides it)", data.display())),
        "{env}"
    );
    std::fs::write(dir.join("ball.raw"), [0u8; 100]).unwrap();
    let text = with(&[(gen, "raw = \"ball.raw\"\ntype = \"u16\"")]);
    assert_eq!(
        in_dir(&text),
        format!(
            "{}: datasets[0].channels.voxel.raw: {} holds 100 bytes of voxel data but dims [4, 4, 4] of u16 needs \
             exactly 128 bytes",
            scene.display(),
            dir.join("ball.raw").display()
        )
    );

    let missing = nowhere().join("no-such-scene.toml");
    let got = shown(&Scene::load(&missing).unwrap_err());
    let want = format!("{}: cannot read the scene file: ", missing.display());
    assert!(got.starts_with(&want) && got.len() > want.len(), "{got}");
}

// ---------------------------------------------------------------------------------------
// Dataset keys go through a catalog (the seam a farm uses).

/// A catalog that knows files only by their headers, as a farm coordinator does: every raw
/// key is 128 bytes long and held by another process.
struct Registry;

impl crate::dataset::Catalog for Registry {
    fn describe(&self, key: &str, kind: FileKind) -> Result<FileInfo, DatasetError> {
        match kind {
            FileKind::Raw => Ok(FileInfo::Raw { bytes: 128, file: DataFile::Remote(key.to_string()) }),
            _ => Err(DatasetError::Remote { key: key.to_string() }),
        }
    }
}

#[test]
fn a_catalog_of_remote_headers_validates_without_reading_and_cannot_load() {
    let gen = "generator = { kind = \"sphere\", radius = 0.4 }";
    let text = with(&[(gen, "raw = \"data/ball.raw\"\ntype = \"u16\"")]);
    let scene = Scene::parse_with(&text, NAME, &Registry).unwrap_or_else(|e| panic!("{e}"));
    let e = scene.datasets()[0].load().unwrap_err();
    assert!(matches!(&e, DatasetError::Remote { key } if key == "data/ball.raw"), "{e:?}");
    // The length the registry reports is checked like a local file's, naming the key.
    let text = with(&[(gen, "raw = \"data/ball.raw\"\ntype = \"u8\"")]);
    let e = Scene::parse_with(&text, NAME, &Registry).unwrap_err();
    assert!(
        matches!(&e.kind, Kind::Dataset(DatasetError::SizeMismatch { path, expected: 64, actual: 128, .. })
            if path == Path::new("data/ball.raw")),
        "{e:?}"
    );
    // A catalog that answers with another kind of file than asked is refused, not trusted.
    struct Confused;
    impl crate::dataset::Catalog for Confused {
        fn describe(&self, _: &str, _: FileKind) -> Result<FileInfo, DatasetError> {
            Ok(FileInfo::Raw { bytes: 64, file: DataFile::Remote("x".into()) })
        }
    }
    let e = Scene::parse_with(&with(&[(BALL, "file = \"a.nhdr\"\n")]), NAME, &Confused).unwrap_err();
    assert!(
        matches!(
            e.kind,
            Kind::Dataset(DatasetError::WrongKind { expected: FileKind::Volume, found: FileKind::Raw, .. })
        ),
        "{e:?}"
    );
}

#[test]
fn a_raw_offset_is_counted_and_may_not_pass_the_end() {
    let dir = scratch("raw-offset");
    std::fs::write(dir.join("ball.raw"), [0u8; 136]).unwrap();
    let gen = "generator = { kind = \"sphere\", radius = 0.4 }";
    accepted_in(&dir, &with(&[(gen, "raw = \"ball.raw\"\ntype = \"u16\"\noffset = 8")]));
    refused!(
        in dir,
        with(&[(gen, "raw = \"ball.raw\"\ntype = \"u16\"\noffset = 4")]),
        "datasets[0].channels.voxel.raw",
        Kind::Dataset(DatasetError::SizeMismatch { expected: 128, actual: 132, .. })
    );
    refused!(
        in dir,
        with(&[(gen, "raw = \"ball.raw\"\ntype = \"u16\"\noffset = 200")]),
        "datasets[0].channels.voxel.raw",
        Kind::Dataset(DatasetError::ShorterThanOffset { len: 136, offset: 200, .. })
    );
}

#[test]
fn an_nrrd_channel_needs_an_nrrd_file() {
    let gen = "generator = { kind = \"sphere\", radius = 0.4 }";
    refused!(
        with(&[(gen, "nrrd = \"ball.nii\"")]),
        "datasets[0].channels.voxel.nrrd",
        Kind::VolumeExtension { file, expected: ".nrrd or .nhdr" } if file == "ball.nii"
    );
}

#[cfg(unix)]
#[test]
fn a_sandboxed_catalog_refuses_keys_that_leave_its_root() {
    let dir = scratch("sandbox");
    let root = dir.join("root");
    std::fs::create_dir_all(&root).unwrap();
    std::fs::write(dir.join("ball.raw"), [0u8; 64]).unwrap();
    std::os::unix::fs::symlink("../ball.raw", root.join("ball.raw")).unwrap();
    let gen = "generator = { kind = \"sphere\", radius = 0.4 }";
    let text = with(&[(gen, "raw = \"ball.raw\"\ntype = \"u8\"")]);
    // Local mode follows the link; a farm worker's sandbox does not.
    Scene::parse_with(&text, NAME, &FsCatalog::trusting(&root)).unwrap_or_else(|e| panic!("{e}"));
    let sandbox = FsCatalog::sandboxed(&root).unwrap();
    let e = Scene::parse_with(&text, NAME, &sandbox).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("datasets[0].channels.voxel.raw"));
    assert!(matches!(&e.kind, Kind::Dataset(DatasetError::OutsideRoot { key }) if key == "ball.raw"), "{e:?}");
    let text = with(&[(gen, "raw = \"../ball.raw\"\ntype = \"u8\"")]);
    let e = Scene::parse_with(&text, NAME, &sandbox).unwrap_err();
    assert!(
        matches!(&e.kind, Kind::Dataset(DatasetError::InvalidKey { problem: KeyProblem::ParentComponent, .. })),
        "{e:?}"
    );
}

#[test]
fn datasets_that_read_the_same_sources_share_an_id() {
    let dir = scratch("ids");
    std::fs::write(dir.join("ball.raw"), [0u8; 64]).unwrap();
    let gen = "generator = { kind = \"sphere\", radius = 0.4 }";
    let text = with(&[(gen, "raw = \"ball.raw\"\ntype = \"u8\"")]);
    let a = accepted_in(&dir, &text);
    let b = accepted_in(
        &dir,
        &text.replace("name = \"ball\"", "name = \"other\"").replace("dataset = \"ball\"", "dataset = \"other\""),
    );
    assert_eq!(a.datasets()[0].id(), b.datasets()[0].id(), "names do not matter");
    assert_ne!(a.datasets()[0].id(), a.datasets()[1].id());
    let generated = accepted(&base());
    assert_eq!(generated.datasets[0].id(), accepted(&base()).datasets[0].id());
    assert_ne!(generated.datasets[0].id(), a.datasets()[0].id());
    let bigger = accepted(&with(&[("dims = [4, 4, 4]", "dims = [4, 4, 5]")]));
    assert_ne!(generated.datasets[0].id(), bigger.datasets[0].id(), "dims matter");
}

#[test]
fn a_scene_can_be_resized_within_the_limits() {
    let s = accepted(&base()).with_image_size(4, 3).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((s.image().width, s.image().height, s.image().background), (4, 3, [0.1, 0.2, 0.3]));
    let e = accepted(&base()).with_image_size(0, 3).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("image.width"));
    assert!(matches!(e.kind, Kind::ImageSide { got: 0 }), "{e:?}");
    let e = accepted(&base()).with_image_size(8, MAX_IMAGE_SIDE + 1).unwrap_err();
    assert!(matches!(e.kind, Kind::ImageSide { got: 16385 }), "{e:?}");
    // A fine step that is affordable at 8×6 pixels is not at 16384².
    let fine = accepted(&with_sampling("1e-6"));
    let e = fine.clone().with_image_size(MAX_IMAGE_SIDE, MAX_IMAGE_SIDE).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("objects[0].sampling_distance"));
    assert!(matches!(e.kind, Kind::RenderTooCostly { width: 16384, height: 16384, .. }), "{e:?}");
    assert_eq!(fine.with_image_size(16, 12).unwrap().image().width, 16);
}

// ---------------------------------------------------------------------------------------
// Effects (SPEC §6): `[[lights]]` and an object's `shading`.

/// The base scene with `lights` (whole `[[lights]]` tables) before its datasets and
/// `shading` on the first object.
fn with_effects(lights: &str, shading: &str) -> String {
    with(&[
        ("\n[[datasets]]\nname = \"ball\"", &format!("\n{lights}\n[[datasets]]\nname = \"ball\"")),
        ("name = \"skull\"", &format!("name = \"skull\"\n{shading}")),
    ])
}

/// A refusal case: the scene's edit, the key refused, and the kind expected.
type Case<T> = (T, &'static str, fn(&Kind) -> bool);

const SUN: &str = "[[lights]]\ntype = \"directional\"\ndirection = [0.0, -3.0, -4.0]";

#[test]
fn lights_and_shading_take_their_defaults_and_normalise_directions() {
    let s = accepted(&with_effects(&format!("{SUN}\n[[lights]]\ntype = \"point\"\nposition = [1, 2, 3]"), ""));
    assert_eq!(s.lights().len(), 2);
    match s.lights()[0].source() {
        crate::scene::LightSource::Directional { direction } => {
            assert!((direction.get() - DVec3::new(0.0, -0.6, -0.8)).length() < 1e-15, "{direction:?}")
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(s.lights()[0].radiance(), [1.0; 3], "white, intensity 1 by default");
    assert_eq!(s.lights()[1].source(), crate::scene::LightSource::Point { position: DVec3::new(1.0, 2.0, 3.0) });
    // No `shading`: the object is unlit even with lights.
    assert!(s.objects()[0].lighting().is_none());

    let s = accepted(&with_effects(SUN, "shading = { ambient = 0.25 }"));
    let (material, lights) = s.objects()[0].lighting().expect("shaded");
    assert_eq!(*material, crate::scene::Shading::new(0.25, 0.7, 0.2, 10.0).unwrap());
    assert_eq!(lights.len(), 1);
    assert!(s.objects()[1].lighting().is_none());
    let s = accepted(&with_effects(&format!("{SUN}\ncolour = [1, 0.5, 0]\nintensity = 2\nshadows = false"), ""));
    assert_eq!(s.lights()[0].radiance(), [2.0, 1.0, 0.0]);
    assert!(!s.lights()[0].shadows());
    let s = accepted(&with_effects(&format!("{SUN}\nshadows = true\n{SUN}"), "shading = {}"));
    assert!(s.lights()[0].shadows() && !s.lights()[1].shadows(), "shadows are per light, off by default");
    assert!(s.casts_shadows());

    // Without lights a scene renders as SPEC §4 says, whatever `shading` says.
    let s = accepted(&with_effects("", "shading = {}"));
    assert_eq!(s.objects()[0].shading(), Some(&crate::scene::Shading::DEFAULT));
    assert!(s.objects()[0].lighting().is_none());
}

#[test]
fn light_keys_are_refused_with_their_path() {
    let cases: &[Case<String>] = &[
        (format!("{SUN}\ncolur = [1, 1, 1]"), "lights[0].colur", |k| matches!(k, Kind::UnknownKey { .. })),
        (
            "[[lights]]\ntype = \"spot\"\nposition = [0, 0, 0]".into(),
            "lights[0].type",
            |k| matches!(k, Kind::UnknownLightType { got } if got == "spot"),
        ),
        ("[[lights]]\ndirection = [0, 0, -1]".into(), "lights[0].type", |k| matches!(k, Kind::MissingKey { .. })),
        (
            "[[lights]]\ntype = \"directional\"".into(),
            "lights[0].direction",
            |k| matches!(k, Kind::MissingKey { field } if field == "direction"),
        ),
        ("[[lights]]\ntype = \"point\"".into(), "lights[0].position", |k| matches!(k, Kind::MissingKey { .. })),
        ("[[lights]]\ntype = \"directional\"\ndirection = [0, 0, 0]".into(), "lights[0].direction", |k| {
            matches!(k, Kind::LightDirection { .. })
        }),
        ("[[lights]]\ntype = \"directional\"\ndirection = [0, nan, 1]".into(), "lights[0].direction", |k| {
            matches!(k, Kind::LightDirection { .. })
        }),
        (format!("{SUN}\nposition = [0, 0, 0]"), "lights[0].position", |k| {
            matches!(k, Kind::LightKeyNotForType { ty: "directional", .. })
        }),
        (
            "[[lights]]\ntype = \"point\"\nposition = [0, 0, 0]\ndirection = [0, 0, -1]".into(),
            "lights[0].direction",
            |k| matches!(k, Kind::LightKeyNotForType { ty: "point", .. }),
        ),
        (format!("{SUN}\nintensity = -1"), "lights[0].intensity", |k| matches!(k, Kind::Light(_))),
        (format!("{SUN}\ncolour = [1, -0.5, 1]"), "lights[0].colour", |k| matches!(k, Kind::Light(_))),
        (format!("{SUN}\ncolour = [1, 1]"), "lights[0].colour", |k| matches!(k, Kind::WrongLength { .. })),
        ("[[lights]]\ntype = \"point\"\nposition = [0, inf, 0]".into(), "lights[0].position", |k| {
            matches!(k, Kind::Light(_))
        }),
        (format!("{SUN}\nshadows = \"yes\""), "lights[0].shadows", |k| matches!(k, Kind::WrongType { .. })),
        (format!("{SUN}\nshadows = 1"), "lights[0].shadows", |k| matches!(k, Kind::WrongType { .. })),
        (format!("{SUN}\n{SUN}\nintensity = -2"), "lights[1].intensity", |k| matches!(k, Kind::Light(_))),
    ];
    for (lights, key, is) in cases {
        refusal(&nowhere(), &with_effects(lights, ""), Some(key), is);
    }
    // Positional values where tables are expected.
    let text = with_effects("", "").replacen("\n[image]", "\nlights = [1, 2]\n[image]", 1);
    refused!(text, "lights[0]", Kind::WrongType { .. });
    let text = with_effects("", "").replacen("\n[image]", "\nlights = 3\n[image]", 1);
    refused!(text, "lights", Kind::NotAnArrayOfTables { .. });
}

#[test]
fn shading_keys_are_refused_with_their_path() {
    let cases: &[Case<&str>] = &[
        ("shading = { shine = 3 }", "objects[0].shading.shine", |k| matches!(k, Kind::UnknownKey { .. })),
        (
            "shading = { ambient = -0.1 }",
            "objects[0].shading.ambient",
            |k| matches!(k, Kind::ShadingCoefficient { got } if *got == -0.1),
        ),
        ("shading = { diffuse = nan }", "objects[0].shading.diffuse", |k| matches!(k, Kind::ShadingCoefficient { .. })),
        ("shading = { specular = -1 }", "objects[0].shading.specular", |k| {
            matches!(k, Kind::ShadingCoefficient { .. })
        }),
        ("shading = { shininess = -inf }", "objects[0].shading.shininess", |k| {
            matches!(k, Kind::ShadingCoefficient { .. })
        }),
        ("shading = { ambient = \"lots\" }", "objects[0].shading.ambient", |k| matches!(k, Kind::WrongType { .. })),
        ("shading = 0.5", "objects[0].shading", |k| matches!(k, Kind::WrongType { .. })),
    ];
    for (shading, key, is) in cases {
        refusal(&nowhere(), &with_effects(SUN, shading), Some(key), is);
    }
}
