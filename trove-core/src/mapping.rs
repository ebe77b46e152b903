//! Colour and opacity mapping functions (paper §2.3.2–2.3.3, SPEC §3.2).
//!
//! Classification happens after interpolation: the sampler interpolates the channel a map
//! reads, then calls [`ColourMap::map`] or [`OpacityMap::map`]. Results are clamped to
//! [0, 1]; a non-finite result is `None` and the sample contributes nothing.

use std::borrow::Cow;
use std::sync::OnceLock;

use crate::dataset::ChannelName;

/// Which channels a raw colour map reads, decided once at scene load from what the
/// dataset has (SPEC §3.2: red/green/blue, else grey, else bit).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RawColour {
    /// `red`, `green`, `blue`, each /255.
    Rgb,
    /// `grey` /255 as (g, g, g).
    Grey,
    /// `bit` as (b, b, b).
    Bit,
}

impl RawColour {
    /// The channels read, in r, g, b order (repeated for grey and bit).
    pub fn channels(self) -> [ChannelName; 3] {
        match self {
            RawColour::Rgb => [ChannelName::Red, ChannelName::Green, ChannelName::Blue],
            RawColour::Grey => [ChannelName::Grey; 3],
            RawColour::Bit => [ChannelName::Bit; 3],
        }
    }
}

/// Finds, for a value v, how many of a sorted list of break points are ≤ v — the segment v
/// falls in — in constant expected time: a uniform grid over the break points' span gives a
/// first guess, and a short walk corrects it. The answer is exactly
/// `breaks.partition_point(|&x| x <= v)`, so maps evaluate as SPEC §3.2 defines them, without
/// a binary search per sample.
#[derive(Clone, Debug)]
struct BreakIndex {
    /// The first break point; bins start here.
    lo: f64,
    /// Bins per unit of value (0 when the span is empty or infinite: one bin).
    scale: f64,
    /// `first[g]`: the answer at the start of bin g (a guess for every value in the bin).
    first: Vec<u32>,
}

/// Most grid bins per map (16 KiB of guesses).
const MAX_BINS: usize = 4096;

impl BreakIndex {
    fn new(breaks: &[f64]) -> BreakIndex {
        let bins = (breaks.len() * 4).next_power_of_two().clamp(8, MAX_BINS);
        let (lo, span) = match (breaks.first(), breaks.last()) {
            (Some(&a), Some(&b)) => (a, b - a),
            _ => (0.0, 0.0),
        };
        let scale = if span > 0.0 && span.is_finite() { bins as f64 / span } else { 0.0 };
        let first = if scale == 0.0 {
            vec![0]
        } else {
            (0..bins).map(|g| breaks.partition_point(|&x| x <= lo + g as f64 / scale) as u32).collect()
        };
        BreakIndex { lo, scale, first }
    }

    /// `breaks.partition_point(|&x| x <= v)`; `breaks` must be the list the index was built on.
    #[inline(always)]
    fn find(&self, breaks: &[f64], v: f64) -> usize {
        if v.is_nan() {
            return 0;
        }
        let g = (((v - self.lo) * self.scale) as i64).clamp(0, self.first.len() as i64 - 1);
        let mut i = self.first[g as usize] as usize;
        while i < breaks.len() && breaks[i] <= v {
            i += 1;
        }
        while i > 0 && breaks[i - 1] > v {
            i -= 1;
        }
        i
    }
}

/// One segment of a [`Piecewise`] map: y0 + ((v − x0)·(1/w))·dy. The reciprocal of the
/// width is taken once, so a sample pays a multiplication instead of a division (the result
/// differs from (v − x0)/w by at most an ulp or two, far below any image tolerance). A
/// constant segment has x0 = 0, 1/w = 1 and dy = 0, so it yields y0 for every finite v.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Segment<const N: usize> {
    x0: f64,
    inv_w: f64,
    y0: [f64; N],
    dy: [f64; N],
}

impl<const N: usize> Segment<N> {
    fn constant(y: [f64; N]) -> Segment<N> {
        Segment { x0: 0.0, inv_w: 1.0, y0: y, dy: [0.0; N] }
    }

    /// The segment's value at `v` (not clamped).
    #[inline(always)]
    fn eval(&self, v: f64) -> [f64; N] {
        let t = (v - self.x0) * self.inv_w;
        std::array::from_fn(|c| self.y0[c] + t * self.dy[c])
    }
}

/// A LUT or a ramp as one kind of map: break points splitting the line into segments, each
/// constant (LUT domains, ramp ends) or linear (ramp pieces), so the sampler needs one loop
/// for both. The segment is found exactly as SPEC §3.2 defines it (bounds and points belong
/// to the upper segment); a LUT entry is returned as is, a ramp piece is `y0 + t·(y1 − y0)`
/// with `t = (v − x0)·(1/(x1 − x0))`.
#[derive(Clone, Debug)]
pub struct Piecewise<const N: usize> {
    breaks: Vec<f64>,
    /// `breaks.len() + 1` segments: segment i holds the values v with i break points ≤ v.
    segments: Vec<Segment<N>>,
    index: BreakIndex,
}

impl<const N: usize> Piecewise<N> {
    fn new(breaks: Vec<f64>, segments: Vec<Segment<N>>) -> Piecewise<N> {
        debug_assert_eq!(segments.len(), breaks.len() + 1);
        let index = BreakIndex::new(&breaks);
        Piecewise { breaks, segments, index }
    }

    /// The map that is `y` everywhere: one constant segment, no break point. For every
    /// finite value it gives exactly what a constant [`Polynomial`] of `y` gives (both add
    /// a zero product to `y`), so a constant opacity can join a piecewise colour map.
    pub(crate) fn constant(y: [f64; N]) -> Piecewise<N> {
        Piecewise::new(Vec::new(), vec![Segment::constant(y)])
    }

    /// Which segment `v` falls in.
    #[inline(always)]
    fn segment(&self, v: f64) -> usize {
        self.index.find(&self.breaks, v)
    }

    /// The map's value at a finite `v` (not clamped).
    #[inline(always)]
    pub fn eval(&self, v: f64) -> [f64; N] {
        self.segments[self.segment(v)].eval(v)
    }
}

/// A piecewise colour map and a piecewise opacity map merged, so that a sample finds both of
/// its segments with one lookup instead of two. The joint break points are the union of the
/// two maps'; each joint segment holds copies of the colour and the opacity segment that
/// apply over it (no break point of either map falls inside it), so every value evaluates
/// with exactly the arithmetic of the two maps apart.
#[derive(Clone, Debug)]
pub(crate) struct JointPiecewise {
    breaks: Vec<f64>,
    /// `breaks.len() + 1` pairs: over joint segment j, the opacity and the colour segment.
    segments: Vec<(Segment<1>, Segment<3>)>,
    index: BreakIndex,
}

impl JointPiecewise {
    pub(crate) fn new(colour: &Piecewise<3>, opacity: &Piecewise<1>) -> JointPiecewise {
        let mut breaks: Vec<f64> = colour.breaks.iter().chain(&opacity.breaks).copied().collect();
        breaks.sort_by(f64::total_cmp);
        breaks.dedup();
        // Over joint segment j ≥ 1, [breaks[j − 1], breaks[j]), a map's segment is the number
        // of its own break points ≤ breaks[j − 1]; below the first break point it is 0.
        let own = |map_breaks: &[f64], j: usize| match j {
            0 => 0,
            _ => map_breaks.partition_point(|&x| x <= breaks[j - 1]),
        };
        let segments = (0..=breaks.len())
            .map(|j| (opacity.segments[own(&opacity.breaks, j)], colour.segments[own(&colour.breaks, j)]))
            .collect();
        let index = BreakIndex::new(&breaks);
        JointPiecewise { breaks, segments, index }
    }

    /// The opacity and colour at a finite `v`, clamped; `None` when the sample contributes
    /// nothing (opacity 0 or a non-finite result). The colour is evaluated only when the
    /// opacity is not 0.
    #[inline(always)]
    pub(crate) fn classify(&self, v: f64) -> Option<(f64, [f64; 3])> {
        let (opacity, colour) = &self.segments[self.find(v)];
        let opacity = clamp1(opacity.eval(v)[0])?;
        if opacity == 0.0 {
            return None;
        }
        Some((opacity, clamp3(colour.eval(v))?))
    }

    /// [`JointPiecewise::classify`] with (0, black) for `None`, and no branch on `v`: both
    /// segments are evaluated and the result selected.
    #[inline(always)]
    pub(crate) fn classify_or_clear(&self, v: f64) -> (f64, [f64; 3]) {
        let (opacity, colour) = &self.segments[self.find(v)];
        let opacity = opacity.eval(v)[0];
        let colour = colour.eval(v);
        // Finite and positive opacity (clamping maps the rest to 0 or drops it), finite
        // colour.
        let ok = colour.iter().fold((opacity > 0.0) & (opacity < f64::INFINITY), |ok, c| ok & c.is_finite());
        if ok {
            (opacity.min(1.0), colour.map(|c| c.clamp(0.0, 1.0)))
        } else {
            (0.0, [0.0; 3])
        }
    }

    /// The break points, and per joint segment the opacity segment's x0, 1/w, y0, dy and
    /// the colour segment's x0, 1/w, y0 (3), dy (3), field by field: what a sampler that
    /// classifies several values at once gathers from.
    pub(crate) fn tables(&self) -> (&[f64], [Vec<f64>; 12]) {
        let field = |f: &dyn Fn(&(Segment<1>, Segment<3>)) -> f64| self.segments.iter().map(f).collect::<Vec<f64>>();
        let tables = [
            field(&|(o, _)| o.x0),
            field(&|(o, _)| o.inv_w),
            field(&|(o, _)| o.y0[0]),
            field(&|(o, _)| o.dy[0]),
            field(&|(_, c)| c.x0),
            field(&|(_, c)| c.inv_w),
            field(&|(_, c)| c.y0[0]),
            field(&|(_, c)| c.y0[1]),
            field(&|(_, c)| c.y0[2]),
            field(&|(_, c)| c.dy[0]),
            field(&|(_, c)| c.dy[1]),
            field(&|(_, c)| c.dy[2]),
        ];
        (&self.breaks, tables)
    }

    /// The joint segment of `v`: a count of break points ≤ v where there are few (no
    /// branch on `v`), else the index.
    #[inline(always)]
    fn find(&self, v: f64) -> usize {
        if self.breaks.len() <= SMALL_MAP {
            self.breaks.iter().map(|&b| usize::from(b <= v)).sum()
        } else {
            self.index.find(&self.breaks, v)
        }
    }
}

/// Maps with at most this many break points find a value's segment by counting.
pub(crate) const SMALL_MAP: usize = 16;

/// What a LUT stores per domain: an opacity or an RGB colour.
pub trait LutValue: Copy + std::fmt::Debug + PartialEq {
    /// The LUT as a [`Piecewise`] map.
    type Piecewise: Clone + std::fmt::Debug;
    /// Builds the piecewise form: one constant segment per domain.
    fn piecewise(bounds: &[f64], entries: &[Self]) -> Self::Piecewise;
}

impl LutValue for f64 {
    type Piecewise = Piecewise<1>;
    fn piecewise(bounds: &[f64], entries: &[f64]) -> Piecewise<1> {
        Piecewise::new(bounds.to_vec(), entries.iter().map(|&e| Segment::constant([e])).collect())
    }
}

impl LutValue for [f64; 3] {
    type Piecewise = Piecewise<3>;
    fn piecewise(bounds: &[f64], entries: &[[f64; 3]]) -> Piecewise<3> {
        Piecewise::new(bounds.to_vec(), entries.iter().map(|&e| Segment::constant(e)).collect())
    }
}

/// A look-up table: `s − 1` strictly increasing bounds split the line into `s` domains.
#[derive(Clone, Debug)]
pub struct Lut<T: LutValue> {
    bounds: Vec<f64>,
    entries: Vec<T>,
    piecewise: T::Piecewise,
    /// Where the map (as an opacity) yields nothing, computed on first use.
    zero: OnceLock<ZeroSet>,
}

impl<T: LutValue> PartialEq for Lut<T> {
    fn eq(&self, other: &Lut<T>) -> bool {
        self.bounds == other.bounds && self.entries == other.entries
    }
}

impl<T: LutValue> Lut<T> {
    /// `entries.len() == bounds.len() + 1` and strictly increasing finite bounds are checked
    /// by the scene validator; this constructor trusts them.
    pub(crate) fn new(bounds: Vec<f64>, entries: Vec<T>) -> Lut<T> {
        debug_assert_eq!(entries.len(), bounds.len() + 1);
        let piecewise = T::piecewise(&bounds, &entries);
        Lut { bounds, entries, piecewise, zero: OnceLock::new() }
    }

    /// v < d1 → e1; d(i−1) ≤ v < d(i) → e(i); v ≥ d(s−1) → es. A value equal to a bound
    /// maps to the upper domain.
    #[inline]
    pub fn lookup(&self, v: f64) -> T {
        self.entries[self.bounds.partition_point(|&d| d <= v)]
    }

    /// The LUT as a piecewise map (what the sampler evaluates).
    pub fn piecewise(&self) -> &T::Piecewise {
        &self.piecewise
    }
}

/// Polynomial coefficients in ascending powers, evaluated by Horner in f64.
#[derive(Clone, Debug, PartialEq)]
pub struct Polynomial(pub Vec<f64>);

impl Polynomial {
    /// The polynomial's value when it has no power of v (unclamped), else `None`.
    pub fn as_constant(&self) -> Option<f64> {
        (self.0.len() <= 1).then(|| self.0.first().copied().unwrap_or(0.0))
    }

    /// p(v).
    #[inline]
    pub fn eval(&self, v: f64) -> f64 {
        self.0.iter().rev().fold(0.0, |acc, &c| acc * v + c)
    }
}

/// A piecewise-linear ramp through points with non-decreasing abscissae, constant beyond
/// the ends. Where two points share an abscissa the ramp steps there, taking the later
/// point's value at the step itself (as a LUT takes its upper domain at a bound).
#[derive(Clone, Debug)]
pub struct Ramp<const N: usize> {
    xs: Vec<f64>,
    ys: Vec<[f64; N]>,
    piecewise: Piecewise<N>,
    /// Where the map (as an opacity) yields nothing, computed on first use.
    zero: OnceLock<ZeroSet>,
}

impl<const N: usize> PartialEq for Ramp<N> {
    fn eq(&self, other: &Ramp<N>) -> bool {
        self.xs == other.xs && self.ys == other.ys
    }
}

impl<const N: usize> Ramp<N> {
    /// Points are validated (finite, non-decreasing, at least one) by the scene validator.
    pub(crate) fn new(points: Vec<(f64, [f64; N])>) -> Ramp<N> {
        let (xs, ys): (Vec<f64>, Vec<[f64; N]>) = points.into_iter().unzip();
        // Segment i holds the values with i points ≤ v: below the first point and from the
        // last on the ramp is constant; between points i − 1 and i it is linear (a step,
        // where the two share an abscissa, holds no value).
        let last = ys.len() - 1;
        let segments = (0..=xs.len())
            .map(|i| {
                if i == 0 || i > last || xs[i - 1] >= xs[i] {
                    Segment::constant(ys[i.saturating_sub(1).min(last)])
                } else {
                    Segment {
                        x0: xs[i - 1],
                        inv_w: 1.0 / (xs[i] - xs[i - 1]),
                        y0: ys[i - 1],
                        dy: std::array::from_fn(|c| ys[i][c] - ys[i - 1][c]),
                    }
                }
            })
            .collect();
        let piecewise = Piecewise::new(xs.clone(), segments);
        Ramp { xs, ys, piecewise, zero: OnceLock::new() }
    }

    /// The ramp's value at `v`.
    #[inline]
    pub fn eval(&self, v: f64) -> [f64; N] {
        self.piecewise.eval(v)
    }

    /// The ramp as a piecewise map (what the sampler evaluates).
    pub fn piecewise(&self) -> &Piecewise<N> {
        &self.piecewise
    }
}

/// The values at which an opacity map yields no contribution — opacity 0 after clamping, or
/// a non-finite result — as sorted, disjoint intervals `[lo, hi)` or `[lo, hi]`. Empty-space
/// skipping asks whether a macrocell's whole range of values lies in one of them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ZeroSet {
    runs: Vec<Run>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct Run {
    lo: f64,
    hi: f64,
    hi_closed: bool,
}

impl ZeroSet {
    /// Whether the map yields something at every value (skipping can never apply).
    pub fn is_empty(&self) -> bool {
        self.runs.is_empty()
    }

    /// The set exactly, as bits (each run's bounds and whether its upper end is closed), so
    /// that a classification worked
    /// out from one can be kept under them (two sets with the same bits are the same set).
    pub(crate) fn bits(&self) -> Vec<[u64; 3]> {
        self.runs.iter().map(|r| [r.lo.to_bits(), r.hi.to_bits(), u64::from(r.hi_closed)]).collect()
    }

    /// Whether every value in `[lo, hi]` yields nothing.
    #[inline]
    pub fn covers(&self, lo: f64, hi: f64) -> bool {
        let i = self.runs.partition_point(|r| r.lo <= lo);
        if i == 0 {
            return false;
        }
        let r = self.runs[i - 1];
        hi < r.hi || (r.hi_closed && hi <= r.hi)
    }

    /// Appends `[lo, hi)` (or `[lo, hi]`), which must not start before the last run ends;
    /// touching runs are merged.
    fn push(&mut self, lo: f64, hi: f64, hi_closed: bool) {
        if let Some(last) = self.runs.last_mut() {
            if last.hi == lo {
                last.hi = hi;
                last.hi_closed = hi_closed;
                return;
            }
        }
        self.runs.push(Run { lo, hi, hi_closed });
    }

    /// The zero set of an opacity map from its segments: `pieces` lists each segment's span
    /// `[lo, hi)` and how the map behaves there, and `zero` is the map itself (true where it
    /// yields nothing), so the set is exact for the arithmetic the sampler does. On a
    /// monotone segment the zero part is an end of it, found by bisection over the f64
    /// values; a segment of any other shape is left out (safe: a smaller set skips less).
    fn of_segments(pieces: impl Iterator<Item = (f64, f64, Shape)>, zero: impl Fn(f64) -> bool) -> ZeroSet {
        let mut set = ZeroSet::default();
        for (lo, hi, shape) in pieces {
            if lo >= hi {
                continue;
            }
            // The last value inside the segment.
            let top = if hi == f64::INFINITY { f64::MAX } else { next_down(hi) };
            let bottom = if lo == f64::NEG_INFINITY { f64::MIN } else { lo };
            let (z_lo, z_top) = (zero(bottom), zero(top));
            match shape {
                Shape::Constant if z_lo => set.push(lo, hi, false),
                Shape::Increasing | Shape::Decreasing if z_lo && z_top => set.push(lo, hi, false),
                Shape::Increasing if z_lo => set.push(lo, last_true(bottom, top, &zero), true),
                Shape::Decreasing if z_top => set.push(first_true(bottom, top, &zero), hi, false),
                _ => {}
            }
        }
        set
    }
}

/// How a map behaves over one segment, for [`ZeroSet::of_segments`].
#[derive(Clone, Copy, Debug, PartialEq)]
enum Shape {
    Constant,
    /// Non-decreasing (in f64 arithmetic too: every step of the evaluation is monotone).
    Increasing,
    /// Non-increasing.
    Decreasing,
    /// Neither: left out of the zero set.
    Other,
}

/// The largest x in `[a, b]` with `pred` true on `[a, x]`, given `pred(a)` and that `pred`
/// is true then false over `[a, b]`.
fn last_true(a: f64, b: f64, pred: &impl Fn(f64) -> bool) -> f64 {
    let (mut lo, mut hi) = (order_key(a), order_key(b));
    if pred(b) {
        return b;
    }
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if pred(from_order_key(mid)) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    from_order_key(lo)
}

/// The smallest x in `[a, b]` with `pred` true on `[x, b]`, given `pred(b)` and that `pred`
/// is false then true over `[a, b]`: the value just above the last one where it is false.
fn first_true(a: f64, b: f64, pred: &impl Fn(f64) -> bool) -> f64 {
    if pred(a) {
        return a;
    }
    from_order_key(order_key(last_true(a, b, &|x| !pred(x))) + 1)
}

/// A key whose unsigned order is the order of the (non-NaN) f64 values, −0 just below +0.
fn order_key(x: f64) -> u64 {
    let b = x.to_bits();
    if b >> 63 == 1 {
        !b
    } else {
        b | 1 << 63
    }
}

fn from_order_key(k: u64) -> f64 {
    f64::from_bits(if k >> 63 == 1 { k & !(1 << 63) } else { !k })
}

/// The largest f64 below a finite `x`.
fn next_down(x: f64) -> f64 {
    from_order_key(order_key(x) - 1)
}

/// A colour mapping function 𝒞(v) (SPEC §3.2).
#[derive(Clone, Debug, PartialEq)]
pub enum ColourMap {
    /// Colour stored in the dataset's colour channels.
    Raw(RawColour),
    /// A look-up table over the voxel channel.
    Lut(Lut<[f64; 3]>),
    /// One polynomial per component over the voxel channel (also `constant` … `cubic`).
    Polynomial([Polynomial; 3]),
    /// A piecewise-linear ramp over the voxel channel.
    Ramp(Ramp<3>),
}

impl ColourMap {
    /// Whether the map reads the `voxel` channel.
    pub fn reads_voxel(&self) -> bool {
        match self {
            ColourMap::Raw(_) => false,
            ColourMap::Polynomial(p) => p.iter().any(|p| p.0.len() > 1),
            _ => true,
        }
    }

    /// 𝒞(v) for an interpolated voxel value, clamped to [0, 1]; `None` when v or the result is
    /// not finite (SPEC §3.2: the sample contributes nothing).
    /// For `Raw`, `v` is ignored: use [`ColourMap::map_raw`].
    #[inline]
    pub fn map(&self, v: f64) -> Option<[f64; 3]> {
        let c = match self {
            ColourMap::Raw(_) => return None,
            ColourMap::Lut(l) => l.piecewise().eval(v),
            ColourMap::Polynomial(p) => [p[0].eval(v), p[1].eval(v), p[2].eval(v)],
            ColourMap::Ramp(r) => r.eval(v),
        };
        clamp3(c)
    }

    /// Raw colour from interpolated channel values (bytes /255, bits as is).
    #[inline]
    pub fn map_raw(kind: RawColour, rgb: [f64; 3]) -> Option<[f64; 3]> {
        let scale = if kind == RawColour::Bit { 1.0 } else { 1.0 / 255.0 };
        clamp3(rgb.map(|c| c * scale))
    }
}

/// An opacity mapping function 𝒪(v) (SPEC §3.2).
#[derive(Clone, Debug, PartialEq)]
pub enum OpacityMap {
    /// Opacity from the `alpha` channel, /255.
    Raw,
    /// A look-up table over the voxel channel.
    Lut(Lut<f64>),
    /// A polynomial over the voxel channel (also `constant` … `cubic`).
    Polynomial(Polynomial),
    /// A piecewise-linear ramp over the voxel channel.
    Ramp(Ramp<1>),
}

impl OpacityMap {
    /// Whether the map reads the `voxel` channel.
    pub fn reads_voxel(&self) -> bool {
        match self {
            OpacityMap::Raw => false,
            OpacityMap::Polynomial(p) => p.0.len() > 1,
            _ => true,
        }
    }

    /// The opacity when the map ignores the data (a constant), so empty space can be
    /// recognised without interpolating.
    pub fn constant(&self) -> Option<f64> {
        match self {
            OpacityMap::Polynomial(p) if p.0.len() <= 1 => Some(p.eval(0.0).clamp(0.0, 1.0)),
            _ => None,
        }
    }

    /// Values where the map yields opacity 0 (a subset of where it yields nothing), for
    /// empty-space skipping:
    /// exact for raw opacity (alpha 0), LUTs, ramps and polynomials of degree ≤ 1, which are
    /// monotone on each piece; empty (no skipping) for polynomials of higher degree. LUTs and
    /// ramps compute it once and keep it.
    pub fn zero_set(&self) -> Cow<'_, ZeroSet> {
        // Only a clamped 0 counts: a non-finite result also yields nothing, but an increasing
        // polynomial overflows to +∞ at the far end, so counting it would break monotonicity.
        let zero = |v: f64| self.map(v) == Some(0.0);
        match self {
            OpacityMap::Raw => {
                let mut set = ZeroSet::default();
                set.push(f64::NEG_INFINITY, 0.0, true);
                Cow::Owned(set)
            }
            OpacityMap::Lut(l) => Cow::Borrowed(l.zero.get_or_init(|| {
                let b = &l.bounds;
                let pieces = (0..=b.len()).map(|i| {
                    let lo = if i == 0 { f64::NEG_INFINITY } else { b[i - 1] };
                    let hi = if i == b.len() { f64::INFINITY } else { b[i] };
                    (lo, hi, Shape::Constant)
                });
                ZeroSet::of_segments(pieces, zero)
            })),
            OpacityMap::Ramp(r) => Cow::Borrowed(r.zero.get_or_init(|| {
                let x = &r.xs;
                let pieces = (0..=x.len()).map(|i| {
                    let lo = if i == 0 { f64::NEG_INFINITY } else { x[i - 1] };
                    let hi = if i == x.len() { f64::INFINITY } else { x[i] };
                    let dy = r.piecewise.segments[i].dy[0];
                    let shape = if dy > 0.0 {
                        Shape::Increasing
                    } else if dy < 0.0 {
                        Shape::Decreasing
                    } else if dy == 0.0 {
                        Shape::Constant
                    } else {
                        Shape::Other
                    };
                    (lo, hi, shape)
                });
                ZeroSet::of_segments(pieces, zero)
            })),
            OpacityMap::Polynomial(p) => {
                // Horner on c0 + c1·v is monotone in v (each rounding step is); higher
                // degrees are not, and get no zero set.
                let shape = match p.0.as_slice() {
                    [] | [_] => Shape::Constant,
                    [_, c1] if *c1 > 0.0 => Shape::Increasing,
                    [_, c1] if *c1 < 0.0 => Shape::Decreasing,
                    [_, c1] if *c1 == 0.0 => Shape::Constant,
                    _ => Shape::Other,
                };
                Cow::Owned(ZeroSet::of_segments([(f64::NEG_INFINITY, f64::INFINITY, shape)].into_iter(), zero))
            }
        }
    }

    /// 𝒪(v), clamped to [0, 1]; `None` when v or the result is not finite. For `Raw`, pass alpha /255 through
    /// [`OpacityMap::map_raw`].
    #[inline]
    pub fn map(&self, v: f64) -> Option<f64> {
        let a = match self {
            OpacityMap::Raw => return None,
            OpacityMap::Lut(l) => l.piecewise().eval(v)[0],
            OpacityMap::Polynomial(p) => p.eval(v),
            OpacityMap::Ramp(r) => r.eval(v)[0],
        };
        clamp1(a)
    }

    /// Raw opacity from an interpolated alpha byte value.
    #[inline]
    pub fn map_raw(alpha: f64) -> Option<f64> {
        clamp1(alpha / 255.0)
    }
}

#[inline]
pub(crate) fn clamp1(a: f64) -> Option<f64> {
    a.is_finite().then(|| a.clamp(0.0, 1.0))
}

#[inline]
pub(crate) fn clamp3(c: [f64; 3]) -> Option<[f64; 3]> {
    c.iter().all(|x| x.is_finite()).then(|| c.map(|x| x.clamp(0.0, 1.0)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lut_bound_maps_to_upper_domain() {
        let l = Lut::new(vec![10.0, 20.0], vec![0.1, 0.2, 0.3]);
        assert_eq!(l.lookup(9.999), 0.1);
        assert_eq!(l.lookup(10.0), 0.2);
        assert_eq!(l.lookup(19.99), 0.2);
        assert_eq!(l.lookup(20.0), 0.3);
        assert_eq!(l.lookup(f64::INFINITY), 0.3);
        assert_eq!(l.lookup(f64::NEG_INFINITY), 0.1);
    }

    #[test]
    fn polynomial_is_horner_in_ascending_powers_and_clamps() {
        let p = Polynomial(vec![1.0, -2.0, 3.0]); // 1 - 2v + 3v^2
        assert_eq!(p.eval(2.0), 9.0);
        let o = OpacityMap::Polynomial(p);
        assert_eq!(o.map(2.0), Some(1.0));
        assert_eq!(o.map(0.5), Some(0.75));
        assert_eq!(OpacityMap::Polynomial(Polynomial(vec![-0.5])).map(3.0), Some(0.0));
        assert_eq!(o.map(f64::NAN), None);
    }

    #[test]
    fn ramp_is_piecewise_linear_constant_beyond_ends_and_steps_upward() {
        let r = Ramp::new(vec![(0.0, [0.0]), (10.0, [1.0]), (10.0, [0.2]), (20.0, [0.4])]);
        assert_eq!(r.eval(-5.0), [0.0]);
        assert_eq!(r.eval(5.0), [0.5]);
        assert_eq!(r.eval(10.0), [0.2]);
        assert!((r.eval(15.0)[0] - 0.3).abs() < 1e-15);
        assert_eq!(r.eval(25.0), [0.4]);
        let o = OpacityMap::Ramp(Ramp::new(vec![(0.0, [-1.0]), (1.0, [2.0])]));
        assert_eq!(o.map(-3.0), Some(0.0));
        assert_eq!(o.map(9.0), Some(1.0));
    }

    #[test]
    fn the_segment_index_finds_what_partition_point_finds() {
        let cases: [Vec<f64>; 5] = [
            vec![],
            vec![3.0],
            vec![0.0, 500.0, 800.0, 1000.0, 1150.0, 1300.0, 3272.0],
            vec![1.0, 1.0, 2.0, 2.0, 2.0, 9.5],
            (0..3000).map(|i| (i as f64).powf(1.3) - 40.0).collect(),
        ];
        for breaks in cases {
            let index = BreakIndex::new(&breaks);
            let mut values = vec![f64::NEG_INFINITY, f64::INFINITY, f64::NAN, -1e300, 1e300, -0.0, 0.0];
            for &b in &breaks {
                values.extend([b, next_down(b), from_order_key(order_key(b) + 1), b + 0.5, b - 0.25]);
            }
            values.extend((0..2000).map(|i| i as f64 * 3.7 - 100.0));
            for v in values {
                assert_eq!(
                    index.find(&breaks, v),
                    breaks.partition_point(|&x| x <= v),
                    "{v} in {} breaks",
                    breaks.len()
                );
            }
        }
    }

    #[test]
    fn luts_and_ramps_as_piecewise_maps_keep_their_values() {
        let l = Lut::new(vec![10.0, 20.0], vec![0.1, 0.2, 0.3]);
        for v in [-5.0, 9.999, 10.0, 15.0, 20.0, 1e9] {
            assert_eq!(l.piecewise().eval(v)[0], l.lookup(v), "{v}");
        }
        let r = Ramp::new(vec![(0.0, [0.0]), (10.0, [1.0]), (10.0, [0.2]), (20.0, [0.4])]);
        assert_eq!(r.eval(10.0), [0.2]);
        assert_eq!(r.eval(-3.0), [0.0]);
        assert!((r.eval(2.5)[0] - 0.25).abs() < 1e-15);
    }

    #[test]
    fn zero_sets_of_luts_are_their_zero_domains() {
        let o = OpacityMap::Lut(Lut::new(vec![10.0, 20.0, 30.0], vec![0.0, 0.0, 0.4, -1.0]));
        let z = o.zero_set();
        // [−∞, 20) and [30, ∞): a bound belongs to the upper domain.
        assert!(z.covers(-1e30, 19.999));
        assert!(!z.covers(5.0, 20.0));
        assert!(!z.covers(25.0, 25.0));
        assert!(z.covers(30.0, 1e30));
        assert!(!z.covers(29.999, 31.0));
    }

    #[test]
    fn zero_sets_of_ramps_end_exactly_where_the_map_stops_being_zero() {
        // Zero up to 500, then rising: the zero set is (−∞, c] with c the last f64 the ramp
        // maps to 0, found by bisection on the map itself.
        let o = OpacityMap::Ramp(Ramp::new(vec![(0.0, [0.0]), (500.0, [0.0]), (800.0, [0.004]), (1300.0, [0.3])]));
        let z = o.zero_set();
        assert!(z.covers(-1e9, 500.0));
        assert!(!z.covers(0.0, 500.000_001));
        let ends: Vec<f64> = z.runs.iter().map(|r| r.hi).collect();
        assert_eq!(ends.len(), 1);
        assert_eq!(o.map(ends[0]), Some(0.0));
        assert!(o.map(from_order_key(order_key(ends[0]) + 1)).unwrap() > 0.0);
        // Falling to zero and staying there: [c, ∞).
        let falling = OpacityMap::Ramp(Ramp::new(vec![(0.0, [0.5]), (10.0, [-0.5])]));
        let z = falling.zero_set();
        assert!(z.covers(5.0, 1e300));
        assert!(!z.covers(4.99, 6.0));
        assert_eq!(falling.map(z.runs[0].lo), Some(0.0));
        assert!(falling.map(next_down(z.runs[0].lo)).unwrap() > 0.0);
        // Never zero.
        assert!(OpacityMap::Ramp(Ramp::new(vec![(0.0, [0.1]), (1.0, [0.5])])).zero_set().is_empty());
        // A step to zero at an abscissa shared by two points.
        let step = OpacityMap::Ramp(Ramp::new(vec![(0.0, [0.5]), (4.0, [0.5]), (4.0, [0.0]), (9.0, [0.0])]));
        assert!(step.zero_set().covers(4.0, 1e9));
        assert!(!step.zero_set().covers(3.999, 5.0));
    }

    #[test]
    fn zero_sets_of_polynomials_and_raw_alpha() {
        let linear = OpacityMap::Polynomial(Polynomial(vec![-1.0, 0.01]));
        let z = linear.zero_set();
        assert!(z.covers(-1e300, 100.0));
        assert!(!z.covers(0.0, 100.000_000_1));
        assert!(OpacityMap::Polynomial(Polynomial(vec![0.0])).zero_set().covers(-1e300, 1e300));
        assert!(OpacityMap::Polynomial(Polynomial(vec![-1.0, 0.0, 1.0])).zero_set().is_empty());
        let raw = OpacityMap::Raw.zero_set();
        assert!(raw.covers(0.0, 0.0));
        assert!(!raw.covers(0.0, 1e-300));
    }

    #[test]
    fn raw_colour_scales_bytes_but_not_bits() {
        assert_eq!(ColourMap::map_raw(RawColour::Rgb, [255.0, 0.0, 51.0]), Some([1.0, 0.0, 0.2]));
        assert_eq!(ColourMap::map_raw(RawColour::Bit, [1.0, 1.0, 1.0]), Some([1.0; 3]));
        assert_eq!(ColourMap::map_raw(RawColour::Grey, [f64::NAN, 0.0, 0.0]), None);
    }

    #[test]
    fn joint_maps_classify_bit_for_bit_as_the_two_maps_apart() {
        // Break points shared, interleaved and doubled (a ramp's step), LUT against ramp.
        let colour_ramp = Ramp::new(vec![
            (0.0, [0.0, 0.1, 0.2]),
            (7.0, [0.3, 0.9, 0.1]),
            (10.0, [1.0, 0.5, 0.0]),
            (10.0, [0.2, 0.2, 0.2]),
            (31.5, [1.2, -0.3, 0.7]),
        ]);
        let colour_lut = Lut::new(vec![3.0, 10.0, 12.25], vec![[0.1; 3], [0.5, 0.6, 0.7], [0.9, 0.0, 0.3], [1.0; 3]]);
        let opacity_ramp = Ramp::new(vec![(2.0, [0.0]), (10.0, [0.3]), (12.25, [0.01]), (40.0, [1.5])]);
        let opacity_lut = Lut::new(vec![5.0, 7.0, 31.5], vec![0.0, 0.2, 0.0, 0.9]);
        let values: Vec<f64> = (-40..=400)
            .map(|i| f64::from(i) * 0.125)
            .chain(
                [3.0, 7.0, 10.0, 12.25, 31.5, 2.0, 40.0].into_iter().flat_map(|b: f64| [b.next_down(), b, b.next_up()]),
            )
            .chain([f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 1e300, -1e300])
            .collect();
        for colour in [colour_ramp.piecewise(), colour_lut.piecewise()] {
            for opacity in [opacity_ramp.piecewise(), opacity_lut.piecewise()] {
                let joint = JointPiecewise::new(colour, opacity);
                for &v in &values {
                    let apart = clamp1(opacity.eval(v)[0])
                        .filter(|&a| a != 0.0)
                        .and_then(|a| clamp3(colour.eval(v)).map(|c| (a, c)));
                    assert_eq!(joint.classify(v), apart, "{v}");
                    assert_eq!(joint.classify_or_clear(v), apart.unwrap_or((0.0, [0.0; 3])), "{v}");
                }
            }
        }
    }

    /// Maps with more break points than are counted find segments through the index; both
    /// ways give the segment a binary search gives.
    #[test]
    fn joint_segments_are_found_alike_by_counting_and_by_the_index() {
        for points in [3usize, SMALL_MAP / 2, SMALL_MAP + 1, 4 * SMALL_MAP] {
            let opacity = Ramp::new((0..points).map(|i| (i as f64 * 3.0, [(i % 3) as f64 * 0.4])).collect());
            let colour = Ramp::new((0..points).map(|i| (i as f64 * 2.0 + 1.0, [0.2, (i % 2) as f64, 0.5])).collect());
            let joint = JointPiecewise::new(colour.piecewise(), opacity.piecewise());
            for i in -20..(points as i32 * 40) {
                let v = f64::from(i) * 0.125;
                assert_eq!(joint.find(v), joint.breaks.partition_point(|&b| b <= v), "{points} points, {v}");
                let expected = joint.classify(v).unwrap_or((0.0, [0.0; 3]));
                assert_eq!(joint.classify_or_clear(v), expected, "{points} points, {v}");
            }
        }
    }
}
