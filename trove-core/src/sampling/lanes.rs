//! The samples of a group ([`super::kernel`]) in AVX2 registers, four to a register, for
//! the commonest combination: trilinear over u8 or little-endian u16 voxels, with piecewise
//! (LUT or ramp) colour and opacity merged into one map of at most [`SMALL_MAP`] break
//! points — the CT head, the synthetic volume and most example scenes. Groups are two
//! registers wide, so that the two halves' chains of dependent steps overlap.
//!
//! It computes what the generic loop computes for a group — positions, cells with SPEC §4.5
//! snapping, the eight voxels, the seven lerps, the segment and the classification —
//! operation by operation in the same order, and x86's `min`/`max` get the operand order
//! that makes NaN and signed zeros come out as Rust's `clamp` and `min` do. Rust never fuses
//! a multiply and an add, so every lane is the scalar sample bit for bit, and images do not
//! depend on which path ran (tests compare the two). Without AVX2, or on other targets, the
//! generic loop runs.

// Elsewhere no `Trilinear4` is ever made, and what serves the AVX2 bodies goes unused.
#![cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]

use std::cmp::Ordering;

use crate::dataset::{U16LeVoxels, U8Voxels, Voxels};
use crate::geometry::LineSamples;
use crate::interp::{Identity, Linear};
use crate::mapping::{JointPiecewise, SMALL_MAP};

/// Where the L samples of a group are: their cells' lower corners and weights.
pub(super) struct Located<const L: usize> {
    /// Lower corner per axis, per lane.
    base: [[u32; L]; 3],
    /// Linear index of each lane's lower corner.
    index: [i32; L],
    /// Weight (offset in the cell) per axis, per lane.
    h: [[f64; L]; 3],
}

impl<const L: usize> Located<L> {
    /// Lane `l`'s lower corner: the base voxel [`crate::interp::Interp::base`] gives.
    #[inline(always)]
    pub(super) fn base(&self, l: usize) -> [u32; 3] {
        [self.base[0][l], self.base[1][l], self.base[2][l]]
    }
}

/// One object's trilinear loop over u8 or u16 voxels with a small joint piecewise map, in
/// AVX2; exists only where the processor has AVX2.
pub(super) struct Trilinear4<'a> {
    voxels: Stored<'a>,
    /// Per axis: largest coordinate, snapping tolerance, largest lower corner.
    rule: [[f64; 3]; 3],
    /// Index offsets of the upper corner along x, y, z.
    offsets: [i32; 3],
    /// Voxels along x and y.
    nx: i32,
    ny: i32,
    /// The largest lower-corner index whose four rows a gather reads (four bytes from each
    /// row's corner) without reaching past the channel's end.
    safe: i32,
    breaks: Vec<f64>,

    /// Per joint segment, field by field ([`JointPiecewise::tables`]).
    tables: [Vec<f64>; 12],
    /// The f32 forms [`super::packet`] casts with, where the processor has AVX-512 F, DQ
    /// and VL and the map's numbers are finite in f32.
    packed: Option<Box<Packed>>,
}

/// What the packet loop ([`super::packet`]) reads, in f32: sixteen lanes to a register
/// halve the instructions per sample. Positions, voxels and classification then differ
/// from the f64 loops by rounding only (about 1e-7 relatively); the one place where that
/// could matter more is a break point where the map jumps (a LUT bound): a value within
/// rounding of one takes its segment from the f64 value instead ([`Packed::jumps`]).
pub(super) struct Packed {
    /// Per axis: largest coordinate and largest lower corner.
    pub rule: [[f32; 2]; 3],
    /// Whether the dataset has at most 2²⁴ voxels, so that voxel and macrocell indices
    /// are exact in f32 (else they are computed in i32).
    pub small: bool,
    /// The break points, rounded to f32.
    pub breaks: Vec<f32>,
    /// Per joint segment ([`Packed::REFERENCE`] and the others): a value in it, and the
    /// opacity and each colour channel there and their slopes, so that one subtraction
    /// serves all four (each is linear over a joint segment). Padded to 32 segments (at
    /// most [`SMALL_MAP`] + 1 are used): the two registers of a two-register permute.
    pub tables: Box<[[f32; 32]; 9]>,
    /// The break points at which the map jumps (LUT bounds): a value whose f32 and f64
    /// forms could lie on either side of one must be classified from the f64 form.
    pub jumps: Vec<f32>,
    /// [`Packed::slack`] for a piece is `slack_per_unit · Σ (|vc0| + |δ|) + slack_fixed`:
    /// the parts that depend on the object only, worked out once.
    slack_per_unit: f64,
    slack_fixed: f64,
}

impl Packed {
    /// Fields of [`Packed::tables`]: the reference value, opacity and its slope there, the
    /// colour's three channels there and their three slopes.
    pub const REFERENCE: usize = 0;
    pub const OPACITY: usize = 1;
    pub const OPACITY_SLOPE: usize = 2;
    pub const COLOUR: usize = 3;
    pub const COLOUR_SLOPE: usize = 6;

    /// `None` where a number of the map does not fit f32, or could overflow it.
    fn new(
        rule: &[[f64; 3]; 3],
        voxels: u64,
        breaks: &[f64],
        tables: &[Vec<f64>; 12],
        range: [f64; 2],
    ) -> Option<Packed> {
        // Output 0 is the opacity (fields 0–3), 1–3 the colour's channels (fields 4–11).
        let parts = |f: usize, s: usize| -> [f64; 4] {
            let (x0, inv_w) = if f == 0 { (tables[0][s], tables[1][s]) } else { (tables[4][s], tables[5][s]) };
            let (y0, dy) = if f == 0 { (tables[2][s], tables[3][s]) } else { (tables[5 + f][s], tables[8 + f][s]) };
            [x0, inv_w, y0, dy]
        };
        let eval = |f: usize, s: usize, v: f64| -> f64 {
            let [x0, inv_w, y0, dy] = parts(f, s);
            y0 + ((v - x0) * inv_w) * dy
        };
        let jumps: Vec<f32> = breaks
            .iter()
            .enumerate()
            .filter(|&(i, &b)| {
                // A NaN difference counts as a jump.
                (0..4).any(|f| (eval(f, i, b) - eval(f, i + 1, b)).abs().partial_cmp(&JUMP) != Some(Ordering::Less))
            })
            .map(|(_, &b)| b as f32)
            .collect();
        let magnitude = range[0].abs().max(range[1].abs());
        let mut packed = Box::new([[0.0f32; 32]; 9]);
        for s in 0..breaks.len() + 1 {
            // Segment s holds the values with s break points ≤ them: its lower break, or the
            // first break for the segment below all of them.
            let reference = breaks.get(s.max(1) - 1).copied().unwrap_or(0.0);
            let mut fields = [reference, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
            for f in 0..4 {
                let [_, inv_w, _, dy] = parts(f, s);
                let (at, slope) = (eval(f, s, reference), inv_w * dy);
                let (value, slope_field) = if f == 0 {
                    (Packed::OPACITY, Packed::OPACITY_SLOPE)
                } else {
                    (Packed::COLOUR + f - 1, Packed::COLOUR_SLOPE + f - 1)
                };
                fields[value] = at;
                fields[slope_field] = slope;
                // The largest |v − reference| times the slope, plus the value there, must
                // stay far inside f32's range.
                let largest = (magnitude + reference.abs()) * slope.abs() + at.abs();
                if largest.partial_cmp(&1e30) != Some(Ordering::Less) {
                    return None;
                }
            }
            for (table, x) in packed.iter_mut().zip(fields) {
                table[s] = x as f32;
            }
        }
        if breaks.len() >= 32 || breaks.iter().any(|&b| !(b as f32).is_finite()) {
            return None;
        }
        // What bounds a sample's f32 value's distance from its f64 value ([`Packed::slack`]):
        // how far the channel's values spread (its range, or its type's), their largest
        // magnitude, the snapping tolerances of the f64 loops, and the largest jump.
        let spread = range[1] - range[0];
        let tolerances: f64 = rule.iter().map(|r| r[1]).sum();
        let largest_jump = jumps.iter().fold(0.0f64, |m, &j| m.max(f64::from(j).abs()));
        Some(Packed {
            rule: rule.map(|[last, _, x0_max]| [last as f32, x0_max as f32]),
            small: voxels <= 1 << 24,
            breaks: breaks.iter().map(|&b| b as f32).collect(),
            tables: packed,
            slack_per_unit: spread * 8.0 * EPS32,
            slack_fixed: spread * 2.0 * tolerances + 8.0 * EPS32 * (magnitude + largest_jump),
            jumps,
        })
    }

    /// How far the f32 value of a sample of `line` can be from its f64 value: its position
    /// is off the f64 one by a few f32 roundings of its coordinates (and either may snap),
    /// the trilinear value moves by at most the channel's spread per unit of position, and
    /// the f32 lerps round; plus the rounding of the jumps to f32.
    pub fn slack(&self, line: &LineSamples) -> f32 {
        let (start, delta) = (line.start(), line.delta());
        let extent: f64 = (0..3).map(|a| start[a].abs() + delta[a].abs()).sum();
        ((self.slack_per_unit * extent + self.slack_fixed) * 1.01) as f32
    }
}

/// f32's machine epsilon, as f64.
pub(super) const EPS32: f64 = f32::EPSILON as f64;

/// A map whose sides of a break point differ by more than this jumps there.
const JUMP: f64 = 1e-9;

impl<'a> Trilinear4<'a> {
    /// The loop for `interp` over `voxels` with `maps`, where the processor has AVX2, the
    /// map at most [`SMALL_MAP`] break points and the dataset fewer than 2³⁰ voxels (so
    /// indices and their neighbours' fit in i32 lanes).
    ///
    /// `range` is the channel's range of values where it is known (else its type's).
    pub(super) fn new(
        interp: &Linear<Identity>,
        voxels: Stored<'a>,
        maps: &JointPiecewise,
        range: Option<[f64; 2]>,
    ) -> Option<Self> {
        if !has_avx2() {
            return None;
        }
        let dims = interp.dims();
        let (breaks, tables) = maps.tables();
        if dims.voxel_count() >= 1 << 30 || breaks.len() > SMALL_MAP {
            return None;
        }
        let (rule, offsets) = interp.rule();
        let [nx, ny, _] = dims.as_array();
        let width = if voxels.is_wide() { 2 } else { 1 };
        let reach = (voxels.bytes().len() as i64 - 4).div_euclid(width) - (offsets[1] + offsets[2]) as i64;
        Some(Trilinear4 {
            voxels,
            rule,
            offsets: offsets.map(|o| o as i32),
            nx: nx as i32,
            ny: ny as i32,
            safe: reach.clamp(-1, i32::MAX as i64) as i32,
            breaks: breaks.to_vec(),
            packed: has_avx512()
                .then(|| {
                    let type_range = [0.0, if voxels.is_wide() { f64::from(u16::MAX) } else { f64::from(u8::MAX) }];
                    Packed::new(&rule, dims.voxel_count(), breaks, &tables, range.unwrap_or(type_range))
                })
                .flatten()
                .map(Box::new),
            tables,
        })
    }

    /// What the sixteen-lane loop of [`super::packet`] needs, where the processor has it.
    pub(super) fn packed(&self) -> Option<&Packed> {
        self.packed.as_deref()
    }

    /// Voxels along x and y.
    pub(super) fn nx_ny(&self) -> (u32, u32) {
        (self.nx as u32, self.ny as u32)
    }

    /// The map's break points (f64), which the f32 lanes count themselves near a jump.
    pub(super) fn breaks(&self) -> &[f64] {
        &self.breaks
    }

    /// Samples k, k + 1, … of `line` located (lanes from `m` on repeat sample k + m − 1).
    #[inline(always)]
    pub(super) fn locate<const L: usize>(&self, line: &LineSamples, k: u64, m: usize) -> Located<L> {
        // SAFETY: a `Trilinear4` exists only where the processor has AVX2 (`new`).
        #[cfg(target_arch = "x86_64")]
        unsafe {
            self.locate_avx2(line, k, m)
        }
        #[cfg(not(target_arch = "x86_64"))]
        unreachable!("no Trilinear4 is made without AVX2")
    }

    /// Each lane's opacity and colour, (0, black) where it contributes nothing.
    #[inline(always)]
    pub(super) fn classify<const L: usize>(&self, at: &Located<L>) -> [(f64, [f64; 3]); L] {
        // SAFETY: as in `locate`.
        #[cfg(target_arch = "x86_64")]
        unsafe {
            self.classify_avx2(at)
        }
        #[cfg(not(target_arch = "x86_64"))]
        unreachable!("no Trilinear4 is made without AVX2")
    }
}

/// The voxel channels the AVX2 loop reads.
#[derive(Clone, Copy, Debug)]
pub(super) enum Stored<'a> {
    U8(U8Voxels<'a>),
    U16(U16LeVoxels<'a>),
}

impl<'a> Stored<'a> {
    fn bytes(&self) -> &'a [u8] {
        match self {
            Stored::U8(v) => v.bytes(),
            Stored::U16(v) => v.bytes(),
        }
    }

    /// Two bytes per voxel.
    fn is_wide(&self) -> bool {
        matches!(self, Stored::U16(_))
    }

    /// Voxels `i` and `i + dx` ([`Voxels::pair`]).
    #[inline]
    pub(super) fn pair(&self, i: usize, dx: usize) -> [f64; 2] {
        match self {
            Stored::U8(v) => v.pair(i, dx),
            Stored::U16(v) => v.pair(i, dx),
        }
    }
}

fn has_avx512() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx512f")
            && std::is_x86_feature_detected!("avx512dq")
            && std::is_x86_feature_detected!("avx512vl")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    //! The AVX2 bodies. Helpers carry the target feature too, so that they and the
    //! intrinsics inline into the two entry points; no closures, which would not.

    use std::arch::x86_64::*;

    use super::{Located, Trilinear4};
    use crate::geometry::LineSamples;

    /// ⌊x⌋ for 0 ≤ x < 2⁵¹, as [`crate::interp::floor_small`] computes it.
    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn floor(x: __m256d) -> __m256d {
        let round = _mm256_set1_pd((1u64 << 52) as f64);
        let r = _mm256_sub_pd(_mm256_add_pd(x, round), round);
        _mm256_sub_pd(r, _mm256_and_pd(_mm256_cmp_pd::<_CMP_GT_OQ>(r, x), _mm256_set1_pd(1.0)))
    }

    /// |x| (clearing the sign bit, as `f64::abs`).
    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn abs(x: __m256d) -> __m256d {
        _mm256_andnot_pd(_mm256_set1_pd(-0.0), x)
    }

    /// v0 − h·(v0 − v1), the lerp of `Linear::apply`.
    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn lerp(v0: __m256d, v1: __m256d, h: __m256d) -> __m256d {
        _mm256_sub_pd(v0, _mm256_mul_pd(h, _mm256_sub_pd(v0, v1)))
    }

    /// `x.clamp(0.0, 1.0)` for non-NaN x: `max(0, x)` keeps x on ties (−0 stays −0), and
    /// `min(1, ·)` likewise.
    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn clamp01(x: __m256d) -> __m256d {
        _mm256_min_pd(_mm256_set1_pd(1.0), _mm256_max_pd(_mm256_setzero_pd(), x))
    }

    /// `table[segment]` per lane.
    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn gather(table: &[f64], segment: __m256i) -> __m256d {
        _mm256_i64gather_pd::<8>(table.as_ptr(), segment)
    }

    impl Trilinear4<'_> {
        #[inline]
        #[target_feature(enable = "avx2")]
        pub(super) unsafe fn locate_avx2<const L: usize>(&self, line: &LineSamples, k: u64, m: usize) -> Located<L> {
            let (vc0, delta, inv_n) = line.parts();
            let last = (m - 1) as u64;
            // `LineSamples::point`: vc0 + δ·((k + ½)·(1/n)), sample indices exact in f64.
            const { assert!(L.is_multiple_of(4), "lanes come in AVX registers of four") };
            let mut s = [0.0; L];
            for (l, s) in s.iter_mut().enumerate() {
                *s = ((k + (l as u64).min(last)) as f64 + 0.5) * inv_n;
            }
            let mut at = Located { base: [[0; L]; 3], index: [0; L], h: [[0.0; L]; 3] };
            for q in (0..L).step_by(4) {
                let s = _mm256_loadu_pd(s.as_ptr().add(q));
                let mut u = [s; 3];
                for (a, u) in u.iter_mut().enumerate() {
                    *u = _mm256_add_pd(_mm256_set1_pd(vc0[a]), _mm256_mul_pd(_mm256_set1_pd(delta[a]), s));
                }
                let (x0, h) = self.cells(u);
                for a in 0..3 {
                    _mm256_storeu_pd(at.h[a].as_mut_ptr().add(q), h[a]);
                    _mm_storeu_si128(at.base[a].as_mut_ptr().add(q).cast(), _mm256_cvttpd_epi32(x0[a]));
                }
                _mm_storeu_si128(at.index.as_mut_ptr().add(q).cast(), self.index(x0));
            }
            at
        }

        #[inline]
        #[target_feature(enable = "avx2")]
        pub(super) unsafe fn classify_avx2<const L: usize>(&self, at: &Located<L>) -> [(f64, [f64; 3]); L] {
            let mut o = [0.0; L];
            let mut rgb = [[0.0; L]; 3];
            for q in (0..L).step_by(4) {
                let mut h = [_mm256_setzero_pd(); 3];
                for (h, w) in h.iter_mut().zip(&at.h) {
                    *h = _mm256_loadu_pd(w.as_ptr().add(q));
                }
                let lanes = at.index[q..q + 4].try_into().expect("four lanes");
                let (opacity, colour) = self.map(self.trilinear(lanes, h));
                _mm256_storeu_pd(o.as_mut_ptr().add(q), opacity);
                for (out, &c) in rgb.iter_mut().zip(&colour) {
                    _mm256_storeu_pd(out.as_mut_ptr().add(q), c);
                }
            }
            let mut out = [(0.0, [0.0; 3]); L];
            for (l, out) in out.iter_mut().enumerate() {
                *out = (o[l], [rgb[0][l], rgb[1][l], rgb[2][l]]);
            }
            out
        }

        /// Per axis, the lower corners x0 (as f64) and weights of four positions `u`, as
        /// `Axis::cell` computes them: clamp to [0, n − 1] (NaN stays NaN), snap, floor, cap.
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn cells(&self, u: [__m256d; 3]) -> ([__m256d; 3], [__m256d; 3]) {
            let mut x0 = [_mm256_setzero_pd(); 3];
            let mut h = [_mm256_setzero_pd(); 3];
            for a in 0..3 {
                let [last, tol, x0_max] = self.rule[a];
                let u = _mm256_min_pd(_mm256_set1_pd(last), _mm256_max_pd(_mm256_setzero_pd(), u[a]));
                let r = floor(_mm256_add_pd(u, _mm256_set1_pd(0.5)));
                let near = _mm256_cmp_pd::<_CMP_LE_OQ>(abs(_mm256_sub_pd(u, r)), _mm256_set1_pd(tol));
                let u = _mm256_blendv_pd(u, r, near);
                // min(x0, x0_max) gives x0_max for a NaN x0, as `f64::min` does.
                x0[a] = _mm256_min_pd(floor(u), _mm256_set1_pd(x0_max));
                h[a] = _mm256_sub_pd(u, x0[a]);
            }
            (x0, h)
        }

        /// x + nx·(y + ny·z) of four lower corners, below 2³⁰: exact in f64, whose
        /// multiplications are quicker than i32 ones.
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn index(&self, x0: [__m256d; 3]) -> __m128i {
            let yz = _mm256_add_pd(x0[1], _mm256_mul_pd(_mm256_set1_pd(self.ny as f64), x0[2]));
            _mm256_cvttpd_epi32(_mm256_add_pd(x0[0], _mm256_mul_pd(_mm256_set1_pd(self.nx as f64), yz)))
        }

        /// The opacity and colour of four values, (0, black) where a value contributes
        /// nothing, as `JointPiecewise::classify_or_clear` computes them.
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn map(&self, v: __m256d) -> (__m256d, [__m256d; 3]) {
            // The segment: how many break points are ≤ v (a NaN counts none).
            let mut segment = _mm256_setzero_si256();
            for &b in &self.breaks {
                let le = _mm256_castpd_si256(_mm256_cmp_pd::<_CMP_LE_OQ>(_mm256_set1_pd(b), v));
                segment = _mm256_sub_epi64(segment, le);
            }
            let f = &self.tables;
            // `Segment::eval`: y0 + ((v − x0)·(1/w))·dy.
            let t = _mm256_mul_pd(_mm256_sub_pd(v, gather(&f[0], segment)), gather(&f[1], segment));
            let opacity = _mm256_add_pd(gather(&f[2], segment), _mm256_mul_pd(t, gather(&f[3], segment)));
            let t = _mm256_mul_pd(_mm256_sub_pd(v, gather(&f[4], segment)), gather(&f[5], segment));
            let mut colour = [_mm256_setzero_pd(); 3];
            for (c, colour) in colour.iter_mut().enumerate() {
                *colour = _mm256_add_pd(gather(&f[6 + c], segment), _mm256_mul_pd(t, gather(&f[9 + c], segment)));
            }
            // Finite positive opacity, finite colour.
            let infinity = _mm256_set1_pd(f64::INFINITY);
            let mut ok = _mm256_and_pd(
                _mm256_cmp_pd::<_CMP_GT_OQ>(opacity, _mm256_setzero_pd()),
                _mm256_cmp_pd::<_CMP_LT_OQ>(opacity, infinity),
            );
            for &c in &colour {
                ok = _mm256_and_pd(ok, _mm256_cmp_pd::<_CMP_LT_OQ>(abs(c), infinity));
            }
            let opacity = _mm256_and_pd(ok, _mm256_min_pd(opacity, _mm256_set1_pd(1.0)));
            for c in &mut colour {
                *c = _mm256_and_pd(ok, clamp01(*c));
            }
            (opacity, colour)
        }

        /// The trilinear value at four lower corners `lanes` (linear indices) with weights
        /// `h`, as `Linear::apply` computes it.
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn trilinear(&self, lanes: &[i32; 4], h: [__m256d; 3]) -> __m256d {
            let [ox, oy, oz] = self.offsets;
            let rows = [0, oy, oz, oz + oy];
            let bytes = self.voxels.bytes();
            let wide = self.voxels.is_wide();
            let width = if wide { 2 } else { 1 };
            // A gather reads four bytes at each row's corner: all inside the channel?
            let index = _mm_loadu_si128(lanes.as_ptr().cast());
            let mut pairs = [[_mm256_setzero_pd(); 2]; 4];
            if _mm_movemask_epi8(_mm_cmpgt_epi32(index, _mm_set1_epi32(self.safe))) == 0 {
                let mask = _mm_set1_epi32(if wide { 0xffff } else { 0xff });
                let shift = _mm_cvtsi32_si128(8 * width * ox);
                let base = bytes.as_ptr().cast::<i32>();
                for (pair, &row) in pairs.iter_mut().zip(&rows) {
                    let at = _mm_add_epi32(index, _mm_set1_epi32(row));
                    let words =
                        if wide { _mm_i32gather_epi32::<2>(base, at) } else { _mm_i32gather_epi32::<1>(base, at) };
                    let v0 = _mm_and_si128(words, mask);
                    let v1 = _mm_and_si128(_mm_srl_epi32(words, shift), mask);
                    *pair = [_mm256_cvtepi32_pd(v0), _mm256_cvtepi32_pd(v1)];
                }
            } else {
                pairs = self.last_corners(lanes, rows);
            }
            let x00 = lerp(pairs[0][0], pairs[0][1], h[0]);
            let x10 = lerp(pairs[1][0], pairs[1][1], h[0]);
            let x01 = lerp(pairs[2][0], pairs[2][1], h[0]);
            let x11 = lerp(pairs[3][0], pairs[3][1], h[0]);
            lerp(lerp(x00, x10, h[1]), lerp(x01, x11, h[1]), h[2])
        }

        /// [`Trilinear4::trilinear`]'s voxels at the channel's last corners, where a
        /// gather's four bytes could reach past its end: voxel by voxel, out of the way of
        /// the loop (which then inlines).
        #[cold]
        #[inline(never)]
        #[target_feature(enable = "avx2")]
        unsafe fn last_corners(&self, lanes: &[i32; 4], rows: [i32; 4]) -> [[__m256d; 2]; 4] {
            let ox = self.offsets[0] as usize;
            let mut pairs = [[_mm256_setzero_pd(); 2]; 4];
            for (pair, &row) in pairs.iter_mut().zip(&rows) {
                let (mut v0, mut v1) = ([0.0; 4], [0.0; 4]);
                for ((v0, v1), &i) in v0.iter_mut().zip(&mut v1).zip(lanes) {
                    [*v0, *v1] = self.voxels.pair((i + row) as usize, ox);
                }
                *pair = [_mm256_loadu_pd(v0.as_ptr()), _mm256_loadu_pd(v1.as_ptr())];
            }
            pairs
        }
    }
}

#[cfg(target_arch = "x86_64")]
pub(super) mod avx512 {
    //! The packet loop's bodies: the AVX2 ones' steps, sixteen f32 lanes wide
    //! ([`super::Packed`]).

    use std::arch::x86_64::*;

    use super::{Packed, Trilinear4};

    /// ⌊x⌋, exactly (the lower corner of a cell).
    #[inline]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
    pub(in crate::sampling) unsafe fn floor(x: __m512) -> __m512 {
        _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC }>(x)
    }

    #[inline]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
    unsafe fn abs(x: __m512) -> __m512 {
        _mm512_andnot_ps(_mm512_set1_ps(-0.0), x)
    }

    #[inline]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
    unsafe fn lerp(v0: __m512, v1: __m512, h: __m512) -> __m512 {
        _mm512_fnmadd_ps(h, _mm512_sub_ps(v0, v1), v0)
    }

    impl Packed {
        /// Per axis, the lower corners x0 (as f32) and weights of sixteen positions `u`:
        /// `Axis::cell`'s clamp, floor and cap. (No snapping: the f64 loops snap within
        /// 1e-9 per voxel, far below f32's own rounding of a position, and a snap moves a
        /// weight by no more than that.)
        #[inline]
        #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
        pub(in crate::sampling) unsafe fn cells16(&self, u: [__m512; 3]) -> ([__m512; 3], [__m512; 3]) {
            let mut x0 = [_mm512_setzero_ps(); 3];
            let mut h = [_mm512_setzero_ps(); 3];
            for a in 0..3 {
                let [last, x0_max] = self.rule[a];
                let u = _mm512_min_ps(_mm512_set1_ps(last), _mm512_max_ps(_mm512_setzero_ps(), u[a]));
                x0[a] = _mm512_min_ps(floor(u), _mm512_set1_ps(x0_max));
                h[a] = _mm512_sub_ps(u, x0[a]);
            }
            (x0, h)
        }

        /// x + nx·(y + ny·z) for sixteen (x, y, z) of integers (as f32) in a grid of `dims`:
        /// in f32 where the grid is small enough for it to be exact, else in i32.
        #[inline]
        #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
        pub(in crate::sampling) unsafe fn index16(&self, [x, y, z]: [__m512; 3], nx: u32, ny: u32) -> __m512i {
            if self.small {
                let yz = _mm512_fmadd_ps(_mm512_set1_ps(ny as f32), z, y);
                _mm512_cvttps_epi32(_mm512_fmadd_ps(_mm512_set1_ps(nx as f32), yz, x))
            } else {
                let [x, y, z] = [x, y, z].map(|c| _mm512_cvttps_epi32(c));
                let yz = _mm512_add_epi32(y, _mm512_mullo_epi32(_mm512_set1_epi32(ny as i32), z));
                _mm512_add_epi32(x, _mm512_mullo_epi32(_mm512_set1_epi32(nx as i32), yz))
            }
        }

        /// The segment of each value: how many break points are ≤ it.
        #[inline]
        #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
        pub(in crate::sampling) unsafe fn segments16(&self, v: __m512) -> __m512i {
            let mut segment = _mm512_setzero_si512();
            let one = _mm512_set1_epi32(1);
            for &b in &self.breaks {
                let le = _mm512_cmp_ps_mask::<_CMP_LE_OQ>(_mm512_set1_ps(b), v);
                segment = _mm512_mask_add_epi32(segment, le, segment, one);
            }
            segment
        }

        /// The lanes whose value lies within `slack` of a break point where the map jumps.
        #[inline]
        #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
        pub(in crate::sampling) unsafe fn near_jumps16(&self, v: __m512, slack: __m512) -> __mmask16 {
            let mut near = 0;
            for &j in &self.jumps {
                near |= _mm512_cmp_ps_mask::<_CMP_LE_OQ>(abs(_mm512_sub_ps(v, _mm512_set1_ps(j))), slack);
            }
            near
        }

        #[inline]
        #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
        unsafe fn lookup(&self, f: usize, segment: __m512i) -> __m512 {
            let t = &self.tables[f];
            _mm512_permutex2var_ps(_mm512_loadu_ps(t.as_ptr()), segment, _mm512_loadu_ps(t.as_ptr().add(16)))
        }

        /// The opacity and colour of sixteen values in their segments, (0, black) where a
        /// value contributes nothing: `JointPiecewise::classify_or_clear`, each output as
        /// its value at the segment's reference plus slope times the distance from it.
        /// (Every result is finite: `Packed::new` admits no map that could overflow.)
        #[inline]
        #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
        pub(in crate::sampling) unsafe fn map16(&self, v: __m512, segment: __m512i) -> (__m512, [__m512; 3]) {
            let one = _mm512_set1_ps(1.0);
            let zero = _mm512_setzero_ps();
            let dv = _mm512_sub_ps(v, self.lookup(Packed::REFERENCE, segment));
            let opacity =
                _mm512_fmadd_ps(dv, self.lookup(Packed::OPACITY_SLOPE, segment), self.lookup(Packed::OPACITY, segment));
            let ok = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(opacity, zero);
            let mut colour = [zero; 3];
            for (c, colour) in colour.iter_mut().enumerate() {
                let at = _mm512_fmadd_ps(
                    dv,
                    self.lookup(Packed::COLOUR_SLOPE + c, segment),
                    self.lookup(Packed::COLOUR + c, segment),
                );
                *colour = _mm512_maskz_max_ps(ok, zero, _mm512_min_ps(one, at));
            }
            (_mm512_maskz_min_ps(ok, opacity, one), colour)
        }
    }

    impl Trilinear4<'_> {
        /// The trilinear value at sixteen lower corners `index` with weights `h`, in f32:
        /// `Linear::apply`'s lerps in its order, each v0 − h·(v0 − v1) rounded once.
        #[inline]
        #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
        pub(in crate::sampling) unsafe fn trilinear16(&self, index: __m512i, h: [__m512; 3]) -> __m512 {
            let [ox, oy, oz] = self.offsets;
            let rows = [0, oy, oz, oz + oy];
            let wide = self.voxels.is_wide();
            let width = if wide { 2 } else { 1 };
            let mut pairs = [[_mm512_setzero_ps(); 2]; 4];
            if _mm512_cmpgt_epi32_mask(index, _mm512_set1_epi32(self.safe)) == 0 {
                let mask = _mm512_set1_epi32(if wide { 0xffff } else { 0xff });
                let shift = _mm_cvtsi32_si128(8 * width * ox);
                let base = self.voxels.bytes().as_ptr().cast::<i32>();
                for (pair, &row) in pairs.iter_mut().zip(&rows) {
                    let at = _mm512_add_epi32(index, _mm512_set1_epi32(row));
                    let words = if wide {
                        _mm512_i32gather_epi32::<2>(at, base.cast())
                    } else {
                        _mm512_i32gather_epi32::<1>(at, base.cast())
                    };
                    let v0 = _mm512_and_si512(words, mask);
                    let v1 = _mm512_and_si512(_mm512_srl_epi32(words, shift), mask);
                    *pair = [_mm512_cvtepi32_ps(v0), _mm512_cvtepi32_ps(v1)];
                }
            } else {
                pairs = self.last_corners16(index, rows);
            }
            let x00 = lerp(pairs[0][0], pairs[0][1], h[0]);
            let x10 = lerp(pairs[1][0], pairs[1][1], h[0]);
            let x01 = lerp(pairs[2][0], pairs[2][1], h[0]);
            let x11 = lerp(pairs[3][0], pairs[3][1], h[0]);
            lerp(lerp(x00, x10, h[1]), lerp(x01, x11, h[1]), h[2])
        }

        /// [`Trilinear4::trilinear16`]'s voxels where a gather's four bytes could reach
        /// past the channel's end: voxel by voxel, out of the loop's way.
        #[cold]
        #[inline(never)]
        #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
        unsafe fn last_corners16(&self, index: __m512i, rows: [i32; 4]) -> [[__m512; 2]; 4] {
            let mut lanes = [0i32; 16];
            _mm512_storeu_si512(lanes.as_mut_ptr().cast(), index);
            let ox = self.offsets[0] as usize;
            let mut pairs = [[_mm512_setzero_ps(); 2]; 4];
            for (pair, &row) in pairs.iter_mut().zip(&rows) {
                let (mut v0, mut v1) = ([0.0f32; 16], [0.0f32; 16]);
                for ((v0, v1), &i) in v0.iter_mut().zip(&mut v1).zip(&lanes) {
                    let [a, b] = self.voxels.pair((i + row) as usize, ox);
                    (*v0, *v1) = (a as f32, b as f32);
                }
                *pair = [_mm512_loadu_ps(v0.as_ptr()), _mm512_loadu_ps(v1.as_ptr())];
            }
            pairs
        }
    }
}
