//! The f32 forms of an object's grid and map that the packet loop ([`super::packet`])
//! casts with ([`Packed`], [`Grid`]), and its steps over them written once over a SIMD
//! width ([`super::simd::Simd`]): locating samples in cells, indexing, the trilinear value,
//! the segment of the joint map and its classification, and opacity correction
//! ([`corrected`]).
//!
//! They keep a different promise from the f64 loops ([`super::kernel`], [`super::lanes`]):
//! those do the generic loop's operations in its order and agree with it bit for bit; these
//! round in f32 (and may fuse multiplies and adds) and agree with it to within rounding, with
//! the one place where that could change a class handled from the f64 value
//! ([`Packed::jumps`]).

use std::cmp::Ordering;

use super::simd::Simd;
use crate::dataset::{F32LeVoxels, U16LeVoxels, U8Voxels, Voxels};
use crate::geometry::LineSamples;

/// The voxel channels the vector loops read: u8, little-endian u16, or little-endian f32
/// (the packet loop only: signed data and simulation grids are f32 once loaded).
#[derive(Clone, Copy, Debug)]
pub(super) enum Stored<'a> {
    U8(U8Voxels<'a>),
    U16(U16LeVoxels<'a>),
    F32(F32LeVoxels<'a>),
}

impl<'a> Stored<'a> {
    pub(super) fn bytes(&self) -> &'a [u8] {
        match self {
            Stored::U8(v) => v.bytes(),
            Stored::U16(v) => v.bytes(),
            Stored::F32(v) => v.bytes(),
        }
    }

    /// Two bytes per voxel.
    pub(super) fn is_wide(&self) -> bool {
        matches!(self, Stored::U16(_))
    }

    /// Whether voxels are f32 bit patterns, which may be non-finite (an integer type's never
    /// are), read one gather per voxel rather than two or four voxels per gather.
    pub(super) fn is_float(&self) -> bool {
        matches!(self, Stored::F32(_))
    }

    /// Voxels `i` and `i + dx` ([`Voxels::pair`]).
    #[inline]
    pub(super) fn pair(&self, i: usize, dx: usize) -> [f64; 2] {
        match self {
            Stored::U8(v) => v.pair(i, dx),
            Stored::U16(v) => v.pair(i, dx),
            Stored::F32(v) => v.pair(i, dx),
        }
    }

    /// The largest lower-corner index whose four rows (`0`, `oy`, `oz`, `oy + oz` voxels
    /// on) a gather of four bytes from each row's corner reads without reaching past the
    /// channel's end (for f32, also the four bytes of the voxel `ox` past each corner);
    /// −1 where none can.
    pub(super) fn safe_corner(&self, ox: usize, oy: usize, oz: usize) -> i32 {
        let (width, past) = match self {
            Stored::U8(_) => (1, 0),
            Stored::U16(_) => (2, 0),
            Stored::F32(_) => (4, ox),
        };
        let reach = (self.bytes().len() as i64 - 4).div_euclid(width) - (oy + oz + past) as i64;
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

impl Grid<'_> {
    /// The gradient of the trilinear field at positions `u` by central differences over one
    /// voxel, (I(u + eₐ) − I(u − eₐ))/2 per axis a, each point located as [`Packed::cells`]
    /// locates a sample (clamped to the grid as `Axis::cell` clamps it): what the f64
    /// loop's `Shaded::gradient` computes, in f32, for the lanes `lit` (the others get
    /// finite values of no meaning).
    ///
    /// Where a sample's cell is at least one voxel from the grid's faces (its lower corner
    /// x₀ has 1 ≤ x₀ ≤ n − 3 on every axis), u ± eₐ lie in the cells next to it along a
    /// with the same weights, and trilinear interpolation is linear in the voxels: the
    /// difference of the two values is the trilinear interpolation, with the sample's own
    /// weights, of the voxels' differences V(c + eₐ) − V(c − eₐ) at its cell's eight
    /// corners. Those are twelve gathers of neighbouring voxels (sixteen for u16) instead of
    /// six trilinear values' twenty-four. A lit lane nearer a face takes the six values
    /// ([`Grid::gradient_at_points`]), whose points clamp. Which way a lane takes depends on
    /// that lane alone, so that every width gives the same bits: a register with lit lanes
    /// on both sides computes both ways and selects.
    #[inline(always)]
    pub(super) fn gradient<S: Simd>(&self, s: S, packed: &Packed, u: [S::F; 3], lit: u32) -> [S::F; 3] {
        let one = s.splat(1.0);
        let (x0, h) = packed.cells(s, u);
        let mut inside = s.ge(x0[0], one);
        for (a, &x0) in x0.iter().enumerate() {
            let inner = s.and_m(s.ge(x0, one), s.le(x0, s.splat(packed.rule[a][0] - 2.0)));
            inside = s.and_m(inside, inner);
        }
        if lit & s.bits(inside) == 0 {
            return self.gradient_at_points(s, packed, u, lit);
        }
        let near = (lit & !s.bits(inside) != 0).then(|| self.gradient_at_points(s, packed, u, lit));
        // Lanes nearer a face (whose gradient, where lit, is `near`'s) read the corner
        // (1, 1, 1) here instead, so that every gather stays inside the channel: some lit
        // lane is inside, so the grid has at least four voxels along every axis.
        let x0 = [s.select(inside, x0[0], one), s.select(inside, x0[1], one), s.select(inside, x0[2], one)];
        let index = packed.index(s, x0, self.nx, self.ny);
        // Only the lit lanes read voxels (so that lanes whose samples are clear bring no
        // cache line in).
        let m = s.mask(lit);
        let [_, oy, oz] = self.offsets;
        let rows = [0, oy, oz, oz + oy];
        // Per row (y₀, z₀), (y₀ + 1, z₀), (y₀, z₀ + 1), (y₀ + 1, z₀ + 1) of the cell: the
        // voxels at x₀ − 1, x₀, x₀ + 1, x₀ + 2 give the differences along x at its two
        // corners; the corners' own voxels are kept for the other axes.
        let mut corner = [[one; 2]; 4];
        let mut d = [[one; 2]; 4];
        for r in 0..4 {
            let [before, c0, c1, after] = self.four(s, s.add_i(index, s.splat_i(rows[r] - 1)), m);
            d[r] = [s.sub(c1, before), s.sub(after, c0)];
            corner[r] = [c0, c1];
        }
        let gx = self.halved(s, d, h);
        // Along y and z: the rows one beyond the cell on either side, against the cell's
        // own. Along y, rows r0 = (y₀, z) and r1 = (y₀ + 1, z) for z = z₀, z₀ + 1.
        for side in 0..2 {
            let (r0, r1, at) = (2 * side, 2 * side + 1, oz * side as i32);
            let below = self.two(s, s.add_i(index, s.splat_i(at - oy)), m);
            let above = self.two(s, s.add_i(index, s.splat_i(at + 2 * oy)), m);
            d[r0] = [s.sub(corner[r1][0], below[0]), s.sub(corner[r1][1], below[1])];
            d[r1] = [s.sub(above[0], corner[r0][0]), s.sub(above[1], corner[r0][1])];
        }
        let gy = self.halved(s, d, h);
        // Along z, rows r0 = (y, z₀) and r1 = (y, z₀ + 1) for y = y₀, y₀ + 1.
        for side in 0..2 {
            let (r0, r1, at) = (side, side + 2, oy * side as i32);
            let below = self.two(s, s.add_i(index, s.splat_i(at - oz)), m);
            let above = self.two(s, s.add_i(index, s.splat_i(at + 2 * oz)), m);
            d[r0] = [s.sub(corner[r1][0], below[0]), s.sub(corner[r1][1], below[1])];
            d[r1] = [s.sub(above[0], corner[r0][0]), s.sub(above[1], corner[r0][1])];
        }
        let gz = self.halved(s, d, h);
        match near {
            Some([nx, ny, nz]) => [s.select(inside, gx, nx), s.select(inside, gy, ny), s.select(inside, gz, nz)],
            None => [gx, gy, gz],
        }
    }

    /// Half the trilinear interpolation, with weights `h`, of values at a cell's corners
    /// given row by row as [`Grid::trilinear`] orders them.
    #[inline(always)]
    fn halved<S: Simd>(&self, s: S, d: [[S::F; 2]; 4], h: [S::F; 3]) -> S::F {
        let x00 = lerp(s, d[0][0], d[0][1], h[0]);
        let x10 = lerp(s, d[1][0], d[1][1], h[0]);
        let x01 = lerp(s, d[2][0], d[2][1], h[0]);
        let x11 = lerp(s, d[3][0], d[3][1], h[0]);
        s.mul(lerp(s, lerp(s, x00, x10, h[1]), lerp(s, x01, x11, h[1]), h[2]), s.splat(0.5))
    }

    /// The four voxels from `at` on along x, as f32, in the lanes of `m` (0 in the others).
    #[inline(always)]
    fn four<S: Simd>(&self, s: S, at: S::I, m: S::M) -> [S::F; 4] {
        let base = self.voxels.bytes().as_ptr();
        if self.voxels.is_float() {
            // SAFETY: [`Grid::gradient`] reads only voxels inside the channel, and an f32
            // gather reads exactly its voxel's four bytes.
            let voxel = |k: i32| unsafe { s.bits_to_f32(s.gather_in::<4>(base, s.add_i(at, s.splat_i(k)), m)) };
            [voxel(0), voxel(1), voxel(2), voxel(3)]
        } else if self.voxels.is_wide() {
            // SAFETY: [`Grid::gradient`] reads only voxels inside the channel.
            let (a, b) =
                unsafe { (s.gather_in::<2>(base, at, m), s.gather_in::<2>(base, s.add_i(at, s.splat_i(2)), m)) };
            let mask = s.splat_i(0xffff);
            let part = |w: S::I, shift: u32| s.to_f32(s.and_i(s.shr_i(w, shift), mask));
            [part(a, 0), part(a, 16), part(b, 0), part(b, 16)]
        } else {
            // SAFETY: as above: the four bytes are four voxels inside the channel.
            let w = unsafe { s.gather_in::<1>(base, at, m) };
            let mask = s.splat_i(0xff);
            let part = |shift: u32| s.to_f32(s.and_i(s.shr_i(w, shift), mask));
            [part(0), part(8), part(16), part(24)]
        }
    }

    /// The two voxels from `at` on along x, as f32, in the lanes of `m` (0 in the others).
    #[inline(always)]
    fn two<S: Simd>(&self, s: S, at: S::I, m: S::M) -> [S::F; 2] {
        let base = self.voxels.bytes().as_ptr();
        if self.voxels.is_float() {
            // SAFETY: as for `four`: the two voxels lie inside the channel.
            let voxel = |k: i32| unsafe { s.bits_to_f32(s.gather_in::<4>(base, s.add_i(at, s.splat_i(k)), m)) };
            return [voxel(0), voxel(1)];
        }
        let wide = self.voxels.is_wide();
        // SAFETY: [`Grid::gradient`] reads rows that are neither the channel's last (for u8,
        // whose four bytes reach two voxels past the pair) nor outside it.
        let w = unsafe {
            if wide {
                s.gather_in::<2>(base, at, m)
            } else {
                s.gather_in::<1>(base, at, m)
            }
        };
        let (mask, shift) = if wide { (s.splat_i(0xffff), 16) } else { (s.splat_i(0xff), 8) };
        [s.to_f32(s.and_i(w, mask)), s.to_f32(s.and_i(s.shr_i(w, shift), mask))]
    }

    /// [`Grid::gradient`] from the six values at u ± eₐ themselves, each point clamped as a
    /// sample's is: six more trilinear values, near the grid's faces, read in the lanes
    /// `lit` only.
    #[inline(always)]
    fn gradient_at_points<S: Simd>(&self, s: S, packed: &Packed, u: [S::F; 3], lit: u32) -> [S::F; 3] {
        let (one, half) = (s.splat(1.0), s.splat(0.5));
        let mut g = [one; 3];
        for (a, g) in g.iter_mut().enumerate() {
            let (mut hi, mut lo) = (u, u);
            hi[a] = s.add(u[a], one);
            lo[a] = s.sub(u[a], one);
            *g = s.mul(s.sub(self.value_at(s, packed, hi, lit), self.value_at(s, packed, lo, lit)), half);
        }
        g
    }

    /// The trilinear value at positions `u`, located as a sample is, in the lanes `lit`.
    #[inline(always)]
    fn value_at<S: Simd>(&self, s: S, packed: &Packed, u: [S::F; 3], lit: u32) -> S::F {
        let (x0, h) = packed.cells(s, u);
        self.trilinear(s, packed.index(s, x0, self.nx, self.ny), h, lit)
    }
}

/// v0 − h·(v0 − v1), `Linear::apply`'s lerp.
#[inline(always)]
fn lerp<S: Simd>(s: S, v0: S::F, v1: S::F, h: S::F) -> S::F {
    s.neg_mul_add(h, s.sub(v0, v1), v0)
}

impl Grid<'_> {
    /// The trilinear value at lower corners `index` with weights `h`, in f32:
    /// `Linear::apply`'s lerps in its order, each v0 − h·(v0 − v1). `wanted`: the lanes
    /// (as bits) whose values are used (not a sample in empty space, an idle lane or a clear
    /// one): the others read no voxel, so that they bring no cache line in, and their
    /// values are not the field's.
    #[inline(always)]
    pub(super) fn trilinear<S: Simd>(&self, s: S, index: S::I, h: [S::F; 3], wanted: u32) -> S::F {
        let [ox, oy, oz] = self.offsets;
        let rows = [0, oy, oz, oz + oy];
        let wide = self.voxels.is_wide();
        let mut pairs = [[s.splat(0.0); 2]; 4];
        let m = s.mask(wanted);
        // Whether every wanted lane's gathers stay inside the channel
        // ([`Stored::safe_corner`]).
        let inside = s.bits(s.gt_i(index, s.splat_i(self.safe))) & wanted == 0;
        if inside && self.voxels.is_float() {
            // One gather per voxel: a corner's and the one `ox` past it, their bits as f32.
            let base = self.voxels.bytes().as_ptr();
            for (pair, &row) in pairs.iter_mut().zip(&rows) {
                let at = s.add_i(index, s.splat_i(row));
                // SAFETY: every wanted lane's corner is at most `safe`, so its row's voxel
                // and the one `ox` past it lie inside the channel ([`Stored::safe_corner`]).
                let (v0, v1) =
                    unsafe { (s.gather_in::<4>(base, at, m), s.gather_in::<4>(base, s.add_i(at, s.splat_i(ox)), m)) };
                *pair = [s.bits_to_f32(v0), s.bits_to_f32(v1)];
            }
        } else if inside {
            let mask = s.splat_i(if wide { 0xffff } else { 0xff });
            let shift = 8 * if wide { 2 } else { 1 } * ox as u32;
            let base = self.voxels.bytes().as_ptr();
            for (pair, &row) in pairs.iter_mut().zip(&rows) {
                let at = s.add_i(index, s.splat_i(row));
                // SAFETY: every wanted lane's corner is at most `safe`, so its row's four
                // bytes lie inside the channel.
                let words = unsafe {
                    if wide {
                        s.gather_in::<2>(base, at, m)
                    } else {
                        s.gather_in::<1>(base, at, m)
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

/// α = 1 − (1 − O)^ℓ per lane (SPEC §4.3), as [`super::corrected_opacity`] computes it,
/// −expm1(ℓ·log1p(−O)), but in f32 lanes: 0 where O ≤ 0, 1 where O ≥ 1. Computed lane by
/// lane in f64 it cost two library calls per lane and sample, which on a scene with opacity
/// correction (the SPEC's default) was most of the loop's time; here it is a few dozen
/// lane operations. Relative to the f64 value it is off by a few f32 roundings (within
/// 2·10⁻⁶ relatively or 10⁻¹² absolutely, over (0, 1) × ℓ ∈ [2⁻⁴, 2⁴], tested on every
/// path): both functions keep their relative precision for small arguments, which a plain
/// `1 − exp(ℓ·ln(1 − O))` would lose to the rounding of 1 − O.
#[inline(always)]
pub(super) fn corrected<S: Simd>(s: S, opacity: S::F, ell: S::F) -> S::F {
    let (zero, one) = (s.splat(0.0), s.splat(1.0));
    let some = s.gt(ell, zero);
    // Lanes outside (0, 1) are computed on ½ and replaced at the end.
    let inside = s.and_m(s.gt(opacity, zero), s.lt(opacity, one));
    let o = s.select(inside, opacity, s.splat(0.5));
    // ℓ·log1p(−O), at least −30 (where eʸ is below f32's rounding of 1 anyway).
    let y = s.max(s.mul(ell, log1p_negative(s, o)), s.splat(-30.0));
    let outside = s.select(s.ge(opacity, one), one, zero);
    s.select(some, s.select(inside, neg_expm1(s, y), outside), zero)
}

/// log1p(−o) for o in (0, 1): ln u of u = 1 − o rounded, corrected by the rounding,
/// (−o − (u − 1))/u, with 1/u taken as 2 − u: exact where u is near 1, where the rounding
/// matters; where u is far from 1 the correction is below f32's rounding of ln u.
#[inline(always)]
fn log1p_negative<S: Simd>(s: S, o: S::F) -> S::F {
    let one = s.splat(1.0);
    let u = s.sub(one, o);
    let rounding = s.sub(s.sub(one, u), o);
    s.mul_add(rounding, s.sub(s.splat(2.0), u), ln(s, u))
}

/// ln u for normal u > 0 (Cephes' `logf`: u = m·2ᵉ with m in [√½, √2), then a polynomial
/// in m − 1, which is exact, so the result keeps its relative precision near u = 1).
#[inline(always)]
fn ln<S: Simd>(s: S, u: S::F) -> S::F {
    let one = s.splat(1.0);
    let bits = s.to_bits(u);
    // u = m·2ᵉ with m in [½, 1).
    let e = s.to_f32(s.add_i(s.shr_i(bits, 23), s.splat_i(-126)));
    let m = s.bits_to_f32(s.add_i(s.and_i(bits, s.splat_i(0x007f_ffff)), s.splat_i(0x3f00_0000)));
    let low = s.lt(m, s.splat(std::f32::consts::FRAC_1_SQRT_2));
    // m < √½: 2m − 1 and e − 1; else m − 1 (both exact).
    let x = s.sub(s.add(m, s.select(low, m, s.splat(0.0))), one);
    let e = s.sub(e, s.select(low, one, s.splat(0.0)));
    let z = s.mul(x, x);
    let mut p = s.splat(7.037_683_6e-2);
    for c in [-1.151_461e-1, 1.167_699_9e-1, -1.242_014_1e-1, 1.424_932_3e-1, -1.666_805_7e-1, 2.000_071_4e-1] {
        p = s.mul_add(p, x, s.splat(c));
    }
    p = s.mul_add(p, x, s.splat(-2.499_999_4e-1));
    p = s.mul_add(p, x, s.splat(3.333_333e-1));
    let mut y = s.mul(s.mul(p, x), z);
    y = s.mul_add(e, s.splat(LN2_LOW), y);
    y = s.neg_mul_add(s.splat(0.5), z, y);
    s.mul_add(e, s.splat(LN2_HIGH), s.add(x, y))
}

/// ln 2 as a sum whose first part (0.693359375) has few bits (so that k·`LN2_HIGH` is exact for the
/// small integers k here), Cephes' split.
const LN2_HIGH: f32 = 0.693_359_4;
const LN2_LOW: f32 = -2.121_944_4e-4;

/// −expm1(y) = 1 − eʸ for y in [−30, 0] ([`exp_parts`]): 1 − 2ᵏ·(1 + expm1(r)) as
/// (1 − 2ᵏ) − 2ᵏ·expm1(r), both parts exact but the last rounding.
#[inline(always)]
fn neg_expm1<S: Simd>(s: S, y: S::F) -> S::F {
    let (two_k, em1) = exp_parts(s, y);
    s.neg_mul_add(two_k, em1, s.sub(s.splat(1.0), two_k))
}

/// eʸ for y in [−87, 1] ([`exp_parts`]): 2ᵏ + 2ᵏ·expm1(r), a few f32 roundings off.
#[inline(always)]
fn exp<S: Simd>(s: S, y: S::F) -> S::F {
    let (two_k, em1) = exp_parts(s, y);
    s.mul_add(two_k, em1, two_k)
}

/// y = k·ln 2 + r with |r| ≤ ½ ln 2, as (2ᵏ, expm1(r)), for y ≥ −87 (so that 2ᵏ, k ≥ −126,
/// is a normal f32 made from its exponent field): expm1(r) as r + r²·P(r) (Cephes' `expf`
/// polynomial, without its 1 +, so that it keeps its relative precision for small r).
#[inline(always)]
fn exp_parts<S: Simd>(s: S, y: S::F) -> (S::F, S::F) {
    let k = s.floor(s.mul_add(y, s.splat(std::f32::consts::LOG2_E), s.splat(0.5)));
    let r = s.neg_mul_add(k, s.splat(LN2_LOW), s.neg_mul_add(k, s.splat(LN2_HIGH), y));
    let mut p = s.splat(1.987_569_1e-4);
    for c in [1.398_199_9e-3, 8.333_452e-3, 4.166_579_6e-2, 1.666_666_6e-1, 0.5] {
        p = s.mul_add(p, r, s.splat(c));
    }
    let em1 = s.mul_add(s.mul(r, r), p, r);
    let two_k = s.bits_to_f32(s.shl_i(s.add_i(s.to_i32(k), s.splat_i(127)), 23));
    (two_k, em1)
}

/// xᵉ per lane for x ≥ 0 and a constant e ≥ 0, as `f64::powf` gives it to f32's rounding
/// (Blinn–Phong's specular term, [`super::shade`]): e^(e·ln x), the exponent held at −87
/// and above (where the power is below 10⁻³⁷ anyway). Where x is 0 (or below f32's smallest
/// normal, which `ln` does not take) it is 0ᵉ: 0, or 1 when e is 0, as `powf` has it.
#[inline(always)]
pub(super) fn pow<S: Simd>(s: S, x: S::F, e: f32) -> S::F {
    let normal = s.ge(x, s.splat(f32::MIN_POSITIVE));
    let safe = s.select(normal, x, s.splat(1.0));
    let y = s.max(s.mul(s.splat(e), ln(s, safe)), s.splat(-87.0));
    s.select(normal, exp(s, y), s.splat(if e == 0.0 { 1.0 } else { 0.0 }))
}

#[cfg(test)]
mod tests {
    #[cfg(target_arch = "x86_64")]
    use super::super::simd::avx2::Avx2;
    #[cfg(target_arch = "x86_64")]
    use super::super::simd::avx512::Avx512;
    #[cfg(target_arch = "aarch64")]
    use super::super::simd::neon::Neon;
    use super::super::simd::scalar::Scalar;
    use super::super::simd::SimdPath;
    use super::*;

    /// [`corrected`] of each (opacity, ℓ), a register at a time.
    fn corrected_all<S: Simd>(s: S, pairs: &[(f32, f32)]) -> Vec<f32> {
        let mut out = Vec::new();
        for chunk in pairs.chunks(S::LANES) {
            let (mut o, mut ell, mut alpha) = ([0.0f32; 16], [0.0f32; 16], [0.0f32; 16]);
            for (l, &(a, b)) in chunk.iter().enumerate() {
                (o[l], ell[l]) = (a, b);
            }
            s.store(&mut alpha, corrected(s, s.load(&o), s.load(&ell)));
            out.extend_from_slice(&alpha[..chunk.len()]);
        }
        out
    }

    /// The f32 lanes' opacity correction agrees with the f64 one ([`super::super::corrected_opacity`])
    /// to a few f32 roundings relatively, on every path this processor has, from the smallest
    /// opacities (where 1 − O rounds) to the largest below 1, over steps of 1/16 to 16 voxels,
    /// and keeps its edges: 0 for O ≤ 0 or ℓ ≤ 0, 1 for O ≥ 1.
    #[test]
    fn corrected_opacity_in_f32_lanes_agrees_with_f64() {
        let mut opacities: Vec<f32> = vec![1e-9, 3e-8, 1e-7, 1e-6, 1e-5];
        opacities.extend((1..1000).map(|i| i as f32 / 1000.0));
        opacities.extend((1..24).map(|e| 1.0 - 2f32.powi(-e)));
        opacities.extend([0.004, 0.3, 0.6, 0.9922, 1.0 - f32::EPSILON / 2.0]);
        let ells = [0.0625, 0.3, 0.5, 0.99, 1.0, 1.0001, 1.37, 2.0, 4.5, 16.0];
        let mut pairs: Vec<(f32, f32)> = opacities.iter().flat_map(|&o| ells.iter().map(move |&l| (o, l))).collect();
        let edges = [(0.0, 1.0), (-0.5, 1.0), (1.0, 1.0), (1.5, 0.7), (0.5, 0.0), (1.0, 0.0), (0.5, -1.0)];
        pairs.extend(edges);
        for path in SimdPath::available() {
            let got = match path {
                #[cfg(target_arch = "x86_64")]
                SimdPath::Avx512 => corrected_all(Avx512::detect().unwrap(), &pairs),
                #[cfg(target_arch = "x86_64")]
                SimdPath::Avx2 => corrected_all(Avx2::detect().unwrap(), &pairs),
                #[cfg(target_arch = "aarch64")]
                SimdPath::Neon => corrected_all(Neon::detect().unwrap(), &pairs),
                SimdPath::Scalar => corrected_all(Scalar, &pairs),
                #[allow(unreachable_patterns)]
                other => unreachable!("{other} is not available on this architecture"),
            };
            for (&(o, ell), &alpha) in pairs.iter().zip(&got) {
                let want = super::super::corrected_opacity(f64::from(o), f64::from(ell));
                let error = (f64::from(alpha) - want).abs();
                assert!(
                    error <= 2e-6 * want || error <= 1e-12,
                    "{path}: O = {o:e}, ℓ = {ell}: {alpha:e} against {want:e} (relative {:e})",
                    error / want
                );
            }
        }
    }
}
