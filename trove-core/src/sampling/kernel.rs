//! The sampler's loop, generic over what an object uses: interpolation `I`, the stored type
//! of its voxel channel `V`, and its colour and opacity maps `M`. Each combination is
//! compiled into its own loop, chosen once per object when it is bound
//! ([`super::bind`]), so the loop has no dispatch, allocation, search or copy per sample.
//! The general instance (`DynInterp`, a decoding reader, the map enums) is the same code
//! deciding per sample; it serves rare combinations and is what the specialised loops are
//! tested against.

use glam::DVec3;

use super::lanes::{Located, Trilinear4};
use super::packet::{Line, Packets};
use super::shade::Shade;
use super::simd::SimdPath;
use super::skip::{cell_of, Jumps, Skipper};
use super::{corrected_opacity, PieceResult};
use crate::composite::Rgba;
use crate::dataset::macrocell::Level;
use crate::dataset::{ChannelReader, Voxels};
use crate::geometry::{LineSamples, SampleWalk, WorldPoints};
use crate::interp::Interp;
use crate::mapping::{clamp1, clamp3, ColourMap, JointPiecewise, OpacityMap, Piecewise, Polynomial, RawColour};

/// Samples of a straight line computed together ([`Kernel::cast_line`]): four f64 lanes
/// are one AVX register, and more would compute more samples past an early termination.
pub(super) const LANES: usize = 4;

/// Samples per group in the AVX2 loop: two registers' worth, whose chains of dependent
/// operations (cell → index → gather → lerps → segment → gather → map) interleave.
#[cfg(target_arch = "x86_64")]
pub(super) const AVX2_LANES: usize = 8;

/// Casting one object over one piece, whatever its combination (the only dynamic call: one
/// per piece).
pub(super) trait Cast: Send + Sync {
    /// See [`super::ObjectCaster::cast`].
    fn cast(&self, walk: SampleWalk<'_>, alpha_in: f64, stop_at: f64) -> PieceResult;
    /// Casts many pieces, `(slot, walk, alpha_in, stop_at)`, each result into `out[slot]`:
    /// the same results as [`Cast::cast`] one by one, which is what this does unless the
    /// loop can cast several pieces at once ([`Cast::casts_packets`]).
    fn cast_many(&self, pieces: &mut dyn Iterator<Item = (usize, SampleWalk<'_>, f64, f64)>, out: &mut [PieceResult]);
    /// Whether this loop is a specialised one (for tests).
    fn is_specialised(&self) -> bool;
    /// Whether empty-space skipping is on (for tests).
    fn skips(&self) -> bool;
    /// Whether lines are cast in AVX2 registers (for tests).
    fn uses_avx2(&self) -> bool;
    /// The instruction set [`Cast::cast_many`] casts many pieces at a time in, one per f32
    /// lane ([`super::packet`]), if it does.
    fn packet_path(&self) -> Option<SimdPath>;
}

/// The value of the `voxel` channel at a sample, if the maps read it.
pub(super) trait VoxelSource: Send + Sync {
    /// Whether the channel is read (a non-finite value then drops the sample, SPEC §4.5).
    const READS: bool;
    /// The interpolated value (0 when not read).
    fn value<I: Interp>(&self, interp: &I, s: &I::Stencil) -> f64;
}

/// The `voxel` channel through a typed view (or the decoding reader).
#[derive(Clone, Copy)]
pub(super) struct Read<V>(pub V);

impl<V: Voxels> VoxelSource for Read<V> {
    const READS: bool = true;
    #[inline(always)]
    fn value<I: Interp>(&self, interp: &I, s: &I::Stencil) -> f64 {
        interp.apply(s, &self.0)
    }
}

/// No map reads the `voxel` channel.
#[derive(Clone, Copy)]
pub(super) struct NoVoxel;

impl VoxelSource for NoVoxel {
    const READS: bool = false;
    #[inline(always)]
    fn value<I: Interp>(&self, _interp: &I, _s: &I::Stencil) -> f64 {
        0.0
    }
}

/// The general path: the channel if some map reads it, else 0.
#[derive(Clone, Copy)]
pub(super) struct MaybeVoxel<'a>(pub Option<ChannelReader<'a>>);

impl VoxelSource for MaybeVoxel<'_> {
    const READS: bool = true;
    #[inline]
    fn value<I: Interp>(&self, interp: &I, s: &I::Stencil) -> f64 {
        self.0.as_ref().map_or(0.0, |r| interp.apply(s, r))
    }
}

/// An opacity map as the loop evaluates it: clamped to [0, 1], `None` when not finite.
pub(super) trait OpacityFn: Send + Sync {
    fn opacity<I: Interp>(&self, interp: &I, s: &I::Stencil, v: f64) -> Option<f64>;
}

/// A colour map as the loop evaluates it: clamped to [0, 1], `None` when not finite.
pub(super) trait ColourFn: Send + Sync {
    fn colour<I: Interp>(&self, interp: &I, s: &I::Stencil, v: f64) -> Option<[f64; 3]>;
}

impl OpacityFn for &Piecewise<1> {
    #[inline(always)]
    fn opacity<I: Interp>(&self, _interp: &I, _s: &I::Stencil, v: f64) -> Option<f64> {
        clamp1(self.eval(v)[0])
    }
}

impl OpacityFn for &Polynomial {
    #[inline(always)]
    fn opacity<I: Interp>(&self, _interp: &I, _s: &I::Stencil, v: f64) -> Option<f64> {
        clamp1(self.eval(v))
    }
}

/// Raw opacity: the `alpha` channel /255.
pub(super) struct RawAlpha<V>(pub V);

impl<V: Voxels> OpacityFn for RawAlpha<V> {
    #[inline(always)]
    fn opacity<I: Interp>(&self, interp: &I, s: &I::Stencil, _v: f64) -> Option<f64> {
        OpacityMap::map_raw(interp.apply(s, &self.0))
    }
}

/// Any opacity map, decided per sample.
pub(super) struct GeneralOpacity<'a> {
    pub map: &'a OpacityMap,
    pub alpha: Option<ChannelReader<'a>>,
}

impl OpacityFn for GeneralOpacity<'_> {
    #[inline]
    fn opacity<I: Interp>(&self, interp: &I, s: &I::Stencil, v: f64) -> Option<f64> {
        match &self.alpha {
            Some(a) => OpacityMap::map_raw(interp.apply(s, a)),
            None => self.map.map(v),
        }
    }
}

impl ColourFn for &Piecewise<3> {
    #[inline(always)]
    fn colour<I: Interp>(&self, _interp: &I, _s: &I::Stencil, v: f64) -> Option<[f64; 3]> {
        clamp3(self.eval(v))
    }
}

impl ColourFn for &[Polynomial; 3] {
    #[inline(always)]
    fn colour<I: Interp>(&self, _interp: &I, _s: &I::Stencil, v: f64) -> Option<[f64; 3]> {
        clamp3([self[0].eval(v), self[1].eval(v), self[2].eval(v)])
    }
}

/// Raw colour from three channels (grey and bit name one channel three times).
pub(super) struct RawRgb<V> {
    pub kind: RawColour,
    pub channels: [V; 3],
}

impl<V: Voxels> ColourFn for RawRgb<V> {
    #[inline(always)]
    fn colour<I: Interp>(&self, interp: &I, s: &I::Stencil, _v: f64) -> Option<[f64; 3]> {
        ColourMap::map_raw(self.kind, self.channels.each_ref().map(|c| interp.apply(s, c)))
    }
}

/// Any colour map, decided per sample.
pub(super) struct GeneralColour<'a> {
    pub map: &'a ColourMap,
    pub raw: Option<(RawColour, [ChannelReader<'a>; 3])>,
    /// A polynomial map that reads no channel, evaluated once.
    pub constant: Option<[f64; 3]>,
}

impl ColourFn for GeneralColour<'_> {
    #[inline]
    fn colour<I: Interp>(&self, interp: &I, s: &I::Stencil, v: f64) -> Option<[f64; 3]> {
        match (&self.raw, self.constant) {
            (Some((kind, rgb)), _) => ColourMap::map_raw(*kind, rgb.each_ref().map(|c| interp.apply(s, c))),
            (None, Some(c)) => Some(c),
            (None, None) => self.map.map(v),
        }
    }
}

/// An object's colour and opacity maps as the loop classifies a sample with them.
pub(super) trait Maps: Send + Sync {
    /// The sample's opacity and colour, clamped; `None` when it contributes nothing (opacity
    /// 0, or a non-finite result). Opacity is mapped first: a sample of opacity 0 would add
    /// nothing whatever its colour, so its colour is not evaluated.
    fn classify<I: Interp>(&self, interp: &I, s: &I::Stencil, v: f64) -> Option<(f64, [f64; 3])>;

    /// [`Maps::classify`] with (0, black) for `None`; maps that can, answer without branching
    /// on `v`.
    #[inline(always)]
    fn classify_or_clear<I: Interp>(&self, interp: &I, s: &I::Stencil, v: f64) -> (f64, [f64; 3]) {
        self.classify(interp, s, v).unwrap_or((0.0, [0.0; 3]))
    }
}

/// A colour map and an opacity map evaluated apart.
pub(super) struct Separate<C, O> {
    pub colour: C,
    pub opacity: O,
}

impl<C: ColourFn, O: OpacityFn> Maps for Separate<C, O> {
    #[inline(always)]
    fn classify<I: Interp>(&self, interp: &I, s: &I::Stencil, v: f64) -> Option<(f64, [f64; 3])> {
        let opacity = self.opacity.opacity(interp, s, v)?;
        if opacity == 0.0 {
            return None;
        }
        Some((opacity, self.colour.colour(interp, s, v)?))
    }
}

/// LUT or ramp colour with LUT or ramp opacity: one segment lookup finds both.
impl Maps for JointPiecewise {
    #[inline(always)]
    fn classify<I: Interp>(&self, _interp: &I, _s: &I::Stencil, v: f64) -> Option<(f64, [f64; 3])> {
        JointPiecewise::classify(self, v)
    }

    #[inline(always)]
    fn classify_or_clear<I: Interp>(&self, _interp: &I, _s: &I::Stencil, v: f64) -> (f64, [f64; 3]) {
        JointPiecewise::classify_or_clear(self, v)
    }
}

/// One combination's loop and what it needs; `S` is whether (and how) it shades, the
/// axis of effects ([`super::shade`]).
pub(super) struct Kernel<'a, I, V, M, S> {
    pub interp: I,
    pub voxels: V,
    pub maps: M,
    pub shade: S,
    pub skip: Option<Skipper<'a>>,
    pub correction: bool,
    pub specialised: bool,
    /// The group's work in AVX2 registers, for the combinations that have it.
    pub lanes: Option<Trilinear4<'a>>,
    /// Many pieces at a time in f32 lanes, for the combinations that have it.
    pub packets: Option<Packets<'a>>,
}

/// Where a group's samples are: one stencil each, or the AVX2 loop's lanes.
enum Group<'k, 'a, S, const L: usize> {
    Stencils([S; L]),
    Lanes(Located<L>, &'k Trilinear4<'a>),
}

impl<I: Interp, V: VoxelSource, M: Maps, S: Shade> Kernel<'_, I, V, M, S> {
    /// The opacity and colour of one sample, or (0, black) when it contributes nothing,
    /// computed without branching on the data: the samples of a group then overlap in the
    /// processor instead of each waiting on a mispredicted branch (opacity 0 in haze is
    /// common and unpredictable). Compositing (0, black) leaves a ray's colour and opacity
    /// unchanged bit for bit, so every sample can be composited.
    #[inline(always)]
    fn mapped(&self, s: &I::Stencil) -> (f64, [f64; 3]) {
        let v = self.voxels.value(&self.interp, s);
        let (opacity, colour) = self.maps.classify_or_clear(&self.interp, s, v);
        // A non-finite value contributes nothing (SPEC §4.5).
        let ok = !V::READS || v.is_finite();
        (if ok { opacity } else { 0.0 }, if ok { colour } else { [0.0; 3] })
    }

    /// Composites a mapped sample behind `acc` (opacity corrected for ℓ when the scene asks);
    /// true when the cast may stop: only a sample that added opacity can end it (`&`, not
    /// `&&`: no branch on the data).
    #[inline(always)]
    fn composite(
        &self,
        (opacity, colour): (f64, [f64; 3]),
        ell: f64,
        acc: &mut Rgba,
        done: impl Fn(&Rgba) -> bool,
    ) -> bool {
        let alpha = if self.correction { corrected_opacity(opacity, ell) } else { opacity };
        acc.add_sample(colour, alpha);
        (alpha != 0.0) & done(acc)
    }

    /// The samples of a straight line in groups ([`LANES`], or [`AVX2_LANES`] in AVX2
    /// registers): positions, stencils, values and classification of a group are independent
    /// of each other, and only compositing, which is sequential, goes sample by sample
    /// (stopping at the same sample as one at a time would). A group whose first sample lies in an empty macrocell jumps instead; later
    /// samples of a group that lie in empty cells are not composited (nor counted).
    fn cast_line(&self, line: &LineSamples, alpha_in: f64, stop_at: f64) -> PieceResult {
        #[cfg(target_arch = "x86_64")]
        if self.lanes.is_some() {
            // SAFETY: lanes exist only where the processor has AVX2.
            return unsafe { self.cast_line_avx2(line, alpha_in, stop_at) };
        }
        self.cast_line_any::<LANES>(line, alpha_in, stop_at, None)
    }

    /// The same loop compiled for AVX2, so that the lanes' intrinsics inline into it (as
    /// separate calls, with their results passed through memory, they gained a third as
    /// much). It runs the same arithmetic: images do not depend on which loop ran.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn cast_line_avx2(&self, line: &LineSamples, alpha_in: f64, stop_at: f64) -> PieceResult {
        self.cast_line_any::<AVX2_LANES>(line, alpha_in, stop_at, None)
    }

    /// [`Kernel::cast_line`]'s loop, for any target. A lit loop (`S::ON`) is given where
    /// its samples are in the world and the unit vector towards the eye (`lit`), and shades
    /// each sample that contributes just before compositing it; for an unlit one (`None`)
    /// that step is not compiled.
    #[inline(always)]
    fn cast_line_any<const L: usize>(
        &self,
        line: &LineSamples,
        alpha_in: f64,
        stop_at: f64,
        lit: Option<(&WorldPoints, DVec3)>,
    ) -> PieceResult {
        let mut acc = Rgba::CLEAR;
        let (mut samples, mut shaded) = (0, 0);
        let done = |acc: &Rgba| alpha_in + (1.0 - alpha_in) * acc.alpha >= stop_at;
        // The macrocell of the last sample looked at, and whether it is empty.
        let mut cell = [u32::MAX; 3];
        let mut empty = false;
        let ell = line.ell();
        let n = line.len();
        let jumps = self.skip.as_ref().map(|_| Jumps::new(&self.interp, line));
        let mut k = 0;
        'groups: while k < n {
            let m = (n - k).min(L as u64) as usize;
            // Lanes past the line's end repeat its last sample and are never composited.
            let group = match &self.lanes {
                Some(fast) => Group::Lanes(fast.locate(line, k, m), fast),
                None => {
                    // (Plain loops: `array::from_fn` is not inlined here, and costs more than
                    // the work.)
                    let mut stencils = [self.interp.locate(line.point(k)); L];
                    for (l, s) in stencils.iter_mut().enumerate().skip(1) {
                        *s = self.interp.locate(line.point(k + l.min(m - 1) as u64));
                    }
                    Group::Stencils(stencils)
                }
            };
            let mut live = [true; L];
            for live in live.iter_mut().skip(m) {
                *live = false;
            }
            if let (Some(skip), Some(jumps)) = (&self.skip, &jumps) {
                for (l, live) in live.iter_mut().enumerate().take(m) {
                    let base = match &group {
                        Group::Stencils(s) => self.interp.base(&s[l]),
                        Group::Lanes(at, _) => at.base(l),
                    };
                    let c = cell_of(base);
                    if c != cell {
                        cell = c;
                        empty = skip.is_empty(&self.interp, Level::Fine, c);
                    }
                    if empty {
                        if l == 0 {
                            k = jumps.skip(&self.interp, skip, k, c);
                            continue 'groups;
                        }
                        *live = false;
                    }
                }
            }
            let mapped = match &group {
                Group::Stencils(stencils) => {
                    let mut mapped = [(0.0, [0.0; 3]); L];
                    for (mapped, s) in mapped.iter_mut().zip(stencils) {
                        *mapped = self.mapped(s);
                    }
                    mapped
                }
                Group::Lanes(at, fast) => fast.classify(at),
            };
            for (l, (&mapped, live)) in mapped.iter().zip(live).enumerate() {
                if !live {
                    continue;
                }
                samples += 1;
                let mut mapped = mapped;
                if let (true, Some((at, view))) = (S::ON, lit) {
                    if mapped.0 > 0.0 {
                        shaded += 1;
                        let j = k + l as u64;
                        mapped.1 = self.shade.shade(&self.interp, line.point(j), at.at(j), view, mapped.1);
                    }
                }
                if self.composite(mapped, ell, &mut acc, done) {
                    break 'groups;
                }
            }
            k += m as u64;
        }
        PieceResult { rgba: acc, samples, shaded }
    }
}

thread_local! {
    /// A batch's straight pieces, kept from batch to batch on each thread: a batch's list
    /// (some 150 KB for 1024 pieces) is above the size from which the allocator maps and
    /// unmaps memory for each, depending on what it has freed before, and each unmapping
    /// stops the other threads to flush their address translations, then each page faults
    /// again (a third more casting time on Table 1's scene where that happened).
    static LINES: std::cell::RefCell<Vec<Line>> = const { std::cell::RefCell::new(Vec::new()) };
}

impl<I: Interp, V: VoxelSource, M: Maps, S: Shade> Cast for Kernel<'_, I, V, M, S> {
    fn cast(&self, walk: SampleWalk<'_>, alpha_in: f64, stop_at: f64) -> PieceResult {
        if let Some(line) = walk.line() {
            if S::ON {
                // A lit line: in groups with jumps over empty space, as the unlit loop casts
                // it ([`Kernel::cast_line_any`]), each contributing sample shaded.
                let at = walk.world_points();
                return self.cast_line_any::<LANES>(&line, alpha_in, stop_at, Some((&at, -walk.ray().dir)));
            }
            return self.cast_line(&line, alpha_in, stop_at);
        }
        // An exact distorted walk: samples one by one, each tested for empty space, and in
        // a lit loop (`S::ON`, a constant) each that contributes shaded before compositing.
        let mut acc = Rgba::CLEAR;
        let (mut samples, mut shaded) = (0, 0);
        let done = |acc: &Rgba| alpha_in + (1.0 - alpha_in) * acc.alpha >= stop_at;
        // The macrocell of the last sample looked at, and whether it is empty.
        let mut cell = [u32::MAX; 3];
        let mut empty = false;
        let (at, view) = (walk.world_points(), -walk.ray().dir);
        for (k, (vc, ell)) in walk.enumerate() {
            let Some(vc) = vc else { continue };
            let s = self.interp.locate(vc);
            if let Some(skip) = &self.skip {
                let c = cell_of(self.interp.base(&s));
                if c != cell {
                    cell = c;
                    empty = skip.is_empty(&self.interp, Level::Fine, c);
                }
                if empty {
                    continue;
                }
            }
            samples += 1;
            let (opacity, mut colour) = self.mapped(&s);
            if S::ON && opacity > 0.0 {
                shaded += 1;
                colour = self.shade.shade(&self.interp, vc, at.at(k as u64), view, colour);
            }
            if self.composite((opacity, colour), ell, &mut acc, done) {
                break;
            }
        }
        PieceResult { rgba: acc, samples, shaded }
    }

    fn cast_many(&self, pieces: &mut dyn Iterator<Item = (usize, SampleWalk<'_>, f64, f64)>, out: &mut [PieceResult]) {
        let Some(packets) = &self.packets else {
            for (slot, walk, alpha_in, stop_at) in pieces {
                out[slot] = self.cast(walk, alpha_in, stop_at);
            }
            return;
        };
        LINES.with_borrow_mut(|lines| {
            // Straight pieces in lanes; the others (exact distorted walks, lines too long for
            // f32 indices) one by one.
            lines.clear();
            for (slot, walk, alpha_in, stop_at) in pieces {
                match walk.line().filter(Line::fits) {
                    Some(line) => lines.push(Line { slot, line, world: walk.world_points(), alpha_in, stop_at }),
                    None => out[slot] = self.cast(walk, alpha_in, stop_at),
                }
            }
            packets.cast(self.skip.as_ref(), self.correction, lines, out);
        });
    }

    fn is_specialised(&self) -> bool {
        self.specialised
    }

    fn skips(&self) -> bool {
        self.skip.is_some()
    }

    fn uses_avx2(&self) -> bool {
        self.lanes.is_some()
    }

    fn packet_path(&self) -> Option<SimdPath> {
        self.packets.as_ref().map(Packets::path)
    }
}
