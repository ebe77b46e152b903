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
//! Skipping never moves a sample: along a straight line the cast jumps from sample k to the
//! first sample of the run that is based in another cell ([`run_end`]). Sample positions
//! are computed from k alone ([`LineSamples::point`]) and each component of the base index
//! is monotone in k, so if samples j < l are based in one cell every sample between them is
//! too: the jump is verified on the run's last sample and never skips a sample of another
//! cell. Images are therefore the same, bit for bit, with skipping on or off. Samples of an
//! exact distorted walk do not lie on a line; they are tested one by one.

use std::borrow::Cow;

use crate::dataset::macrocell::{Macrocells, MACROCELL_SHIFT};
use crate::geometry::LineSamples;
use crate::interp::Interp;
use crate::mapping::ZeroSet;

/// One object's view of its dataset's macrocells: the ranges of the channel its opacity
/// map reads and where that map is zero.
#[derive(Debug)]
pub(super) struct Skipper<'a> {
    cells: &'a Macrocells,
    zero: Cow<'a, ZeroSet>,
    /// Whether the channel holds integers (bit, u8, u16, u32): convex interpolation of them
    /// stays inside a cell's range exactly.
    integer: bool,
}

impl<'a> Skipper<'a> {
    /// `None` when the map is non-zero everywhere: nothing could ever be skipped, so the
    /// cast does not even look at cells.
    pub(super) fn new(cells: &'a Macrocells, zero: Cow<'a, ZeroSet>, integer: bool) -> Option<Skipper<'a>> {
        (!zero.is_empty()).then_some(Skipper { cells, zero, integer })
    }

    /// Whether no sample based in macrocell `cell` can contribute.
    #[inline]
    pub(super) fn is_empty<I: Interp>(&self, interp: &I, cell: [u32; 3]) -> bool {
        let radius = interp.cell_radius();
        let [lo, hi] = if radius == 0 { self.cells.range(cell) } else { self.cells.range_around(cell, radius) };
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

/// Given that sample `k` of `line` is based in `cell`, the index of the first sample after
/// it that is not (or `line.len()`), up to one short: the cast resumes there and looks
/// again. The crossing is estimated from the cell's span along each axis, then verified on
/// the run's last sample; if rounding made the estimate too long, a bisection over the
/// (monotone) membership finds the exact end.
pub(super) fn run_end<I: Interp>(interp: &I, line: &LineSamples, k: u64, cell: [u32; 3]) -> u64 {
    let n = line.len();
    let in_cell = |j: u64| cell_of(interp.base(&interp.locate(line.point(j)))) == cell;
    let (vc0, delta) = (line.start(), line.delta());
    let mut end = n;
    for (a, (&d, &u0)) in delta.iter().zip(&vc0).enumerate() {
        let (lo, hi) = interp.cell_span(a, cell[a]);
        let bound = if d > 0.0 {
            hi
        } else if d < 0.0 {
            lo
        } else {
            continue;
        };
        // u(j) = u0 + d·(j + ½)/n reaches the bound at j = n·(bound − u0)/d − ½.
        let j = (n as f64 * (bound - u0) / d - 0.5).ceil();
        if j < n as f64 {
            end = end.min(j.max(0.0) as u64);
        }
    }
    let last = end.max(k + 1) - 1;
    if last == k || in_cell(last) {
        return last + 1;
    }
    // Sample k is in the cell and `last` is not: bisect for the run's last sample.
    let (mut inside, mut outside) = (k, last);
    while outside - inside > 1 {
        let mid = inside + (outside - inside) / 2;
        if in_cell(mid) {
            inside = mid;
        } else {
            outside = mid;
        }
    }
    inside + 1
}
