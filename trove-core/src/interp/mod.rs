//! Interpolation functions ℐ (paper §2.3.4, SPEC §3.3 and §4.5).
//!
//! A sample point in volume coordinates becomes a stencil ([`Interp::locate`]): the voxels
//! read and how they are weighted. The stencil is built once per sample and applied to every
//! channel the object's mappings read, so a raw-RGBA object pays for one index computation,
//! not four. Each function is its own type implementing [`Interp`], so the sampler compiles
//! one loop per function; [`DynInterp`] chooses per sample and is the general path.

pub mod cubic;

use crate::dataset::{Dims, Voxels};

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
    /// The 20-term cubic field of eq. 4, fitted per cell (see `interp::cubic`).
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

/// One axis of a dataset with what every sample needs precomputed. The arithmetic is the
/// SPEC §3.3/§4.5 rule, written once: clamp to [0, n − 1], snap to the nearest integer (or
/// half-integer) within `SNAP_TOLERANCE · n`. Truncating casts stand in for `round` and
/// `floor` on these non-negative values: without SSE4.1 those are libm calls, and this runs
/// for every axis of every sample.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Axis {
    /// Voxels along the axis.
    n: u32,
    /// n − 1, the largest coordinate.
    last: f64,
    /// The snapping tolerance, SNAP_TOLERANCE · n.
    tol: f64,
    /// max(n − 2, 0): the largest lower cell corner.
    x0_max: f64,
}

impl Axis {
    fn new(n: u32) -> Axis {
        Axis { n, last: (n - 1) as f64, tol: SNAP_TOLERANCE * n as f64, x0_max: (n as f64 - 2.0).max(0.0) }
    }

    /// Trilinear's (and the cubic's) cell along this axis: lower corner x0 and offset
    /// t = u − x0 ∈ [0, 1].
    #[inline(always)]
    fn cell(&self, u: f64) -> (u32, f64) {
        let u = u.clamp(0.0, self.last);
        let r = floor_small(u + 0.5);
        let u = if (u - r).abs() <= self.tol { r } else { u };
        // `min` returns x0_max for a NaN u (whose t stays NaN, so the sample is dropped).
        let x0 = floor_small(u).min(self.x0_max);
        // SAFETY: x0 is an integer in [0, x0_max] ⊂ [0, i32::MAX], so it converts exactly.
        (unsafe { x0.to_int_unchecked::<u32>() }, u - x0)
    }

    /// The nearest voxel, the upper one at a tie.
    #[inline(always)]
    fn nearest(&self, u: f64) -> u32 {
        let u = u.clamp(0.0, self.last);
        let r = ((u / 0.5 + 0.5) as i64) as f64 * 0.5;
        let u = if (u - r).abs() <= self.tol { r } else { u };
        ((u + 0.5) as i64 as u32).min(self.n - 1)
    }
}

/// ⌊x⌋ for 0 ≤ x < 2⁵¹ (and NaN for NaN) in plain arithmetic: adding and subtracting 2⁵²
/// rounds x to the nearest integer, which is one too high when x is below it. The same value
/// as truncating casts, without their saturation checks and without a libm call where SSE4.1
/// is not assumed.
#[inline(always)]
pub(crate) fn floor_small(x: f64) -> f64 {
    const ROUND: f64 = (1u64 << 52) as f64;
    let r = (x + ROUND) - ROUND;
    r - f64::from(u8::from(r > x))
}

fn axes(dims: Dims) -> [Axis; 3] {
    dims.as_array().map(Axis::new)
}

/// An interpolation function bound to a dataset's dims: where a sample reads and how it
/// weights what it reads. The sampler is generic over it, so each function is compiled into
/// its own loop; [`DynInterp`] is the general instance that decides per sample, kept for
/// rare combinations and as the reference the specialised loops are tested against.
pub trait Interp: Copy + Send + Sync {
    /// What one sample reads: computed once per sample, applied to every channel read.
    type Stencil: Copy;

    /// The stencil at VC point `vc`. Coordinates are clamped to the dataset first (SPEC
    /// §3.3), so every index is valid.
    fn locate(&self, vc: [f64; 3]) -> Self::Stencil;

    /// The interpolated value of one channel. Non-finite when any voxel the stencil reads is
    /// non-finite, zero weights included (SPEC §4.5): 0·∞ is NaN, so plain arithmetic
    /// carries the poison through and the caller tests the result once.
    fn apply<V: Voxels>(&self, s: &Self::Stencil, voxels: &V) -> f64;

    /// The stencil's base voxel per axis (the nearest voxel, or the cell's lower corner),
    /// whose macrocell ([`crate::dataset::macrocell`]) the sample belongs to. Along a
    /// straight line of samples each component is monotone in the sample index.
    fn base(&self, s: &Self::Stencil) -> [u32; 3];

    /// How many macrocells around its base cell a stencil reaches (0, or 1 for the cubic).
    fn cell_radius(&self) -> u32;

    /// Along `axis`: the largest base index, and where base index b starts in raw VC minus
    /// b (0 for a cell corner, whose base is b over [b, b + 1); −½ for the nearest voxel,
    /// over [b − ½, b + ½)). Rounding rules aside (see [`Interp::span_tolerance`]), a sample
    /// based in macrocell c along the axis then has its coordinate in
    /// `[c·B + offset, (c + 1)·B + offset)`, unbounded beyond the first and last cell.
    fn base_grid(&self, axis: usize) -> (u32, f64);

    /// How far (in VC) rounding rules can move a coordinate across a span's bound along
    /// `axis`: the snapping tolerance of SPEC §4.5.
    fn span_tolerance(&self, axis: usize) -> f64;

    /// The values the interpolation can produce from voxels whose finite values lie in
    /// `[lo, hi]`, rounding included: `integer` says the values are integers below 2⁵³
    /// (bit, u8, u16, u32 channels), for which convex combinations in f64 stay in
    /// `[lo, hi]` exactly.
    fn value_bounds(&self, lo: f64, hi: f64, integer: bool) -> (f64, f64);
}

/// Slack for rounding in a few nested f64 operations over values up to `magnitude`.
fn rounding_slack(magnitude: f64, operations: f64) -> f64 {
    operations * f64::EPSILON * magnitude
}

/// The stencil of [`Nearest`]: one voxel.
#[derive(Clone, Copy, Debug)]
pub struct NearestAt {
    index: usize,
    base: [u32; 3],
}

/// `nearest` (SPEC §3.3): the nearest voxel; at an exact half-way point, the upper one.
#[derive(Clone, Copy, Debug)]
pub struct Nearest {
    dims: Dims,
    axes: [Axis; 3],
}

impl Nearest {
    /// Bound to a dataset of `dims`.
    pub fn new(dims: Dims) -> Nearest {
        Nearest { dims, axes: axes(dims) }
    }
}

impl Interp for Nearest {
    type Stencil = NearestAt;

    #[inline(always)]
    fn locate(&self, vc: [f64; 3]) -> NearestAt {
        let base = [self.axes[0].nearest(vc[0]), self.axes[1].nearest(vc[1]), self.axes[2].nearest(vc[2])];
        NearestAt { index: self.dims.index(base[0] as usize, base[1] as usize, base[2] as usize), base }
    }

    #[inline(always)]
    fn apply<V: Voxels>(&self, s: &NearestAt, voxels: &V) -> f64 {
        voxels.get_f64(s.index)
    }

    #[inline(always)]
    fn base(&self, s: &NearestAt) -> [u32; 3] {
        s.base
    }

    fn cell_radius(&self) -> u32 {
        0
    }

    fn base_grid(&self, axis: usize) -> (u32, f64) {
        (self.axes[axis].n - 1, -0.5)
    }

    fn span_tolerance(&self, axis: usize) -> f64 {
        self.axes[axis].tol
    }

    fn value_bounds(&self, lo: f64, hi: f64, _integer: bool) -> (f64, f64) {
        // The value is a voxel's, exactly.
        (lo, hi)
    }
}

/// The per-axis weight of [`Linear`]: h(t).
pub trait Weight: Copy + Send + Sync + std::fmt::Debug {
    /// h(t) for t ∈ [0, 1].
    fn h(&self, t: f64) -> f64;
    /// Bounds on h over t ∈ [0, 1], rounding included.
    fn range(&self) -> (f64, f64);
}

/// Trilinear's weight: h(t) = t.
#[derive(Clone, Copy, Debug)]
pub struct Identity;

impl Weight for Identity {
    #[inline(always)]
    fn h(&self, t: f64) -> f64 {
        t
    }

    fn range(&self) -> (f64, f64) {
        (0.0, 1.0)
    }
}

/// The nonlinear weight of eq. 3: h(t) = ω2·t² + ω1·t + ω0.
#[derive(Clone, Copy, Debug)]
pub struct Omega(pub [f64; 3]);

impl Weight for Omega {
    #[inline(always)]
    fn h(&self, t: f64) -> f64 {
        let omega = self.0;
        omega[2] * t * t + omega[1] * t + omega[0]
    }

    fn range(&self) -> (f64, f64) {
        // A quadratic on [0, 1]: its ends and its vertex bound it; widened for rounding.
        let [w0, w1, w2] = self.0;
        let vertex = if w2 != 0.0 { (-w1 / (2.0 * w2)).clamp(0.0, 1.0) } else { 0.0 };
        let values = [0.0, 1.0, vertex].map(|t| w2 * t * t + w1 * t + w0);
        let lo = values.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let slack = rounding_slack(w0.abs() + w1.abs() + w2.abs(), 8.0);
        (lo - slack, hi + slack)
    }
}

/// The stencil of [`Linear`]: the cell's lower corner and the per-axis weights.
#[derive(Clone, Copy, Debug)]
pub struct LinearAt {
    index: usize,
    base: [u32; 3],
    h: [f64; 3],
}

/// `trilinear` (W = [`Identity`]) and `nonlinear` (W = [`Omega`]), in eq. 3's form
/// v0 − h·(v0 − v1) per axis.
#[derive(Clone, Copy, Debug)]
pub struct Linear<W> {
    dims: Dims,
    axes: [Axis; 3],
    /// Index offsets of the upper corner along x, y, z (0 along a single-voxel axis, whose
    /// upper neighbour is clamped onto the voxel itself).
    offsets: [usize; 3],
    weight: W,
    /// How far h leaves [0, 1] over t ∈ [0, 1] (0 for trilinear): lerps then overshoot.
    h_excess: f64,
}

impl<W: Weight> Linear<W> {
    /// Bound to a dataset of `dims`.
    pub fn new(dims: Dims, weight: W) -> Linear<W> {
        let [nx, ny, nz] = dims.as_array().map(|n| n as usize);
        let offsets = [usize::from(nx > 1), if ny > 1 { nx } else { 0 }, if nz > 1 { nx * ny } else { 0 }];
        let (h_lo, h_hi) = weight.range();
        Linear { dims, axes: axes(dims), offsets, weight, h_excess: (-h_lo).max(h_hi - 1.0).max(0.0) }
    }
}

impl Linear<Identity> {
    /// Per axis, what [`Axis`]'s cell rule reads: the largest coordinate, the snapping
    /// tolerance and the largest lower corner; and the index offsets of the upper corner
    /// (for samplers that locate several samples at once by the same rule).
    pub(crate) fn rule(&self) -> ([[f64; 3]; 3], [usize; 3]) {
        (self.axes.map(|a| [a.last, a.tol, a.x0_max]), self.offsets)
    }

    /// The dataset's dims.
    pub(crate) fn dims(&self) -> Dims {
        self.dims
    }
}

impl<W: Weight> Interp for Linear<W> {
    type Stencil = LinearAt;

    #[inline(always)]
    fn locate(&self, vc: [f64; 3]) -> LinearAt {
        let (x, tx) = self.axes[0].cell(vc[0]);
        let (y, ty) = self.axes[1].cell(vc[1]);
        let (z, tz) = self.axes[2].cell(vc[2]);
        LinearAt {
            index: self.dims.index(x as usize, y as usize, z as usize),
            base: [x, y, z],
            h: [self.weight.h(tx), self.weight.h(ty), self.weight.h(tz)],
        }
    }

    #[inline(always)]
    fn apply<V: Voxels>(&self, s: &LinearAt, voxels: &V) -> f64 {
        let [ox, oy, oz] = self.offsets;
        let i = s.index;
        let lerp = |[v0, v1]: [f64; 2], h: f64| v0 - h * (v0 - v1);
        let h = s.h;
        let x00 = lerp(voxels.pair(i, ox), h[0]);
        let x10 = lerp(voxels.pair(i + oy, ox), h[0]);
        let x01 = lerp(voxels.pair(i + oz, ox), h[0]);
        let x11 = lerp(voxels.pair(i + oz + oy, ox), h[0]);
        lerp([lerp([x00, x10], h[1]), lerp([x01, x11], h[1])], h[2])
    }

    #[inline(always)]
    fn base(&self, s: &LinearAt) -> [u32; 3] {
        s.base
    }

    fn cell_radius(&self) -> u32 {
        0
    }

    fn base_grid(&self, axis: usize) -> (u32, f64) {
        (self.axes[axis].x0_max as u32, 0.0)
    }

    fn span_tolerance(&self, axis: usize) -> f64 {
        self.axes[axis].tol
    }

    fn value_bounds(&self, lo: f64, hi: f64, integer: bool) -> (f64, f64) {
        let s = self.h_excess;
        let magnitude = lo.abs().max(hi.abs());
        if s == 0.0 && integer {
            // Each lerp is a convex combination of two values in [lo, hi] whose difference
            // is exact and whose rounding cannot leave the interval (module tests).
            return (lo, hi);
        }
        // Each of the three nested lerps can overshoot its inputs' interval by s times its
        // width on each side, so the width grows by (1 + 2s) per level.
        let growth = (1.0 + 2.0 * s).powi(3);
        let overshoot = (hi - lo) * (growth - 1.0) / 2.0 + rounding_slack(magnitude, 32.0 * growth);
        (lo - overshoot, hi + overshoot)
    }
}

/// The stencil of [`Cubic`]: the cell's lower corner and offsets.
#[derive(Clone, Copy, Debug)]
pub struct CubicAt {
    x0: [u32; 3],
    t: [f64; 3],
}

/// `cubic` (SPEC §3.3): the fitted 20-term field of eq. 4 over the 32-point stencil of the
/// cell (see [`cubic`]).
#[derive(Clone, Copy, Debug)]
pub struct Cubic {
    dims: Dims,
    axes: [Axis; 3],
}

impl Cubic {
    /// Bound to a dataset of `dims`.
    pub fn new(dims: Dims) -> Cubic {
        Cubic { dims, axes: axes(dims) }
    }
}

impl Interp for Cubic {
    type Stencil = CubicAt;

    #[inline(always)]
    fn locate(&self, vc: [f64; 3]) -> CubicAt {
        let (x, tx) = self.axes[0].cell(vc[0]);
        let (y, ty) = self.axes[1].cell(vc[1]);
        let (z, tz) = self.axes[2].cell(vc[2]);
        CubicAt { x0: [x, y, z], t: [tx, ty, tz] }
    }

    #[inline]
    fn apply<V: Voxels>(&self, s: &CubicAt, voxels: &V) -> f64 {
        let n = self.dims.as_array();
        let at = |a: usize, off: i64| (s.x0[a] as i64 + off).clamp(0, n[a] as i64 - 1) as usize;
        let mut idx = [0usize; 32];
        for c in 0..8 {
            let corner = [c & 1, c >> 1 & 1, c >> 2 & 1];
            idx[c] = self.dims.index(at(0, corner[0] as i64), at(1, corner[1] as i64), at(2, corner[2] as i64));
            for a in 0..3 {
                let mut off = corner.map(|v| v as i64);
                off[a] = if corner[a] == 0 { -1 } else { 2 };
                idx[8 + 3 * c + a] = self.dims.index(at(0, off[0]), at(1, off[1]), at(2, off[2]));
            }
        }
        let w = cubic::weights(s.t);
        idx.iter().zip(&w).map(|(&i, &w)| w * voxels.get_f64(i)).sum()
    }

    #[inline(always)]
    fn base(&self, s: &CubicAt) -> [u32; 3] {
        s.x0
    }

    fn cell_radius(&self) -> u32 {
        1
    }

    fn base_grid(&self, axis: usize) -> (u32, f64) {
        (self.axes[axis].x0_max as u32, 0.0)
    }

    fn span_tolerance(&self, axis: usize) -> f64 {
        self.axes[axis].tol
    }

    fn value_bounds(&self, lo: f64, hi: f64, _integer: bool) -> (f64, f64) {
        // Σ wᵢvᵢ with Σ wᵢ = 1 lies within [lo − N·w, hi + N·w], N bounding the sum of the
        // negative weights over the cell; plus rounding of 32 products and of the weights.
        let negative = cubic::negative_weight_bound();
        let magnitude = lo.abs().max(hi.abs());
        let overshoot = (hi - lo) * negative + rounding_slack(magnitude, 64.0 * (1.0 + 2.0 * negative) + 1e4);
        (lo - overshoot, hi + overshoot)
    }
}

/// Interpolation for maps that read no channel (constant colour and opacity): no stencil.
#[derive(Clone, Copy, Debug)]
pub struct NoInterp;

impl Interp for NoInterp {
    type Stencil = ();

    #[inline(always)]
    fn locate(&self, _vc: [f64; 3]) {}

    #[inline(always)]
    fn apply<V: Voxels>(&self, _s: &(), _voxels: &V) -> f64 {
        0.0
    }

    fn base(&self, _s: &()) -> [u32; 3] {
        [0; 3]
    }

    fn cell_radius(&self) -> u32 {
        0
    }

    fn base_grid(&self, _axis: usize) -> (u32, f64) {
        (0, 0.0)
    }

    fn span_tolerance(&self, _axis: usize) -> f64 {
        0.0
    }

    fn value_bounds(&self, lo: f64, hi: f64, _integer: bool) -> (f64, f64) {
        (lo, hi)
    }
}

/// The stencil of [`DynInterp`].
#[derive(Clone, Copy, Debug)]
pub enum DynStencil {
    /// Of [`Nearest`].
    Nearest(NearestAt),
    /// Of [`Linear`].
    Linear(LinearAt),
    /// Of [`Cubic`].
    Cubic(CubicAt),
}

/// Any interpolation function, chosen per sample: the general instance of [`Interp`].
#[derive(Clone, Copy, Debug)]
pub enum DynInterp {
    /// `nearest`.
    Nearest(Nearest),
    /// `trilinear`.
    Trilinear(Linear<Identity>),
    /// `nonlinear`.
    Nonlinear(Linear<Omega>),
    /// `cubic`.
    Cubic(Cubic),
}

impl DynInterp {
    /// `interp` bound to a dataset of `dims`.
    pub fn new(interp: &Interpolation, dims: Dims) -> DynInterp {
        match *interp {
            Interpolation::Nearest => DynInterp::Nearest(Nearest::new(dims)),
            Interpolation::Trilinear => DynInterp::Trilinear(Linear::new(dims, Identity)),
            Interpolation::Nonlinear { omega } => DynInterp::Nonlinear(Linear::new(dims, Omega(omega))),
            Interpolation::Cubic => DynInterp::Cubic(Cubic::new(dims)),
        }
    }
}

/// Delegates a method to the bound function; stencils of another kind never reach it.
macro_rules! each {
    ($self:ident, $f:ident => $body:expr) => {
        match $self {
            DynInterp::Nearest($f) => $body,
            DynInterp::Trilinear($f) => $body,
            DynInterp::Nonlinear($f) => $body,
            DynInterp::Cubic($f) => $body,
        }
    };
}

impl Interp for DynInterp {
    type Stencil = DynStencil;

    #[inline]
    fn locate(&self, vc: [f64; 3]) -> DynStencil {
        match self {
            DynInterp::Nearest(f) => DynStencil::Nearest(f.locate(vc)),
            DynInterp::Trilinear(f) => DynStencil::Linear(f.locate(vc)),
            DynInterp::Nonlinear(f) => DynStencil::Linear(f.locate(vc)),
            DynInterp::Cubic(f) => DynStencil::Cubic(f.locate(vc)),
        }
    }

    #[inline]
    fn apply<V: Voxels>(&self, s: &DynStencil, voxels: &V) -> f64 {
        match (self, s) {
            (DynInterp::Nearest(f), DynStencil::Nearest(s)) => f.apply(s, voxels),
            (DynInterp::Trilinear(f), DynStencil::Linear(s)) => f.apply(s, voxels),
            (DynInterp::Nonlinear(f), DynStencil::Linear(s)) => f.apply(s, voxels),
            (DynInterp::Cubic(f), DynStencil::Cubic(s)) => f.apply(s, voxels),
            _ => unreachable!("a stencil is applied by the function that located it"),
        }
    }

    #[inline]
    fn base(&self, s: &DynStencil) -> [u32; 3] {
        match s {
            DynStencil::Nearest(s) => s.base,
            DynStencil::Linear(s) => s.base,
            DynStencil::Cubic(s) => s.x0,
        }
    }

    fn cell_radius(&self) -> u32 {
        each!(self, f => f.cell_radius())
    }

    fn base_grid(&self, axis: usize) -> (u32, f64) {
        each!(self, f => f.base_grid(axis))
    }

    fn span_tolerance(&self, axis: usize) -> f64 {
        each!(self, f => f.span_tolerance(axis))
    }

    fn value_bounds(&self, lo: f64, hi: f64, integer: bool) -> (f64, f64) {
        each!(self, f => f.value_bounds(lo, hi, integer))
    }
}

/// `interp`'s value of one channel at VC point `vc` of a dataset of `dims` (SPEC §3.3):
/// the general path, one sample at a time (the sampler's own loops are specialised; the
/// interpolation tests use this).
#[cfg(test)]
pub(crate) fn interpolate<V: Voxels>(interp: &Interpolation, dims: Dims, vc: [f64; 3], voxels: &V) -> f64 {
    let f = DynInterp::new(interp, dims);
    f.apply(&f.locate(vc), voxels)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floor_small_is_the_truncating_cast_it_replaces() {
        let mut values = vec![0.0, -0.0, 0.5, 1.0, 2.5, 3.5, 1e-300, 0.999_999_999_999, (1u64 << 31) as f64];
        for i in 0..2000 {
            let x = f64::from(i) * 0.37 + f64::from(i % 7) * 1e-10;
            values.extend([x, x.next_down(), x.next_up(), f64::from(i), f64::from(i).next_down(), x * 1e6]);
        }
        for x in values.into_iter().filter(|&x| x >= 0.0) {
            assert_eq!(floor_small(x), (x as i64) as f64, "{x}");
        }
        assert!(floor_small(f64::NAN).is_nan());
    }
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
            let v = interpolate(&Interpolation::Trilinear, dims, p, &r);
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
            let a = interpolate(&Interpolation::Trilinear, dims, p, &r);
            let b = interpolate(&nl, dims, p, &r);
            assert_eq!(a, b);
        }
    }

    #[test]
    fn nearest_picks_the_nearest_voxel_and_the_upper_one_at_ties() {
        let dims = Dims::new([4, 1, 1]).unwrap();
        let ch = field(dims, |x, _, _| x as f32 * 10.0);
        let r = ch.reader();
        let at = |u: f64| interpolate(&Interpolation::Nearest, dims, [u, 0.0, 0.0], &r);
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
        let at = |u: f64| interpolate(&Interpolation::Trilinear, dims, [u, -0.4, 0.4], &r);
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
            let v = interpolate(&Interpolation::Trilinear, dims, [0.0, 0.0, 0.0], &r);
            assert!(!v.is_finite(), "{bad}: {v}");
        }
    }
    fn cubic_poly(x: f64, y: f64, z: f64) -> f64 {
        0.5 + x - 2.0 * y + 0.25 * z + 0.1 * x * x - 0.3 * y * z + 0.05 * x * y * z + 0.02 * x * x * x
            - 0.04 * y * y * x
            + 0.03 * z * z * z
    }

    #[test]
    fn cubic_reproduces_a_cubic_polynomial_in_the_interior() {
        let dims = Dims::new([7, 6, 8]).unwrap();
        let ch = field(dims, |x, y, z| cubic_poly(x, y, z) as f32);
        let r = ch.reader();
        // Interior: the 32-point stencil of the cell needs x0 − 1 ≥ 0 and x0 + 2 ≤ n − 1.
        for &p in &[[1.25, 1.5, 2.75], [3.9, 2.01, 4.5], [2.0, 3.0, 5.0], [4.999, 1.0, 1.0]] {
            let v = interpolate(&Interpolation::Cubic, dims, p, &r);
            // The field is stored in f32, so compare against the f32-rounded data's scale.
            assert!((v - cubic_poly(p[0], p[1], p[2])).abs() < 1e-4, "{p:?}: {v} vs {}", cubic_poly(p[0], p[1], p[2]));
        }
        // Trilinear cannot: the same points are off by the curvature.
        let tri = interpolate(&Interpolation::Trilinear, dims, [1.25, 1.5, 2.75], &r);
        assert!((tri - cubic_poly(1.25, 1.5, 2.75)).abs() > 1e-3);
    }

    #[test]
    fn cubic_takes_the_cell_whose_lower_corner_is_the_integer() {
        // A field that is not cubic, so the two cells' fits differ on their shared face.
        let dims = Dims::new([6, 6, 6]).unwrap();
        let ch = field(dims, |x, y, z| ((x * 3.0 + y * 5.0 + z * 7.0) % 4.0) as f32 * (x - 2.5).abs() as f32);
        let r = ch.reader();
        let at = |u: f64| interpolate(&Interpolation::Cubic, dims, [u, 2.3, 1.7], &r);
        // The value at x = 3 from the cell [3, 4] (t = 0) versus from the cell [2, 3] (t = 1).
        let upper_cell = {
            let w = cubic::weights([0.0, 0.3, 0.7]);
            gather(&r, dims, [3, 2, 1], &w)
        };
        let lower_cell = {
            let w = cubic::weights([1.0, 0.3, 0.7]);
            gather(&r, dims, [2, 2, 1], &w)
        };
        assert!((upper_cell - lower_cell).abs() > 1e-6, "the test field must tell the cells apart");
        assert!((at(3.0) - upper_cell).abs() < 1e-12);
        // Rounding noise just below the integer still picks the upper cell (SPEC §4.5).
        assert!((at(3.0 - 1e-12) - upper_cell).abs() < 1e-9);
    }

    /// Σ w·v over the 32 fit points of the cell with lower corner `x0`, clamped to `dims`.
    fn gather(r: &crate::dataset::ChannelReader<'_>, dims: Dims, x0: [usize; 3], w: &[f64; 32]) -> f64 {
        let n = dims.as_array();
        (0..32)
            .map(|i| {
                let p = cubic::sample_point(i);
                let idx: [usize; 3] =
                    std::array::from_fn(|a| (x0[a] as i64 + p[a] as i64).clamp(0, n[a] as i64 - 1) as usize);
                w[i] * r.read(dims.index(idx[0], idx[1], idx[2])) as f64
            })
            .sum()
    }
}
