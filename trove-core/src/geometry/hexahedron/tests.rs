//! Tests of the distorted box: the Bernstein fold test, exact inversion and ray segments, each
//! against an independent reference (direct Jacobians, slab tests for parallelepipeds) or a
//! property over random boxes.

use super::*;
use proptest::prelude::*;

fn unit_corners() -> [DVec3; 8] {
    std::array::from_fn(|i| DVec3::new((i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64))
}

fn hex(c: [DVec3; 8]) -> Hexahedron {
    match Hexahedron::new(c) {
        Ok(h) => h,
        Err(e) => panic!("box refused: {e}"),
    }
}

/// Rotation + non-uniform scale + shear + translation.
fn skewed_matrix() -> DMat4 {
    let rot = DMat4::from_axis_angle(DVec3::new(1.0, 2.0, -0.5).normalize(), 0.7);
    let scale = DMat4::from_scale(DVec3::new(2.0, 0.5, 1.25));
    let mut shear = DMat4::IDENTITY;
    shear.y_axis.x = 0.4; // x += 0.4 y
    shear.z_axis.y = -0.3; // y -= 0.3 z
    DMat4::from_translation(DVec3::new(-0.3, 1.1, 0.2)) * rot * shear * scale
}

/// Top face (z = 1) rotated by `deg` about the vertical axis through the centre: faces become saddles,
/// so the box is not convex.
fn twisted(deg: f64) -> [DVec3; 8] {
    twisted_scaled(deg, 1.0)
}

/// A frustum: the top face a quarter the width of the bottom face (planar faces, not a parallelepiped).
fn frustum() -> [DVec3; 8] {
    let top = DVec3::new(0.5, 0.5, 1.0);
    unit_corners().map(|c| if c.z == 1.0 { top + 0.25 * (c - top) } else { c })
}

/// As [`twisted`], with the top face also scaled by `scale` about its centre.
fn twisted_scaled(deg: f64, scale: f64) -> [DVec3; 8] {
    let r = DMat3::from_rotation_z(deg.to_radians());
    let top = DVec3::new(0.5, 0.5, 1.0);
    unit_corners().map(|c| if c.z == 1.0 { top + scale * (r * (c - top)) } else { c })
}

/// Independent Jacobian determinant, straight from the corners (central differences of the blend are
/// exact for a map of degree 1 per variable).
fn det_direct(c: &[DVec3; 8], q: DVec3) -> f64 {
    let w = |q: DVec3| {
        (0..8).fold(DVec3::ZERO, |s, i| {
            let f = |b: usize, t: f64| if b == 1 { t } else { 1.0 - t };
            s + c[i] * f(i & 1, q.x) * f((i >> 1) & 1, q.y) * f((i >> 2) & 1, q.z)
        })
    };
    let h = 0.5;
    let col = |e: DVec3| (w(q + h * e) - w(q - h * e)) / (2.0 * h);
    DMat3::from_cols(col(DVec3::X), col(DVec3::Y), col(DVec3::Z)).determinant()
}

fn bern_eval(b: &Bern, q: DVec3) -> f64 {
    let bb = |t: f64| [(1.0 - t) * (1.0 - t), 2.0 * t * (1.0 - t), t * t];
    let (bx, by, bz) = (bb(q.x), bb(q.y), bb(q.z));
    let mut s = 0.0;
    for i in 0..3 {
        for j in 0..3 {
            for k in 0..3 {
                s += b[i][j][k] * bx[i] * by[j] * bz[k];
            }
        }
    }
    s
}

/// Reference segment of a parallelepiped: slab test in box coordinates, `None` for an empty one.
fn slab(m: &DMat4, o: DVec3, d: DVec3) -> Option<(f64, f64)> {
    let inv = m.inverse();
    let (oq, dq) = (inv.transform_point3(o), inv.transform_vector3(d));
    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
    for a in 0..3 {
        if dq[a] == 0.0 {
            if !(0.0..=1.0).contains(&oq[a]) {
                return None;
            }
        } else {
            let (ta, tb) = (-oq[a] / dq[a], (1.0 - oq[a]) / dq[a]);
            t0 = t0.max(ta.min(tb));
            t1 = t1.min(ta.max(tb));
        }
    }
    (t0 <= t1).then_some((t0, t1))
}

fn perturbed() -> impl Strategy<Value = [DVec3; 8]> {
    prop::array::uniform8(prop::array::uniform3(-0.25f64..0.25))
        .prop_map(|p| std::array::from_fn(|i| unit_corners()[i] + DVec3::from_array(p[i])))
}

// ---------------------------------------------------------------- construction and the fold test

#[test]
fn corners_of_affine_follow_the_spec_order() {
    let m = skewed_matrix();
    let c = corners_of_affine(&m);
    for (i, ci) in c.iter().enumerate() {
        let want = m.transform_point3(unit_corners()[i]);
        assert!((*ci - want).length() < 1e-15, "corner {i}");
    }
    assert_eq!(corners_of_affine(&DMat4::IDENTITY), unit_corners());
}

#[test]
fn affine_boxes_are_recognised() {
    for m in [DMat4::IDENTITY, skewed_matrix()] {
        let h = hex(corners_of_affine(&m));
        let a = h.as_affine().expect("a parallelepiped is affine");
        assert!(a.abs_diff_eq(m, 1e-12), "{a:?} vs {m:?}");
    }
    assert!(hex(twisted(30.0)).as_affine().is_none());
    let mut c = unit_corners();
    c[7].z += 1e-6;
    assert!(hex(c).as_affine().is_none(), "a 1e-6 dent is not affine");
}

proptest! {
    #[test]
    fn bernstein_expansion_is_exact(c in perturbed(), q in prop::array::uniform3(0.0f64..=1.0)) {
        let b = det_bernstein(&c);
        let q = DVec3::from_array(q);
        let (x, y) = (bern_eval(&b, q), det_direct(&c, q));
        prop_assert!((x - y).abs() <= 1e-12 * (1.0 + y.abs()), "{x} vs {y}");
        if let Ok(h) = Hexahedron::new(c) {
            prop_assert!((h.jacobian(q).determinant() - y).abs() <= 1e-12 * (1.0 + y.abs()));
            // Accepted boxes really keep one sign (checked on a grid, as a sanity check).
            for i in 0..64 {
                let g = DVec3::new((i & 3) as f64, ((i >> 2) & 3) as f64, (i >> 4) as f64) / 3.0;
                prop_assert!(h.orientation() * det_direct(&c, g) > 0.0);
            }
        }
    }
}

#[test]
fn de_casteljau_split_matches_the_polynomial() {
    let c = twisted(100.0);
    let b = det_bernstein(&c);
    for axis in 0..3 {
        let (lo, hi) = split(&b, axis);
        for q in [DVec3::new(0.3, 0.7, 0.1), DVec3::new(0.9, 0.2, 0.55)] {
            let mut ql = q;
            ql[axis] *= 0.5;
            let mut qh = q;
            qh[axis] = 0.5 + 0.5 * q[axis];
            assert!((bern_eval(&lo, q) - bern_eval(&b, ql)).abs() < 1e-13);
            assert!((bern_eval(&hi, q) - bern_eval(&b, qh)).abs() < 1e-13);
        }
    }
}

#[test]
fn folded_boxes_are_refused() {
    // Two corners swapped: the box turns inside out along one edge.
    let mut c = unit_corners();
    c.swap(6, 7);
    let e = Hexahedron::new(c).expect_err("swapped corners fold");
    assert!(matches!(e, HexahedronError::Folds { .. }), "{e:?}");
    // One corner pushed through the opposite face.
    let mut c = unit_corners();
    c[7] = DVec3::new(0.3, 0.3, -0.5);
    assert!(Hexahedron::new(c).is_err());
    // The top face twisted by 180°: det J = 0 on the axis.
    assert!(Hexahedron::new(twisted(180.0)).is_err());
    // The top face mirrored (x ↦ 1 − x): det J is +1 at the bottom, −1 at the top.
    let e = Hexahedron::new(unit_corners().map(|c| if c.z == 1.0 { DVec3::new(1.0 - c.x, c.y, c.z) } else { c }))
        .expect_err("mirrored top");
    let HexahedronError::Folds { at_corner0, value, .. } = e else { panic!("{e:?}") };
    assert!(at_corner0 > 0.0 && value < 0.0, "{e:?}");
    // The wording a user sees after the key `transform.corners`.
    let shown = e.to_string();
    assert!(shown.starts_with("the hexahedron folds over itself: the Jacobian determinant is "), "{shown}");
    assert!(shown.ends_with("(check the corner order: i = x + 2y + 4z)"), "{shown}");
}

#[test]
fn strongly_distorted_boxes_are_accepted() {
    // Frustum: top face a quarter the width of the bottom face.
    let h = hex(frustum());
    assert!(h.as_affine().is_none());
    assert_eq!(h.orientation(), 1.0);
    // Twisted top faces.
    for deg in [30.0, 60.0, 90.0, 120.0] {
        assert!(Hexahedron::new(twisted(deg)).is_ok(), "twist {deg}");
    }
    // A mirrored box (det J < 0 throughout) keeps its sign: allowed.
    let mirrored = hex(unit_corners().map(|c| DVec3::new(-c.x, c.y, c.z)));
    assert_eq!(mirrored.orientation(), -1.0);
    let mirrored_twist = hex(twisted(45.0).map(|c| DVec3::new(c.x, -c.y, c.z)));
    assert_eq!(mirrored_twist.orientation(), -1.0);
}

/// Whether `e` refuses a box for having no volume somewhere (rather than for folding).
fn degenerate(e: &HexahedronError) -> bool {
    matches!(
        e,
        HexahedronError::SinglePoint
            | HexahedronError::NoVolume
            | HexahedronError::DegenerateAtCorner0
            | HexahedronError::DegenerateAt { .. }
    )
}

#[test]
fn degenerate_and_non_finite_boxes_are_refused() {
    let flat = unit_corners().map(|c| DVec3::new(c.x, c.y, 0.0));
    assert!(degenerate(&Hexahedron::new(flat).expect_err("flat")));
    let point = [DVec3::ONE; 8];
    assert_eq!(Hexahedron::new(point).unwrap_err(), HexahedronError::SinglePoint);
    let mut collapsed_edge = unit_corners();
    collapsed_edge[1] = collapsed_edge[0];
    assert!(degenerate(&Hexahedron::new(collapsed_edge).expect_err("edge")));
    let mut nan = unit_corners();
    nan[5].y = f64::NAN;
    let e = Hexahedron::new(nan).expect_err("nan");
    assert!(matches!(e, HexahedronError::NonFiniteCorner { index: 5, .. }), "{e:?}");
    assert!(e.to_string().starts_with("corner 5 is not finite"), "{e}");
    let mut inf = unit_corners();
    inf[2].x = f64::INFINITY;
    assert!(matches!(Hexahedron::new(inf), Err(HexahedronError::NonFiniteCorner { index: 2, .. })));
    // Very thin but genuine slabs (a depth-1 image placed as a sheet) are fine.
    assert!(Hexahedron::new(unit_corners().map(|c| DVec3::new(c.x, c.y, 1e-6 * c.z))).is_ok());
}

/// Soundness: this box (found by a random search on a quarter grid, exact in binary) has `det J > 0`
/// at all eight corners and at the centre, yet `det J ≈ −0.28` on the edge from corner 4 to corner 5
/// (`y = 0, z = 1`, near `x = 0.4`). Along that edge `det J` is a quadratic in `x` whose middle Bernstein
/// coefficient is strongly negative while both ends are positive: the edge's frame (`J_y × J_z`)
/// turns over and back between the corners. A test that samples corners and centre accepts it; the
/// Bernstein test subdivides until a sub-box corner lands in the negative region, and refuses.
#[test]
fn fold_between_sample_points_is_caught() {
    let c = [
        [-0.75, 0.5, 0.5],
        [1.5, 0.75, 0.0],
        [-0.5, 1.5, 0.75],
        [0.5, 1.5, 0.25],
        [0.75, 0.75, 1.5],
        [0.5, -0.75, 0.25],
        [-0.5, 1.25, 1.0],
        [1.5, 1.5, 1.75],
    ]
    .map(DVec3::from_array);
    for i in 0..8 {
        let q = unit_corners()[i];
        assert!(det_direct(&c, q) > 0.05, "corner {i}");
    }
    assert!(det_direct(&c, DVec3::splat(0.5)) > 0.05, "centre");
    assert!(det_direct(&c, DVec3::new(0.4, 0.0, 1.0)) < -0.25);
    let e = Hexahedron::new(c).expect_err("folded between the sample points");
    assert!(matches!(e, HexahedronError::Folds { .. }), "{e:?}");
}

/// The box whose top face is twisted by almost 180° and scaled by 2 pinches near `z = 1/3`, where every
/// cross-section shrinks to almost nothing: `det J` stays positive but comes within ~10⁻⁷ of zero on a
/// plane that no dyadic subdivision ever puts a corner on. No proof of positivity exists at depth 10,
/// so the box is refused as too close to folding; at exactly 180° it is degenerate; at 179° it is fine.
#[test]
fn nearly_pinched_box_is_refused_as_too_close() {
    assert!(Hexahedron::new(twisted_scaled(179.0, 2.0)).is_ok());
    let e = Hexahedron::new(twisted_scaled(179.9, 2.0)).expect_err("pinched");
    assert!(matches!(e, HexahedronError::TooCloseToFolding { .. }), "{e:?}");
    assert!(Hexahedron::new(twisted_scaled(180.0, 2.0)).is_err());
}

// ---------------------------------------------------------------- inversion

proptest! {
    #[test]
    fn invert_round_trip(c in perturbed(), q in prop::array::uniform3(0.0f64..=1.0),
                         jitter in prop::array::uniform3(-0.05f64..0.05)) {
        let Ok(h) = Hexahedron::new(c) else { return Ok(()); };
        let q = DVec3::from_array(q);
        let p = h.world(q);
        let tol_q = 1e-9;
        for guess in [None, Some(q + DVec3::from_array(jitter))] {
            let Some(r) = h.invert(p, guess, tol_q) else {
                return Err(TestCaseError::fail(format!("no inverse for q = {q} ({guess:?})")));
            };
            prop_assert!((r - q).abs().max_element() < 1e-6 / h.size(), "{r} vs {q}");
            prop_assert!((r - q).abs().max_element() < 1e-9, "{r} vs {q}: worse than tol_q");
            prop_assert!((h.world(r) - p).length() < 1e-6 * h.size());
            prop_assert!(Hexahedron::contains_q(r));
        }
    }

    #[test]
    fn invert_of_outside_points_is_outside(c in perturbed(), q in prop::array::uniform3(-0.2f64..=1.2)) {
        let Ok(h) = Hexahedron::new(c) else { return Ok(()); };
        let q = DVec3::from_array(q);
        let p = h.world(q);
        // Whatever comes back must be a genuine preimage; and a point inside must be found inside.
        if let Some(r) = h.invert(p, None, 1e-10) {
            prop_assert!((h.world(r) - p).length() < 1e-8);
        }
        if Hexahedron::contains_q(q) {
            prop_assert!(h.invert(p, None, 1e-10).is_some_and(Hexahedron::contains_q));
        }
    }
}

#[test]
fn invert_affine_and_outside() {
    let h = hex(corners_of_affine(&skewed_matrix()));
    let q = DVec3::new(1.5, -0.25, 0.5);
    let r = h.invert(h.world(q), None, 1e-12).expect("affine inverse");
    assert!((r - q).length() < 1e-12);
    assert!(!Hexahedron::contains_q(r));
    assert!(h.invert(DVec3::new(f64::NAN, 0.0, 0.0), None, 1e-9).is_none());
    let t = hex(twisted(60.0));
    let q = DVec3::new(0.2, 0.9, 0.4);
    let r = t.invert(t.world(q), Some(DVec3::splat(0.5)), 1e-12).expect("twisted inverse");
    assert!((r - q).length() < 1e-10);
}

#[test]
fn contains_q_is_closed() {
    assert!(Hexahedron::contains_q(DVec3::ZERO));
    assert!(Hexahedron::contains_q(DVec3::ONE));
    assert!(Hexahedron::contains_q(DVec3::new(-1e-12, 0.5, 1.0 + 1e-12)));
    assert!(!Hexahedron::contains_q(DVec3::new(-1e-6, 0.5, 0.5)));
    assert!(!Hexahedron::contains_q(DVec3::new(0.5, f64::NAN, 0.5)));
}

// ---------------------------------------------------------------- segments

fn assert_seg(h: &Hexahedron, o: [f64; 3], d: [f64; 3], want: Option<(f64, f64)>) {
    let got = h.segment(DVec3::from_array(o), DVec3::from_array(d));
    match (got, want) {
        (Some((a, b)), Some((x, y))) => {
            assert!((a - x).abs() < 1e-9 && (b - y).abs() < 1e-9, "o {o:?} d {d:?}: {got:?} vs {want:?}")
        }
        (None, None) => {}
        _ => panic!("o {o:?} d {d:?}: {got:?} vs {want:?}"),
    }
}

#[test]
fn segment_special_rays_unit_cube() {
    let h = hex(unit_corners());
    type Case = ([f64; 3], [f64; 3], Option<(f64, f64)>);
    let cases: &[Case] = &[
        // Along an edge, both directions.
        ([-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], Some((1.0, 2.0))),
        ([0.0, 1.0, 3.0], [0.0, 0.0, -1.0], Some((2.0, 3.0))),
        ([1.0, 1.0, -2.0], [0.0, -0.0, 1.0], Some((2.0, 3.0))),
        // Through corners: the main diagonal, and one only touching corner (1,1,1).
        ([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], Some((1.0, 2.0))),
        ([2.0, 0.0, 1.0], [-1.0, 1.0, 0.0], Some((1.0, 1.0))),
        // In face planes (closed box: inside).
        ([-1.0, 0.5, 0.0], [1.0, 0.0, 0.0], Some((1.0, 2.0))),
        ([0.5, -1.0, 1.0], [0.0, 1.0, 0.0], Some((1.0, 2.0))),
        ([0.0, -1.0, -1.0], [0.0, 1.0, 1.0], Some((1.0, 2.0))),
        ([0.0, 2.0, 0.5], [-0.0, -1.0, 0.0], Some((1.0, 2.0))),
        // Parallel to faces with +0.0 and −0.0 components.
        ([-1.0, 0.3, 0.7], [1.0, 0.0, -0.0], Some((1.0, 2.0))),
        ([2.0, 0.3, 0.7], [-1.0, -0.0, 0.0], Some((1.0, 2.0))),
        ([0.5, 0.5, 5.0], [-0.0, -0.0, -1.0], Some((4.0, 5.0))),
        ([-1.0, 1.5, 0.5], [1.0, 0.0, 0.0], None),
        ([-1.0, 1.0 + 1e-6, 0.5], [1.0, -0.0, 0.0], None),
        ([-1.0, 0.5, 0.5], [-1.0, 0.0, 0.0], None),
        // Origin inside.
        ([0.5, 0.5, 0.5], [1.0, 0.0, 0.0], Some((0.0, 0.5))),
        ([0.25, 0.5, 0.5], [-1.0, -1.0, 0.0], Some((0.0, 0.25))),
        // Origin exactly on a face: going in, going out, and staying in the face.
        ([0.0, 0.5, 0.5], [1.0, 0.0, 0.0], Some((0.0, 1.0))),
        ([0.0, 0.5, 0.5], [-1.0, 0.0, 0.0], Some((0.0, 0.0))),
        ([0.0, 0.5, 0.5], [0.0, 1.0, 0.0], Some((0.0, 0.5))),
        // Origin on a corner and on an edge.
        ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0], Some((0.0, 1.0))),
        ([1.0, 0.5, 0.0], [0.0, 1.0, 0.0], Some((0.0, 0.5))),
    ];
    for &(o, d, want) in cases {
        assert_seg(&h, o, d, want);
    }
}

#[test]
fn segment_special_rays_affine_and_distorted() {
    let boxes = [corners_of_affine(&skewed_matrix()), frustum(), twisted(30.0), twisted(100.0)];
    for c in boxes {
        let h = hex(c);
        let check = |o: DVec3, d: DVec3, lo: f64, hi: f64, what: &str| {
            let s = h.segment(o, d);
            let Some((a, b)) = s else { panic!("{what}: miss") };
            assert!(a.is_finite() && b.is_finite() && 0.0 <= a && a <= b, "{what}: {s:?}");
            assert!(a <= lo + 1e-9 && b >= hi - 1e-9, "{what}: {s:?} does not cover [{lo}, {hi}]");
        };
        // Every edge, as a ray from one step before its start: [1, 2] is on the edge.
        for i in 0..8 {
            for a in 0..3 {
                let j = i | (1 << a);
                if j != i {
                    let (p, q) = (c[i], c[j]);
                    check(p - (q - p), q - p, 1.0, 2.0, "edge");
                    check(q + (q - p), p - q, 1.0, 2.0, "edge reversed");
                }
            }
        }
        // Through every corner from outside, aimed at the centre.
        for (i, &p) in c.iter().enumerate() {
            let d = h.world(DVec3::splat(0.5)) - p;
            let s = h.segment(p - d, d).unwrap_or_else(|| panic!("corner {i} missed"));
            assert!(s.0 <= 1.0 + 1e-9 && s.1 >= 1.0, "corner {i}: {s:?}");
        }
        // Along the middle ruling of every face (lies in the face, planar or not).
        for axis in 0..3 {
            for side in [0.0, 1.0] {
                let (ua, va) = ((axis + 1) % 3, (axis + 2) % 3);
                let mut q0 = DVec3::ZERO;
                q0[axis] = side;
                q0[ua] = 0.5;
                let mut q1 = q0;
                q1[va] = 1.0;
                let (p0, p1) = (h.world(q0), h.world(q1));
                check(p0 - (p1 - p0), p1 - p0, 1.0, 2.0, "ruling");
                // Origin in the face, looking along it.
                let s = h.segment(h.world(0.5 * (q0 + q1)), p1 - p0).expect("origin on a face");
                assert!(s.0 == 0.0 && s.1 >= 0.5 - 1e-9, "ruling from the face: {s:?}");
            }
        }
    }
}

fn ray() -> impl Strategy<Value = (DVec3, DVec3)> {
    (prop::array::uniform3(-3.0f64..3.0), prop::array::uniform3(-1.0f64..1.0))
        .prop_filter("direction", |(_, d)| DVec3::from_array(*d).length() > 1e-3)
        .prop_map(|(o, d)| (DVec3::from_array(o), DVec3::from_array(d).normalize()))
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]
    #[test]
    fn segment_matches_slab_for_parallelepipeds((o, d) in ray()) {
        for m in [DMat4::IDENTITY, skewed_matrix()] {
            let h = hex(corners_of_affine(&m));
            let got = h.segment(o, d);
            let want = slab(&m, o, d);
            match (got, want) {
                (Some((a, b)), Some((x, y))) => {
                    prop_assert!((a - x).abs() < 1e-9 * (1.0 + x) && (b - y).abs() < 1e-9 * (1.0 + y),
                        "{got:?} vs {want:?}");
                }
                (None, None) => {}
                // Grazing rays: either side may see a zero-length contact.
                (Some((a, b)), None) => prop_assert!(b - a < 1e-9, "{got:?} vs miss"),
                (None, Some((x, y))) => prop_assert!(y - x < 1e-9, "miss vs {want:?}"),
            }
        }
    }

    #[test]
    fn segment_axis_aligned_rays_never_nan(o in prop::array::uniform3(prop::sample::select(
            vec![-1.0, -0.0, 0.0, 0.25, 0.5, 1.0, 1.5])),
            d in prop::array::uniform3(prop::sample::select(vec![-1.0, -0.0, 0.0, 0.5, 1.0]))) {
        let h = hex(unit_corners());
        let (o, d) = (DVec3::from_array(o), DVec3::from_array(d));
        let got = h.segment(o, d);
        let want = if d == DVec3::ZERO { None } else { slab(&DMat4::IDENTITY, o, d) };
        if let Some((a, b)) = got {
            prop_assert!(a.is_finite() && b.is_finite() && 0.0 <= a && a <= b, "{got:?}");
        }
        if let Some((x, y)) = want {
            let (a, b) = got.ok_or_else(|| TestCaseError::fail(format!("miss, want {want:?}")))?;
            prop_assert!((a - x).abs() < 1e-12 && (b - y).abs() < 1e-12, "{got:?} vs {want:?}");
        } else if d != DVec3::ZERO {
            prop_assert!(got.is_none(), "{got:?} vs miss");
        }
    }

    /// Closed boxes never lose a point: a ray through any point of the box — a corner, an edge point, a
    /// face point or an interior point — has a segment covering every inside point near it, whatever
    /// its direction (rays grazing a corner or an edge, or lying in a face's tangent plane, included).
    /// The one thing allowed to go unreported is an isolated touch (the ray meets the box in that single
    /// point, a zero-length piece that SPEC §4.5 drops anyway): a tangent touch on a curved face is a
    /// double root, located only to about √ε.
    #[test]
    fn segment_covers_every_point(c in perturbed(), twist in 0.0f64..100.0,
                                  q in prop::array::uniform3(0.0f64..=1.0),
                                  snap in prop::array::uniform3(0usize..3),
                                  dir in prop::array::uniform3(-1.0f64..1.0),
                                  in_face in any::<bool>()) {
        let mut corners = twisted(twist);
        for (k, ck) in corners.iter_mut().enumerate() {
            *ck += 0.5 * (c[k] - unit_corners()[k]);
        }
        let Ok(h) = Hexahedron::new(corners) else { return Ok(()); };
        // Snap some coordinates to 0 or 1: none snapped = interior, 1 = face, 2 = edge, 3 = corner.
        let mut q = DVec3::from_array(q);
        for a in 0..3 {
            if snap[a] < 2 {
                q[a] = snap[a] as f64;
            }
        }
        let p = h.world(q);
        let mut d = DVec3::from_array(dir);
        if in_face {
            // In the tangent plane of the face q_a = const at p.
            if let Some(a) = (0..3).find(|&a| snap[a] < 2) {
                let j = h.jacobian(q);
                d = dir[0] * j.col((a + 1) % 3) + dir[1] * j.col((a + 2) % 3);
            }
        }
        prop_assume!(d.length() > 1e-3);
        let d = d.normalize();
        let o = p - 2.0 * d;
        // Strictly inside (tolerance 1e-14, not contains_q's 1e-9, at offsets of at least 1e-3), so that
        // the points of a ray grazing a curved face, outside by ~curvature·offset², do not count as inside.
        let strict = |q: DVec3| q.cmpge(DVec3::splat(-1e-14)).all() && q.cmple(DVec3::splat(1.0 + 1e-14)).all();
        let inside = |t: f64| h.invert(o + t * d, None, 1e-13).is_some_and(strict);
        let near: Vec<f64> =
            (-10..=10).filter(|&k| k != 0).map(|k| 2.0 + f64::from(k) * 1e-3).filter(|&t| inside(t)).collect();
        let seg = h.segment(o, d);
        if let Some((a, b)) = seg {
            prop_assert!(a.is_finite() && b.is_finite() && 0.0 <= a && a <= b, "{seg:?}");
        }
        if !near.is_empty() || snap.iter().all(|&s| s == 2) {
            let (a, b) = seg.ok_or_else(|| TestCaseError::fail(format!("miss through q = {q}")))?;
            prop_assert!(a <= 2.0 + 1e-9 && b >= 2.0 - 1e-9, "q = {q}: {seg:?} does not cover t = 2");
            for t in near {
                prop_assert!(a <= t + 1e-9 && b >= t - 1e-9, "q = {q}: {seg:?} does not cover t = {t}");
            }
        }
        // From the point itself (origin on the boundary, or inside): always inside at t = 0.
        let (a, b) = h.segment(p, d).ok_or_else(|| TestCaseError::fail(format!("miss from q = {q}")))?;
        prop_assert!(a == 0.0 && b >= 0.0);
    }

    /// Non-convex boxes: every sampled inside point lies within [t_near, t_far], the ends are on the
    /// box, and a miss has no inside point at all.
    ///
    /// "Inside" is the renderer's test, `contains_q`, which keeps box coordinates up to `CONTAINS_EPS`
    /// (10⁻⁹) outside [0,1]³ (boxes are closed). Beyond an exit through a face at a shallow angle that
    /// sliver reaches `CONTAINS_EPS / |dq/dt|` along the ray, more than any fixed slack in t (the saved
    /// regression case: the ray leaves the face y = 0 with dq_y/dt = −0.186, so t_far + 2.4·10⁻⁹ has
    /// q_y = −4.4·10⁻¹⁰ and is accepted, while q_y at t_far is −1.3·10⁻¹⁶: the end is exact). So a point
    /// beyond the bracket by more than 10⁻⁹ must be one of those: outside the exact box [0,1]³. A point
    /// genuinely in the box that the segment cut off still fails. The renderer places no sample outside
    /// [t_near, t_far], so the sliver never reaches an image.
    #[test]
    fn segment_brackets_inside_points(c in perturbed(), twist in 0.0f64..110.0,
                                      o in prop::array::uniform3(-1.5f64..2.5),
                                      target in prop::array::uniform3(0.0f64..1.0)) {
        let mut corners = twisted(twist);
        for (k, ck) in corners.iter_mut().enumerate() {
            *ck += 0.5 * (c[k] - unit_corners()[k]);
        }
        let Ok(h) = Hexahedron::new(corners) else { return Ok(()); };
        let o = DVec3::from_array(o);
        let d = (h.world(DVec3::from_array(target)) - o).normalize_or_zero();
        prop_assume!(d != DVec3::ZERO);
        let seg = h.segment(o, d);
        let q_at = |t: f64| h.invert(o + t * d, None, 1e-12);
        let n = 600;
        let t_max = 6.0;
        let mut any = false;
        for k in 0..=n {
            let t = t_max * k as f64 / n as f64;
            if let Some(q) = q_at(t).filter(|q| Hexahedron::contains_q(*q)) {
                any = true;
                let (a, b) = seg.ok_or_else(|| TestCaseError::fail(format!("miss, but t = {t} is inside")))?;
                // > 0: outside [0,1]³, accepted only by `contains_q`'s tolerance.
                let outside_by = (-q).max(q - DVec3::ONE).max_element();
                prop_assert!(a - 1e-9 <= t && t <= b + 1e-9 || outside_by > 0.0,
                    "t = {t} inside (q = {q:?}), outside {seg:?}");
            }
        }
        // The ray aims at an interior point, so it must hit.
        prop_assert!(any || seg.is_some());
        let (a, b) = seg.ok_or_else(|| TestCaseError::fail("miss".to_string()))?;
        prop_assert!(0.0 <= a && a <= b && b.is_finite());
        for t in [a, b] {
            let q = h.invert(o + t * d, None, 1e-12);
            prop_assert!(q.is_some_and(|q| (q.abs().min(DVec3::ONE - q).min_element()).abs() < 1e-7
                && Hexahedron::contains_q(q)) || (t == 0.0 && q.is_some_and(Hexahedron::contains_q)),
                "end t = {t} not on the boundary: {q:?}");
        }
    }
}
