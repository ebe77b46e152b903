//! The AVX-512 side of the AVX2 loop's objects ([`super::Trilinear4`]): the f32 forms of
//! an object's grid and map ([`Packed`]) and the steps, sixteen f32 lanes to a register,
//! that the packet loop ([`super::super::packet`]) runs with them.
//!
//! They live apart from the AVX2 bodies because they keep a different promise: the AVX2
//! lanes do the generic loop's operations in its order and agree with it bit for bit, these
//! round in f32 (and fuse multiplies and adds) and agree with it to within rounding, with
//! the one place where that could change a class handled from the f64 value
//! ([`Packed::jumps`]).

use std::cmp::Ordering;

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

#[cfg(target_arch = "x86_64")]
use super::Trilinear4;
use crate::geometry::LineSamples;

/// Whether the processor has what the packet loop's bodies are compiled for.
pub(super) fn has_avx512() -> bool {
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

/// What the packet loop ([`super::super::packet`]) reads, in f32: sixteen lanes to a register
/// halve the instructions per sample. Positions, voxels and classification then differ
/// from the f64 loops by rounding only (about 1e-7 relatively); the one place where that
/// could matter more is a break point where the map jumps (a LUT bound): a value within
/// rounding of one takes its segment from the f64 value instead ([`Packed::jumps`]).
pub(in crate::sampling) struct Packed {
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
    /// most [`crate::mapping::SMALL_MAP`] + 1 are used): the two registers of a
    /// two-register permute.
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
    pub(super) fn new(
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
const EPS32: f64 = f32::EPSILON as f64;

/// A map whose sides of a break point differ by more than this jumps there.
const JUMP: f64 = 1e-9;

#[cfg(target_arch = "x86_64")]
/// ⌊x⌋, exactly (the lower corner of a cell).
#[inline]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
pub(in crate::sampling) unsafe fn floor(x: __m512) -> __m512 {
    _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC }>(x)
}

#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
unsafe fn abs(x: __m512) -> __m512 {
    _mm512_andnot_ps(_mm512_set1_ps(-0.0), x)
}

#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
unsafe fn lerp(v0: __m512, v1: __m512, h: __m512) -> __m512 {
    _mm512_fnmadd_ps(h, _mm512_sub_ps(v0, v1), v0)
}

#[cfg(target_arch = "x86_64")]
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

#[cfg(target_arch = "x86_64")]
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
