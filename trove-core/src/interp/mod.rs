//! Interpolation functions ℐ (paper §2.3.4, SPEC §3.3 and §4.5).
//!
//! A sample point in volume coordinates becomes a [`Stencil`]: the voxels read and how they
//! are weighted. The stencil is built once per sample and applied to every channel the
//! object's mappings read, so a raw-RGBA object pays for one index computation, not four.

pub mod cubic;

use crate::dataset::{ChannelReader, Dims};

/// Which interpolation function an object uses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Interpolation {
    /// The nearest voxel; at an exact half-way point, the upper one.
    Nearest,
    /// Trilinear, in eq. 3's form v0 − t·(v0 − v1) per axis.
    Trilinear,
    /// Trilinear with each axis weight t replaced by h(t) = ω2·t² + ω1·t + ω0 (eq. 3).
    Nonlinear {
        /// [ω0, ω1, ω2].
        omega: [f64; 3],
    },
    /// The 20-term cubic field of eq. 4, fitted per cell (see [`cubic`]).
    Cubic,
}

impl Interpolation {
    /// The scene's name for the function.
    pub fn name(&self) -> &'static str {
        match self {
            Interpolation::Nearest => "nearest",
            Interpolation::Trilinear => "trilinear",
            Interpolation::Nonlinear { .. } => "nonlinear",
            Interpolation::Cubic => "cubic",
        }
    }
}

/// Relative tolerance within which a coordinate is taken as the integer (or, for
/// `nearest`, the half-integer) it is near (SPEC §4.5), so images do not depend on rounding
/// noise in the geometry.
pub const SNAP_TOLERANCE: f64 = 1e-9;

/// `u` snapped to the nearest multiple of `step` when within the tolerance, relative to an
/// axis of `n` voxels.
#[inline(always)]
fn snap(u: f64, n: u32, step: f64) -> f64 {
    let r = (u / step).round() * step;
    if (u - r).abs() <= SNAP_TOLERANCE * n as f64 {
        r
    } else {
        u
    }
}

/// One axis of trilinear's cell: lower index x0, upper index (clamped) and offset t.
#[inline(always)]
fn cell_axis(u: f64, n: u32) -> (usize, f64) {
    let last = (n - 1) as f64;
    let u = snap(u.clamp(0.0, last), n, 1.0);
    let x0 = u.floor().min((n as f64 - 2.0).max(0.0));
    (x0 as usize, u - x0)
}

/// The voxels a sample reads and their weights.
// Built on the stack once per sample: boxing the cubic variant would allocate per sample.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug)]
pub enum Stencil {
    /// One voxel.
    Nearest(usize),
    /// The 8 cell corners (index x + 2y + 4z) and the per-axis weights h.
    Linear {
        /// Linear voxel indices of the corners.
        idx: [usize; 8],
        /// Weight of the upper corner along x, y, z.
        h: [f64; 3],
    },
    /// The 32 points of the cubic fit (ordering in [`cubic`]) and their weights.
    Cubic {
        /// Linear voxel indices.
        idx: [usize; 32],
        /// Weights; Σ wᵢ vᵢ is the fitted field at the sample.
        w: [f64; 32],
    },
}

impl Stencil {
    /// The stencil of `interp` at VC point `vc` in a dataset of `dims`. Coordinates are
    /// clamped to the dataset first (SPEC §3.3), so every index is valid.
    #[inline]
    pub fn new(interp: &Interpolation, dims: Dims, vc: [f64; 3]) -> Stencil {
        let n = dims.as_array();
        match interp {
            Interpolation::Nearest => {
                let i: [usize; 3] = std::array::from_fn(|a| {
                    let last = (n[a] - 1) as f64;
                    let u = snap(vc[a].clamp(0.0, last), n[a], 0.5);
                    (u + 0.5).floor().clamp(0.0, last) as usize
                });
                Stencil::Nearest(dims.index(i[0], i[1], i[2]))
            }
            Interpolation::Trilinear | Interpolation::Nonlinear { .. } => {
                let mut lo = [0usize; 3];
                let mut hi = [0usize; 3];
                let mut h = [0.0; 3];
                for a in 0..3 {
                    let (x0, t) = cell_axis(vc[a], n[a]);
                    lo[a] = x0;
                    hi[a] = (x0 + 1).min(n[a] as usize - 1);
                    h[a] = match interp {
                        Interpolation::Nonlinear { omega } => omega[2] * t * t + omega[1] * t + omega[0],
                        _ => t,
                    };
                }
                let idx = std::array::from_fn(|c| {
                    let pick = |a: usize| if c >> a & 1 == 0 { lo[a] } else { hi[a] };
                    dims.index(pick(0), pick(1), pick(2))
                });
                Stencil::Linear { idx, h }
            }
            Interpolation::Cubic => {
                let mut x0 = [0usize; 3];
                let mut t = [0.0; 3];
                for a in 0..3 {
                    (x0[a], t[a]) = cell_axis(vc[a], n[a]);
                }
                let at = |a: usize, off: i64| (x0[a] as i64 + off).clamp(0, n[a] as i64 - 1) as usize;
                let mut idx = [0usize; 32];
                for c in 0..8 {
                    let corner = [c & 1, c >> 1 & 1, c >> 2 & 1];
                    idx[c] = dims.index(at(0, corner[0] as i64), at(1, corner[1] as i64), at(2, corner[2] as i64));
                    for a in 0..3 {
                        let mut off = corner.map(|v| v as i64);
                        off[a] = if corner[a] == 0 { -1 } else { 2 };
                        idx[8 + 3 * c + a] = dims.index(at(0, off[0]), at(1, off[1]), at(2, off[2]));
                    }
                }
                Stencil::Cubic { idx, w: cubic::weights(t) }
            }
        }
    }

    /// The interpolated value of one channel. Non-finite when any voxel the stencil reads is
    /// non-finite, zero weights included (SPEC §4.5): 0·∞ is NaN, so plain arithmetic
    /// carries the poison through and the caller tests the result once.
    #[inline]
    pub fn apply(&self, ch: &ChannelReader<'_>) -> f64 {
        match self {
            Stencil::Nearest(i) => ch.read(*i) as f64,
            Stencil::Linear { idx, h } => {
                let v = idx.map(|i| ch.read(i) as f64);
                let lerp = |v0: f64, v1: f64, h: f64| v0 - h * (v0 - v1);
                let x00 = lerp(v[0], v[1], h[0]);
                let x10 = lerp(v[2], v[3], h[0]);
                let x01 = lerp(v[4], v[5], h[0]);
                let x11 = lerp(v[6], v[7], h[0]);
                lerp(lerp(x00, x10, h[1]), lerp(x01, x11, h[1]), h[2])
            }
            Stencil::Cubic { idx, w } => idx.iter().zip(w).map(|(&i, &w)| w * ch.read(i) as f64).sum(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::Channel;

    fn field(dims: Dims, f: impl Fn(f64, f64, f64) -> f32) -> Channel {
        let [nx, ny, nz] = dims.as_array();
        let mut v = Vec::new();
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    v.push(f(i as f64, j as f64, k as f64));
                }
            }
        }
        Channel::from_f32(&v, dims).unwrap()
    }

    #[test]
    fn trilinear_reproduces_linear_fields_exactly() {
        let dims = Dims::new([5, 4, 3]).unwrap();
        let lin = |x: f64, y: f64, z: f64| 2.0 * x - 3.0 * y + 0.5 * z + 7.0;
        let ch = field(dims, |x, y, z| lin(x, y, z) as f32);
        let r = ch.reader();
        for &p in &[[0.25, 1.5, 0.75], [3.9, 2.999, 1.2], [4.0, 3.0, 2.0], [0.0, 0.0, 0.0], [2.5, 0.1, 1.9]] {
            let v = Stencil::new(&Interpolation::Trilinear, dims, p).apply(&r);
            assert!((v - lin(p[0], p[1], p[2])).abs() < 1e-12, "{p:?}: {v}");
        }
    }

    #[test]
    fn nonlinear_with_identity_omega_equals_trilinear() {
        let dims = Dims::new([4, 4, 4]).unwrap();
        let ch = field(dims, |x, y, z| ((x * 7.0 + y * 3.0 + z * z) % 5.0) as f32);
        let r = ch.reader();
        let nl = Interpolation::Nonlinear { omega: [0.0, 1.0, 0.0] };
        for &p in &[[0.3, 1.7, 2.2], [2.9, 0.01, 1.5]] {
            let a = Stencil::new(&Interpolation::Trilinear, dims, p).apply(&r);
            let b = Stencil::new(&nl, dims, p).apply(&r);
            assert_eq!(a, b);
        }
    }

    #[test]
    fn nearest_picks_the_nearest_voxel_and_the_upper_one_at_ties() {
        let dims = Dims::new([4, 1, 1]).unwrap();
        let ch = field(dims, |x, _, _| x as f32 * 10.0);
        let r = ch.reader();
        let at = |u: f64| Stencil::new(&Interpolation::Nearest, dims, [u, 0.0, 0.0]).apply(&r);
        assert_eq!(at(1.49), 10.0);
        assert_eq!(at(1.5), 20.0);
        // Rounding noise below the tie is still the tie (SPEC §4.5).
        assert_eq!(at(1.5 - 1e-12), 20.0);
        assert_eq!(at(-3.0), 0.0);
        assert_eq!(at(9.0), 30.0);
    }

    #[test]
    fn trilinear_clamps_at_borders_and_handles_single_voxel_axes() {
        let dims = Dims::new([3, 1, 1]).unwrap();
        let ch = field(dims, |x, _, _| [5.0, 7.0, 11.0][x as usize]);
        let r = ch.reader();
        let at = |u: f64| Stencil::new(&Interpolation::Trilinear, dims, [u, -0.4, 0.4]).apply(&r);
        assert_eq!(at(-0.5), 5.0);
        assert_eq!(at(2.0), 11.0);
        assert_eq!(at(2.5), 11.0);
        assert_eq!(at(1.5), 9.0);
    }

    #[test]
    fn a_non_finite_voxel_poisons_the_sample_even_with_zero_weight() {
        let dims = Dims::new([2, 1, 1]).unwrap();
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let ch = field(dims, |x, _, _| if x == 1.0 { bad } else { 3.0 });
            let r = ch.reader();
            let v = Stencil::new(&Interpolation::Trilinear, dims, [0.0, 0.0, 0.0]).apply(&r);
            assert!(!v.is_finite(), "{bad}: {v}");
        }
    }
}
