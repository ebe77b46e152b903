//! Lighting end to end (SPEC §6): whole renders of shaded scenes by both algorithms, checked
//! against values worked out by hand and against the same scene turned as a whole.

use glam::{DMat3, DVec3};

use super::{render, Algorithm, RenderOptions, Rendered};
use crate::scene::Scene;

fn rendered(text: &str, algorithm: Algorithm) -> Rendered {
    let scene = Scene::parse(text, "effects.toml").unwrap_or_else(|e| panic!("{e}\n{text}"));
    render(&scene, &RenderOptions { algorithm, ..RenderOptions::default() }).unwrap()
}

fn max_difference(a: &Rendered, b: &Rendered) -> f64 {
    let (a, b) = (a.image.pixels(), b.image.pixels());
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).flat_map(|(p, q)| (0..3).map(move |i| (p[i] - q[i]).abs())).fold(0.0, f64::max)
}

/// A 5×5 view straight down −z onto a radially graded sphere whose surface (value 0.3) is
/// opaque, lit by `light`: the centre pixel's ray runs along the axis through the centre.
fn sphere_scene(light: &str) -> String {
    format!(
        r#"
[image]
width = 5
height = 5
background = [0.0, 0.0, 0.0]
[camera]
eye = [0.5, 0.5, 3.0]
target = [0.5, 0.5, 0.5]
up = [0.0, 1.0, 0.0]
fov_y = 20.0
{light}
[[datasets]]
name = "ball"
dims = [32, 32, 32]
[datasets.channels.voxel]
generator = {{ kind = "sphere", radius = 0.4, profile = "radial", type = "f32", value = 1.0 }}
[[objects]]
name = "ball"
dataset = "ball"
colour = {{ type = "lut", bounds = [0.3], colours = [[0, 0, 0], [0.5, 0.25, 0.1]] }}
opacity = {{ type = "lut", bounds = [0.3], values = [0.0, 1.0] }}
shading = {{ ambient = 0.1, diffuse = 0.6, specular = 0.3, shininess = 20.0 }}
"#
    )
}

#[test]
fn a_sphere_lit_from_the_viewer_has_the_hand_computed_colour_at_its_centre() {
    // N = V = L = H = +z at the first opaque sample: N·L = N·H = 1, so with E = 1.5·(1, 0.8,
    // 0.6) = (1.5, 1.2, 0.9): c' = c·(0.1 + 0.6·E) + 0.3·E for c = (0.5, 0.25, 0.1).
    let want: [f64; 3] = [0.5 * (0.1 + 0.9) + 0.45, 0.25 * (0.1 + 0.72) + 0.36, 0.1 * (0.1 + 0.54) + 0.27];
    assert!((want[0] - 0.95).abs() < 1e-12 && (want[1] - 0.565).abs() < 1e-12 && (want[2] - 0.334).abs() < 1e-12);
    let directional = "[[lights]]\ntype = \"directional\"\ndirection = [0.0, 0.0, -1.0]\n\
                       colour = [1.0, 0.8, 0.6]\nintensity = 1.5\n";
    // A point light at the eye lights the centre from the same direction.
    let point = "[[lights]]\ntype = \"point\"\nposition = [0.5, 0.5, 3.0]\ncolour = [1.0, 0.8, 0.6]\nintensity = 1.5\n";
    for light in [directional, point] {
        for (algorithm, tolerance) in [(Algorithm::PerRay, 1e-9), (Algorithm::Grouped, 1e-6)] {
            let out = rendered(&sphere_scene(light), algorithm);
            let got = out.image.pixel(2, 2);
            for i in 0..3 {
                assert!((got[i] - want[i]).abs() < tolerance, "{algorithm:?}, {light}: {got:?} vs {want:?}");
            }
            assert_eq!(out.stats.effects[0].ran, ["shading"]);
            assert!(out.stats.effects[0].shading_evaluations.is_some_and(|n| n >= 9), "{:?}", out.stats.effects);
        }
    }
    // Unlit, the same pixel is the mapped colour.
    let unlit = rendered(&sphere_scene(""), Algorithm::PerRay);
    assert_eq!(unlit.image.pixel(2, 2), [0.5, 0.25, 0.1]);
    assert!(unlit.stats.effects[0].ran.is_empty());
    assert_eq!(unlit.stats.effects[0].shading_evaluations, Some(0));
}

/// A scene of one shaded object lit by a directional and a point light, every world
/// position, direction and box turned by `r` (rotation about the world origin). `distorted`
/// places the object by eight corners that form no parallelepiped, else by a matrix that
/// scales unevenly (so normals need the inverse transpose).
fn turned_scene(r: DMat3, distorted: bool, lights: bool) -> String {
    let v = |p: [f64; 3]| {
        let q = r * DVec3::from(p);
        format!("[{:.17e}, {:.17e}, {:.17e}]", q.x, q.y, q.z)
    };
    let placement = if distorted {
        let corners: Vec<String> = (0..8)
            .map(|i| {
                let (x, y, z) = ((i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64);
                let bend = if i == 7 {
                    [0.15, -0.1, 0.12]
                } else if i == 2 {
                    [-0.1, 0.05, 0.0]
                } else {
                    [0.0; 3]
                };
                v([x * 1.1 - 0.05 + bend[0], y * 0.8 + 0.05 + bend[1], z * 0.9 + bend[2]])
            })
            .collect();
        format!("transform = {{ corners = [{}] }}", corners.join(", "))
    } else {
        // Rows of R·M, M = [[1.1, 0.2, 0, −0.05], [0, 0.7, 0.1, 0.1], [0.1, 0, 0.9, 0]].
        let m = DMat3::from_cols(DVec3::new(1.1, 0.0, 0.1), DVec3::new(0.2, 0.7, 0.0), DVec3::new(0.0, 0.1, 0.9));
        let rm = r * m;
        let t = r * DVec3::new(-0.05, 0.1, 0.0);
        let row =
            |i: usize| format!("[{:.17e}, {:.17e}, {:.17e}, {:.17e}]", rm.x_axis[i], rm.y_axis[i], rm.z_axis[i], t[i]);
        format!("transform = {{ matrix = [{}, {}, {}, [0, 0, 0, 1]] }}", row(0), row(1), row(2))
    };
    let lights = if lights {
        format!(
            "[[lights]]\ntype = \"directional\"\ndirection = {}\ncolour = [1.0, 0.9, 0.8]\n\
             [[lights]]\ntype = \"point\"\nposition = {}\nintensity = 0.6\n",
            v([-0.3, -0.5, -1.0]),
            v([2.0, 1.5, 2.5])
        )
    } else {
        String::new()
    };
    format!(
        r#"
[image]
width = 24
height = 20
background = [0.1, 0.1, 0.1]
[camera]
eye = {eye}
target = {target}
up = {up}
fov_y = 35.0
{lights}
[[datasets]]
name = "blob"
dims = [20, 18, 16]
[datasets.channels.voxel]
generator = {{ kind = "sphere", centre = [0.45, 0.55, 0.5], radius = 0.45, profile = "radial", type = "f32", value = 1.0 }}
[[objects]]
name = "blob"
dataset = "blob"
colour = {{ type = "ramp", points = [[0.0, 0.2, 0.4, 0.8], [0.5, 1.0, 0.6, 0.3]] }}
opacity = {{ type = "ramp", points = [[0.05, 0.0], [0.6, 0.5]] }}
shading = {{ ambient = 0.15, specular = 0.4, shininess = 12.0 }}
{placement}
"#,
        eye = v([0.3, 0.4, 3.2]),
        target = v([0.5, 0.45, 0.5]),
        up = v([0.1, 1.0, 0.0]),
    )
}

#[test]
fn turning_an_object_its_lights_and_the_camera_together_leaves_the_image_unchanged() {
    let r = DMat3::from_axis_angle(DVec3::new(1.0, 2.0, 0.5).normalize(), 0.7);
    for distorted in [false, true] {
        let still = rendered(&turned_scene(DMat3::IDENTITY, distorted, true), Algorithm::PerRay);
        let turned = rendered(&turned_scene(r, distorted, true), Algorithm::PerRay);
        let d = max_difference(&still, &turned);
        // Distorted boxes are inverted to 1e-6 of a voxel, which moves values by about that.
        let tolerance = if distorted { 1e-4 } else { 1e-9 };
        assert!(d < tolerance, "distorted {distorted}: turned image differs by {d}");
        // The lights matter here, so a normal left unturned would show.
        let unlit = rendered(&turned_scene(DMat3::IDENTITY, distorted, false), Algorithm::PerRay);
        assert!(max_difference(&still, &unlit) > 0.05, "distorted {distorted}: shading changed nothing");
        // The grouped algorithm casts the same shaded samples (in f32 pieces).
        let grouped = rendered(&turned_scene(r, distorted, true), Algorithm::Grouped);
        assert!(max_difference(&turned, &grouped) < 1e-5, "distorted {distorted}");
        assert!(grouped.stats.effects[0].shading_evaluations > Some(0));
    }
}

#[test]
fn without_lights_shading_is_not_computed_and_the_image_is_unlit_bit_for_bit() {
    let text = turned_scene(DMat3::IDENTITY, false, false);
    let plain = text.replace("shading = { ambient = 0.15, specular = 0.4, shininess = 12.0 }\n", "");
    assert_ne!(text, plain);
    for algorithm in [Algorithm::PerRay, Algorithm::Grouped] {
        let (a, b) = (rendered(&text, algorithm), rendered(&plain, algorithm));
        assert_eq!(a.image.pixels(), b.image.pixels(), "{algorithm:?}");
        assert!(a.stats.effects[0].ran.is_empty() && a.stats.effects[0].shading_evaluations == Some(0));
    }
}

/// A 12×12 view of an RGBA dataset (no `voxel`) whose alpha is a sphere, lit by one light,
/// with `colour` and `opacity` maps and a `shading` table.
fn rgba_scene(colour: &str, opacity: &str, lights: bool) -> String {
    let light = if lights { "[[lights]]\ntype = \"directional\"\ndirection = [1.0, -1.0, -1.0]\n" } else { "" };
    format!(
        r#"
[image]
width = 12
height = 12
background = [0.0, 0.0, 0.0]
[camera]
eye = [0.5, 0.5, 3.0]
target = [0.5, 0.5, 0.5]
up = [0.0, 1.0, 0.0]
fov_y = 25.0
{light}
[[datasets]]
name = "rgba"
dims = [16, 16, 16]
[datasets.channels.red]
generator = {{ kind = "constant", value = 200, type = "u8" }}
[datasets.channels.green]
generator = {{ kind = "constant", value = 150, type = "u8" }}
[datasets.channels.blue]
generator = {{ kind = "constant", value = 90, type = "u8" }}
[datasets.channels.alpha]
generator = {{ kind = "sphere", radius = 0.45, profile = "radial", value = 255, type = "u8" }}
[[objects]]
name = "rgba"
dataset = "rgba"
colour = {colour}
opacity = {opacity}
shading = {{ ambient = 0.1, diffuse = 0.9, specular = 0.5 }}
"#
    )
}

#[test]
fn a_raw_opacity_is_lit_from_the_alpha_channel_and_a_constant_one_without_a_field_is_not() {
    let raw = "{ type = \"raw\" }";
    for (interpolation, colour) in [("", raw), ("\ninterpolation = \"cubic\"", raw)] {
        let text = rgba_scene(colour, raw, true) + interpolation;
        for algorithm in [Algorithm::PerRay, Algorithm::Grouped] {
            let lit = rendered(&text, algorithm);
            let unlit = rendered(&(rgba_scene(colour, raw, false) + interpolation), algorithm);
            assert_eq!(lit.stats.effects[0].ran, ["shading"], "{algorithm:?}{interpolation}");
            assert!(lit.stats.effects[0].shading_evaluations > Some(0));
            assert!(max_difference(&lit, &unlit) > 0.05, "{algorithm:?}{interpolation}: the light changed nothing");
        }
    }
    // Raw colour with a constant opacity reads no channel to take normals from: unlit,
    // bit for bit.
    let constant = "{ type = \"constant\", coefficients = [0.2] }";
    let lit = rendered(&rgba_scene(raw, constant, true), Algorithm::PerRay);
    let unlit = rendered(&rgba_scene(raw, constant, false), Algorithm::PerRay);
    assert!(lit.stats.effects[0].ran.is_empty());
    assert_eq!(lit.image.pixels(), unlit.image.pixels());
}
