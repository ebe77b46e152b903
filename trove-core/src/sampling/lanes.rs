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
//! depend on which path ran (tests compare the two). Without AVX2, on other targets, or
//! where the scalar or NEON path is chosen ([`super::simd::SimdPath`]), the generic loop
//! runs.
//!
//! The f32 packet loop that casts many pieces of such an object at once, and agrees with
//! this loop only to within rounding, is [`super::packet`].

// Elsewhere no `Trilinear4` is ever made, and what serves the AVX2 bodies goes unused.
#![cfg_attr(not(target_arch = "x86_64"), allow(dead_code, unused_variables))]

use super::packed::Stored;
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
}

impl<'a> Trilinear4<'a> {
    /// The loop for `interp` over `voxels` with `maps`, where the processor has AVX2, the
    /// map at most [`SMALL_MAP`] break points and the dataset fewer than 2³⁰ voxels (so
    /// indices and their neighbours' fit in i32 lanes).
    pub(super) fn new(interp: &Linear<Identity>, voxels: Stored<'a>, maps: &JointPiecewise) -> Option<Self> {
        // Its gathers take two or four integer voxels a word; f32 voxels have the packet
        // loop alone.
        if !has_avx2() || voxels.is_float() {
            return None;
        }
        let dims = interp.dims();
        let (breaks, tables) = maps.tables();
        if dims.voxel_count() >= 1 << 30 || breaks.len() > SMALL_MAP {
            return None;
        }
        let (rule, offsets) = interp.rule();
        let [nx, ny, _] = dims.as_array();
        Some(Trilinear4 {
            voxels,
            rule,
            offsets: offsets.map(|o| o as i32),
            nx: nx as i32,
            ny: ny as i32,
            safe: voxels.safe_corner(offsets[0], offsets[1], offsets[2]),
            breaks: breaks.to_vec(),
            tables,
        })
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
