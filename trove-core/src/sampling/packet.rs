//! Many pieces at a time, one per f32 lane, for a trilinear object over u8, u16 or f32 voxels
//! with a small joint LUT or ramp map when it casts many pieces at once (a batch of
//! Algorithm 2, a farm batch): [`Packets`]. The loop is written once over a SIMD width
//! ([`Simd`]) and compiled for each instruction set ([`SimdPath`]): two registers of
//! sixteen lanes on AVX-512, of eight on AVX2 with FMA, of four on NEON, and of four plain
//! array lanes anywhere.
//!
//! Along one ray, compositing is a chain (each sample waits for the opacity before it) and
//! a group of samples needs a long sequence of dependent steps, so the processor cannot run
//! far enough ahead to keep its units busy. Across rays there is no chain: each lane walks
//! its own piece sample by sample, and each step (position, cell, voxels, map, compositing)
//! does a register's worth of pieces' samples at once. Two registers ("halves") go side by
//! side, so that their chains of dependent steps interleave. A lane whose piece ends (its
//! last sample, or the opacity at which it may stop) takes the batch's next piece.
//! Neighbouring pieces of a batch are neighbouring pixels, so the lanes read nearby voxels.
//!
//! Each lane runs the operations the single-sample loop runs for its piece, in the same
//! order, in f32 ([`Packed`]): a register holds twice as many f32 lanes as f64 ones. Sample
//! k is where the f64 loop puts it up to a few f32 roundings (about 1e-7 of the
//! coordinates), so results differ from the f64 loops' by rounding (tests bound it to 1e-5
//! per piece on every path); a value that rounding could move across a LUT bound takes its
//! segment from the f64 value, so no sample changes class. Jumps over empty cells widen
//! their margins by f32's rounding of positions ([`Jumps::for_f32`]), and a sample is tested
//! empty by the cell of its f32 base, which is where its f32 value reads: skipping changes
//! no result.

use super::packed::{corrected, Grid, Packed, Stored};
use super::shade::{LaneShading, HALF_VECTORS};
use super::simd::avx2::Avx2;
use super::simd::avx512::Avx512;
use super::simd::neon::Neon;
use super::simd::scalar::Scalar;
use super::simd::{Simd, SimdPath};
use super::skip::{cell_of, FineClasses, Jumps, Skipper};
use super::PieceResult;
use crate::composite::Rgba;
use crate::dataset::macrocell::{Level, MACROCELL_SHIFT};
use crate::geometry::{LineSamples, WorldPoints};
use crate::interp::{Identity, Interp, Linear};
use crate::mapping::{JointPiecewise, SMALL_MAP};

/// A straight piece waiting for a lane: its slot in the results, its samples (in VC, and in
/// the world for lighting), the opacity in front of it and where it may stop.
pub(super) struct Line {
    pub slot: usize,
    pub line: LineSamples,
    pub world: WorldPoints,
    pub alpha_in: f64,
    pub stop_at: f64,
}

impl Line {
    /// Whether a lane can cast it: sample indices must be exact in f32.
    pub(super) fn fits(line: &LineSamples) -> bool {
        line.len() < 1 << 24
    }
}

/// Registers side by side: two halves, whose chains of dependent steps (position → cell →
/// voxels → map → compositing) interleave in the processor, as two registers' groups do
/// along a line ([`super::kernel::AVX2_LANES`]).
const HALVES: usize = 2;

/// Lanes of the widest path (AVX-512's sixteen, two halves): the size of the lane-by-lane
/// arrays, of which a narrower path uses the first `LANES · HALVES`.
const MAX_W: usize = 32;

/// The instruction set a [`Packets`] runs in, as the token its loop needs.
#[derive(Clone, Copy, Debug)]
enum Token {
    Avx512(Avx512),
    Avx2(Avx2),
    Neon(Neon),
    Scalar(Scalar),
}

impl Token {
    fn of(path: SimdPath) -> Option<Token> {
        Some(match path {
            SimdPath::Avx512 => Token::Avx512(Avx512::detect()?),
            SimdPath::Avx2 => Token::Avx2(Avx2::detect()?),
            SimdPath::Neon => Token::Neon(Neon::detect()?),
            SimdPath::Scalar => Token::Scalar(Scalar),
        })
    }
}

/// One object's packet loop: the f32 forms of its grid and map, the f64 interpolation and
/// break points it classifies values near a LUT bound with, the instruction set, and its
/// lighting when the object is shaded.
pub(super) struct Packets<'a> {
    interp: Linear<Identity>,
    grid: Grid<'a>,
    packed: Packed,
    breaks: Vec<f64>,
    token: Token,
    /// The lit loop's lighting ([`Packets::lit`]); `None`: the unlit loop, in which no
    /// step of lighting is compiled.
    shading: Option<LaneShading>,
}

/// The largest magnitude of f32 voxel values the packet loop takes: differences of two
/// values, and their trilinear blends, then stay finite in f32, so a sample is non-finite
/// there exactly where one of its eight voxels is, as in the f64 loops.
const F32_MAGNITUDE: f64 = 1e30;

impl<'a> Packets<'a> {
    /// The loop for `interp` over `voxels` with `maps` on `path`, where the processor has
    /// it, the map has at most [`SMALL_MAP`] break points and finite f32 forms, and the
    /// dataset fewer than 2³⁰ voxels (so indices and their neighbours' fit in i32 lanes).
    /// `range` is the channel's range of finite values where it is known (else its type's;
    /// f32 voxels need it, and it must be within [`F32_MAGNITUDE`]).
    pub(super) fn new(
        interp: &Linear<Identity>,
        voxels: Stored<'a>,
        maps: &JointPiecewise,
        range: Option<[f64; 2]>,
        path: SimdPath,
    ) -> Option<Packets<'a>> {
        // Gathers read voxels, and macrocell bits, as little-endian words.
        if cfg!(target_endian = "big") {
            return None;
        }
        let token = Token::of(path)?;
        let dims = interp.dims();
        let (breaks, tables) = maps.tables();
        if dims.voxel_count() >= 1 << 30 || breaks.len() > SMALL_MAP {
            return None;
        }
        let (rule, offsets) = interp.rule();
        let range = match voxels {
            Stored::U8(_) => range.unwrap_or([0.0, f64::from(u8::MAX)]),
            Stored::U16(_) => range.unwrap_or([0.0, f64::from(u16::MAX)]),
            // f32 values have no type's range to fall back on, and must stay where f32
            // differences of them cannot overflow (the f64 loops' never do).
            Stored::F32(_) => match range? {
                [lo, hi] if lo.abs().max(hi.abs()) <= F32_MAGNITUDE => [lo, hi],
                _ => return None,
            },
        };
        let packed = Packed::new(&rule, dims.voxel_count(), breaks, &tables, range)?;
        let [nx, ny, _] = dims.as_array();
        let grid = Grid {
            voxels,
            offsets: offsets.map(|o| o as i32),
            nx,
            ny,
            safe: voxels.safe_corner(offsets[0], offsets[1], offsets[2]),
        };
        Some(Packets { interp: *interp, grid, packed, breaks: breaks.to_vec(), token, shading: None })
    }

    /// The same loop lit by `shading` (SPEC §6): each sample that contributes shaded before
    /// it is composited.
    pub(super) fn lit(self, shading: LaneShading) -> Packets<'a> {
        let shading = if self.grid.voxels.is_float() { shading.rescaled() } else { shading };
        Packets { shading: Some(shading), ..self }
    }

    /// The instruction set the loop runs in.
    pub(super) fn path(&self) -> SimdPath {
        match self.token {
            Token::Avx512(_) => SimdPath::Avx512,
            Token::Avx2(_) => SimdPath::Avx2,
            Token::Neon(_) => SimdPath::Neon,
            Token::Scalar(_) => SimdPath::Scalar,
        }
    }

    /// Casts `lines` (each [`Line::fits`]), writing each result to `out[line.slot]`;
    /// `skip` is the object's empty-space skipper, `correction` whether opacity is
    /// corrected for the step.
    pub(super) fn cast(&self, skip: Option<&Skipper<'_>>, correction: bool, lines: &[Line], out: &mut [PieceResult]) {
        let cast = Cast { packets: self, skip, correction, lines };
        // Lighting is a constant of the loop: the unlit loop has no trace of it.
        match (self.token, self.shading.is_some()) {
            // SAFETY: a token exists only where the processor has its instructions.
            (Token::Avx512(s), false) => unsafe { cast.avx512::<false>(s, out) },
            (Token::Avx512(s), true) => unsafe { cast.avx512::<true>(s, out) },
            (Token::Avx2(s), false) => unsafe { cast.avx2::<false>(s, out) },
            (Token::Avx2(s), true) => unsafe { cast.avx2::<true>(s, out) },
            (Token::Neon(s), false) => unsafe { cast.neon::<false>(s, out) },
            (Token::Neon(s), true) => unsafe { cast.neon::<true>(s, out) },
            (Token::Scalar(s), false) => cast.run::<_, false>(s, out),
            (Token::Scalar(s), true) => cast.run::<_, true>(s, out),
        }
    }
}

/// One call's casting: the loop and what it is given.
struct Cast<'p, 'a, 's> {
    packets: &'p Packets<'a>,
    skip: Option<&'p Skipper<'s>>,
    correction: bool,
    lines: &'p [Line],
}

/// Each lane's piece and where it has got to, lane by lane: what the registers are loaded
/// from when a lane changes piece, and stored to when one ends.
struct Lanes {
    /// Index in the batch's lines of each lane's piece; `None` for an idle lane, whose
    /// registers keep positions inside the volume and which is never composited.
    piece: [Option<usize>; MAX_W],
    /// Sample k is at `origin + step·k` ([`Cast::refill`]).
    origin: [[f32; MAX_W]; 3],
    step: [[f32; MAX_W]; 3],
    n: [f32; MAX_W],
    /// The piece's own opacity at which it may stop ([`stop_alpha`]).
    stop_alpha: [f32; MAX_W],
    /// How far a sample's f32 value may be from its f64 value ([`Packed::slack`]).
    slack: [f32; MAX_W],
    /// The piece's step in voxels, ℓ, where opacity is corrected ([`corrected`]).
    ell: [f32; MAX_W],
    /// The sample each lane is at (an integer, exact in f32: pieces have fewer than 2²⁴).
    k: [f32; MAX_W],
    /// Σ c·w per colour channel, then A.
    acc: [[f32; MAX_W]; 4],
    samples: [f32; MAX_W],
    /// The macrocell of the lane's last sample and whether it is empty, where cells are
    /// classified on entry.
    cell: [[u32; 3]; MAX_W],
    empty: [bool; MAX_W],
    jumps: [Option<Jumps>; MAX_W],
    /// Each lane's [`Jumps::parts`]: start, samples per unit and margin, per axis.
    leap: [[[f32; MAX_W]; 3]; 3],
    /// For a lit loop: sample k is at `world + world_step·k` in the world, and `view` is the
    /// unit vector towards the eye; `shaded` counts the samples lit.
    world: [[f32; MAX_W]; 3],
    world_step: [[f32; MAX_W]; 3],
    view: [[f32; MAX_W]; 3],
    /// H of the directional lights whose H is kept per piece ([`LaneShading::half_vector`]).
    half_vector: [[[f32; MAX_W]; 3]; HALF_VECTORS],
    shaded: [f32; MAX_W],
}

impl Lanes {
    fn idle() -> Lanes {
        Lanes {
            piece: [None; MAX_W],
            origin: [[0.0; MAX_W]; 3],
            step: [[0.0; MAX_W]; 3],
            n: [0.0; MAX_W],
            stop_alpha: [0.0; MAX_W],
            slack: [0.0; MAX_W],
            ell: [0.0; MAX_W],
            k: [0.0; MAX_W],
            acc: [[0.0; MAX_W]; 4],
            samples: [0.0; MAX_W],
            cell: [[u32::MAX; 3]; MAX_W],
            empty: [false; MAX_W],
            jumps: [const { None }; MAX_W],
            leap: [[[0.0; MAX_W]; 3]; 3],
            world: [[0.0; MAX_W]; 3],
            world_step: [[0.0; MAX_W]; 3],
            view: [[0.0; MAX_W]; 3],
            half_vector: [[[0.0; MAX_W]; 3]; HALF_VECTORS],
            shaded: [0.0; MAX_W],
        }
    }

    /// The lanes that have a piece, one bit each.
    fn active(&self) -> u32 {
        let mut active = 0;
        for (l, piece) in self.piece.iter().enumerate() {
            active |= u32::from(piece.is_some()) << l;
        }
        active
    }
}

/// The piece's own opacity A at which `composite`'s test, α_in + (1 − α_in)·A ≥ stop_at,
/// holds: one comparison per sample instead of three operations and one.
fn stop_alpha(alpha_in: f64, stop_at: f64) -> f32 {
    if stop_at == f64::INFINITY {
        f32::INFINITY
    } else if alpha_in >= 1.0 {
        if stop_at <= 1.0 {
            f32::NEG_INFINITY
        } else {
            f32::INFINITY
        }
    } else {
        ((stop_at - alpha_in) / (1.0 - alpha_in)) as f32
    }
}

/// Half `h`'s bits of the lane bits `m` (`lanes` to a half).
#[inline(always)]
fn half(m: u32, h: usize, lanes: usize) -> u32 {
    (m >> (lanes * h)) & ((1u64 << lanes) - 1) as u32
}

/// Half `h` of a lane-by-lane array as a register.
#[inline(always)]
fn load<S: Simd>(s: S, a: &[f32; MAX_W], h: usize) -> S::F {
    s.load(&a[S::LANES * h..])
}

/// A register into half `h` of a lane-by-lane array.
#[inline(always)]
fn store<S: Simd>(s: S, a: &mut [f32; MAX_W], h: usize, v: S::F) {
    s.store(&mut a[S::LANES * h..], v)
}

/// The integer lanes of `v` (integers as f32), lane by lane (the first `S::LANES`).
#[inline(always)]
fn integers<S: Simd>(s: S, v: S::F) -> [i32; 16] {
    let mut a = [0; 16];
    s.store_i(&mut a, s.to_i32(v));
    a
}

/// Which of the cells `i` have their bit set in `bits` (read as 32-bit words: on a
/// little-endian processor bit i of the u64 words is bit i % 32 of word i / 32).
#[inline(always)]
fn bit_set<S: Simd>(s: S, bits: &[u64], i: S::I) -> u32 {
    // SAFETY: cell indices are below the cell count, whose bits lie inside `bits`.
    let words = unsafe { s.gather::<4>(bits.as_ptr().cast(), s.shr_i(i, 5)) };
    let bit = s.and_i(i, s.splat_i(31));
    let set = s.and_i(s.shr_each_i(words, bit), s.splat_i(1));
    s.bits(s.gt_i(set, s.splat_i(0)))
}

/// [`Jumps::skip`] for the lanes of half `h`, whose samples k lie in empty cells `cells`
/// (coordinates as f32, index) of a skipper with distances: `Jumps::leap`, operation by
/// operation, in f32 (whose rounding [`Jumps::for_f32`]'s margins cover; lanes not in empty
/// cells get a value that is not used).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn leaps<S: Simd>(
    s: S,
    lanes: &Lanes,
    h: usize,
    distance: &[u8],
    grid: &[(f32, f32); 3],
    (cell, index): ([S::F; 3], S::I),
    k: S::F,
    n: S::F,
) -> S::F {
    let one = s.splat(1.0);
    let zero = s.splat(0.0);
    let infinity = s.splat(f32::INFINITY);
    let size = s.splat((1u32 << MACROCELL_SHIFT) as f32);
    // SAFETY: the distance table has three bytes of padding: four bytes at any cell are
    // inside.
    let d = s.and_i(unsafe { s.gather::<1>(distance.as_ptr(), index) }, s.splat_i(0xff));
    let reach = s.sub(s.max(s.to_f32(d), one), one);
    let after = s.add(k, one);
    let mut next = n;
    for (a, &(last, offset)) in grid.iter().enumerate() {
        let start = load(s, &lanes.leap[0][a], h);
        let per_unit = load(s, &lanes.leap[1][a], h);
        let margin = load(s, &lanes.leap[2][a], h);
        let c = cell[a];
        let finite = s.lt(s.abs(per_unit), infinity);
        let up = s.and_m(finite, s.and_m(s.gt(per_unit, zero), s.lt(s.add(c, reach), s.splat(last))));
        let down = s.and_m(finite, s.and_m(s.lt(per_unit, zero), s.gt(c, reach)));
        let offset = s.splat(offset);
        let above = s.mul_add(s.add(s.add(c, reach), one), size, offset);
        let below = s.mul_add(s.sub(c, reach), size, offset);
        let bound = s.select(up, above, below);
        let j = s.sub(s.mul(s.sub(bound, start), per_unit), s.splat(0.5));
        // `ceil_index(j − margin)`, and k + 1 for a NaN j.
        let x = s.sub(j, margin);
        let first_unsafe = s.select(s.gt(x, zero), s.ceil(x), zero);
        let first_unsafe = s.select(s.is_nan(j), after, first_unsafe);
        next = s.select(s.or_m(up, down), s.min(next, first_unsafe), next);
    }
    s.max(next, after)
}

/// One half's registers: its lanes' pieces and where they have got to.
struct Half<S: Simd> {
    origin: [S::F; 3],
    step: [S::F; 3],
    n: S::F,
    stop_alpha: S::F,
    k: S::F,
    acc: [S::F; 4],
    samples: S::F,
}

impl<S: Simd> Half<S> {
    #[inline(always)]
    fn load(s: S, lanes: &Lanes, h: usize) -> Half<S> {
        let zero = s.splat(0.0);
        let mut origin = [zero; 3];
        let mut step = [zero; 3];
        let mut acc = [zero; 4];
        for a in 0..3 {
            origin[a] = load(s, &lanes.origin[a], h);
            step[a] = load(s, &lanes.step[a], h);
        }
        for (acc, lane) in acc.iter_mut().zip(&lanes.acc) {
            *acc = load(s, lane, h);
        }
        Half {
            origin,
            step,
            n: load(s, &lanes.n, h),
            stop_alpha: load(s, &lanes.stop_alpha, h),
            k: load(s, &lanes.k, h),
            acc,
            samples: load(s, &lanes.samples, h),
        }
    }

    /// Puts back what changes as the lanes walk.
    #[inline(always)]
    fn store(&self, s: S, lanes: &mut Lanes, h: usize) {
        store(s, &mut lanes.k, h, self.k);
        for (lane, &acc) in lanes.acc.iter_mut().zip(&self.acc) {
            store(s, lane, h, acc);
        }
        store(s, &mut lanes.samples, h, self.samples);
    }
}

/// The samples at each lane's k, looked up ahead of compositing them (so that their
/// voxels are fetched while the samples before are composited): per half, their values,
/// which lanes composite them (not those in empty cells), and the k each lane goes on to.
struct Looked<S: Simd> {
    value: [S::F; HALVES],
    live: u32,
    next_k: [S::F; HALVES],
}

/// What stays fixed over a batch.
struct Batch<'c> {
    classified: Option<FineClasses<'c>>,
    /// Per axis: the last macrocell a sample can be based in, and the base grid's offset.
    grid: [(f32, f32); 3],
}

impl Cast<'_, '_, '_> {
    /// [`Cast::run`] compiled for AVX-512.
    ///
    /// # Safety
    /// The processor must have what [`Avx512`] detects (the token proves it).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2,fma")]
    unsafe fn avx512<const LIT: bool>(&self, s: Avx512, out: &mut [PieceResult]) {
        self.run::<_, LIT>(s, out)
    }

    /// [`Cast::run`] compiled for AVX2 and FMA.
    ///
    /// # Safety
    /// The processor must have what [`Avx2`] detects (the token proves it).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn avx2<const LIT: bool>(&self, s: Avx2, out: &mut [PieceResult]) {
        self.run::<_, LIT>(s, out)
    }

    /// [`Cast::run`] compiled for NEON.
    ///
    /// # Safety
    /// The processor must have NEON (the token proves it).
    #[cfg(target_arch = "aarch64")]
    #[target_feature(enable = "neon")]
    unsafe fn neon<const LIT: bool>(&self, s: Neon, out: &mut [PieceResult]) {
        self.run::<_, LIT>(s, out)
    }

    /// Where the instruction set cannot be, neither can its token.
    #[cfg(not(target_arch = "x86_64"))]
    unsafe fn avx512<const LIT: bool>(&self, s: Avx512, _out: &mut [PieceResult]) {
        match s {}
    }

    #[cfg(not(target_arch = "x86_64"))]
    unsafe fn avx2<const LIT: bool>(&self, s: Avx2, _out: &mut [PieceResult]) {
        match s {}
    }

    #[cfg(not(target_arch = "aarch64"))]
    unsafe fn neon<const LIT: bool>(&self, s: Neon, _out: &mut [PieceResult]) {
        match s {}
    }

    /// The loop, for any instruction set, lit or (`LIT` false) not: casts the lines, each
    /// result to `out[line.slot]`.
    ///
    /// It is pipelined by one sample: the samples at k + 1 (or where a lane jumps to) are
    /// located, tested for empty space and interpolated before the samples at k are mapped
    /// and composited, so the voxel gathers of the one overlap the other's chain of
    /// dependent steps.
    #[inline(always)]
    fn run<S: Simd, const LIT: bool>(&self, s: S, out: &mut [PieceResult]) {
        let (packets, lines) = (self.packets, self.lines);
        let w = S::LANES * HALVES;
        // Lanes idle (their pieces ended) before they all take new pieces: a quarter.
        let refill_at = w / 4;
        let batch = Batch {
            classified: self.skip.and_then(Skipper::fine_classes),
            grid: std::array::from_fn(|a| {
                let (max_base, offset) = packets.interp.base_grid(a);
                ((max_base >> MACROCELL_SHIFT) as f32, offset as f32)
            }),
        };
        let mut lanes = Lanes::idle();
        let mut next = 0;
        for l in 0..w {
            next = self.refill(&mut lanes, l, next);
        }
        let one = s.splat(1.0);
        let zero = s.splat(0.0);
        let jumps = !packets.packed.jumps.is_empty();
        let (float, infinity) = (packets.grid.voxels.is_float(), s.splat(f32::INFINITY));
        // Lanes change pieces only here: the registers are loaded from `lanes`, the loop runs
        // until some lane ends, and its state goes back to `lanes`.
        'refilled: while lanes.active() != 0 {
            let mut active = lanes.active();
            let mut regs = [Half::load(s, &lanes, 0), Half::load(s, &lanes, 1)];
            let mut looked = self.look(s, &batch, &mut lanes, &regs, [regs[0].k, regs[1].k], active);
            loop {
                let ahead = self.look(s, &batch, &mut lanes, &regs, looked.next_k, active);
                let mut ended = 0;
                for (h, r) in regs.iter_mut().enumerate() {
                    let live_bits = half(looked.live & active, h, S::LANES);
                    let live = s.mask(live_bits);
                    let mut v = looked.value[h];
                    // An f32 voxel may be non-finite, and a sample blending one is: it
                    // contributes nothing (SPEC §4.5) but is looked at, as in the f64 loops.
                    // It is classified as 0, so that its colour is finite and its weight of
                    // 0 leaves the sums as they are. (The map's clamps would also give such a
                    // sample opacity 0, but only through the order of their operands.)
                    let finite = float.then(|| s.lt(s.abs(v), infinity));
                    if let Some(finite) = finite {
                        v = s.select(finite, v, zero);
                    }
                    let mut segment = packets.packed.segments(s, v);
                    if jumps {
                        let near = packets.packed.near_jumps(s, v, load(s, &lanes.slack, h)) & live_bits;
                        if near != 0 {
                            segment = self.exact_segments(s, &lanes, h, near, r.k, segment);
                        }
                    }
                    let (mut opacity, mut colour) = packets.packed.map(s, v, segment);
                    if let Some(finite) = finite {
                        opacity = s.select(finite, opacity, zero);
                    }
                    if let (true, Some(shading)) = (LIT, &packets.shading) {
                        // The samples that contribute (opacity > 0), as the f64 loop picks
                        // them; a register with none skips the gradient's gathers.
                        let lit = live_bits & s.bits(s.gt(opacity, zero));
                        if lit != 0 {
                            colour = self.shade(s, shading, &mut lanes, h, r, lit, colour);
                        }
                    }
                    let alpha = if self.correction { corrected(s, opacity, load(s, &lanes.ell, h)) } else { opacity };
                    // `Rgba::add_sample` in live lanes, then the stopping test of `composite`.
                    // Other lanes add a weight of +0 (colours are finite), which leaves
                    // their sums as they are, bit for bit: no select between the old and
                    // the new sum, which, with the sums kept in memory (AVX2 has too few
                    // registers for both halves), compiles to masked stores, slow on AMD
                    // processors and a stall for the loads that read them back.
                    let weight = s.select(live, s.neg_mul_add(alpha, r.acc[3], alpha), zero);
                    for (acc, &c) in r.acc.iter_mut().zip(&colour) {
                        *acc = s.mul_add(c, weight, *acc);
                    }
                    r.acc[3] = s.add(r.acc[3], weight);
                    let done = live_bits & s.bits(s.and_m(s.ne(alpha, zero), s.ge(r.acc[3], r.stop_alpha)));
                    r.samples = s.add(r.samples, s.select(live, one, zero));
                    r.k = looked.next_k[h];
                    let end = half(active, h, S::LANES) & (done | s.bits(s.ge(r.k, r.n)));
                    ended |= end << (S::LANES * h);
                }
                if ended != 0 {
                    // Ended lanes give their results and idle; they take new pieces only when
                    // a few are idle, since refilling reloads every register and looks at
                    // every lane's sample again.
                    for (h, r) in regs.iter().enumerate() {
                        r.store(s, &mut lanes, h);
                    }
                    for l in (0..w).filter(|l| ended >> l & 1 == 1) {
                        let piece = lanes.piece[l].take().expect("an ended lane was active");
                        let acc = &lanes.acc;
                        out[lines[piece].slot] = PieceResult {
                            rgba: Rgba {
                                colour: [acc[0][l], acc[1][l], acc[2][l]].map(f64::from),
                                alpha: f64::from(acc[3][l]),
                            },
                            samples: lanes.samples[l] as u64,
                            shaded: lanes.shaded[l] as u64,
                        };
                    }
                    active &= !ended;
                    let idle = w - active.count_ones() as usize;
                    if active == 0 || (idle >= refill_at && next < lines.len()) {
                        for l in 0..w {
                            if lanes.piece[l].is_none() {
                                next = self.refill(&mut lanes, l, next);
                            }
                        }
                        continue 'refilled;
                    }
                }
                looked = ahead;
            }
        }
    }

    /// The colours of half `h`'s samples at `r.k` (mapped to `colour`) lit by `shading`, and
    /// the lanes `lit` (those that contribute) counted as shaded: the gradient of the
    /// trilinear field there ([`Grid::gradient`]), then Blinn–Phong ([`LaneShading::shade`]).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn shade<S: Simd>(
        &self,
        s: S,
        shading: &LaneShading,
        lanes: &mut Lanes,
        h: usize,
        r: &Half<S>,
        lit: u32,
        colour: [S::F; 3],
    ) -> [S::F; 3] {
        let packets = self.packets;
        let (zero, one) = (s.splat(0.0), s.splat(1.0));
        let shaded = s.add(load(s, &lanes.shaded, h), s.select(s.mask(lit), one, zero));
        store(s, &mut lanes.shaded, h, shaded);
        let (mut u, mut x, mut view) = ([zero; 3], [zero; 3], [zero; 3]);
        for a in 0..3 {
            u[a] = s.mul_add(r.step[a], r.k, r.origin[a]);
            x[a] = s.mul_add(load(s, &lanes.world_step[a], h), r.k, load(s, &lanes.world[a], h));
            view[a] = load(s, &lanes.view[a], h);
        }
        let g = packets.grid.gradient(s, &packets.packed, u, lit);
        let half = |j: usize| -> [S::F; 3] { std::array::from_fn(|a| load(s, &lanes.half_vector[j][a], h)) };
        shading.shade(s, g, x, view, half, colour)
    }

    /// The samples at `k` (per half) of the lanes `active`: located
    /// ([`LineSamples::point`], then `Axis::cell`), tested for empty space (lanes in empty
    /// cells jump, as the single-sample loop does, and are not composited) and
    /// interpolated.
    #[inline(always)]
    fn look<S: Simd>(
        &self,
        s: S,
        batch: &Batch<'_>,
        lanes: &mut Lanes,
        regs: &[Half<S>; HALVES],
        k: [S::F; HALVES],
        active: u32,
    ) -> Looked<S> {
        let (packed, grid) = (&self.packets.packed, &self.packets.grid);
        let one = s.splat(1.0);
        let mut x0 = [[one; 3]; HALVES];
        let mut weights = [[one; 3]; HALVES];
        let mut next_k = [one; HALVES];
        for (h, r) in regs.iter().enumerate() {
            let mut u = [one; 3];
            for (a, u) in u.iter_mut().enumerate() {
                *u = s.mul_add(r.step[a], k[h], r.origin[a]);
            }
            (x0[h], weights[h]) = packed.cells(s, u);
            next_k[h] = s.select(s.mask(half(active, h, S::LANES)), s.add(k[h], one), k[h]);
        }
        let mut live = active;
        if let Some(skip) = self.skip {
            let mut empty = 0;
            let mut cells = [([one; 3], s.splat_i(0)); HALVES];
            for (h, &x0) in x0.iter().enumerate() {
                let e = match &batch.classified {
                    Some(classes) => {
                        let scale = s.splat(1.0 / (1u32 << MACROCELL_SHIFT) as f32);
                        let c =
                            [s.floor(s.mul(x0[0], scale)), s.floor(s.mul(x0[1], scale)), s.floor(s.mul(x0[2], scale))];
                        let [cx, cy, _] = classes.dims;
                        cells[h] = (c, packed.index(s, c, cx, cy));
                        bit_set(s, classes.bits, cells[h].1)
                    }
                    None => self.empty_lanes(s, skip, lanes, h, x0),
                };
                empty |= e << (S::LANES * h);
            }
            empty &= active;
            if empty != 0 {
                if let Some(FineClasses { distance, .. }) = batch.classified {
                    // Leaps over cubes of empty cells, in registers.
                    for (h, r) in regs.iter().enumerate() {
                        let e = half(empty, h, S::LANES);
                        if e != 0 {
                            let leap = leaps(s, lanes, h, distance, &batch.grid, cells[h], k[h], r.n);
                            next_k[h] = s.select(s.mask(e), leap, next_k[h]);
                        }
                    }
                } else {
                    for (h, &k) in k.iter().enumerate() {
                        store(s, &mut lanes.k, h, k);
                    }
                    self.jump(s, lanes, skip, empty, x0);
                    for (h, next_k) in next_k.iter_mut().enumerate() {
                        *next_k = s.select(s.mask(half(empty, h, S::LANES)), load(s, &lanes.k, h), *next_k);
                    }
                }
                live &= !empty;
            }
        }
        // Only the samples composited read voxels: a lane in empty space (about a fifth of
        // the CT head's lane slots are leaps) would otherwise bring in lines nothing else
        // needs.
        let mut value = [one; HALVES];
        for (h, value) in value.iter_mut().enumerate() {
            let index = packed.index(s, x0[h], grid.nx, grid.ny);
            *value = grid.trilinear(s, index, weights[h], half(live, h, S::LANES));
        }
        Looked { value, live, next_k }
    }

    /// The segments of half `h`'s lanes `near`, whose f32 values lie within rounding of a
    /// break point where the map jumps, counted from their f64 values (the rest of
    /// `segment` as it is).
    #[inline(always)]
    fn exact_segments<S: Simd>(&self, s: S, lanes: &Lanes, h: usize, near: u32, k: S::F, segment: S::I) -> S::I {
        let (mut ks, mut segments) = ([0.0f32; 16], [0i32; 16]);
        s.store(&mut ks, k);
        s.store_i(&mut segments, segment);
        self.exact_segments_of(lanes, S::LANES * h, near, &ks[..S::LANES], &mut segments[..S::LANES]);
        s.load_i(&segments)
    }

    /// [`Cast::exact_segments`] lane by lane, out of the loop's way: lane `l` of `near` is
    /// lane `first + l` of `lanes`, at sample `ks[l]`; its segment goes to `segments[l]`,
    /// as the single-sample loop computes it.
    #[cold]
    #[inline(never)]
    fn exact_segments_of(&self, lanes: &Lanes, first: usize, near: u32, ks: &[f32], segments: &mut [i32]) {
        let packets = self.packets;
        for (l, (segment, &k)) in segments.iter_mut().zip(ks).enumerate() {
            if near >> l & 1 == 0 {
                continue;
            }
            let piece = lanes.piece[first + l].expect("a live lane has a piece");
            let at = packets.interp.locate(self.lines[piece].line.point(k as u64));
            let v = match packets.grid.voxels {
                Stored::U8(voxels) => packets.interp.apply(&at, &voxels),
                Stored::U16(voxels) => packets.interp.apply(&at, &voxels),
                Stored::F32(voxels) => packets.interp.apply(&at, &voxels),
            };
            *segment = packets.breaks.iter().filter(|&&b| b <= v).count() as i32;
        }
    }

    /// The lanes of half `h` (as bits) whose samples, with lower corners `x0`, lie in empty
    /// macrocells, where cells are classified on entry: lane by lane, each lane classifying
    /// a cell when it enters it, as the single-sample loop does.
    #[inline(always)]
    fn empty_lanes<S: Simd>(&self, s: S, skip: &Skipper<'_>, lanes: &mut Lanes, h: usize, x0: [S::F; 3]) -> u32 {
        let base = [integers(s, x0[0]), integers(s, x0[1]), integers(s, x0[2])];
        let mut empty = 0;
        for (l, ((&x, &y), &z)) in base[0].iter().zip(&base[1]).zip(&base[2]).take(S::LANES).enumerate() {
            let lane = S::LANES * h + l;
            if lanes.piece[lane].is_none() {
                continue;
            }
            let c = cell_of([x as u32, y as u32, z as u32]);
            if c != lanes.cell[lane] {
                lanes.cell[lane] = c;
                lanes.empty[lane] = skip.is_empty(&self.packets.interp, Level::Fine, c);
            }
            empty |= u32::from(lanes.empty[lane]) << l;
        }
        empty
    }

    /// Moves each lane of `empty`, whose sample is based at `x0` (per half) in an empty
    /// cell, to the next sample that may contribute ([`Jumps::skip`]).
    #[inline(always)]
    fn jump<S: Simd>(&self, s: S, lanes: &mut Lanes, skip: &Skipper<'_>, empty: u32, x0: [[S::F; 3]; HALVES]) {
        let mut base = [[[0; 16]; 3]; HALVES];
        for (base, x0) in base.iter_mut().zip(&x0) {
            *base = [integers(s, x0[0]), integers(s, x0[1]), integers(s, x0[2])];
        }
        for l in (0..S::LANES * HALVES).filter(|l| empty >> l & 1 == 1) {
            let jumps = lanes.jumps[l].as_ref().expect("a lane of a skipping cast has jumps");
            let (b, i) = (&base[l / S::LANES], l % S::LANES);
            let cell = cell_of([b[0][i] as u32, b[1][i] as u32, b[2][i] as u32]);
            lanes.k[l] = jumps.skip(&self.packets.interp, skip, lanes.k[l] as u64, cell) as f32;
        }
    }

    /// Gives lane `l` the piece `lines[next]`, or leaves it idle when none is left;
    /// returns the next piece to hand out.
    fn refill(&self, lanes: &mut Lanes, l: usize, next: usize) -> usize {
        let Some(piece) = self.lines.get(next) else {
            lanes.piece[l] = None;
            return next;
        };
        let packed = &self.packets.packed;
        // `LineSamples::point`, vc0 + δ·((k + ½)/n), as origin + step·k: rounded to f32, a
        // few roundings of |vc0| + |δ| off (within `Jumps::for_f32`'s margins).
        let (vc0, delta, inv_n) = piece.line.parts();
        lanes.piece[l] = Some(next);
        for a in 0..3 {
            let step = delta[a] * inv_n;
            lanes.origin[a][l] = (vc0[a] + 0.5 * step) as f32;
            lanes.step[a][l] = step as f32;
        }
        lanes.n[l] = piece.line.len() as f32;
        lanes.stop_alpha[l] = stop_alpha(piece.alpha_in, piece.stop_at);
        // The slack serves only maps that jump.
        lanes.slack[l] = if packed.jumps.is_empty() { 0.0 } else { packed.slack(&piece.line) };
        // ℓ (a square root) only where opacity is corrected.
        lanes.ell[l] = if self.correction { piece.line.ell() as f32 } else { 0.0 };
        lanes.k[l] = 0.0;
        for acc in &mut lanes.acc {
            acc[l] = 0.0;
        }
        lanes.samples[l] = 0.0;
        if let Some(shading) = &self.packets.shading {
            // `WorldPoints::at` as first + step·k, and V = −(ray direction).
            let (first, step, dir) = piece.world.parts();
            for a in 0..3 {
                lanes.world[a][l] = first[a] as f32;
                lanes.world_step[a][l] = step[a] as f32;
                lanes.view[a][l] = -dir[a] as f32;
            }
            for j in 0..shading.half_vectors() {
                for (a, &h) in shading.half_vector(j, -dir).iter().enumerate() {
                    lanes.half_vector[j][a][l] = h;
                }
            }
            lanes.shaded[l] = 0.0;
        }
        lanes.cell[l] = [u32::MAX; 3];
        lanes.empty[l] = false;
        lanes.jumps[l] = self.skip.map(|_| Jumps::for_f32(&self.packets.interp, &piece.line));
        if let Some(jumps) = &lanes.jumps[l] {
            for (lane, part) in lanes.leap.iter_mut().zip(jumps.parts()) {
                for a in 0..3 {
                    lane[a][l] = part[a] as f32;
                }
            }
        }
        next + 1
    }
}
