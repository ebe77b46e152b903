//! Convergence against the closed-form reference scenes of `trove_tests::reference`: cheap
//! versions of what `trove-bench accuracy` measures at full size, as tests (no timings).

use trove_core::render::{render, Algorithm, RenderOptions};
use trove_core::Interpolation;
use trove_tests::reference::{log_log_slope, rmse_and_max, Reference, Setup};

/// The red channel (= accumulated opacity: white objects on black) of a reference render.
fn render_alpha(r: Reference, s: &Setup) -> Vec<f64> {
    let scene = r.scene(s).unwrap_or_else(|e| panic!("{}: {e}", r.name()));
    // Per ray, in f64 throughout: grouped piece results are f32 (see docs/algorithms.md).
    let options = RenderOptions { algorithm: Algorithm::PerRay, ..Default::default() };
    render(&scene, &options).expect("render").image.pixels().iter().map(|p| p[0]).collect()
}

fn exact(r: Reference, s: &Setup) -> Vec<f64> {
    let scene = r.scene(s).expect("scene");
    r.exact_image(scene.camera(), s.image_side, s.image_side)
}

fn setup(dims: u32, interpolation: Interpolation, step_voxels: f64, opacity_correction: bool) -> Setup {
    Setup { dims, image_side: 24, interpolation, step_voxels, opacity_correction }
}

#[test]
fn trilinear_with_opacity_correction_converges_at_second_order_on_a_gaussian() {
    // The sampling error against a render of the same voxels at 1/256 voxel, over steps ¼ …
    // 1/32 voxel (at 1 and ½ voxel the samples are commensurate with the grid and errors
    // partly cancel, see `trove-bench accuracy`). The midpoint rule's order is 2.
    let g = Reference::Gaussian;
    let converged = render_alpha(g, &setup(16, Interpolation::Trilinear, 1.0 / 256.0, true));
    let points: Vec<(f64, f64)> = [0.25, 0.125, 1.0 / 16.0, 1.0 / 32.0]
        .iter()
        .map(|&step| {
            let img = render_alpha(g, &setup(16, Interpolation::Trilinear, step, true));
            (step, rmse_and_max(img, converged.iter().copied()).0)
        })
        .collect();
    let order = log_log_slope(&points).unwrap();
    eprintln!("sampling error {points:?}: order {order:.3}");
    assert!(order >= 1.8, "measured order {order} on {points:?}");
}

#[test]
fn overlapping_constant_boxes_are_exact_at_any_step_with_correction_and_not_without() {
    let b = Reference::TwoBoxes;
    let truth = exact(b, &setup(8, Interpolation::Trilinear, 1.0, true));
    assert!(truth.iter().any(|&a| a > 0.5), "the boxes should be visible");
    for step in [4.0, 1.0, 0.3, 0.125] {
        let img = render_alpha(b, &setup(8, Interpolation::Trilinear, step, true));
        let (rmse, max) = rmse_and_max(img, truth.iter().copied());
        // Exact up to rounding: a slack that lengthened chords (5e-11 before) would show here.
        assert!(max < 1e-14, "step {step}: rmse {rmse:e}, max {max:e}");
    }
    let img = render_alpha(b, &setup(8, Interpolation::Trilinear, 0.25, false));
    assert!(rmse_and_max(img, truth.iter().copied()).1 > 0.1, "without correction a quarter-voxel step over-darkens");
}

#[test]
fn the_representation_error_shrinks_as_the_resolution_grows() {
    // Trilinear at a step fine enough that the sampling error is negligible: what is left is
    // what the voxels get wrong about the continuous field.
    for r in [Reference::Gaussian, Reference::Ramp, Reference::Sphere] {
        let errors: Vec<(f64, f64)> = [8u32, 16, 32]
            .iter()
            .map(|&n| {
                let s = setup(n, Interpolation::Trilinear, 0.125, true);
                let (rmse, _) = rmse_and_max(render_alpha(r, &s), exact(r, &s));
                (1.0 / n as f64, rmse)
            })
            .collect();
        eprintln!("{}: {errors:?}", r.name());
        assert!(errors.windows(2).all(|w| w[1].1 < w[0].1), "{}: {errors:?}", r.name());
        assert!(errors[2].1 < 0.02, "{}: {errors:?}", r.name());
    }
}
