//! The f32 forms of an object's grid and map that the packet loop ([`super::packet`])
//! casts with ([`Packed`], [`Grid`]), and its steps over them written once over a SIMD
//! width ([`super::simd::Simd`]): locating samples in cells, indexing, the trilinear value,
//! the segment of the joint map and its classification.
//!
//! They keep a different promise from the f64 loops ([`super::kernel`], [`super::lanes`]):
//! those do the generic loop's operations in its order and agree with it bit for bit; these
//! round in f32 (and may fuse multiplies and adds) and agree with it to within rounding, with
//! the one place where that could change a class handled from the f64 value
//! ([`Packed::jumps`]).

use std::cmp::Ordering;

use super::simd::Simd;
use crate::dataset::{U16LeVoxels, U8Voxels, Voxels};
use crate::geometry::LineSamples;

/// The voxel channels the vector loops read: u8 or little-endian u16.
#[derive(Clone, Copy, Debug)]
pub(super) enum Stored<'a> {
    U8(U8Voxels<'a>),
    U16(U16LeVoxels<'a>),
}

impl<'a> Stored<'a> {
    pub(super) fn bytes(&self) -> &'a [u8] {
        match self {
            Stored::U8(v) => v.bytes(),
            Stored::U16(v) => v.bytes(),
        }
    }

    /// Two bytes per voxel.
    pub(super) fn is_wide(&self) -> bool {
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

    /// The largest lower-corner index whose four rows (`0`, `oy`, `oz`, `oy + oz` voxels
    /// on) a gather of four bytes from each row's corner reads without reaching past the
    /// channel's end; −1 where none can.
    pub(super) fn safe_corner(&self, oy: usize, oz: usize) -> i32 {
        let width = if self.is_wide() { 2 } else { 1 };
        let reach = (self.bytes().len() as i64 - 4).div_euclid(width) - (oy + oz) as i64;
        reach.clamp(-1, i32::MAX as i64) as i32
    }
}

/// The voxels the packet loop gathers from and how their grid is laid out.
pub(super) struct Grid<'a> {
    pub voxels: Stored<'a>,
    /// Index offsets of the upper corner along x, y, z.
    pub offsets: [i32; 3],
    /// Voxels along x and y.
    pub nx: u32,
    pub ny: u32,
    /// [`Stored::safe_corner`].
    pub safe: i32,
}

/// What the packet loop ([`super::packet`]) reads of an object's map and grid, in f32: a
/// register holds twice as many f32 lanes as f64 ones, halving the instructions per sample.
/// Positions, voxels and classification then differ
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
    /// most [`crate::mapping::SMALL_MAP`] + 1 are used): on AVX-512 the two registers of
    /// one two-register permute, on AVX2 a permute per eight segments used.
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

impl Packed {
    /// Per axis, the lower corners x0 (as f32) and weights of the positions `u`:
    /// `Axis::cell`'s clamp, floor and cap. (No snapping: the f64 loops snap within
    /// 1e-9 per voxel, far below f32's own rounding of a position, and a snap moves a
    /// weight by no more than that.) A NaN position takes the last cell (`min`'s operand
    /// order).
    #[inline(always)]
    pub(super) fn cells<S: Simd>(&self, s: S, u: [S::F; 3]) -> ([S::F; 3], [S::F; 3]) {
        let mut x0 = [s.splat(0.0); 3];
        let mut h = [s.splat(0.0); 3];
        for a in 0..3 {
            let [last, x0_max] = self.rule[a];
            let u = s.min(s.splat(last), s.max(s.splat(0.0), u[a]));
            x0[a] = s.min(s.floor(u), s.splat(x0_max));
            h[a] = s.sub(u, x0[a]);
        }
        (x0, h)
    }

    /// x + nx·(y + ny·z) for (x, y, z) of integers (as f32) in a grid `nx` by `ny` in x
    /// and y: in f32 where the grid is small enough for it to be exact, else in i32.
    #[inline(always)]
    pub(super) fn index<S: Simd>(&self, s: S, [x, y, z]: [S::F; 3], nx: u32, ny: u32) -> S::I {
        if self.small {
            let yz = s.mul_add(s.splat(ny as f32), z, y);
            s.to_i32(s.mul_add(s.splat(nx as f32), yz, x))
        } else {
            let (x, y, z) = (s.to_i32(x), s.to_i32(y), s.to_i32(z));
            let yz = s.add_i(y, s.mul_i(s.splat_i(ny as i32), z));
            s.add_i(x, s.mul_i(s.splat_i(nx as i32), yz))
        }
    }

    /// The segment of each value: how many break points are ≤ it (a NaN counts none).
    #[inline(always)]
    pub(super) fn segments<S: Simd>(&self, s: S, v: S::F) -> S::I {
        let mut segment = s.splat_i(0);
        for &b in &self.breaks {
            segment = s.count_i(segment, s.le(s.splat(b), v));
        }
        segment
    }

    /// The lanes whose value lies within `slack` of a break point where the map jumps.
    #[inline(always)]
    pub(super) fn near_jumps<S: Simd>(&self, s: S, v: S::F, slack: S::F) -> u32 {
        let mut near = 0;
        for &j in &self.jumps {
            near |= s.bits(s.le(s.abs(s.sub(v, s.splat(j))), slack));
        }
        near
    }

    /// The opacity and colour of values in their segments, (0, black) where a value
    /// contributes nothing: `JointPiecewise::classify_or_clear`, each output as its value
    /// at the segment's reference plus slope times the distance from it. (Every result is
    /// finite: `Packed::new` admits no map that could overflow.)
    #[inline(always)]
    pub(super) fn map<S: Simd>(&self, s: S, v: S::F, segment: S::I) -> (S::F, [S::F; 3]) {
        let (one, zero) = (s.splat(1.0), s.splat(0.0));
        let dv = s.sub(v, self.lookup(s, Packed::REFERENCE, segment));
        let opacity =
            s.mul_add(dv, self.lookup(s, Packed::OPACITY_SLOPE, segment), self.lookup(s, Packed::OPACITY, segment));
        let ok = s.gt(opacity, zero);
        let mut colour = [zero; 3];
        for (c, colour) in colour.iter_mut().enumerate() {
            let slope = self.lookup(s, Packed::COLOUR_SLOPE + c, segment);
            let at = s.mul_add(dv, slope, self.lookup(s, Packed::COLOUR + c, segment));
            *colour = s.select(ok, s.max(zero, s.min(one, at)), zero);
        }
        (s.select(ok, s.min(opacity, one), zero), colour)
    }

    /// Field `f` of [`Packed::tables`] for each lane's segment.
    #[inline(always)]
    fn lookup<S: Simd>(&self, s: S, f: usize, segment: S::I) -> S::F {
        s.lookup(&self.tables[f], self.breaks.len() + 1, segment)
    }
}

/// v0 − h·(v0 − v1), `Linear::apply`'s lerp.
#[inline(always)]
fn lerp<S: Simd>(s: S, v0: S::F, v1: S::F, h: S::F) -> S::F {
    s.neg_mul_add(h, s.sub(v0, v1), v0)
}

impl Grid<'_> {
    /// The trilinear value at lower corners `index` with weights `h`, in f32:
    /// `Linear::apply`'s lerps in its order, each v0 − h·(v0 − v1).
    #[inline(always)]
    pub(super) fn trilinear<S: Simd>(&self, s: S, index: S::I, h: [S::F; 3]) -> S::F {
        let [ox, oy, oz] = self.offsets;
        let rows = [0, oy, oz, oz + oy];
        let wide = self.voxels.is_wide();
        let mut pairs = [[s.splat(0.0); 2]; 4];
        if s.bits(s.gt_i(index, s.splat_i(self.safe))) == 0 {
            let mask = s.splat_i(if wide { 0xffff } else { 0xff });
            let shift = 8 * if wide { 2 } else { 1 } * ox as u32;
            let base = self.voxels.bytes().as_ptr();
            for (pair, &row) in pairs.iter_mut().zip(&rows) {
                let at = s.add_i(index, s.splat_i(row));
                // SAFETY: every lane's corner is at most `safe`, so its row's four bytes lie
                // inside the channel.
                let words = unsafe {
                    if wide {
                        s.gather::<2>(base, at)
                    } else {
                        s.gather::<1>(base, at)
                    }
                };
                let v0 = s.and_i(words, mask);
                let v1 = s.and_i(s.shr_i(words, shift), mask);
                *pair = [s.to_f32(v0), s.to_f32(v1)];
            }
        } else {
            let mut lanes = [0i32; 16];
            s.store_i(&mut lanes, index);
            for (pair, &row) in pairs.iter_mut().zip(&rows) {
                let (v0, v1) = self.last_corners(&lanes[..S::LANES], row);
                *pair = [s.load(&v0), s.load(&v1)];
            }
        }
        let x00 = lerp(s, pairs[0][0], pairs[0][1], h[0]);
        let x10 = lerp(s, pairs[1][0], pairs[1][1], h[0]);
        let x01 = lerp(s, pairs[2][0], pairs[2][1], h[0]);
        let x11 = lerp(s, pairs[3][0], pairs[3][1], h[0]);
        lerp(s, lerp(s, x00, x10, h[1]), lerp(s, x01, x11, h[1]), h[2])
    }

    /// [`Grid::trilinear`]'s voxels `row` on from each of the corners `lanes`, where a
    /// gather's four bytes could reach past the channel's end: voxel by voxel, out of the
    /// loop's way.
    #[cold]
    #[inline(never)]
    fn last_corners(&self, lanes: &[i32], row: i32) -> ([f32; 16], [f32; 16]) {
        let ox = self.offsets[0] as usize;
        let (mut v0, mut v1) = ([0.0f32; 16], [0.0f32; 16]);
        for ((v0, v1), &i) in v0.iter_mut().zip(&mut v1).zip(lanes) {
            let [a, b] = self.voxels.pair((i + row) as usize, ox);
            (*v0, *v1) = (a as f32, b as f32);
        }
        (v0, v1)
    }
}
