//! Distorted boxes (SPEC §2, §4.2; paper §2.3.5): eight-corner placements against matrix
//! placements, convergence as the distortion vanishes, and refusal of folded boxes.

use trove_core::geometry::Shape;
use trove_core::scene::{Scene, SceneErrorKind};
use trove_tests::{render_text, scratch, Header};

const M: [[f64; 4]; 3] = [[1.2, 0.3, 0.0, -0.7], [-0.2, 1.0, 0.1, -0.5], [0.1, 0.0, 0.9, -0.4]];

fn corners(distortion: f64) -> [[f64; 3]; 8] {
    // A fixed, non-affine perturbation pattern (it twists the top face and pinches one edge).
    let pattern = [
        [0.0; 3],
        [0.3, -0.2, 0.1],
        [-0.1, 0.2, 0.0],
        [0.2, 0.1, -0.3],
        [0.1, 0.0, 0.2],
        [-0.3, 0.1, 0.0],
        [0.0, -0.2, 0.1],
        [0.2, 0.2, 0.2],
    ];
    std::array::from_fn(|i| {
        let q = [(i & 1) as f64, (i >> 1 & 1) as f64, (i >> 2 & 1) as f64];
        std::array::from_fn(|r| M[r][0] * q[0] + M[r][1] * q[1] + M[r][2] * q[2] + M[r][3] + distortion * pattern[i][r])
    })
}

fn scene(transform: &str, extra_render: &str) -> String {
    let header = Header::new(40, [0.6, 0.8, 3.5], [0.0, 0.0, 0.0], 45.0).background([0.1; 3]);
    format!(
        r#"{header}
[render]
termination = 1.0
{extra_render}
[[datasets]]
name = "ml"
dims = [20, 18, 16]
[datasets.channels.voxel]
generator = {{ kind = "marschner_lobb", fm = 3.0 }}
[[objects]]
name = "o"
dataset = "ml"
colour = {{ type = "ramp", points = [[0.0, 1.0, 0.2, 0.1], [1.0, 0.1, 0.5, 1.0]] }}
opacity = {{ type = "linear", coefficients = [0.0, 0.15] }}
transform = {transform}
"#
    )
}

fn matrix_text() -> String {
    let rows: Vec<String> = M.iter().map(|r| format!("[{}, {}, {}, {}]", r[0], r[1], r[2], r[3])).collect();
    format!("{{ matrix = [{}, [0, 0, 0, 1]] }}", rows.join(", "))
}

fn corners_text(c: [[f64; 3]; 8]) -> String {
    let pts: Vec<String> = c.iter().map(|p| format!("[{:?}, {:?}, {:?}]", p[0], p[1], p[2])).collect();
    format!("{{ corners = [{}] }}", pts.join(", "))
}

#[test]
fn a_matrix_and_its_eight_corners_render_the_same_image() {
    let dir = scratch("corners-vs-matrix");
    let by_matrix = render_text(&dir, &scene(&matrix_text(), ""));
    let by_corners = render_text(&dir, &scene(&corners_text(corners(0.0)), ""));
    assert!(
        trove_tests::max_abs_difference(&by_matrix, &by_corners) < 1e-9,
        "{}",
        trove_tests::max_abs_difference(&by_matrix, &by_corners)
    );
    assert!(by_matrix.pixels().iter().any(|p| *p != [0.1, 0.1, 0.1]));
}

#[test]
fn a_slightly_distorted_box_converges_to_the_affine_one() {
    let dir = scratch("converge");
    let affine = render_text(&dir, &scene(&matrix_text(), ""));
    let mut last = f64::INFINITY;
    for eps in [1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6] {
        let text = scene(&corners_text(corners(eps)), "");
        let parsed = Scene::parse(&text, dir.join("scene.toml")).unwrap();
        assert!(
            matches!(parsed.objects()[0].placement().shape(), Shape::Distorted { .. }),
            "ε = {eps} must take the distorted path"
        );
        let err = trove_tests::max_abs_difference(&render_text(&dir, &text), &affine);
        // The image depends smoothly on the corners: the error is first order in ε.
        assert!(err < last * if eps < 1e-2 { 0.2 } else { 1.0 }, "ε = {eps}: error {err} did not shrink from {last}");
        last = err;
    }
    assert!(last < 1e-4, "ε = 1e-6 still differs by {last}");
}

#[test]
fn the_paper_straight_line_mode_approximates_the_exact_inversion() {
    let dir = scratch("straight");
    let exact = render_text(&dir, &scene(&corners_text(corners(0.15)), ""));
    let straight = render_text(&dir, &scene(&corners_text(corners(0.15)), "distorted_sampling = \"straight\""));
    let diff = trove_tests::max_abs_difference(&exact, &straight);
    assert!(diff > 1e-4, "straight-line sampling should differ visibly on a distorted box, got {diff}");
    assert!(
        exact.psnr(&straight) > 20.0,
        "but it is an approximation of the same object: PSNR {}",
        exact.psnr(&straight)
    );
    // On a parallelepiped the two modes are the same path.
    let a = render_text(&dir, &scene(&corners_text(corners(0.0)), ""));
    let b = render_text(&dir, &scene(&corners_text(corners(0.0)), "distorted_sampling = \"straight\""));
    assert_eq!(a, b);
}

#[test]
fn a_folded_hexahedron_is_refused_naming_transform_corners() {
    let dir = scratch("folded");
    let mut c = corners(0.0);
    c.swap(0, 7);
    let err = Scene::parse(&scene(&corners_text(c), ""), dir.join("scene.toml")).unwrap_err();
    assert_eq!(err.key.as_deref(), Some("objects[0].transform.corners"));
    assert!(matches!(err.kind, SceneErrorKind::Hexahedron(_)), "{err:?}");
    assert!(err.to_string().contains("scene.toml"), "{err}");
}
