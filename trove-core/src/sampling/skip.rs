//! Empty-space skipping (issue 10): which macrocells an object's samples cannot contribute
//! from, and how far a straight line of samples stays in one.
//!
//! A sample contributes nothing when its opacity is 0. Its value comes from voxels whose
//! finite values lie in its macrocell's range ([`crate::dataset::macrocell`]), widened by
//! how far the interpolation can overshoot them ([`Interp::value_bounds`]); if the opacity
//! map is 0 over that whole interval ([`ZeroSet::covers`]) no sample based in the cell can
//! contribute, and the cast passes over them without interpolating. A sample that reads a
//! non-finite voxel contributes nothing either way, so the ranges ignore such voxels.
//!
//! Skipping never moves a sample: along a straight line the cast jumps from a sample in an
//! empty cell over every following sample that lies in that cell or in the empty cells the
//! line crosses next ([`Jumps::skip`], a 3-D DDA over cells), to the first sample that may be
//! based in a non-empty one; positions are computed from the sample index alone
//! ([`LineSamples::point`]), so the samples that are looked at are exactly those of the walk.
//! Crossings are computed on the ideal line; a sample's base can differ from the cell its
//! ideal position lies in only within the SPEC §4.5 snapping tolerance plus rounding of a
//! boundary, so a jump stops that margin short of a non-empty cell, and at cell corners,
//! where a sample may be counted in a cell the line does not cross. Images are therefore
//! the same, bit for bit, with skipping on or off. Samples of an exact distorted walk do not
//! lie on a line; they are tested one by one.

use std::borrow::Cow;
use std::sync::Arc;

use crate::dataset::macrocell::{Level, Macrocells, COARSE_SHIFT, MACROCELL_SHIFT};
use crate::dataset::ChannelName;
use crate::geometry::LineSamples;
use crate::interp::{Interp, Interpolation};
use crate::mapping::ZeroSet;

/// One object's view of its dataset's macrocells: the ranges of the channel its opacity
/// map reads and where that map is zero.
#[derive(Debug)]
pub(super) struct Skipper<'a> {
    cells: &'a Macrocells,
    /// The channel whose ranges `cells` are.
    channel: ChannelName,
    zero: Cow<'a, ZeroSet>,
    /// Whether the channel holds integers (bit, u8, u16, u32): convex interpolation of them
    /// stays inside a cell's range exactly.
    integer: bool,
    /// Every cell's answer, when the caster will serve many pieces
    /// ([`Skipper::classified`]); shared with the casters that found it kept
    /// ([`super::ClassificationCache`]).
    classes: Option<Arc<Classes>>,
}

/// Everything an object's classification of one loaded dataset's macrocells depends on
/// besides those macrocells: the channel, whether it holds integers, the interpolation
/// (which bounds how far a sample's value can leave its cell's range) and the opacity map's
/// zero set, all by their exact bits. Two objects of one load with equal keys have the same
/// classes and distances, bit for bit, whatever else their maps say.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub(crate) struct ClassKey {
    channel: ChannelName,
    integer: bool,
    /// The interpolation's kind and its ω (0 for the others).
    interpolation: (u8, [u64; 3]),
    zero: Vec<[u64; 3]>,
}

/// Every cell's answer worked out at bind: an object's classification of one loaded
/// dataset, which a [`super::ClassificationCache`] may keep for later binds.
#[derive(Debug)]
pub(crate) struct Classes {
    /// One bit per cell of each level (set: empty), x fastest.
    bits: [Vec<u64>; 2],
    /// Per macrocell, its chessboard distance in cells to the nearest non-empty one (0 for
    /// a non-empty cell, at most 255), so that a jump can leave a whole cube of empty cells
    /// at once ([`Jumps::skip`]); three bytes of padding after the last cell, so that
    /// reading four bytes at any cell stays inside.
    distance: Vec<u8>,
}

impl Classes {
    /// Bytes of its tables (what a cache that keeps it counts).
    pub(crate) fn bytes(&self) -> u64 {
        (8 * (self.bits[0].len() + self.bits[1].len()) + self.distance.len()) as u64
    }

    /// [`Classes::bytes`] of the classification of `cells`, before working it out.
    fn bytes_for(cells: &Macrocells) -> u64 {
        let count = |level| cells.cells(level).iter().map(|&n| n as usize).product::<usize>();
        let (fine, coarse) = (count(Level::Fine), count(Level::Coarse));
        (8 * (fine.div_ceil(64) + coarse.div_ceil(64)) + fine + 3) as u64
    }
}

/// The macrocells' answers as a vector loop reads them ([`Skipper::fine_classes`]).
pub(super) struct FineClasses<'s> {
    /// One bit per macrocell (set: empty), x fastest.
    pub bits: &'s [u64],
    /// Chessboard distances, as [`Classes::distance`].
    pub distance: &'s [u8],
    /// Macrocells along each axis.
    pub dims: [u32; 3],
}

/// The index of `cell` in a grid of `dims` cells, x fastest.
#[inline(always)]
fn cell_index(dims: [u32; 3], cell: [u32; 3]) -> usize {
    cell[0] as usize + dims[0] as usize * (cell[1] as usize + dims[1] as usize * cell[2] as usize)
}

impl<'a> Skipper<'a> {
    /// `None` when the map is non-zero everywhere: nothing could ever be skipped, so the
    /// cast does not even look at cells.
    pub(super) fn new(
        cells: &'a Macrocells,
        channel: ChannelName,
        zero: Cow<'a, ZeroSet>,
        integer: bool,
    ) -> Option<Skipper<'a>> {
        (!zero.is_empty()).then_some(Skipper { cells, channel, zero, integer, classes: None })
    }

    /// This classification with every cell's answer for `interp` worked out now, one bit per
    /// cell of each level: a cast then tests a bit (in a table that stays in cache) instead
    /// of fetching a range, bounding the interpolation and searching the zero set each time
    /// a ray enters a cell. Worth it for a caster that serves a dataset's whole turn (about
    /// 10 ns per cell, once); a caster bound for one piece does without.
    pub(super) fn classified<I: Interp>(self, interp: &I) -> Skipper<'a> {
        let classes = Arc::new(self.classify(interp));
        self.with_classes(classes)
    }

    /// This classification with `classes`, which must be what [`Skipper::classify`] gives
    /// for the interpolation the cast uses (found kept under [`Skipper::key`]).
    pub(super) fn with_classes(mut self, classes: Arc<Classes>) -> Skipper<'a> {
        debug_assert_eq!(classes.bytes(), Classes::bytes_for(self.cells));
        self.classes = Some(classes);
        self
    }

    /// What the classification depends on besides the macrocells, for `interpolation`, the
    /// function `interp` implements.
    pub(super) fn key(&self, interpolation: Interpolation) -> ClassKey {
        let interpolation = match interpolation {
            Interpolation::Nearest => (0, [0; 3]),
            Interpolation::Trilinear => (1, [0; 3]),
            Interpolation::Nonlinear { omega } => (2, omega.map(f64::to_bits)),
            Interpolation::Cubic => (3, [0; 3]),
        };
        ClassKey { channel: self.channel, integer: self.integer, interpolation, zero: self.zero.bits() }
    }

    /// The bytes [`Skipper::classify`] will take.
    pub(super) fn classes_bytes(&self) -> u64 {
        Classes::bytes_for(self.cells)
    }

    /// Every cell's answer for `interp` and each macrocell's distance to the nearest
    /// non-empty one ([`Skipper::classified`]).
    pub(super) fn classify<I: Interp>(&self, interp: &I) -> Classes {
        let bits = [Level::Fine, Level::Coarse].map(|level| {
            let [nx, ny, nz] = self.cells.cells(level);
            let mut bits = vec![0u64; (nx as usize * ny as usize * nz as usize).div_ceil(64)];
            let mut i = 0;
            for z in 0..nz {
                for y in 0..ny {
                    for x in 0..nx {
                        bits[i / 64] |= u64::from(self.compute(interp, level, [x, y, z])) << (i % 64);
                        i += 1;
                    }
                }
            }
            bits
        });
        let mut distance = chessboard_distance(&bits[Level::Fine as usize], self.cells.cells(Level::Fine));
        distance.extend([0; 3]);
        Classes { bits, distance }
    }

    /// The macrocells' answers and distances, if they were worked out at bind
    /// ([`Skipper::classified`]).
    pub(super) fn fine_classes(&self) -> Option<FineClasses<'_>> {
        self.classes.as_ref().map(|c| FineClasses {
            bits: &c.bits[Level::Fine as usize],
            distance: &c.distance,
            dims: self.cells.cells(Level::Fine),
        })
    }

    /// The range of the channel's finite values (`None` if it has none).
    pub(super) fn value_range(&self) -> Option<[f64; 2]> {
        self.cells.value_range()
    }

    /// Whether no sample based in cell `cell` of `level` can contribute.
    #[inline]
    pub(super) fn is_empty<I: Interp>(&self, interp: &I, level: Level, cell: [u32; 3]) -> bool {
        match &self.classes {
            Some(classes) => {
                let i = cell_index(self.cells.cells(level), cell);
                classes.bits[level as usize][i / 64] >> (i % 64) & 1 == 1
            }
            None => self.compute(interp, level, cell),
        }
    }

    /// [`Skipper::is_empty`] worked out from the cell's range.
    fn compute<I: Interp>(&self, interp: &I, level: Level, cell: [u32; 3]) -> bool {
        let radius = interp.cell_radius();
        let [lo, hi] =
            if radius == 0 { self.cells.range(level, cell) } else { self.cells.range_around(level, cell, radius) };
        if lo > hi {
            // No finite voxel in reach: every sample here is non-finite.
            return true;
        }
        let (lo, hi) = interp.value_bounds(lo as f64, hi as f64, self.integer);
        self.zero.covers(lo, hi)
    }
}

/// The macrocell a sample with base voxel `base` belongs to.
#[inline(always)]
pub(super) fn cell_of(base: [u32; 3]) -> [u32; 3] {
    base.map(|b| b >> MACROCELL_SHIFT)
}

/// A straight line of samples prepared for jumps: per axis, where it starts, how many
/// samples it takes per unit of VC, where sample bases fall, and the margin (in samples)
/// within which a sample near a cell's bound might be based across it (computed once per
/// piece).
pub(super) struct Jumps {
    n: u64,
    start: [f64; 3],
    /// n/δ per axis: sample index per unit of coordinate (±∞ where the line is parallel).
    samples_per_unit: [f64; 3],
    /// Per axis: the largest base index and the offset of base cells ([`Interp::base_grid`]).
    grid: [(u32, f64); 3],
    /// Per axis: how far, in samples, the base cell of a sample may be from where its ideal
    /// position puts it — the snapping tolerance and the rounding of its coordinate, times
    /// samples per unit, plus the rounding of the crossing index itself.
    margin: [f64; 3],
}

/// Jumps stop at a crossing whose margin is this wide or wider (a line nearly parallel to
/// a cell face, or a huge dataset's snapping tolerance): the samples there are looked at
/// one by one instead.
const MAX_MARGIN: f64 = 0.25;

impl Jumps {
    pub(super) fn new<I: Interp>(interp: &I, line: &LineSamples) -> Jumps {
        Jumps::with_rounding(interp, line, f64::EPSILON)
    }

    /// For samples whose positions, and leaps, are computed in f32 ([`super::packet`]):
    /// the margins cover f32's rounding of their coordinates and of the crossing indices.
    pub(super) fn for_f32<I: Interp>(interp: &I, line: &LineSamples) -> Jumps {
        Jumps::with_rounding(interp, line, f64::from(f32::EPSILON))
    }

    /// Jumps for samples whose coordinates are computed with machine epsilon `epsilon`.
    fn with_rounding<I: Interp>(interp: &I, line: &LineSamples, epsilon: f64) -> Jumps {
        let n = line.len() as f64;
        let (start, delta) = (line.start(), line.delta());
        let samples_per_unit = delta.map(|d| n / d);
        let margin = std::array::from_fn(|a| {
            // A coordinate is vc0 + δ·((k + ½)·(1/n)): a few roundings off the ideal line
            // (five in f32, where vc0, δ and 1/n are rounded too).
            let position = 8.0 * epsilon * (start[a].abs() + delta[a].abs());
            let index = 8.0 * epsilon * (n + 1.0);
            2.0 * ((interp.span_tolerance(a) + position) * samples_per_unit[a].abs() + index) + 1e-12
        });
        let grid = std::array::from_fn(|a| interp.base_grid(a));
        Jumps { n: line.len(), start, samples_per_unit, grid, margin }
    }

    /// Per axis: where the line starts, samples per unit of VC, and the margin of a
    /// crossing (for loops that leap in registers as [`Jumps::skip`] does).
    pub(super) fn parts(&self) -> [[f64; 3]; 3] {
        [self.start, self.samples_per_unit, self.margin]
    }

    /// Given that sample `k` is based in macrocell `cell`, which `skipper` classifies empty:
    /// the index of the next sample that may contribute. If the coarse block around the cell
    /// is empty too, the jump runs over coarse blocks, else over macrocells.
    pub(super) fn skip<I: Interp>(&self, interp: &I, skipper: &Skipper<'_>, k: u64, cell: [u32; 3]) -> u64 {
        if let Some(classes) = &skipper.classes {
            let d = classes.distance[cell_index(skipper.cells.cells(Level::Fine), cell)];
            return self.leap(k, cell, u32::from(d));
        }
        let block = cell.map(|c| c >> (COARSE_SHIFT - MACROCELL_SHIFT));
        if skipper.is_empty(interp, Level::Coarse, block) {
            self.walk_empty(interp, skipper, Level::Coarse, k, block)
        } else {
            self.walk_empty(interp, skipper, Level::Fine, k, cell)
        }
    }

    /// Walks the cells of `level` the line crosses from `cell` (a 3-D DDA) while they are
    /// empty, without locating samples, and stops before the first sample that may be based
    /// in a non-empty cell: one within a crossing's margin of a non-empty cell, near two
    /// crossings at once (a cell corner, where a sample may be based in a cell the line does
    /// not cross), or at a crossing whose margin is too wide to trust.
    fn walk_empty<I: Interp>(&self, interp: &I, skipper: &Skipper<'_>, level: Level, k: u64, cell: [u32; 3]) -> u64 {
        let n = self.n;
        let shift = level.shift();
        let size = (1u64 << shift) as f64;
        let mut cell = cell;
        // Sample k itself is based in an empty cell.
        let mut resume = k + 1;
        loop {
            let mut exits = [f64::INFINITY; 3];
            for (a, exit) in exits.iter_mut().enumerate() {
                let per_unit = self.samples_per_unit[a];
                let (max_base, offset) = self.grid[a];
                let c = cell[a];
                // The bound ahead: the cell's upper face going up, its lower face going down;
                // none beyond the last and first cells, whose samples are clamped into them.
                let bound = if per_unit > 0.0 && per_unit.is_finite() && c < max_base >> shift {
                    (c + 1) as f64 * size + offset
                } else if per_unit < 0.0 && per_unit.is_finite() && c > 0 {
                    c as f64 * size + offset
                } else {
                    continue;
                };
                // u(j) = u0 + δ·(j + ½)/n reaches the bound at j = (bound − u0)·n/δ − ½.
                *exit = (bound - self.start[a]) * per_unit - 0.5;
            }
            let a = if exits[0] <= exits[1] && exits[0] <= exits[2] {
                0
            } else if exits[1] <= exits[2] {
                1
            } else {
                2
            };
            let j = exits[a];
            if j.is_nan() || j >= n as f64 {
                // The line stays in this cell to the end of the piece (as before the
                // comparison was spelled out: NaN, which finite bounds cannot produce, too).
                return n;
            }
            // Samples before j − margin are based in this cell; the first one after it may not be.
            let first_unsafe = ceil_index(j - self.margin[a]);
            if first_unsafe <= resume {
                return resume;
            }
            resume = first_unsafe;
            let corner = (0..3).any(|b| b != a && (exits[b] - j).abs() <= self.margin[a] + self.margin[b]);
            if corner || self.margin[a] >= MAX_MARGIN {
                return resume;
            }
            // Samples within the margin of the crossing are based in this cell or the next.
            let mut next = cell;
            next[a] = if self.samples_per_unit[a] > 0.0 { cell[a] + 1 } else { cell[a] - 1 };
            if !skipper.is_empty(interp, level, next) {
                return resume;
            }
            cell = next;
        }
    }

    /// Given that sample `k` is based in macrocell `cell`, every cell within chessboard
    /// distance `d − 1` of which is empty (`d ≥ 1`): the first sample that may be based
    /// outside that cube of cells, found in one step (the line is monotone along each axis,
    /// so it stays in the cube until it crosses one of the faces ahead of it, with the same
    /// margins as the walk's crossings). Faces at the dataset's border are no bounds: samples
    /// beyond them are clamped into the border cells.
    fn leap(&self, k: u64, cell: [u32; 3], d: u32) -> u64 {
        let shift = Level::Fine.shift();
        let size = (1u64 << shift) as f64;
        let reach = d.max(1) - 1;
        let mut next = self.n;
        for (a, &c) in cell.iter().enumerate() {
            let per_unit = self.samples_per_unit[a];
            let (max_base, offset) = self.grid[a];
            let bound = if per_unit > 0.0 && per_unit.is_finite() && c + reach < max_base >> shift {
                (c + reach + 1) as f64 * size + offset
            } else if per_unit < 0.0 && per_unit.is_finite() && c > reach {
                (c - reach) as f64 * size + offset
            } else {
                continue;
            };
            let j = (bound - self.start[a]) * per_unit - 0.5;
            let x = j - self.margin[a];
            // NaN, which finite bounds cannot produce, leaps nowhere; past the piece's end (a
            // line nearly parallel to the face), as far as the end.
            let first_unsafe = if j.is_nan() {
                k + 1
            } else if x >= self.n as f64 {
                self.n
            } else {
                ceil_index(x)
            };
            next = next.min(first_unsafe);
        }
        next.max(k + 1)
    }
}

/// Per cell of a grid of `dims` cells whose empty ones are the set bits of `empty` (x
/// fastest): the chessboard distance to the nearest non-empty cell, at most 255 (so also
/// where there is none). Two raster passes with the 26-neighbourhood compute it exactly: a
/// forward pass takes each cell's minimum with one more than the 13 neighbours before it
/// in (z, y, x) order, and a backward pass (the forward pass over the grid mirrored on every
/// axis) the same with those after it.
fn chessboard_distance(empty: &[u64], dims: [u32; 3]) -> Vec<u8> {
    let n = dims.iter().map(|&n| n as usize).product();
    let mut d: Vec<u8> = (0..n).map(|i| if empty[i / 64] >> (i % 64) & 1 == 1 { u8::MAX } else { 0 }).collect();
    forward_pass(&mut d, dims);
    // Reversing the cells mirrors the grid on all three axes at once.
    d.reverse();
    forward_pass(&mut d, dims);
    d.reverse();
    d
}

/// [`chessboard_distance`]'s forward pass, a slice and a row at a time: the 9 neighbours in
/// the slice below are the previous slice's 3×3 minimum, the 3 in the row before are that
/// row's 3-minimum, both final by then, and the one before along the row a running minimum.
/// (The same minima as visiting the 13 neighbours cell by cell, in loops over whole rows and
/// slices, without a test per cell, that the compiler vectorises.)
fn forward_pass(d: &mut [u8], [nx, ny, nz]: [u32; 3]) {
    let [nx, ny, nz] = [nx, ny, nz].map(|n| n as usize);
    let plane = nx * ny;
    // Per cell of the slice just finished: the minimum of its row's 3 cells around it
    // (`across`), then one more than the minimum of 3 of those rows (`below`, its 3×3
    // neighbourhood, for the next slice); `before`, one more than the 3-minimum of the row
    // before in this slice.
    let mut across = vec![u8::MAX; plane];
    let mut below = vec![u8::MAX; plane];
    let mut before = vec![u8::MAX; nx];
    for z in 0..nz {
        let slice = &mut d[z * plane..(z + 1) * plane];
        if z > 0 {
            for (c, &b) in slice.iter_mut().zip(&below) {
                *c = (*c).min(b);
            }
        }
        for y in 0..ny {
            let (done, rest) = slice.split_at_mut(y * nx);
            let row = &mut rest[..nx];
            if y > 0 {
                three_min_row(&done[(y - 1) * nx..], &mut before);
                for (c, &b) in row.iter_mut().zip(&before) {
                    *c = (*c).min(b.saturating_add(1));
                }
            }
            for x in 1..nx {
                row[x] = row[x].min(row[x - 1].saturating_add(1));
            }
        }
        // The 3×3 minimum of this (final) slice, plus one, for the next.
        for (row, out) in slice.chunks_exact(nx).zip(across.chunks_exact_mut(nx)) {
            three_min_row(row, out);
        }
        for y in 0..ny {
            let out = &mut below[y * nx..(y + 1) * nx];
            out.copy_from_slice(&across[y * nx..(y + 1) * nx]);
            if y > 0 {
                for (m, &a) in out.iter_mut().zip(&across[(y - 1) * nx..y * nx]) {
                    *m = (*m).min(a);
                }
            }
            if y + 1 < ny {
                for (m, &a) in out.iter_mut().zip(&across[(y + 1) * nx..(y + 2) * nx]) {
                    *m = (*m).min(a);
                }
            }
            for m in out.iter_mut() {
                *m = m.saturating_add(1);
            }
        }
    }
}

/// `out[x]`: the minimum of `row[x − 1..=x + 1]` within the row's `out.len()` cells.
#[inline(always)]
fn three_min_row(row: &[u8], out: &mut [u8]) {
    let nx = out.len();
    let row = &row[..nx];
    out.copy_from_slice(row);
    if nx > 1 {
        for (m, &r) in out[..nx - 1].iter_mut().zip(&row[1..]) {
            *m = (*m).min(r);
        }
        for (m, &r) in out[1..].iter_mut().zip(&row[..nx - 1]) {
            *m = (*m).min(r);
        }
    }
}

/// The smallest sample index ≥ x (0 for x ≤ 0), without a libm call.
#[inline]
fn ceil_index(x: f64) -> u64 {
    if x > 0.0 {
        let t = x as u64;
        t + u64::from((t as f64) < x)
    } else {
        0
    }
}

#[cfg(test)]
mod tests {
    use super::chessboard_distance;

    #[test]
    fn chessboard_distances_are_those_of_a_brute_force_search() {
        for (dims, seed, rarity) in [
            ([7u32, 5, 6], 1u64, 11),
            ([1, 9, 4], 2, 11),
            ([12, 1, 1], 3, 11),
            ([5, 5, 5], 4, 11),
            ([23, 17, 14], 5, 601),
        ] {
            let n = (dims[0] * dims[1] * dims[2]) as usize;
            // Empty everywhere but a few scattered cells (none at all for seed 4).
            let full: Vec<bool> =
                (0..n as u64).map(|i| seed != 4 && ((i * 2_654_435_761) ^ (seed * 97)) % rarity == 0).collect();
            let mut empty = vec![0u64; n.div_ceil(64)];
            for (i, &f) in full.iter().enumerate() {
                empty[i / 64] |= u64::from(!f) << (i % 64);
            }
            let d = chessboard_distance(&empty, dims);
            let at = |i: usize| {
                let (x, y, z) = (
                    i as i64 % dims[0] as i64,
                    i as i64 / dims[0] as i64 % dims[1] as i64,
                    i as i64 / (dims[0] * dims[1]) as i64,
                );
                (x, y, z)
            };
            for (i, &d) in d.iter().enumerate() {
                let (x, y, z) = at(i);
                let nearest = (0..n)
                    .filter(|&j| full[j])
                    .map(|j| {
                        let (a, b, c) = at(j);
                        (x - a).abs().max((y - b).abs()).max((z - c).abs())
                    })
                    .min()
                    .unwrap_or(255)
                    .min(255);
                assert_eq!(i64::from(d), nearest, "cell {i} of {dims:?}");
            }
        }
    }
}
