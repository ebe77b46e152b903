//! Rendering semantics of SPEC §2–4 checked against closed forms, end to end through the
//! scene parser, checked on Algorithm 1 (f64 end to end) and held to it for Algorithm 2.

use trove_core::render::Image;
use trove_tests::{render_text, scratch, write_f32, Header};

const W: u32 = 33;

/// A camera looking down −z at the unit box's centre, plus `body`.
fn scene(termination: f64, correction: bool, body: &str) -> String {
    let header = Header::new(W, [0.5, 0.5, 3.0], [0.5, 0.5, 0.5], 20.0).background([0.2, 0.4, 0.6]);
    format!("{header}[render]\ntermination = {termination}\nopacity_correction = {correction}\n{body}")
}

/// The ray direction of pixel (col, row) for the camera above (SPEC §4.1).
fn ray_dir(col: u32, row: u32) -> [f64; 3] {
    let s = (10.0f64).to_radians().tan();
    let x = (2.0 * (col as f64 + 0.5) / W as f64 - 1.0) * s;
    let y = (1.0 - 2.0 * (row as f64 + 0.5) / W as f64) * s;
    let n = (x * x + y * y + 1.0).sqrt();
    [x / n, y / n, -1.0 / n]
}

/// Unit-box entry/exit of a ray from (0.5, 0.5, 3) along d, or None.
fn unit_box_path(d: [f64; 3]) -> Option<(f64, f64)> {
    let o = [0.5, 0.5, 3.0];
    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
    for a in 0..3 {
        if d[a] == 0.0 {
            continue;
        }
        let (ta, tb) = ((0.0 - o[a]) / d[a], (1.0 - o[a]) / d[a]);
        t0 = t0.max(ta.min(tb));
        t1 = t1.min(ta.max(tb));
    }
    (t1 > t0).then_some((t0, t1))
}

fn constant_box(n: u32, opacity: f64) -> String {
    format!(
        r#"
[[datasets]]
name = "c"
dims = [{n}, {n}, {n}]
[datasets.channels.voxel]
generator = {{ kind = "constant", value = 7.0 }}
[[objects]]
name = "box"
dataset = "c"
colour = {{ type = "constant", red = [0.9], green = [0.5], blue = [0.1] }}
opacity = {{ type = "lut", bounds = [5.0], values = [0.0, {opacity}] }}
"#
    )
}

#[test]
fn a_constant_box_matches_the_closed_form_at_every_pixel() {
    let dir = scratch("closed-form");
    let (n, o) = (16u32, 0.07f64);
    for correction in [true, false] {
        let img = render_text(&dir, &scene(1.0, correction, &constant_box(n, o)));
        for row in 0..W {
            for col in 0..W {
                let d = ray_dir(col, row);
                let px = img.pixel(col, row);
                let bg = [0.2, 0.4, 0.6];
                let expected = match unit_box_path(d) {
                    None => bg,
                    Some((t0, t1)) => {
                        // VC length of the path: n voxels per world unit on every axis.
                        let vc_len = (t1 - t0) * n as f64;
                        let a = if correction {
                            1.0 - (1.0 - o).powf(vc_len)
                        } else {
                            let samples = vc_len.round().max(1.0);
                            1.0 - (1.0 - o).powf(samples)
                        };
                        let c = [0.9, 0.5, 0.1];
                        std::array::from_fn(|i| c[i] * a + bg[i] * (1.0 - a))
                    }
                };
                for i in 0..3 {
                    assert!(
                        (px[i] - expected[i]).abs() < 1e-9,
                        "correction {correction}, pixel ({col}, {row}) channel {i}: {} vs {}",
                        px[i],
                        expected[i]
                    );
                }
            }
        }
    }
}

#[test]
fn termination_stops_rays_within_its_tolerance() {
    let dir = scratch("termination");
    let never = render_text(&dir, &scene(1.0, true, &constant_box(16, 0.5)));
    let early = render_text(&dir, &scene(0.95, true, &constant_box(16, 0.5)));
    let mut differs = false;
    for (a, b) in never.pixels().iter().zip(early.pixels()) {
        for i in 0..3 {
            assert!((a[i] - b[i]).abs() <= 0.05 + 1e-12);
            differs |= a[i] != b[i];
        }
    }
    assert!(differs, "termination at 0.95 must change some opaque pixels");
}

#[test]
fn an_extent_sub_box_equals_cropping_the_dataset() {
    let dir = scratch("extent");
    let n = 8usize;
    let field = |i: usize, j: usize, k: usize| ((i * 7 + j * 3 + k * 5) % 11) as f32;
    let mut full = Vec::new();
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                full.push(field(i, j, k));
            }
        }
    }
    write_f32(&dir.join("full.raw"), &full);
    // The sub-box x ∈ [0.25, 0.75], z ∈ [0.5, 1]: voxels 2..6 in x, 4..8 in z.
    let mut crop = Vec::new();
    for k in 4..8 {
        for j in 0..n {
            for i in 2..6 {
                crop.push(field(i, j, k));
            }
        }
    }
    write_f32(&dir.join("crop.raw"), &crop);
    let object = |dataset: &str, extent: &str| {
        format!(
            r#"
[[objects]]
name = "{dataset}"
dataset = "{dataset}"
interpolation = "nearest"
colour = {{ type = "linear", red = [0, 0.1], green = [1, -0.09], blue = [0.5, 0] }}
opacity = {{ type = "linear", coefficients = [0.0, 0.02] }}
{extent}
"#
        )
    };
    let datasets = |dims: &str, file: &str, name: &str| {
        format!("[[datasets]]\nname = \"{name}\"\ndims = {dims}\n[datasets.channels.voxel]\nraw = \"{file}\"\ntype = \"f32\"\n")
    };
    let a = render_text(
        &dir,
        &scene(
            1.0,
            true,
            &(datasets("[8, 8, 8]", "full.raw", "full")
                + &object("full", "extent = { min = [0.25, 0.0, 0.5], max = [0.75, 1.0, 1.0] }")),
        ),
    );
    let b = render_text(&dir, &scene(1.0, true, &(datasets("[4, 8, 4]", "crop.raw", "crop") + &object("crop", ""))));
    assert!(a.pixels().iter().any(|p| p != &[0.2, 0.4, 0.6]), "the object must be visible");
    assert_eq!(a.max_byte_difference(&b), 0);
    assert!(a.psnr(&b) > 120.0, "PSNR {}", a.psnr(&b));
}

#[test]
fn overlapping_objects_of_one_colour_act_as_one_medium() {
    let dir = scratch("colocated");
    let (o1, o2) = (0.05f64, 0.12f64);
    let combined = 1.0 - (1.0 - o1) * (1.0 - o2);
    let two = constant_box(8, o1).replace("name = \"box\"", "name = \"a\"")
        + &constant_box(8, o2)
            .replace("name = \"c\"", "name = \"d\"")
            .replace("\"c\"", "\"d\"")
            .replace("name = \"box\"", "name = \"b\"");
    let one = constant_box(8, combined);
    for correction in [true, false] {
        let a = render_text(&dir, &scene(1.0, correction, &two));
        let b = render_text(&dir, &scene(1.0, correction, &one));
        for (p, q) in a.pixels().iter().zip(b.pixels()) {
            for i in 0..3 {
                assert!((p[i] - q[i]).abs() < 1e-12, "{p:?} vs {q:?}");
            }
        }
    }
}

#[test]
fn rays_in_a_face_plane_and_along_edges_neither_miss_nor_make_nan() {
    let dir = scratch("face-plane");
    // The eye sits on the plane x = 1 of the box's face; with an odd width the middle
    // column's rays have a direction x-component of exactly zero and lie in that plane.
    let body = constant_box(4, 0.3);
    let text = scene(1.0, true, &body)
        .replace("eye = [0.5, 0.5, 3.0]", "eye = [1.0, 0.5, 3.0]")
        .replace("target = [0.5, 0.5, 0.5]", "target = [1.0, 0.5, 0.5]");
    let img = render_text(&dir, &text);
    assert!(img.pixels().iter().flatten().all(|c| c.is_finite()));
    let mid = W / 2;
    for row in 0..W {
        let left = img.pixel(mid - 1, row);
        let centre = img.pixel(mid, row);
        if left != [0.2, 0.4, 0.6] {
            assert_ne!(centre, [0.2, 0.4, 0.6], "row {row}: a ray in the face plane x = 1 missed the closed box");
        }
    }
}

#[test]
fn nan_and_infinite_voxels_contribute_nothing() {
    let dir = scratch("nan");
    let n = 4usize;
    let mut v = vec![1.0f32; n * n * n];
    // Poison one voxel on the central column (x = 1, y = 1, z = 2) with NaN and another with +∞.
    v[1 + n + 2 * n * n] = f32::NAN;
    v[2 + 2 * n + n * n] = f32::INFINITY;
    write_f32(&dir.join("v.raw"), &v);
    let body = r#"
[[datasets]]
name = "v"
dims = [4, 4, 4]
[datasets.channels.voxel]
raw = "v.raw"
type = "f32"
[[objects]]
name = "o"
dataset = "v"
interpolation = "nearest"
colour = { type = "constant", red = [1], green = [1], blue = [1] }
opacity = { type = "linear", coefficients = [0.0, 0.25] }
"#;
    let img = render_text(&dir, &scene(1.0, false, body));
    assert!(img.pixels().iter().flatten().all(|c| c.is_finite()));
    // A near-axial ray through a clean column takes 4 samples; one through a poisoned voxel 3.
    let full = 1.0 - 0.75f64.powi(4);
    let holed = 1.0 - 0.75f64.powi(3);
    let a_of = |p: [f64; 3]| (p[0] - 0.2) / 0.8;
    let centre_of_voxel = |i: u32, j: u32| -> (u32, u32) {
        // Pixel whose ray crosses the middle of voxel column (i, j) at z ≈ 0.5.
        let s = (10.0f64).to_radians().tan();
        let x = (i as f64 + 0.5) / 4.0 - 0.5;
        let y = (j as f64 + 0.5) / 4.0 - 0.5;
        let col = ((x / 2.5 / s + 1.0) / 2.0 * W as f64 - 0.5).round() as u32;
        let row = ((1.0 - y / 2.5 / s) / 2.0 * W as f64 - 0.5).round() as u32;
        (col, row)
    };
    let (c, r) = centre_of_voxel(0, 0);
    assert!((a_of(Image::pixel(&img, c, r)) - full).abs() < 1e-9);
    let (c, r) = centre_of_voxel(1, 1);
    assert!((a_of(img.pixel(c, r)) - holed).abs() < 1e-9, "{}", a_of(img.pixel(c, r)));
    let (c, r) = centre_of_voxel(2, 2);
    assert!((a_of(img.pixel(c, r)) - holed).abs() < 1e-9, "{}", a_of(img.pixel(c, r)));
}

#[test]
fn a_depth_one_image_plane_head_on_shows_the_photo_composited_by_its_alpha() {
    let dir = scratch("photo-plane");
    // A 3×3 RGBA photo; row 0 of the file is the top of the picture.
    let mut png = image::RgbaImage::new(3, 3);
    for (x, y, p) in png.enumerate_pixels_mut() {
        *p = image::Rgba([(40 + 80 * x) as u8, (30 + 90 * y) as u8, 200, (255 - 100 * y - 20 * x) as u8]);
    }
    png.save(dir.join("photo.png")).unwrap();
    // Camera straight on, each of the 33 pixels per axis lands on one of 3 texels.
    let body = r#"
[[datasets]]
name = "photo"
image = "photo.png"
[[objects]]
name = "plane"
dataset = "photo"
interpolation = "nearest"
colour = { type = "raw" }
opacity = { type = "raw" }
"#;
    let img = render_text(&dir, &scene(1.0, true, body));
    let bg = [0.2, 0.4, 0.6];
    let mut checked = 0;
    for row in 0..W {
        for col in 0..W {
            let d = ray_dir(col, row);
            // Where the ray crosses the plane's middle (z = 0.5) in box coordinates.
            let t = (0.5 - 3.0) / d[2];
            let (x, y) = (0.5 + t * d[0], 0.5 + t * d[1]);
            let (fx, fy) = (x * 3.0, y * 3.0);
            // Skip rays within rounding of a texel border, or outside the plane.
            if !(0.0..3.0).contains(&fx)
                || !(0.0..3.0).contains(&fy)
                || (fx - fx.round()).abs() < 0.05
                || (fy - fy.round()).abs() < 0.05
            {
                continue;
            }
            // Only rays that cross the whole depth (enter at z = 1, leave at z = 0).
            let through = [1.0, 0.0].iter().all(|&z| {
                let t = (z - 3.0) / d[2];
                (0.0..=1.0).contains(&(0.5 + t * d[0])) && (0.0..=1.0).contains(&(0.5 + t * d[1]))
            });
            if !through {
                continue;
            }
            let (tx, ty_up) = (fx.floor() as u32, fy.floor() as u32);
            let p = png.get_pixel(tx, 2 - ty_up); // y points up: voxel y = h − 1 − row
                                                  // The slanted ray crosses the one-voxel-deep plane with VC length ℓ ≥ 1.
            let vc = [d[0] / d[2] * 3.0, d[1] / d[2] * 3.0, 1.0];
            let ell = (vc[0] * vc[0] + vc[1] * vc[1] + 1.0).sqrt();
            let a = 1.0 - (1.0 - p[3] as f64 / 255.0).powf(ell);
            for i in 0..3 {
                let want = p[i] as f64 / 255.0 * a + bg[i] * (1.0 - a);
                assert!(
                    (img.pixel(col, row)[i] - want).abs() < 1e-9,
                    "({col},{row})[{i}]: {:?} want {want}, texel {tx},{ty_up} {p:?}",
                    img.pixel(col, row)
                );
            }
            checked += 1;
        }
    }
    assert!(checked > 500, "only {checked} pixels checked");
}
