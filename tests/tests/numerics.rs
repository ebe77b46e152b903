//! The hard numerical cases of `docs/numerics.md`, one test (or property) per row: each
//! fails if the guard it names is removed.

use glam::{DMat4, DVec3};
use proptest::prelude::*;
use trove_core::corrected_opacity;
use trove_core::dataset::Dims;
use trove_core::geometry::hexahedron::{Hexahedron, HexahedronError};
use trove_core::geometry::{Extent, Placement, Ray, Shape};
use trove_core::render::{render, Image, RenderOptions};
use trove_core::scene::{Scene, SceneErrorKind};
use trove_tests::reference::unit_cube_chord;
use trove_tests::Header;

/// Scene text: an image, a camera and `body` (datasets and objects).
struct View {
    side: u32,
    eye: DVec3,
    target: DVec3,
    up: DVec3,
    fov: f64,
    correction: bool,
}

impl View {
    fn new(eye: DVec3, target: DVec3, fov: f64) -> View {
        View { side: 33, eye, target, up: DVec3::Y, fov, correction: true }
    }

    fn text(&self, body: &str) -> String {
        let header =
            Header::new(self.side, self.eye.to_array(), self.target.to_array(), self.fov).up(self.up.to_array());
        format!("{header}[render]\ntermination = 1.0\nopacity_correction = {}\n{body}", self.correction)
    }
}

fn v(p: DVec3) -> String {
    format!("[{:?}, {:?}, {:?}]", p.x, p.y, p.z)
}

fn matrix(m: &DMat4) -> String {
    let r = |i: usize| {
        let row = m.row(i);
        format!("[{:?}, {:?}, {:?}, {:?}]", row.x, row.y, row.z, row.w)
    };
    format!("{{ matrix = [{}, {}, {}, {}] }}", r(0), r(1), r(2), r(3))
}

fn parse(text: &str) -> Scene {
    Scene::parse(text, "numerics.toml").unwrap_or_else(|e| panic!("scene: {e}\n{text}"))
}

fn draw(scene: &Scene) -> Image {
    render(scene, &f64_path()).expect("render").image
}

/// A white box of constant per-voxel opacity `o` over `dims` voxels, placed by `transform`.
fn constant_box(name: &str, dims: [u32; 3], o: f64, transform: &str, extra: &str) -> String {
    format!(
        "[[datasets]]\nname = \"{name}\"\ndims = [{}, {}, {}]\n[datasets.channels.voxel]\n\
         generator = {{ kind = \"constant\", value = 0.0 }}\n\
         [[objects]]\nname = \"{name}\"\ndataset = \"{name}\"\n\
         colour = {{ type = \"constant\", red = [1.0], green = [1.0], blue = [1.0] }}\n\
         opacity = {{ type = \"constant\", coefficients = [{o:?}] }}\ntransform = {transform}\n{extra}\n",
        dims[0], dims[1], dims[2]
    )
}

fn max_diff(a: &Image, b: &Image) -> f64 {
    a.pixels().iter().zip(b.pixels()).flat_map(|(p, q)| (0..3).map(move |i| (p[i] - q[i]).abs())).fold(0.0, f64::max)
}

fn all_finite(img: &Image) -> bool {
    img.pixels().iter().flatten().all(|c| c.is_finite())
}

/// 1 − (1 − o)^ℓ: the exact accumulated opacity over ℓ voxels of constant opacity o, with
/// opacity correction (any step: the product telescopes).
fn through(o: f64, ell: f64) -> f64 {
    -(ell * (-o).ln_1p()).exp_m1()
}

fn unit_placement(m: DMat4, dims: [u64; 3]) -> Placement {
    Placement::new(
        Shape::Affine { world_from_box: m, box_from_world: m.inverse() },
        Extent::FULL,
        Dims::new(dims).unwrap(),
    )
}

// ---------------------------------------------------------------------------------------
// Rays parallel to faces, in face planes, through edges and corners.

/// A point of the closed box in box coordinates, pushed onto faces, edges and corners often.
fn box_point() -> impl Strategy<Value = DVec3> {
    let coord = prop_oneof![3 => 0.0f64..=1.0, 1 => Just(0.0), 1 => Just(1.0)];
    (coord.clone(), coord.clone(), coord).prop_map(|(x, y, z)| DVec3::new(x, y, z))
}

/// A direction, often with exact +0.0 and −0.0 components.
fn direction() -> impl Strategy<Value = DVec3> {
    let comp = prop_oneof![3 => -1.0f64..1.0, 1 => Just(0.0), 1 => Just(-0.0)];
    (comp.clone(), comp.clone(), comp).prop_filter("non-zero", |(x, y, z)| x * x + y * y + z * z > 1e-6).prop_map(
        |(x, y, z)| {
            let n = (x * x + y * y + z * z).sqrt();
            // Dividing keeps the sign of a zero component.
            DVec3::new(x / n, y / n, z / n)
        },
    )
}

/// Boxes: scaled, sheared, rotated and translated.
fn box_matrix() -> impl Strategy<Value = DMat4> {
    (0.1f64..10.0, 0.1f64..10.0, 0.1f64..10.0, 0.0f64..6.3, -5.0f64..5.0, prop::bool::ANY).prop_map(
        |(sx, sy, sz, angle, t, rotate)| {
            let r = if rotate {
                DMat4::from_axis_angle(DVec3::new(1.0, -2.0, 0.5).normalize(), angle)
            } else {
                DMat4::IDENTITY
            };
            DMat4::from_translation(DVec3::splat(t)) * r * DMat4::from_scale(DVec3::new(sx, sy, sz))
        },
    )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    /// A ray through any point of the closed box hits it (faces, edges and corners
    /// included), never with NaN, exit ≥ entry, the point within the segment; and the
    /// reversed ray gives the same chord (intersection symmetry).
    #[test]
    fn a_ray_through_any_point_of_the_closed_box_hits_it_symmetrically(
        m in box_matrix(), q in box_point(), d in direction(), back in 0.5f64..20.0,
    ) {
        let p = unit_placement(m, [4, 4, 4]);
        let target = m.transform_point3(q);
        let origin = target - back * d;
        let (t0, t1) = p.segment(&Ray { origin, dir: d }).expect("a ray through a point of the closed box must hit it");
        prop_assert!(t0.is_finite() && t1.is_finite() && t0 >= 0.0 && t1 >= t0, "{t0} {t1}");
        let tol = 1e-9 * (1.0 + back);
        prop_assert!(t0 <= back + tol && back <= t1 + tol, "point at {back} outside [{t0}, {t1}]");
        if t0 == 0.0 {
            // The origin is inside: the reversed ray below would start its chord elsewhere.
            return Ok(());
        }
        // Reversed: from beyond the exit back towards the origin.
        let far = t1 + 1.0;
        let (r0, r1) = p.segment(&Ray { origin: origin + far * d, dir: -d }).expect("reverse ray hits");
        let scale = 1e-9 * (1.0 + far);
        prop_assert!((r0 - (far - t1)).abs() <= scale && (r1 - (far - t0)).abs() <= scale,
            "forward [{t0}, {t1}] reverse [{r0}, {r1}] from {far}");
    }

    /// The same for distorted boxes (the exact ray/bilinear-patch path): a ray through any
    /// point of the closed box, faces, edges and corners included, hits it without NaN.
    #[test]
    fn a_ray_through_any_point_of_a_distorted_box_hits_it(
        offsets in prop::collection::vec((-0.2f64..0.2, -0.2f64..0.2, -0.2f64..0.2), 8),
        q in box_point(), d in direction(), back in 0.5f64..20.0,
    ) {
        let corners: [DVec3; 8] = std::array::from_fn(|i| {
            let c = DVec3::new((i & 1) as f64, (i >> 1 & 1) as f64, (i >> 2 & 1) as f64);
            c + DVec3::new(offsets[i].0, offsets[i].1, offsets[i].2)
        });
        let Ok(hex) = Hexahedron::new(corners) else { return Ok(()) };
        let target = hex.world(q);
        let origin = target - back * d;
        let (t0, t1) = hex.segment(origin, d).expect("a ray through a point of the closed box must hit it");
        prop_assert!(t0.is_finite() && t1.is_finite() && t0 >= 0.0 && t1 >= t0, "{t0} {t1}");
        let tol = 1e-9 * (1.0 + back);
        prop_assert!(t0 <= back + tol && back <= t1 + tol, "point at {back} outside [{t0}, {t1}]");
    }

    /// Newton inversion of a distorted box: either the box is refused at load, or every
    /// point maps back to its box coordinates to 1e-6 voxel (for 256 voxels per axis), with
    /// ‖W(q(p)) − p‖ within what that tolerance allows.
    #[test]
    fn distorted_boxes_invert_to_a_millionth_of_a_voxel_or_are_refused(
        offsets in prop::collection::vec((-0.45f64..0.45, -0.45f64..0.45, -0.45f64..0.45), 8),
        q in (0.0f64..=1.0, 0.0f64..=1.0, 0.0f64..=1.0),
    ) {
        let corners: [DVec3; 8] = std::array::from_fn(|i| {
            let c = DVec3::new((i & 1) as f64, (i >> 1 & 1) as f64, (i >> 2 & 1) as f64);
            c + DVec3::new(offsets[i].0, offsets[i].1, offsets[i].2)
        });
        let Ok(hex) = Hexahedron::new(corners) else { return Ok(()) };
        let placement = Placement::new(
            Shape::Distorted { hex: Box::new(hex.clone()), straight: false },
            Extent::FULL,
            Dims::new([256, 256, 256]).unwrap(),
        );
        if placement.check_inversion_precision().is_err() {
            return Ok(());
        }
        let tol_q = 1e-6 / 256.0;
        let q = DVec3::new(q.0, q.1, q.2);
        let p = hex.world(q);
        let back = hex.invert(p, None, tol_q).expect("an accepted box inverts every point inside it");
        prop_assert!((back - q).abs().max_element() <= tol_q, "q {q:?} came back as {back:?}");
        let j = hex.jacobian(back);
        let jnorm = j.x_axis.length() + j.y_axis.length() + j.z_axis.length();
        prop_assert!((hex.world(back) - p).length() <= jnorm * tol_q + 1e-12, "residual");
    }
}

#[test]
fn a_ray_in_the_face_plane_of_a_rotated_box_is_inside_despite_rounding() {
    // A quarter turn about z: cos(π/2) = 6e-17, so the box's faces are "planes" only up to
    // rounding, and a ray along a face picks up a direction component of order 1e-17 in box
    // coordinates. The slack on (nearly) parallel axes keeps it inside for its whole length.
    let m = DMat4::from_translation(DVec3::new(3.0, -2.0, 1.0))
        * DMat4::from_rotation_z(std::f64::consts::FRAC_PI_2)
        * DMat4::from_scale(DVec3::new(2.0, 1.0, 0.5));
    let p = unit_placement(m, [4, 4, 4]);
    for (q0, q1) in [
        (DVec3::new(0.0, 0.3, 0.2), DVec3::new(1.0, 0.3, 0.2)),
        (DVec3::new(0.0, 0.0, 0.7), DVec3::new(1.0, 0.0, 0.7)),
        (DVec3::new(0.4, 1.0, 1.0), DVec3::new(0.4, 0.0, 1.0)),
        (DVec3::new(0.0, 0.0, 0.0), DVec3::new(1.0, 1.0, 1.0)),
    ] {
        let (a, b) = (m.transform_point3(q0), m.transform_point3(q1));
        let d = (b - a).normalize();
        let origin = a - 5.0 * d;
        let (t0, t1) = p.segment(&Ray { origin, dir: d }).expect("in-plane ray hits");
        assert!((t0 - 5.0).abs() < 1e-9 && (t1 - 5.0 - (b - a).length()).abs() < 1e-9, "{q0} → {q1}: [{t0}, {t1}]");
    }
}

// ---------------------------------------------------------------------------------------
// Scales from 1e-6 to 1e6.

/// A Gaussian blob in a box of size `s` centred at the origin, seen from `s`·(0.4, 0.3, 2.5)
/// with a step of `s`·0.37/16.
fn scaled_blob(s: f64) -> String {
    let m = DMat4::from_scale(DVec3::splat(s)) * DMat4::from_translation(DVec3::splat(-0.5));
    let body = format!(
        "[[datasets]]\nname = \"g\"\ndims = [16, 16, 16]\n[datasets.channels.voxel]\n\
         generator = {{ kind = \"gaussian\", sigma = 0.2 }}\n\
         [[objects]]\nname = \"g\"\ndataset = \"g\"\n\
         colour = {{ type = \"linear\", red = [0.2, 0.8], green = [0.9, -0.5], blue = [0.5, 0.0] }}\n\
         opacity = {{ type = \"linear\", coefficients = [0.0, 0.3] }}\n\
         sampling_distance = {:?}\ntransform = {}\n",
        s * 0.37 / 16.0,
        matrix(&m)
    );
    View::new(s * DVec3::new(0.4, 0.3, 2.5), DVec3::ZERO, 40.0).text(&body)
}

#[test]
fn an_image_does_not_change_when_the_whole_scene_is_scaled_from_1e_minus_6_to_1e6() {
    let base = draw(&parse(&scaled_blob(1.0)));
    assert!(base.pixels().iter().any(|p| p[0] > 0.05), "the blob should be visible");
    for s in [1e-6, 1e-3, 7.3, 1e3, 1e6] {
        let img = draw(&parse(&scaled_blob(s)));
        let d = max_diff(&base, &img);
        assert!(all_finite(&img) && d < 1e-9, "scale {s}: max difference {d:e}");
    }
}

#[test]
fn a_box_seen_from_a_million_units_away_matches_its_chord_lengths() {
    // The exact chord through the unit box (no slack) against the renderer: with the old
    // slab slack of 1e-12·|origin| the chords came out 1e-6 too long at this distance.
    let (n, o) = (8u32, 0.2f64);
    for dist in [10.0, 1e3, 1e6] {
        let centre = DVec3::splat(0.5);
        let eye = centre + dist * DVec3::new(0.3, 0.5, 1.0).normalize();
        let fov = 2.0 * (0.9 / dist).atan().to_degrees();
        let scene = parse(&View::new(eye, centre, fov).text(&constant_box(
            "b",
            [n; 3],
            o,
            "{ corners = [[0,0,0],[1,0,0],[0,1,0],[1,1,0],[0,0,1],[1,0,1],[0,1,1],[1,1,1]] }",
            "",
        )));
        let img = draw(&scene);
        let mut hit = 0;
        for row in 0..33 {
            for col in 0..33 {
                let ray = scene.camera().ray(col, row, 33, 33);
                let want = unit_cube_chord(ray.origin, ray.dir).map_or(0.0, |(a, b)| through(o, (b - a) * n as f64));
                let got = img.pixel(col, row)[0];
                hit += (want > 0.0) as u32;
                assert!((got - want).abs() < 1e-9, "distance {dist}, pixel ({col}, {row}): {got} vs {want}");
            }
        }
        assert!(hit > 300, "distance {dist}: only {hit} pixels see the box");
    }
}

#[test]
fn sampling_distances_from_1e_minus_6_to_1e6_agree_with_the_closed_form() {
    // A box of size s sampled at s/37: the same image for every s (constant opacity with
    // correction telescopes exactly, so any n gives 1 − (1 − o)^ℓ).
    let o = 0.15;
    let mut first: Option<Image> = None;
    for s in [1e-6, 1.0, 1e6] {
        let m = DMat4::from_scale(DVec3::splat(s));
        let scene = parse(&View::new(s * DVec3::new(0.6, 0.7, 3.0), DVec3::splat(0.5 * s), 30.0).text(&constant_box(
            "b",
            [16; 3],
            o,
            &matrix(&m),
            &format!("sampling_distance = {:?}", s / 37.0),
        )));
        let img = draw(&scene);
        for row in (0..33).step_by(4) {
            for col in (0..33).step_by(4) {
                let ray = scene.camera().ray(col, row, 33, 33);
                let (o_box, d_box) = (ray.origin / s, ray.dir / s);
                let want = unit_cube_chord(o_box, d_box).map_or(0.0, |(a, b)| through(o, (b - a) * 16.0 / s));
                assert!((img.pixel(col, row)[0] - want).abs() < 1e-9, "scale {s} ({col}, {row})");
            }
        }
        if let Some(f) = &first {
            assert!(max_diff(f, &img) < 1e-9, "scale {s}");
        }
        first.get_or_insert(img);
    }
}

// ---------------------------------------------------------------------------------------
// Camera inside an object, and exactly on its boundary.

#[test]
fn a_camera_inside_a_box_or_on_its_boundary_sees_the_exact_depth() {
    let (n, o) = (8u32, 0.1f64);
    let unit = "{ matrix = [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]] }";
    let cases = [
        ("inside", DVec3::new(0.4, 0.55, 0.5), DVec3::new(0.5, 0.5, 0.0), 100.0),
        ("on a face, looking in", DVec3::new(0.5, 0.5, 1.0), DVec3::new(0.5, 0.5, 0.0), 120.0),
        ("on a face, looking out", DVec3::new(0.5, 0.5, 1.0), DVec3::new(0.5, 0.5, 2.0), 120.0),
        ("on an edge", DVec3::new(1.0, 0.5, 1.0), DVec3::new(0.0, 0.5, 0.0), 90.0),
        ("at a corner", DVec3::new(1.0, 1.0, 1.0), DVec3::new(0.5, 0.5, 0.5), 90.0),
    ];
    for (what, eye, target, fov) in cases {
        let scene = parse(&View::new(eye, target, fov).text(&constant_box("b", [n; 3], o, unit, "")));
        let img = draw(&scene);
        assert!(all_finite(&img), "{what}: NaN");
        let mut seen = 0;
        for row in 0..33 {
            for col in 0..33 {
                let ray = scene.camera().ray(col, row, 33, 33);
                let want = unit_cube_chord(ray.origin, ray.dir).map_or(0.0, |(a, b)| through(o, (b - a) * n as f64));
                seen += (want > 0.0) as u32;
                let got = img.pixel(col, row)[0];
                assert!((got - want).abs() < 1e-12, "{what} ({col}, {row}): {got} vs {want}");
            }
        }
        if what.ends_with("looking out") {
            assert_eq!(seen, 0, "{what}");
        } else {
            assert!(seen > 500, "{what}: {seen}");
        }
    }
}

// ---------------------------------------------------------------------------------------
// Thin boxes and degenerate dataset shapes.

#[test]
fn a_box_a_millionth_as_thick_as_it_is_wide_gets_its_exact_voxel_depth() {
    // dims [8, 8, 1] over a box 1e-6 thick: each ray crosses about one voxel in z, so
    // A = 1 − (1 − o)^ℓ with ℓ the chord's VC length. In box coordinates the eye is 3·10⁶
    // thicknesses away; a slack proportional to that lengthened ℓ by ~1e-5 before.
    let o = 0.4;
    let m = DMat4::from_scale(DVec3::new(1.0, 1.0, 1e-6));
    let scene = parse(&View::new(DVec3::new(0.3, 0.6, 3.0), DVec3::new(0.5, 0.5, 0.0), 30.0).text(&constant_box(
        "thin",
        [8, 8, 1],
        o,
        &matrix(&m),
        "",
    )));
    let img = draw(&scene);
    let inv = m.inverse();
    let mut hit = 0;
    for row in 0..33 {
        for col in 0..33 {
            let ray = scene.camera().ray(col, row, 33, 33);
            let (ob, db) = (inv.transform_point3(ray.origin), inv.transform_vector3(ray.dir));
            let want = unit_cube_chord(ob, db).map_or(0.0, |(a, b)| {
                let dq = (b - a) * db;
                through(o, (dq * DVec3::new(8.0, 8.0, 1.0)).length())
            });
            hit += (want > 0.0) as u32;
            let got = img.pixel(col, row)[0];
            assert!((got - want).abs() < 1e-8, "({col}, {row}): {got} vs {want}");
        }
    }
    assert!(hit > 200, "{hit}");
    // Edge-on: a ray inside the sheet, parallel to it, crosses its whole width.
    let p = unit_placement(m, [8, 8, 1]);
    for z in [0.0, 0.5e-6, 1e-6] {
        let (a, b) = p.segment(&Ray { origin: DVec3::new(-1.0, 0.5, z), dir: DVec3::X }).expect("edge-on ray hits");
        assert!((a - 1.0).abs() < 1e-12 && (b - 2.0).abs() < 1e-12, "z {z}: [{a}, {b}]");
    }
}

fn ramp_object(dims: [u32; 3], axis: &str, interpolation: &str) -> String {
    format!(
        "[[datasets]]\nname = \"r\"\ndims = [{}, {}, {}]\n[datasets.channels.voxel]\n\
         generator = {{ kind = \"ramp\", axis = \"{axis}\", from = 0.1, to = 0.9 }}\n\
         [[objects]]\nname = \"r\"\ndataset = \"r\"\ninterpolation = \"{interpolation}\"\n\
         colour = {{ type = \"linear\", red = [0.0, 1.0], green = [1.0, -1.0], blue = [0.5, 0.0] }}\n\
         opacity = {{ type = \"linear\", coefficients = [0.0, 0.05] }}\nsampling_distance = 0.013\n",
        dims[0], dims[1], dims[2]
    )
}

#[test]
fn depth_one_and_one_by_one_by_n_datasets_render_like_their_thicker_twins() {
    // Without correction α = O(v) does not depend on the voxel shape, so a field constant
    // along an axis renders the same with 1 or 4 voxels on that axis (the clamped stencil of
    // a single-voxel axis reads that voxel twice, SPEC §3.3).
    let mut view = View::new(DVec3::new(0.2, 0.7, 2.5), DVec3::splat(0.5), 35.0);
    view.correction = false;
    for interpolation in ["nearest", "trilinear", "cubic"] {
        for (thin, thick, axis) in [([16, 16, 1], [16, 16, 4], "x"), ([1, 1, 24], [4, 4, 24], "z")] {
            let a = draw(&parse(&view.text(&ramp_object(thin, axis, interpolation))));
            let b = draw(&parse(&view.text(&ramp_object(thick, axis, interpolation))));
            assert!(all_finite(&a) && a.pixels().iter().any(|p| p[2] > 0.01));
            let d = max_diff(&a, &b);
            assert!(d < 1e-12, "{interpolation} {thin:?} vs {thick:?}: {d:e}");
        }
    }
}

// ---------------------------------------------------------------------------------------
// Distorted boxes close to folding.

#[test]
fn boxes_approaching_a_fold_are_inverted_exactly_until_they_are_refused() {
    // Pull corner 7 along the diagonal to (s, s, s): det J at that corner is 3s − 2, so the
    // box folds at s = 2/3. Every box the loader accepts (256 voxels per axis) must invert
    // every grid point to 1e-6 voxel; at and past the fold, and wherever f64 cannot reach
    // that precision (‖J⁻¹‖ too large), the scene is refused. Without the conditioning
    // check, boxes with δ ≤ 1e-8 were accepted and inverted only to ~6e-6 voxel.
    let (mut accepted, mut refused) = (Vec::new(), Vec::new());
    for delta in [0.3, 0.1, 0.03, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-10, 0.0, -1e-8, -1e-3, -0.1] {
        let s = 2.0 / 3.0 + delta;
        let mut corners: Vec<DVec3> =
            (0..8).map(|i| DVec3::new((i & 1) as f64, (i >> 1 & 1) as f64, (i >> 2 & 1) as f64)).collect();
        corners[7] = DVec3::splat(s);
        let list: Vec<String> = corners.iter().map(|&c| v(c)).collect();
        let transform = format!("{{ corners = [{}] }}", list.join(", "));
        let text = View::new(DVec3::new(0.5, 0.5, 3.0), DVec3::splat(0.5), 30.0)
            .text(&constant_box("f", [256; 3], 0.1, &transform, ""));
        match Scene::parse(&text, "numerics.toml") {
            Err(e) => {
                assert_eq!(e.key.as_deref(), Some("objects[0].transform.corners"), "{e}");
                // Folding or degenerate (the fold proof), or too close to folding to invert.
                assert!(matches!(e.kind, SceneErrorKind::Hexahedron(_) | SceneErrorKind::Inversion(_)), "{e:?}");
                refused.push(delta);
            }
            Ok(scene) => {
                accepted.push(delta);
                assert!(delta > 0.0, "a box with det J ≤ 0 at a corner was accepted (δ = {delta})");
                let Shape::Distorted { hex, .. } = scene.objects()[0].placement().shape() else { panic!("distorted") };
                let tol_q = 1e-6 / 256.0;
                for i in 0..=8 {
                    for j in 0..=8 {
                        for l in 0..=8 {
                            let q = DVec3::new(i as f64, j as f64, l as f64) / 8.0;
                            let back = hex.invert(hex.world(q), None, tol_q);
                            let back = back.unwrap_or_else(|| panic!("δ {delta}: {q} not inverted"));
                            assert!((back - q).abs().max_element() <= tol_q, "δ {delta}: {q} → {back}");
                        }
                    }
                }
            }
        }
    }
    eprintln!("accepted δ {accepted:?}, refused δ {refused:?}");
    assert!(accepted.len() >= 6 && refused.len() >= 5, "accepted {accepted:?}, refused {refused:?}");
}

#[test]
fn a_folding_box_in_a_scene_is_refused_at_load_naming_its_corners() {
    let folded = "{ corners = [[0,0,0],[1,0,0],[0,1,0],[1,1,0],[0,0,1],[1,0,1],[0,1,1],[-0.5,-0.5,-0.5]] }";
    let text =
        View::new(DVec3::new(0.5, 0.5, 3.0), DVec3::splat(0.5), 30.0).text(&constant_box("f", [4; 3], 0.1, folded, ""));
    let e = Scene::parse(&text, "numerics.toml").expect_err("a folding box must be refused");
    assert_eq!(e.key.as_deref(), Some("objects[0].transform.corners"), "{e}");
    assert!(matches!(e.kind, SceneErrorKind::Hexahedron(HexahedronError::Folds { .. })), "{e:?}");
}

// ---------------------------------------------------------------------------------------
// Opacity exactly 0 and 1, maps that leave [0, 1], non-finite mapped values.

fn mapped_box(colour: &str, opacity: &str, step: f64) -> String {
    View::new(DVec3::new(0.5, 0.5, 3.0), DVec3::splat(0.5), 20.0).text(&format!(
        "[[datasets]]\nname = \"g\"\ndims = [8, 8, 8]\n[datasets.channels.voxel]\n\
         generator = {{ kind = \"ramp\", axis = \"z\", from = 0.0, to = 10.0 }}\n\
         [[objects]]\nname = \"g\"\ndataset = \"g\"\ncolour = {colour}\nopacity = {opacity}\n\
         sampling_distance = {step:?}\n"
    ))
}

#[test]
fn opacity_exactly_one_and_zero_make_no_nan_at_any_step() {
    let white = "{ type = \"constant\", red = [1.0], green = [0.5], blue = [0.25] }";
    for step in [1e-4, 0.01, 0.3] {
        // O = 1 everywhere: the first sample is opaque, α = 1 − 0^ℓ = 1 (no log(0), no 0·∞).
        let one = draw(&parse(&mapped_box(white, "{ type = \"constant\", coefficients = [1.0] }", step)));
        // O = 0: transparent, α = 1 − 1^ℓ = 0.
        let zero = draw(&parse(&mapped_box(white, "{ type = \"constant\", coefficients = [0.0] }", step)));
        // A LUT that jumps from exactly 0 to exactly 1 inside the box.
        let lut = draw(&parse(&mapped_box(white, "{ type = \"lut\", bounds = [5.0], values = [0.0, 1.0] }", step)));
        for img in [&one, &zero, &lut] {
            assert!(all_finite(img), "step {step}");
        }
        let centre = (16, 16);
        assert_eq!(one.pixel(centre.0, centre.1), [1.0, 0.5, 0.25], "step {step}");
        assert_eq!(zero.pixel(centre.0, centre.1), [0.0, 0.0, 0.0], "step {step}");
        assert_eq!(lut.pixel(centre.0, centre.1), [1.0, 0.5, 0.25], "step {step}");
    }
    // The guard itself, at the ends and beyond.
    assert_eq!(corrected_opacity(1.0, 1e-300), 1.0);
    assert_eq!(corrected_opacity(1.0, 0.0), 0.0);
    assert_eq!(corrected_opacity(0.0, 1e300), 0.0);
    assert_eq!(corrected_opacity(1.0 - 1e-16, 1e-3), -(1e-3 * (-(1.0 - 1e-16f64)).ln_1p()).exp_m1());
    assert!(corrected_opacity(0.5, f64::INFINITY) == 1.0);
}

#[test]
fn polynomial_maps_that_leave_the_unit_interval_are_clamped_and_overflow_contributes_nothing() {
    // The ramp runs 0.625 … 9.375 over z at voxel centres; along the central ray the map
    // 2v − 3 is < 0 in front and > 1 behind: clamped, the image equals that of the clamped
    // map written as a ramp.
    let colour = "{ type = \"linear\", red = [-3.0, 2.0], green = [1.5, 0.0], blue = [0.3, 0.0] }";
    let poly = draw(&parse(&mapped_box(colour, "{ type = \"linear\", coefficients = [-0.5, 0.1] }", 0.01)));
    let ramp = draw(&parse(&mapped_box(
        "{ type = \"ramp\", points = [[1.5, 0.0, 1.0, 0.3], [2.0, 1.0, 1.0, 0.3]] }",
        "{ type = \"ramp\", points = [[5.0, 0.0], [15.0, 1.0]] }",
        0.01,
    )));
    assert!(all_finite(&poly));
    let d = max_diff(&poly, &ramp);
    assert!(d < 1e-12, "clamped polynomial vs ramp: {d:e}");
    // Coefficients that overflow to ±∞ (or make ∞ − ∞ = NaN) are non-finite results: those
    // samples contribute nothing rather than poisoning the pixel.
    let white = "{ type = \"constant\", red = [1.0], green = [1.0], blue = [1.0] }";
    for opacity in [
        "{ type = \"quadratic\", coefficients = [0.0, 0.0, 1e308] }",
        "{ type = \"quadratic\", coefficients = [0.0, -1e308, -1e308] }",
        "{ type = \"quadratic\", coefficients = [1e308, 1e308, -1e308] }",
    ] {
        let img = draw(&parse(&mapped_box(white, opacity, 0.05)));
        assert!(all_finite(&img), "{opacity}");
    }
    let blown =
        draw(&parse(&mapped_box(white, "{ type = \"quadratic\", coefficients = [1e308, 1e308, 1e308] }", 0.05)));
    assert_eq!(blown.pixel(16, 16), [0.0, 0.0, 0.0], "every sample overflows: nothing is drawn");
}

// ---------------------------------------------------------------------------------------
// 10⁵ samples along one ray: f64 against f32 and the closed form.

#[test]
fn a_hundred_thousand_samples_accumulate_within_the_documented_bounds() {
    // One ray straight down a 64-voxel column of constant opacity, n = 10⁵ samples.
    let (n, dims, o, c) = (100_000u64, 64u32, 0.05f64, 0.7f64);
    let mut view = View::new(DVec3::new(0.5, 0.5, 3.0), DVec3::new(0.5, 0.5, 0.0), 10.0);
    view.side = 1;
    let body = format!(
        "[[datasets]]\nname = \"b\"\ndims = [4, 4, {dims}]\n[datasets.channels.voxel]\n\
         generator = {{ kind = \"constant\", value = 0.0 }}\n\
         [[objects]]\nname = \"b\"\ndataset = \"b\"\n\
         colour = {{ type = \"constant\", red = [{c:?}], green = [{c:?}], blue = [{c:?}] }}\n\
         opacity = {{ type = \"constant\", coefficients = [{o:?}] }}\nsampling_distance = 1e-5\n"
    );
    let scene = parse(&view.text(&body));
    let out = render(&scene, &f64_path()).unwrap();
    assert_eq!(out.stats.samples, n);
    let rendered = out.image.pixel(0, 0);
    // The same α the renderer uses: ℓ = 64 voxels / 10⁵ samples.
    let alpha = corrected_opacity(o, dims as f64 / n as f64);
    // Closed form: A = 1 − (1 − α)^n = 1 − (1 − o)^64, C = c·A.
    let exact_a = -((n as f64) * (-alpha).ln_1p()).exp_m1();
    assert!((exact_a - through(o, dims as f64)).abs() < 1e-13);
    // The compositing loop of eq. 5 in f32.
    let (a32, c32) = {
        let (mut acc_a, mut acc_c) = (0.0f32, 0.0f32);
        let (al, cl) = (alpha as f32, c as f32);
        for _ in 0..n {
            let w = al * (1.0 - acc_a);
            acc_c += cl * w;
            acc_a += w;
        }
        (acc_a as f64, acc_c as f64)
    };
    let err64 = (rendered[0] - c * exact_a).abs();
    let err32 = (c32 - c * exact_a).abs().max((a32 - exact_a).abs());
    // Bounds: each step adds at most about two roundings of a value ≤ 1, so n steps stay
    // within 2nε: 4.4e-11 in f64 (ε = 2⁻⁵²) and 2.4e-2 in f32 (ε = 2⁻²³). Rounding errors
    // of this loop largely cancel: measured 1e-14 in f64 and 1e-5 in f32.
    let (bound64, bound32) = (2.0 * n as f64 * f64::EPSILON, 2.0 * n as f64 * f32::EPSILON as f64);
    eprintln!("10⁵ samples: f64 error {err64:.2e} (bound {bound64:.1e}), f32 error {err32:.2e} (bound {bound32:.1e})");
    assert!(err64 <= bound64, "f64 {err64:e}");
    assert!(err32 <= bound32, "f32 {err32:e}");
    assert!(err64 < err32, "f64 must beat f32");
}

// ---------------------------------------------------------------------------------------
// Termination 1.0 and runaway sample counts.

#[test]
fn a_tiny_sampling_distance_is_refused_at_load_instead_of_rendering_for_hours() {
    let mut view = View::new(DVec3::new(0.5, 0.5, 3.0), DVec3::splat(0.5), 30.0);
    view.side = 512;
    let started = std::time::Instant::now();
    for step in ["1e-9", "1e-6"] {
        let text = view.text(&constant_box(
            "b",
            [256; 3],
            0.01,
            "{ matrix = [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]] }",
            &format!("sampling_distance = {step}"),
        ));
        let e = Scene::parse(&text, "numerics.toml").expect_err("refused").to_string();
        assert!(e.contains("objects[0].sampling_distance") && e.contains("samples"), "{step}: {e}");
    }
    assert!(started.elapsed().as_secs_f64() < 5.0, "refusal must be immediate");
    // A fine step on a small image is fine, and termination 1.0 visits every sample (the
    // rays stay short of opaque: 1 − 0.5⁴ ≈ 0.94).
    view.side = 3;
    let scene = parse(&view.text(&constant_box(
        "b",
        [4; 3],
        0.5,
        "{ matrix = [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]] }",
        "sampling_distance = 1e-4",
    )));
    let out = render(&scene, &f64_path()).unwrap();
    let expected: u64 = (0..9)
        .map(|i| {
            let ray = scene.camera().ray(i % 3, i / 3, 3, 3);
            unit_cube_chord(ray.origin, ray.dir)
                .map_or(0, |(a, b)| trove_core::geometry::sample_count(b - a, 1e-4, 0.0))
        })
        .sum();
    assert!(expected > 50_000);
    assert_eq!(out.stats.samples, expected, "termination 1.0 must visit every sample");
}

// ---------------------------------------------------------------------------------------
// Image-level invariants.

/// Three objects with matrix placements: a Gaussian, a Marschner–Lobb box and a ramp, some
/// overlapping, under the world rotation `r`.
fn three_objects(r: DMat4) -> String {
    let m1 = DMat4::from_translation(DVec3::new(-0.6, -0.4, -0.5)) * DMat4::from_scale(DVec3::new(1.2, 1.0, 0.9));
    let m2 = DMat4::from_translation(DVec3::new(0.1, -0.2, -0.3))
        * DMat4::from_axis_angle(DVec3::new(0.3, 1.0, 0.2).normalize(), 0.6)
        * DMat4::from_scale(DVec3::new(0.8, 0.7, 1.1));
    let m3 = DMat4::from_translation(DVec3::new(-0.3, 0.2, -0.8))
        * DMat4::from_axis_angle(DVec3::X, -0.4)
        * DMat4::from_scale(DVec3::new(1.0, 0.3, 0.6));
    let object = |name: &str, dims: &str, generator: &str, m: DMat4, extra: &str| {
        format!(
            "[[datasets]]\nname = \"{name}\"\ndims = {dims}\n[datasets.channels.voxel]\ngenerator = {generator}\n\
             [[objects]]\nname = \"{name}\"\ndataset = \"{name}\"\n\
             colour = {{ type = \"linear\", red = [0.1, 0.9], green = [0.8, -0.6], blue = [0.3, 0.4] }}\n\
             opacity = {{ type = \"linear\", coefficients = [0.01, 0.15] }}\ntransform = {}\n{extra}\n",
            matrix(&(r * m))
        )
    };
    object("g", "[12, 12, 12]", "{ kind = \"gaussian\", sigma = 0.25 }", m1, "")
        + &object("ml", "[10, 14, 9]", "{ kind = \"marschner_lobb\" }", m2, "sampling_distance = 0.031")
        + &object("r", "[9, 5, 7]", "{ kind = \"ramp\", axis = \"y\" }", m3, "interpolation = \"cubic\"")
}

#[test]
fn rotating_every_object_and_the_camera_together_leaves_the_image_unchanged() {
    let (eye, target, up) = (DVec3::new(0.7, 1.1, 3.2), DVec3::new(0.0, 0.1, -0.2), DVec3::new(0.1, 1.0, 0.0));
    let base = draw(&parse(
        &View { side: 41, eye, target, up, fov: 45.0, correction: true }.text(&three_objects(DMat4::IDENTITY)),
    ));
    assert!(base.pixels().iter().filter(|p| p[0] > 0.05).count() > 300, "objects should fill the view");
    for (axis, angle) in
        [(DVec3::new(1.0, 2.0, 3.0), 0.7), (DVec3::Z, std::f64::consts::FRAC_PI_2), (DVec3::new(-2.0, 0.5, 1.0), 2.9)]
    {
        let r = DMat4::from_axis_angle(axis.normalize(), angle);
        let view = View {
            side: 41,
            eye: r.transform_point3(eye),
            target: r.transform_point3(target),
            up: r.transform_vector3(up),
            fov: 45.0,
            correction: true,
        };
        let img = draw(&parse(&view.text(&three_objects(r))));
        let d = max_diff(&base, &img);
        // Linear values agree to rounding (1e-9 leaves room for sample positions that move by
        // ~1e-15 through a cubic stencil); the PNG bytes are then identical.
        assert!(d < 1e-9, "rotation {axis} by {angle}: max difference {d:e}");
        assert_eq!(base.max_byte_difference(&img), 0);
    }
}

fn corners_of(m: &DMat4, bump: DVec3) -> String {
    let c: Vec<String> = (0..8)
        .map(|i| {
            let p = m.transform_point3(DVec3::new((i & 1) as f64, (i >> 1 & 1) as f64, (i >> 2 & 1) as f64));
            v(if i == 7 { p + bump } else { p })
        })
        .collect();
    format!("{{ corners = [{}] }}", c.join(", "))
}

fn placed_blob(transform: &str) -> String {
    View::new(DVec3::new(0.9, 1.3, 3.0), DVec3::ZERO, 35.0).text(&format!(
        "[[datasets]]\nname = \"g\"\ndims = [10, 12, 8]\n[datasets.channels.voxel]\n\
         generator = {{ kind = \"marschner_lobb\", fm = 2.0 }}\n\
         [[objects]]\nname = \"g\"\ndataset = \"g\"\n\
         colour = {{ type = \"linear\", red = [0.2, 0.8], green = [0.9, -0.5], blue = [0.5, 0.0] }}\n\
         opacity = {{ type = \"linear\", coefficients = [0.0, 0.2] }}\nsampling_distance = 0.021\n\
         transform = {transform}\n"
    ))
}

#[test]
fn a_matrix_and_its_eight_corners_render_the_same_and_tiny_distortions_converge_to_it() {
    let m = DMat4::from_translation(DVec3::new(-0.5, -0.6, -0.4))
        * DMat4::from_axis_angle(DVec3::new(1.0, 1.0, -0.5).normalize(), 0.8)
        * DMat4::from_scale(DVec3::new(1.1, 1.3, 0.9));
    let by_matrix = draw(&parse(&placed_blob(&matrix(&m))));
    let by_corners = draw(&parse(&placed_blob(&corners_of(&m, DVec3::ZERO))));
    let d = max_diff(&by_matrix, &by_corners);
    assert!(d < 1e-12, "matrix vs its corners: {d:e}");
    // A bump of corner 7 forces the distorted (Newton) path; the image converges to the
    // affine one linearly in the bump.
    let mut diffs = Vec::new();
    for bump in [1e-2, 1e-4, 1e-6] {
        let text = placed_blob(&corners_of(&m, DVec3::new(bump, -bump, bump)));
        let scene = parse(&text);
        assert!(
            matches!(scene.objects()[0].placement().shape(), Shape::Distorted { .. }),
            "bump {bump} must be distorted"
        );
        diffs.push(max_diff(&by_matrix, &draw(&scene)));
    }
    assert!(diffs[2] < 1e-5 && diffs[1] < diffs[0] && diffs[2] < diffs[1], "{diffs:?}");
}

/// The per-ray algorithm, which accumulates in f64 end to end: these tests bound errors far
/// below the grouped algorithm's f32 piece results (about 6e-8 per piece, its wire format),
/// and `tests/tests/algorithms.rs` holds grouped to per-ray.
fn f64_path() -> RenderOptions {
    RenderOptions { algorithm: trove_core::render::Algorithm::PerRay, ..Default::default() }
}
