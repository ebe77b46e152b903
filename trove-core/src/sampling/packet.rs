//! Sixteen pieces at a time, one per f32 lane of an AVX-512 register (two registers side
//! by side), for an object with the vector loop ([`super::lanes`]) when it casts many
//! pieces at once (a batch of Algorithm 2, a farm batch) on a processor with AVX-512.
//!
//! Along one ray, compositing is a chain (each sample waits for the opacity before it) and
//! a group of samples needs a long sequence of dependent steps, so the processor cannot run
//! far enough ahead to keep its units busy. Across rays there is no chain: each lane walks
//! its own piece sample by sample, and each step (position, cell, voxels, map, compositing)
//! does sixteen pieces' samples in one register. A lane whose piece ends (its last sample,
//! or the opacity at which it may stop) takes the batch's next piece. Neighbouring pieces of
//! a batch are neighbouring pixels, so the lanes read nearby voxels.
//!
//! Each lane runs the operations the single-sample loop runs for its piece, in the same
//! order, in f32 ([`Packed`]): sixteen lanes to a register halve the
//! instructions per sample against f64. Sample k is where the f64 loop puts it up to a few
//! f32 roundings (about 1e-7 of the coordinates), so results differ from
//! [`super::kernel::Cast::cast`]'s by rounding (tests bound it); a value that rounding could
//! move across a LUT bound takes its segment from the f64 value, so no sample changes
//! class. Jumps over empty cells widen their margins by f32's rounding of positions
//! ([`Jumps::for_f32`]), and a sample is tested empty by the cell of its f32 base, which is
//! where its f32 value reads: skipping changes no result.

use std::arch::x86_64::*;

use super::kernel::{Cast, Kernel, Maps, VoxelSource};
use super::lanes::avx512::{floor, Packed};
use super::lanes::Trilinear4;
use super::skip::{cell_of, FineClasses, Jumps, Skipper};
use super::{corrected_opacity, PieceResult};
use crate::composite::Rgba;
use crate::dataset::macrocell::{Level, MACROCELL_SHIFT};
use crate::geometry::{LineSamples, SampleWalk};
use crate::interp::Interp;

/// A straight piece waiting for a lane: its slot in the results, its samples, the opacity
/// in front of it and where it may stop.
struct Line {
    pub slot: usize,
    pub line: LineSamples,
    pub alpha_in: f64,
    pub stop_at: f64,
}

impl Line {
    /// Whether a lane can cast it: sample indices must be exact in f32.
    fn fits(line: &LineSamples) -> bool {
        line.len() < 1 << 24
    }
}

/// Lanes per register, and registers side by side: two halves of sixteen lanes, whose
/// chains of dependent steps (position → cell → voxels → map → compositing) interleave in
/// the processor, as two registers' groups do along a line ([`super::kernel::AVX2_LANES`]).
const LANES: usize = 16;
const HALVES: usize = 2;
const W: usize = LANES * HALVES;

/// Lanes idle (their pieces ended) before they all take new pieces.
const REFILL_AT: usize = 8;

/// Each lane's piece and where it has got to, lane by lane: what the registers are loaded
/// from when a lane changes piece, and stored to when one ends.
struct Lanes {
    /// Index in the batch's lines of each lane's piece; `None` for an idle lane, whose
    /// registers keep positions inside the volume and which is never composited.
    piece: [Option<usize>; W],
    /// Sample k is at `origin + step·k` ([`Lanes::refill`]).
    origin: [[f32; W]; 3],
    step: [[f32; W]; 3],
    n: [f32; W],
    /// The piece's own opacity at which it may stop ([`stop_alpha`]).
    stop_alpha: [f32; W],
    /// How far a sample's f32 value may be from its f64 value ([`Packed::slack`]).
    slack: [f32; W],
    ell: [f64; W],
    /// The sample each lane is at (an integer, exact in f32: pieces have fewer than 2²⁴).
    k: [f32; W],
    /// Σ c·w per colour channel, then A.
    acc: [[f32; W]; 4],
    samples: [f32; W],
    /// The macrocell of the lane's last sample and whether it is empty, where cells are
    /// classified on entry.
    cell: [[u32; 3]; W],
    empty: [bool; W],
    jumps: [Option<Jumps>; W],
    /// Each lane's [`Jumps::parts`]: start, samples per unit and margin, per axis.
    leap: [[[f32; W]; 3]; 3],
}

impl Lanes {
    fn idle() -> Lanes {
        Lanes {
            piece: [None; W],
            origin: [[0.0; W]; 3],
            step: [[0.0; W]; 3],
            n: [0.0; W],
            stop_alpha: [0.0; W],
            slack: [0.0; W],
            ell: [0.0; W],
            k: [0.0; W],
            acc: [[0.0; W]; 4],
            samples: [0.0; W],
            cell: [[u32::MAX; 3]; W],
            empty: [false; W],
            jumps: [const { None }; W],
            leap: [[[0.0; W]; 3]; 3],
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

/// Half `h`'s lanes of `m`.
fn half(m: u32, h: usize) -> __mmask16 {
    (m >> (LANES * h)) as __mmask16
}

/// Half `h` of a lane-by-lane array as a register.
#[inline]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
unsafe fn load(a: &[f32; W], h: usize) -> __m512 {
    _mm512_loadu_ps(a.as_ptr().add(LANES * h))
}

/// A register into half `h` of a lane-by-lane array.
#[inline]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
unsafe fn store(a: &mut [f32; W], h: usize, v: __m512) {
    _mm512_storeu_ps(a.as_mut_ptr().add(LANES * h), v)
}

/// Sixteen integer lanes of `v` (integers as f32), lane by lane.
#[inline]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
unsafe fn integers(v: __m512) -> [u32; LANES] {
    let mut a = [0u32; LANES];
    _mm512_storeu_si512(a.as_mut_ptr().cast(), _mm512_cvttps_epi32(v));
    a
}

/// Which of the cells `i` have their bit set in `bits` (read as 32-bit words: x86 is
/// little-endian, so bit i of the u64 words is bit i % 32 of word i / 32).
#[inline]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
unsafe fn bit_set(bits: &[u64], i: __m512i) -> __mmask16 {
    let words = _mm512_i32gather_epi32::<4>(_mm512_srli_epi32::<5>(i), bits.as_ptr().cast());
    let bit = _mm512_and_si512(i, _mm512_set1_epi32(31));
    let set = _mm512_and_si512(_mm512_srlv_epi32(words, bit), _mm512_set1_epi32(1));
    _mm512_test_epi32_mask(set, set)
}

/// [`Jumps::skip`] for the lanes of half `h`, whose samples k lie in empty cells `cells`
/// (coordinates as f32, index) of a skipper with distances: `Jumps::leap`, operation by
/// operation, in f32 (whose rounding [`Jumps::for_f32`]'s margins cover; lanes not in empty
/// cells get a value that is not used).
#[inline]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
unsafe fn leaps(
    lanes: &Lanes,
    h: usize,
    distance: &[u8],
    grid: &[(f32, f32); 3],
    (cell, index): ([__m512; 3], __m512i),
    k: __m512,
    n: __m512,
) -> __m512 {
    let one = _mm512_set1_ps(1.0);
    let zero = _mm512_setzero_ps();
    let infinity = _mm512_set1_ps(f32::INFINITY);
    let size = _mm512_set1_ps((1u32 << MACROCELL_SHIFT) as f32);
    // The distance table has three bytes of padding: four bytes at any cell are inside.
    let d = _mm512_and_si512(_mm512_i32gather_epi32::<1>(index, distance.as_ptr().cast()), _mm512_set1_epi32(0xff));
    let reach = _mm512_sub_ps(_mm512_max_ps(_mm512_cvtepi32_ps(d), one), one);
    let after = _mm512_add_ps(k, one);
    let mut next = n;
    for (a, &(last, offset)) in grid.iter().enumerate() {
        let [start, per_unit, margin] = [0, 1, 2].map(|p| load(&lanes.leap[p][a], h));
        let c = cell[a];
        let finite = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(_mm512_andnot_ps(_mm512_set1_ps(-0.0), per_unit), infinity);
        let up = finite
            & _mm512_cmp_ps_mask::<_CMP_GT_OQ>(per_unit, zero)
            & _mm512_cmp_ps_mask::<_CMP_LT_OQ>(_mm512_add_ps(c, reach), _mm512_set1_ps(last));
        let down =
            finite & _mm512_cmp_ps_mask::<_CMP_LT_OQ>(per_unit, zero) & _mm512_cmp_ps_mask::<_CMP_GT_OQ>(c, reach);
        let offset = _mm512_set1_ps(offset);
        let above = _mm512_fmadd_ps(_mm512_add_ps(_mm512_add_ps(c, reach), one), size, offset);
        let below = _mm512_fmadd_ps(_mm512_sub_ps(c, reach), size, offset);
        let bound = _mm512_mask_blend_ps(up, below, above);
        let j = _mm512_sub_ps(_mm512_mul_ps(_mm512_sub_ps(bound, start), per_unit), _mm512_set1_ps(0.5));
        // `ceil_index(j − margin)`, and k + 1 for a NaN j.
        let x = _mm512_sub_ps(j, margin);
        let ceil = _mm512_roundscale_ps::<{ _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC }>(x);
        let first_unsafe = _mm512_maskz_mov_ps(_mm512_cmp_ps_mask::<_CMP_GT_OQ>(x, zero), ceil);
        let first_unsafe = _mm512_mask_blend_ps(_mm512_cmp_ps_mask::<_CMP_UNORD_Q>(j, j), first_unsafe, after);
        next = _mm512_mask_min_ps(next, up | down, next, first_unsafe);
    }
    _mm512_max_ps(next, after)
}

/// One half's registers: its lanes' pieces and where they have got to.
#[derive(Clone, Copy)]
struct Half {
    origin: [__m512; 3],
    step: [__m512; 3],
    n: __m512,
    stop_alpha: __m512,
    k: __m512,
    acc: [__m512; 4],
    samples: __m512,
}

impl Half {
    #[inline]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
    unsafe fn load(lanes: &Lanes, h: usize) -> Half {
        let mut origin = [_mm512_setzero_ps(); 3];
        let mut step = [_mm512_setzero_ps(); 3];
        let mut acc = [_mm512_setzero_ps(); 4];
        for a in 0..3 {
            origin[a] = load(&lanes.origin[a], h);
            step[a] = load(&lanes.step[a], h);
        }
        for (acc, lane) in acc.iter_mut().zip(&lanes.acc) {
            *acc = load(lane, h);
        }
        Half {
            origin,
            step,
            n: load(&lanes.n, h),
            stop_alpha: load(&lanes.stop_alpha, h),
            k: load(&lanes.k, h),
            acc,
            samples: load(&lanes.samples, h),
        }
    }

    /// Puts back what changes as the lanes walk.
    #[inline]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
    unsafe fn store(&self, lanes: &mut Lanes, h: usize) {
        store(&mut lanes.k, h, self.k);
        for (lane, &acc) in lanes.acc.iter_mut().zip(&self.acc) {
            store(lane, h, acc);
        }
        store(&mut lanes.samples, h, self.samples);
    }
}

/// The samples at each lane's k, looked up ahead of compositing them (so that their
/// voxels are fetched while the samples before are composited): per half, their values,
/// which lanes composite them (not those in empty cells), and the k each lane goes on to.
struct Looked {
    value: [__m512; HALVES],
    live: u32,
    next_k: [__m512; HALVES],
}

/// What stays fixed over a batch.
struct Batch<'c> {
    fast: &'c Trilinear4<'c>,
    packed: &'c Packed,
    classified: Option<FineClasses<'c>>,
    /// Per axis: the last macrocell a sample can be based in, and the base grid's offset.
    grid: [(f32, f32); 3],
}

impl<I: Interp, V: VoxelSource, M: Maps> Kernel<'_, I, V, M> {
    /// [`Cast::cast_many`] for an object whose loop has packed forms: straight pieces
    /// sixteen at a time; the others (exact distorted walks, lines too long for f32
    /// indices) one by one.
    ///
    /// # Safety
    /// As for [`Kernel::cast_packets`].
    pub(super) unsafe fn cast_many_packed(
        &self,
        fast: &Trilinear4<'_>,
        packed: &Packed,
        pieces: Vec<(usize, SampleWalk<'_>, f64, f64)>,
        out: &mut [PieceResult],
    ) {
        let mut lines = Vec::with_capacity(pieces.len());
        for (slot, walk, alpha_in, stop_at) in pieces {
            match walk.line().filter(Line::fits) {
                Some(line) => lines.push(Line { slot, line, alpha_in, stop_at }),
                None => out[slot] = self.cast(walk, alpha_in, stop_at),
            }
        }
        // SAFETY: the caller's promise is this function's.
        unsafe { self.cast_packets(fast, packed, &lines, out) };
    }

    /// Casts `lines` (each [`Line::fits`]), writing each result to `out[line.slot]`.
    ///
    /// The loop is pipelined by one sample: the samples at k + 1 (or where a lane jumps to)
    /// are located, tested for empty space and interpolated before the samples at k are
    /// mapped and composited, so the voxel gathers of the one overlap the other's chain of
    /// dependent steps.
    ///
    /// # Safety
    /// The processor must have AVX-512 F, DQ and VL ([`Trilinear4::packed`] is `Some`).
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
    unsafe fn cast_packets(&self, fast: &Trilinear4<'_>, packed: &Packed, lines: &[Line], out: &mut [PieceResult]) {
        let batch = Batch {
            fast,
            packed,
            classified: self.skip.as_ref().and_then(Skipper::fine_classes),
            grid: std::array::from_fn(|a| {
                let (max_base, offset) = self.interp.base_grid(a);
                ((max_base >> MACROCELL_SHIFT) as f32, offset as f32)
            }),
        };
        let mut lanes = Lanes::idle();
        let mut next = 0;
        for l in 0..W {
            next = self.refill(packed, &mut lanes, l, lines, next);
        }
        let one = _mm512_set1_ps(1.0);
        let jumps = !packed.jumps.is_empty();
        // Lanes change pieces only here: the registers are loaded from `lanes`, the loop runs
        // until some lane ends, and its state goes back to `lanes`.
        'refilled: while lanes.active() != 0 {
            let mut active = lanes.active();
            let mut regs = [Half::load(&lanes, 0), Half::load(&lanes, 1)];
            let mut looked = self.look(&batch, &mut lanes, &regs, [regs[0].k, regs[1].k], active);
            loop {
                let ahead = self.look(&batch, &mut lanes, &regs, looked.next_k, active);
                let mut ended = 0;
                for (h, r) in regs.iter_mut().enumerate() {
                    let live = half(looked.live & active, h);
                    let v = looked.value[h];
                    let mut segment = packed.segments16(v);
                    if jumps {
                        let near = packed.near_jumps16(v, load(&lanes.slack, h)) & live;
                        if near != 0 {
                            segment = self.exact_segments(fast.breaks(), lines, &lanes, h, near, r.k, segment);
                        }
                    }
                    let (opacity, colour) = packed.map16(v, segment);
                    let alpha = if self.correction {
                        let mut alpha = [0.0; LANES];
                        _mm512_storeu_ps(alpha.as_mut_ptr(), opacity);
                        for (alpha, &ell) in alpha.iter_mut().zip(&lanes.ell[LANES * h..]) {
                            *alpha = corrected_opacity(f64::from(*alpha), ell) as f32;
                        }
                        _mm512_loadu_ps(alpha.as_ptr())
                    } else {
                        opacity
                    };
                    // `Rgba::add_sample` in live lanes, then the stopping test of `composite`.
                    let w = _mm512_fnmadd_ps(alpha, r.acc[3], alpha);
                    for (acc, &c) in r.acc.iter_mut().zip(&colour) {
                        *acc = _mm512_mask3_fmadd_ps(c, w, *acc, live);
                    }
                    r.acc[3] = _mm512_mask_add_ps(r.acc[3], live, r.acc[3], w);
                    let done = live
                        & _mm512_cmp_ps_mask::<_CMP_NEQ_UQ>(alpha, _mm512_setzero_ps())
                        & _mm512_cmp_ps_mask::<_CMP_GE_OQ>(r.acc[3], r.stop_alpha);
                    r.samples = _mm512_mask_add_ps(r.samples, live, r.samples, one);
                    r.k = looked.next_k[h];
                    let end = half(active, h) & (done | _mm512_cmp_ps_mask::<_CMP_GE_OQ>(r.k, r.n));
                    ended |= u32::from(end) << (LANES * h);
                }
                if ended != 0 {
                    // Ended lanes give their results and idle; they take new pieces only when
                    // a few are idle, since refilling reloads every register and looks at
                    // every lane's sample again.
                    for (h, r) in regs.iter().enumerate() {
                        r.store(&mut lanes, h);
                    }
                    for l in (0..W).filter(|l| ended >> l & 1 == 1) {
                        let piece = lanes.piece[l].take().expect("an ended lane was active");
                        let acc = &lanes.acc;
                        out[lines[piece].slot] = PieceResult {
                            rgba: Rgba {
                                colour: [acc[0][l], acc[1][l], acc[2][l]].map(f64::from),
                                alpha: f64::from(acc[3][l]),
                            },
                            samples: lanes.samples[l] as u64,
                        };
                    }
                    active &= !ended;
                    let idle = W - active.count_ones() as usize;
                    if active == 0 || (idle >= REFILL_AT && next < lines.len()) {
                        for l in 0..W {
                            if lanes.piece[l].is_none() {
                                next = self.refill(packed, &mut lanes, l, lines, next);
                            }
                        }
                        continue 'refilled;
                    }
                }
                looked = ahead;
            }
        }
    }

    /// The samples at `k` (per half) of the lanes `active`: located
    /// ([`LineSamples::point`], then `Axis::cell`), tested for empty space (lanes in empty
    /// cells jump, as the single-sample loop does, and are not composited) and
    /// interpolated.
    #[inline]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
    unsafe fn look(
        &self,
        batch: &Batch<'_>,
        lanes: &mut Lanes,
        regs: &[Half; HALVES],
        k: [__m512; HALVES],
        active: u32,
    ) -> Looked {
        let (packed, fast) = (batch.packed, batch.fast);
        let one = _mm512_set1_ps(1.0);
        let (nx, ny) = fast.nx_ny();
        let mut x0 = [[one; 3]; HALVES];
        let mut weights = [[one; 3]; HALVES];
        let mut next_k = [one; HALVES];
        for (h, r) in regs.iter().enumerate() {
            let mut u = [one; 3];
            for (a, u) in u.iter_mut().enumerate() {
                *u = _mm512_fmadd_ps(r.step[a], k[h], r.origin[a]);
            }
            (x0[h], weights[h]) = packed.cells16(u);
            next_k[h] = _mm512_mask_add_ps(k[h], half(active, h), k[h], one);
        }
        let mut live = active;
        if let Some(skip) = &self.skip {
            let mut empty = 0;
            let mut cells = [([one; 3], _mm512_setzero_si512()); HALVES];
            for (h, &x0) in x0.iter().enumerate() {
                let e = match &batch.classified {
                    Some(classes) => {
                        let scale = _mm512_set1_ps(1.0 / (1u32 << MACROCELL_SHIFT) as f32);
                        let c = x0.map(|x| floor(_mm512_mul_ps(x, scale)));
                        let [cx, cy, _] = classes.dims;
                        cells[h] = (c, packed.index16(c, cx, cy));
                        bit_set(classes.bits, cells[h].1)
                    }
                    None => self.empty_lanes(skip, lanes, h, x0),
                };
                empty |= u32::from(e) << (LANES * h);
            }
            empty &= active;
            if empty != 0 {
                if let Some(FineClasses { distance, .. }) = batch.classified {
                    // Leaps over cubes of empty cells, in registers.
                    for (h, r) in regs.iter().enumerate() {
                        let e = half(empty, h);
                        if e != 0 {
                            let leap = leaps(lanes, h, distance, &batch.grid, cells[h], k[h], r.n);
                            next_k[h] = _mm512_mask_blend_ps(e, next_k[h], leap);
                        }
                    }
                } else {
                    for (h, &k) in k.iter().enumerate() {
                        store(&mut lanes.k, h, k);
                    }
                    self.jump(lanes, skip, empty, x0);
                    for (h, next_k) in next_k.iter_mut().enumerate() {
                        *next_k = _mm512_mask_blend_ps(half(empty, h), *next_k, load(&lanes.k, h));
                    }
                }
                live &= !empty;
            }
        }
        let mut value = [one; HALVES];
        for (h, value) in value.iter_mut().enumerate() {
            *value = fast.trilinear16(packed.index16(x0[h], nx, ny), weights[h]);
        }
        Looked { value, live, next_k }
    }

    /// The segments of half `h`'s lanes `near`, whose f32 values lie within rounding of a
    /// break point where the map jumps, counted from their f64 values as the single-sample
    /// loop computes them (the rest of `segment` as it is).
    #[cold]
    #[inline(never)]
    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
    unsafe fn exact_segments(
        &self,
        breaks: &[f64],
        lines: &[Line],
        lanes: &Lanes,
        h: usize,
        near: __mmask16,
        k: __m512,
        segment: __m512i,
    ) -> __m512i {
        let (mut ks, mut segments) = ([0.0f32; LANES], [0i32; LANES]);
        _mm512_storeu_ps(ks.as_mut_ptr(), k);
        _mm512_storeu_si512(segments.as_mut_ptr().cast(), segment);
        for l in (0..LANES).filter(|l| near >> l & 1 == 1) {
            let piece = lanes.piece[LANES * h + l].expect("a live lane has a piece");
            let s = self.interp.locate(lines[piece].line.point(ks[l] as u64));
            let v = self.voxels.value(&self.interp, &s);
            segments[l] = breaks.iter().filter(|&&b| b <= v).count() as i32;
        }
        _mm512_loadu_si512(segments.as_ptr().cast())
    }

    /// The lanes of half `h` whose samples, with lower corners `x0`, lie in empty
    /// macrocells, where cells are classified on entry: lane by lane, each lane classifying
    /// a cell when it enters it, as the single-sample loop does.
    #[inline]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
    unsafe fn empty_lanes(&self, skip: &Skipper<'_>, lanes: &mut Lanes, h: usize, x0: [__m512; 3]) -> __mmask16 {
        let base = x0.map(|x| integers(x));
        let mut empty = 0;
        for l in (0..LANES).filter(|&l| lanes.piece[LANES * h + l].is_some()) {
            let c = cell_of([base[0][l], base[1][l], base[2][l]]);
            let lane = LANES * h + l;
            if c != lanes.cell[lane] {
                lanes.cell[lane] = c;
                lanes.empty[lane] = skip.is_empty(&self.interp, Level::Fine, c);
            }
            empty |= u16::from(lanes.empty[lane]) << l;
        }
        empty
    }

    /// Moves each lane of `empty`, whose sample is based at `x0` (per half) in an empty
    /// cell, to the next sample that may contribute ([`Jumps::skip`]).
    #[inline]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
    unsafe fn jump(&self, lanes: &mut Lanes, skip: &Skipper<'_>, empty: u32, x0: [[__m512; 3]; HALVES]) {
        let base = x0.map(|x0| x0.map(|x| integers(x)));
        for l in (0..W).filter(|l| empty >> l & 1 == 1) {
            let jumps = lanes.jumps[l].as_ref().expect("a lane of a skipping cast has jumps");
            let [x, y, z] = base[l / LANES].map(|axis| axis[l % LANES]);
            lanes.k[l] = jumps.skip(&self.interp, skip, lanes.k[l] as u64, cell_of([x, y, z])) as f32;
        }
    }

    /// Gives lane `l` the piece `lines[next]`, or leaves it idle when none is left;
    /// returns the next piece to hand out.
    fn refill(&self, packed: &Packed, lanes: &mut Lanes, l: usize, lines: &[Line], next: usize) -> usize {
        let Some(piece) = lines.get(next) else {
            lanes.piece[l] = None;
            return next;
        };
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
        lanes.ell[l] = if self.correction { piece.line.ell() } else { 0.0 };
        lanes.k[l] = 0.0;
        for acc in &mut lanes.acc {
            acc[l] = 0.0;
        }
        lanes.samples[l] = 0.0;
        lanes.cell[l] = [u32::MAX; 3];
        lanes.empty[l] = false;
        lanes.jumps[l] = self.skip.as_ref().map(|_| Jumps::for_f32(&self.interp, &piece.line));
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
