//! The slab test of one affine box against many rays of an image row at once.
//!
//! The intersection phase tests every ray of a row against every object that can meet the
//! row, and on a scene of many objects that was half of the coordinator's CPU per piece. The
//! rays of a row differ only in their direction, and an affine box's part of the test that
//! depends on the eye is worked out once ([`BoxOrigin`]), so the rest is the same few
//! products, divisions and comparisons for every ray: here they run over a span of columns
//! held component by component, in loops the compiler turns into vector instructions (four
//! or eight f64 lanes, by [`VectorWidth`]).
//!
//! The results are [`BoxOrigin::segment`]'s to the bit. Every lane does the same IEEE
//! operations in the same order as the one-ray test (no fused multiply-adds: Rust never
//! contracts, and these loops never ask for it), so the width changes the speed only, and a
//! farm whose machines differ renders the bytes local mode does. A ray that grazes a face
//! (a direction component zero, or small enough that the one-ray test must look closer)
//! is marked, and the caller gives it to [`BoxOrigin::segment`].

use glam::DVec3;

use super::camera::PixelRays;
use super::placement::BoxOrigin;
use super::Ray;
use crate::width::VectorWidth;

/// The unit directions of a row's rays, one array per component, indexed by column.
#[derive(Clone, Debug, Default)]
pub(crate) struct RowDirections {
    x: Vec<f64>,
    y: Vec<f64>,
    z: Vec<f64>,
}

impl RowDirections {
    /// The directions of columns `cols` of a row whose [`PixelRays::row`] is `row_part`:
    /// [`PixelRays::ray`]'s, to the bit (the sum, then `DVec3::normalize`'s square root of
    /// `(x² + y²) + z²`, reciprocal and three products). Indexed from `cols.start`.
    pub(crate) fn fill(&mut self, rays: &PixelRays, row_part: DVec3, cols: std::ops::Range<usize>) {
        let columns = &rays.columns()[cols];
        self.x.clear();
        self.y.clear();
        self.z.clear();
        for c in columns {
            let v = *c + row_part;
            let recip = 1.0 / ((v.x * v.x) + (v.y * v.y) + (v.z * v.z)).sqrt();
            self.x.push(v.x * recip);
            self.y.push(v.y * recip);
            self.z.push(v.z * recip);
        }
    }

    /// The direction of the `i`-th column filled.
    #[inline]
    pub(crate) fn dir(&self, i: usize) -> DVec3 {
        DVec3::new(self.x[i], self.y[i], self.z[i])
    }

    /// The ray of the `i`-th column filled, from `eye`.
    #[inline]
    pub(crate) fn ray(&self, eye: DVec3, i: usize) -> Ray {
        Ray { origin: eye, dir: self.dir(i) }
    }

    /// Columns filled.
    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        self.x.len()
    }
}

/// What [`BoxOrigin::cross_many`] found for one ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Crossing {
    /// The ray crosses the box over `(t_near, t_far)`, `t_far > t_near`.
    Segment(f64, f64),
    /// The ray misses the box, or meets it in a single point.
    Miss,
    /// The ray grazes a face: ask [`BoxOrigin::segment`].
    Graze,
}

/// One entry per ray: `near < far` for a segment, NaN for a graze, anything else a miss.
/// Kept as two plain arrays so the loop that fills them stores whole vectors.
#[derive(Clone, Debug, Default)]
pub(crate) struct Crossings {
    near: Vec<f64>,
    far: Vec<f64>,
}

impl Crossings {
    /// Ray `i`'s crossing.
    #[inline]
    pub(crate) fn get(&self, i: usize) -> Crossing {
        let (near, far) = (self.near[i], self.far[i]);
        if near < far {
            Crossing::Segment(near, far)
        } else if near.is_nan() {
            Crossing::Graze
        } else {
            Crossing::Miss
        }
    }

    /// Rays held.
    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        self.near.len()
    }
}

impl BoxOrigin {
    /// The crossing of every ray in `dirs[rays]` with the box, into `out` (indexed from
    /// `rays.start`): for rays that do not graze a face, the segment [`BoxOrigin::segment`]
    /// would give when it is longer than zero, to the bit.
    pub(crate) fn cross_many(
        &self,
        dirs: &RowDirections,
        rays: std::ops::Range<usize>,
        width: VectorWidth,
        out: &mut Crossings,
    ) {
        let n = rays.len();
        out.near.resize(n, 0.0);
        out.far.resize(n, 0.0);
        let (x, y, z) = (&dirs.x[rays.clone()], &dirs.y[rays.clone()], &dirs.z[rays]);
        let (near, far) = (&mut out.near[..n], &mut out.far[..n]);
        match width {
            #[cfg(target_arch = "x86_64")]
            VectorWidth::Avx512 => {
                // SAFETY: `VectorWidth::Avx512` is only chosen where the processor has AVX-512 F
                // ([`VectorWidth::detect`]).
                unsafe { cross_avx512(self, x, y, z, near, far) }
            }
            #[cfg(target_arch = "x86_64")]
            VectorWidth::Avx2 => {
                // SAFETY: as above, for AVX2.
                unsafe { cross_avx2(self, x, y, z, near, far) }
            }
            _ => cross_body(self, x, y, z, near, far),
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn cross_avx512(o: &BoxOrigin, x: &[f64], y: &[f64], z: &[f64], near: &mut [f64], far: &mut [f64]) {
    cross_body(o, x, y, z, near, far)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn cross_avx2(o: &BoxOrigin, x: &[f64], y: &[f64], z: &[f64], near: &mut [f64], far: &mut [f64]) {
    cross_body(o, x, y, z, near, far)
}

/// `slab_segment`'s path for a ray that crosses all three slabs, lane by lane without a
/// branch: the direction mapped as `DMat3::mul_vec3` maps it, the cheap parallel test whose
/// failure sends a ray to the careful path, then the crossing parameters with the same
/// `min`/`max` in the same order. A ray that `slab_segment` would find to cross with
/// `t_near < t_far` and a finite exit is exactly a lane stored with `near < far`.
#[inline(always)]
fn cross_body(o: &BoxOrigin, x: &[f64], y: &[f64], z: &[f64], near: &mut [f64], far: &mut [f64]) {
    let m = o.linear();
    let (m0, m1, m2) = (m.x_axis, m.y_axis, m.z_axis);
    let (org, slack, num) = (o.box_point(), o.slack(), o.o_len() + 2.0);
    let lo = [0.0 - org.x, 0.0 - org.y, 0.0 - org.z];
    let hi = [1.0 - org.x, 1.0 - org.y, 1.0 - org.z];
    let n = near.len();
    let (x, y, z, far) = (&x[..n], &y[..n], &z[..n], &mut far[..n]);
    for i in 0..n {
        let (dx, dy, dz) = (x[i], y[i], z[i]);
        let d = [
            ((m0.x * dx) + (m1.x * dy)) + (m2.x * dz),
            ((m0.y * dx) + (m1.y * dy)) + (m2.y * dz),
            ((m0.z * dx) + (m1.z * dy)) + (m2.z * dz),
        ];
        let ad = [d[0].abs(), d[1].abs(), d[2].abs()];
        let l1_slack = slack * ((ad[0] + ad[1]) + ad[2]) * (1.0 + 1e-6);
        let graze = (d[0] == 0.0)
            | (ad[0] * num <= l1_slack)
            | (d[1] == 0.0)
            | (ad[1] * num <= l1_slack)
            | (d[2] == 0.0)
            | (ad[2] * num <= l1_slack);
        let (mut t_near, mut t_far) = (0.0f64, f64::INFINITY);
        for a in 0..3 {
            let (ta, tb) = (lo[a] / d[a], hi[a] / d[a]);
            t_near = t_near.max(ta.min(tb));
            t_far = t_far.min(ta.max(tb));
        }
        let hit = (t_near < t_far) & t_far.is_finite();
        near[i] = if graze {
            f64::NAN
        } else if hit {
            t_near
        } else {
            f64::INFINITY
        };
        far[i] = if graze {
            f64::NAN
        } else if hit {
            t_far
        } else {
            f64::NEG_INFINITY
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Camera;
    use glam::DMat3;
    use proptest::prelude::*;

    /// Every width this processor runs.
    fn widths() -> Vec<VectorWidth> {
        [VectorWidth::Baseline, VectorWidth::Avx2, VectorWidth::Avx512]
            .into_iter()
            .filter(|&w| w <= VectorWidth::detect(VectorWidth::Avx512))
            .collect()
    }

    #[test]
    fn row_directions_are_the_pixel_rays_to_the_bit() {
        let camera = Camera::new(DVec3::new(0.3, 2.3, 7.0), DVec3::new(0.0, -0.3, 0.1), DVec3::Y, 37.0).unwrap();
        let (w, h) = (53, 31);
        let rays = camera.pixel_rays(w, h);
        let mut dirs = RowDirections::default();
        for row in [0, 7, h - 1] {
            let part = rays.row(row);
            dirs.fill(&rays, part, 5..40);
            assert_eq!(dirs.len(), 35);
            for col in 5..40u32 {
                let want = camera.ray(col, row, w, h);
                let got = dirs.ray(want.origin, col as usize - 5);
                assert_eq!(got.dir.to_array().map(f64::to_bits), want.dir.to_array().map(f64::to_bits));
            }
        }
    }

    /// A direction component: ordinary, tiny (nearly parallel to a face), or zero.
    fn component() -> impl Strategy<Value = f64> {
        prop_oneof![
            6 => -3.0f64..3.0,
            1 => -1e-9f64..1e-9,
            1 => -1e-14f64..1e-14,
            1 => Just(0.0),
            1 => Just(-0.0),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(3000))]
        #[test]
        fn many_rays_cross_as_one_ray_does_to_the_bit(
            m in prop::array::uniform9(-2.0f64..2.0),
            eye in prop::array::uniform3(-4.0f64..4.0),
            shift in prop::array::uniform3(-1.0f64..1.0),
            dirs in prop::collection::vec(prop::array::uniform3(component()), 1..40),
        ) {
            let linear = DMat3::from_cols_array(&m);
            let eye = DVec3::from_array(eye);
            // The box point of the eye: shifted so that some eyes sit inside the box.
            let origin = BoxOrigin::new(eye, linear.mul_vec3(eye) + DVec3::from_array(shift), linear);
            let mut row = RowDirections::default();
            for d in &dirs {
                row.x.push(d[0]);
                row.y.push(d[1]);
                row.z.push(d[2]);
            }
            for width in widths() {
                let mut out = Crossings::default();
                origin.cross_many(&row, 0..dirs.len(), width, &mut out);
                prop_assert_eq!(out.len(), dirs.len());
                for i in 0..dirs.len() {
                    let ray = row.ray(eye, i);
                    let want = origin.segment(&ray).filter(|(a, b)| b > a);
                    match (out.get(i), want) {
                        (Crossing::Graze, _) => {}
                        (Crossing::Segment(a, b), Some((wa, wb))) => {
                            prop_assert_eq!((a.to_bits(), b.to_bits()), (wa.to_bits(), wb.to_bits()), "{:?}", width);
                        }
                        (Crossing::Miss, None) => {}
                        (got, want) => prop_assert!(false, "ray {}: {:?} against {:?} ({:?})", i, got, want, width),
                    }
                }
            }
        }
    }

    #[test]
    fn grazing_rays_are_sent_to_the_careful_test() {
        let origin = BoxOrigin::new(DVec3::ZERO, DVec3::new(-1.0, 0.5, 0.5), DMat3::IDENTITY);
        let mut row = RowDirections::default();
        for d in [[1.0, 0.0, 0.0], [1.0, 1e-300, 0.2], [1.0, 0.1, 0.1], [-1.0, 0.1, 0.1]] {
            row.x.push(d[0]);
            row.y.push(d[1]);
            row.z.push(d[2]);
        }
        for width in widths() {
            let mut out = Crossings::default();
            origin.cross_many(&row, 0..4, width, &mut out);
            assert_eq!(out.get(0), Crossing::Graze);
            assert_eq!(out.get(1), Crossing::Graze);
            assert!(matches!(out.get(2), Crossing::Segment(a, b) if a == 1.0 && b == 2.0), "{:?}", out.get(2));
            assert_eq!(out.get(3), Crossing::Miss);
        }
    }
}
