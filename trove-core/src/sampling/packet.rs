//! Eight pieces at a time, one per AVX-512 lane, for an object with the vector loop
//! ([`super::lanes`]) when it casts many pieces at once (a batch of Algorithm 2, a farm
//! batch) on a processor with AVX-512.
//!
//! Along one ray, compositing is a chain (each sample waits for the opacity before it) and
//! a group of samples needs a long sequence of dependent steps, so the processor cannot run
//! far enough ahead to keep its units busy. Across rays there is no chain: each lane walks
//! its own piece sample by sample, and each step (position, cell, voxels, map, compositing)
//! does eight pieces' samples in one register. A lane whose piece ends (its last sample,
//! or the opacity at which it may stop) takes the batch's next piece. Neighbouring pieces of
//! a batch are neighbouring pixels, so the lanes read nearby voxels.
//!
//! Each lane runs exactly the operations the single-sample loop runs for its piece, in the
//! same order: its sample k is at the same position, it jumps over the same empty cells
//! (with the same [`Jumps`]) and stops at the same sample, so every result and every sample
//! count is the one [`super::kernel::Cast::cast`] gives (tests compare them).

use std::arch::x86_64::*;

use super::kernel::{Kernel, Maps, VoxelSource};
use super::lanes::Trilinear4;
use super::skip::{cell_of, FineClasses, Jumps, Skipper};
use super::{corrected_opacity, PieceResult};
use crate::composite::Rgba;
use crate::dataset::macrocell::{Level, MACROCELL_SHIFT};
use crate::geometry::LineSamples;
use crate::interp::Interp;

/// A straight piece waiting for a lane: its slot in the results, its samples, the opacity
/// in front of it and where it may stop.
pub(super) struct Line {
    pub slot: usize,
    pub line: LineSamples,
    pub alpha_in: f64,
    pub stop_at: f64,
}

/// Lanes per register, and registers side by side: two halves of eight lanes, whose
/// chains of dependent steps (position → cell → voxels → map → compositing) interleave in
/// the processor, as two registers' groups do along a line ([`super::kernel::AVX2_LANES`]).
const LANES: usize = 8;
const HALVES: usize = 2;
const W: usize = LANES * HALVES;

/// Each lane's piece and where it has got to, lane by lane: what the registers are loaded
/// from when a lane changes piece, and stored to when one ends.
struct Lanes {
    /// Index in the batch's lines of each lane's piece; `None` for an idle lane, whose
    /// registers keep positions inside the volume and which is never composited.
    piece: [Option<usize>; W],
    vc0: [[f64; W]; 3],
    delta: [[f64; W]; 3],
    inv_n: [f64; W],
    n: [f64; W],
    alpha_in: [f64; W],
    stop_at: [f64; W],
    ell: [f64; W],
    /// The sample each lane is at (an integer, exact in f64).
    k: [f64; W],
    /// Σ c·w per colour channel, then A.
    acc: [[f64; W]; 4],
    samples: [f64; W],
    /// The macrocell of the lane's last sample and whether it is empty, where cells are
    /// classified on entry.
    cell: [[u32; 3]; W],
    empty: [bool; W],
    jumps: [Option<Jumps>; W],
    /// Each lane's [`Jumps::parts`]: start, samples per unit and margin, per axis.
    leap: [[[f64; W]; 3]; 3],
}

impl Lanes {
    fn idle() -> Lanes {
        Lanes {
            piece: [None; W],
            vc0: [[0.0; W]; 3],
            delta: [[0.0; W]; 3],
            inv_n: [0.0; W],
            n: [0.0; W],
            alpha_in: [0.0; W],
            stop_at: [0.0; W],
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
    fn active(&self) -> u16 {
        let mut active = 0;
        for (l, piece) in self.piece.iter().enumerate() {
            active |= u16::from(piece.is_some()) << l;
        }
        active
    }
}

/// Half `h`'s lanes of `m`.
fn half(m: u16, h: usize) -> __mmask8 {
    (m >> (LANES * h)) as __mmask8
}

/// Half `h` of a lane-by-lane array as a register.
#[inline]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
unsafe fn load(a: &[f64; W], h: usize) -> __m512d {
    _mm512_loadu_pd(a.as_ptr().add(LANES * h))
}

/// A register into half `h` of a lane-by-lane array.
#[inline]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
unsafe fn store(a: &mut [f64; W], h: usize, v: __m512d) {
    _mm512_storeu_pd(a.as_mut_ptr().add(LANES * h), v)
}

/// Each lane's lower corner as integers.
#[inline]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
unsafe fn bases(x0: [__m512d; 3]) -> [[u32; LANES]; 3] {
    let mut base = [[0u32; LANES]; 3];
    for (base, x0) in base.iter_mut().zip(x0) {
        _mm256_storeu_si256(base.as_mut_ptr().cast(), _mm512_cvttpd_epi32(x0));
    }
    base
}

/// The macrocells of eight lower corners `x0` (as f64) and their indices in a grid of
/// `dims` cells, x fastest: in f64, exact below 2³⁰ (as the dataset's voxel
/// indices are), whose multiplications are quicker than i32 ones.
#[inline]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
unsafe fn cells_of(x0: [__m512d; 3], [cx, cy, _]: [u32; 3]) -> ([__m512d; 3], __m256i) {
    let scale = _mm512_set1_pd(1.0 / (1u32 << MACROCELL_SHIFT) as f64);
    let mut c = [_mm512_setzero_pd(); 3];
    for (c, x0) in c.iter_mut().zip(x0) {
        *c = _mm512_roundscale_pd::<{ _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC }>(_mm512_mul_pd(x0, scale));
    }
    let yz = _mm512_add_pd(c[1], _mm512_mul_pd(_mm512_set1_pd(cy as f64), c[2]));
    (c, _mm512_cvttpd_epi32(_mm512_add_pd(c[0], _mm512_mul_pd(_mm512_set1_pd(cx as f64), yz))))
}

/// Which of the cells `i` have their bit set in `bits`.
#[inline]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
unsafe fn bit_set(bits: &[u64], i: __m256i) -> __mmask8 {
    let words = _mm512_i32gather_epi64::<8>(_mm256_srli_epi32::<6>(i), bits.as_ptr().cast());
    let bit = _mm512_cvtepu32_epi64(_mm256_and_si256(i, _mm256_set1_epi32(63)));
    let set = _mm512_and_si512(_mm512_srlv_epi64(words, bit), _mm512_set1_epi64(1));
    _mm512_test_epi64_mask(set, set)
}

/// [`Jumps::skip`] for the lanes of half `h`, whose samples k lie in empty cells `cells`
/// (coordinates, index) of a skipper with distances: `Jumps::leap`, operation by operation,
/// eight lanes at once (lanes not in empty cells get a value that is not used).
#[inline]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
unsafe fn leaps(
    lanes: &Lanes,
    h: usize,
    distance: &[u8],
    grid: &[(f64, f64); 3],
    (cell, index): ([__m512d; 3], __m256i),
    k: __m512d,
    n: __m512d,
) -> __m512d {
    let one = _mm512_set1_pd(1.0);
    let zero = _mm512_setzero_pd();
    let infinity = _mm512_set1_pd(f64::INFINITY);
    let size = _mm512_set1_pd((1u32 << MACROCELL_SHIFT) as f64);
    // The distance table has three bytes of padding: four bytes at any cell are inside.
    let d = _mm256_and_si256(_mm256_i32gather_epi32::<1>(distance.as_ptr().cast(), index), _mm256_set1_epi32(0xff));
    let reach = _mm512_sub_pd(_mm512_max_pd(_mm512_cvtepi32_pd(d), one), one);
    let after = _mm512_add_pd(k, one);
    let mut next = n;
    for (a, &(last, offset)) in grid.iter().enumerate() {
        let [start, per_unit, margin] = [0, 1, 2].map(|p| load(&lanes.leap[p][a], h));
        let c = cell[a];
        let finite = _mm512_cmp_pd_mask::<_CMP_LT_OQ>(_mm512_andnot_pd(_mm512_set1_pd(-0.0), per_unit), infinity);
        let up = finite
            & _mm512_cmp_pd_mask::<_CMP_GT_OQ>(per_unit, zero)
            & _mm512_cmp_pd_mask::<_CMP_LT_OQ>(_mm512_add_pd(c, reach), _mm512_set1_pd(last));
        let down =
            finite & _mm512_cmp_pd_mask::<_CMP_LT_OQ>(per_unit, zero) & _mm512_cmp_pd_mask::<_CMP_GT_OQ>(c, reach);
        let offset = _mm512_set1_pd(offset);
        let above = _mm512_add_pd(_mm512_mul_pd(_mm512_add_pd(_mm512_add_pd(c, reach), one), size), offset);
        let below = _mm512_add_pd(_mm512_mul_pd(_mm512_sub_pd(c, reach), size), offset);
        let bound = _mm512_mask_blend_pd(up, below, above);
        let j = _mm512_sub_pd(_mm512_mul_pd(_mm512_sub_pd(bound, start), per_unit), _mm512_set1_pd(0.5));
        // `ceil_index(j − margin)`, and k + 1 for a NaN j.
        let x = _mm512_sub_pd(j, margin);
        let ceil = _mm512_roundscale_pd::<{ _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC }>(x);
        let first_unsafe = _mm512_maskz_mov_pd(_mm512_cmp_pd_mask::<_CMP_GT_OQ>(x, zero), ceil);
        let first_unsafe = _mm512_mask_blend_pd(_mm512_cmp_pd_mask::<_CMP_UNORD_Q>(j, j), first_unsafe, after);
        next = _mm512_mask_min_pd(next, up | down, next, first_unsafe);
    }
    _mm512_max_pd(next, after)
}

/// One half's registers: its lanes' pieces and where they have got to.
#[derive(Clone, Copy)]
struct Half {
    vc0: [__m512d; 3],
    delta: [__m512d; 3],
    inv_n: __m512d,
    n: __m512d,
    alpha_in: __m512d,
    stop_at: __m512d,
    k: __m512d,
    acc: [__m512d; 4],
    samples: __m512d,
}

impl Half {
    #[inline]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
    unsafe fn load(lanes: &Lanes, h: usize) -> Half {
        let mut vc0 = [_mm512_setzero_pd(); 3];
        let mut delta = [_mm512_setzero_pd(); 3];
        let mut acc = [_mm512_setzero_pd(); 4];
        for a in 0..3 {
            vc0[a] = load(&lanes.vc0[a], h);
            delta[a] = load(&lanes.delta[a], h);
        }
        for (acc, lane) in acc.iter_mut().zip(&lanes.acc) {
            *acc = load(lane, h);
        }
        Half {
            vc0,
            delta,
            inv_n: load(&lanes.inv_n, h),
            n: load(&lanes.n, h),
            alpha_in: load(&lanes.alpha_in, h),
            stop_at: load(&lanes.stop_at, h),
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

impl<I: Interp, V: VoxelSource, M: Maps> Kernel<'_, I, V, M> {
    /// Casts `lines`, writing each result to `out[line.slot]`.
    ///
    /// # Safety
    /// The processor must have AVX-512 F, DQ and VL ([`Trilinear4::has_avx512`]).
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
    pub(super) unsafe fn cast_packets(&self, fast: &Trilinear4<'_>, lines: &[Line], out: &mut [PieceResult]) {
        let mut lanes = Lanes::idle();
        let mut next = 0;
        for l in 0..W {
            next = self.refill(&mut lanes, l, lines, next);
        }
        let one = _mm512_set1_pd(1.0);
        let point_five = _mm512_set1_pd(0.5);
        let classified = self.skip.as_ref().and_then(Skipper::fine_classes);
        // Per axis: the last macrocell a sample can be based in, and the base grid's offset.
        let grid: [(f64, f64); 3] = std::array::from_fn(|a| {
            let (max_base, offset) = self.interp.base_grid(a);
            ((max_base >> MACROCELL_SHIFT) as f64, offset)
        });
        // Lanes change pieces only here: the registers are loaded from `lanes`, the loop runs
        // until some lane ends, and its state goes back to `lanes`.
        'refilled: while lanes.active() != 0 {
            let active = lanes.active();
            let mut regs = [Half::load(&lanes, 0), Half::load(&lanes, 1)];
            loop {
                // `LineSamples::point`, then the cells and weights of `Axis::cell`.
                let mut x0 = [[one; 3]; HALVES];
                let mut weights = [[one; 3]; HALVES];
                let mut index = [0i32; W];
                // The next sample of each lane: k + 1, except where a lane jumps (below).
                let mut next_k = [one; HALVES];
                for (h, r) in regs.iter().enumerate() {
                    let s = _mm512_mul_pd(_mm512_add_pd(r.k, point_five), r.inv_n);
                    let mut u = [s; 3];
                    for ((u, &vc0), &delta) in u.iter_mut().zip(&r.vc0).zip(&r.delta) {
                        *u = _mm512_add_pd(vc0, _mm512_mul_pd(delta, s));
                    }
                    (x0[h], weights[h]) = fast.cells8(u);
                    _mm256_storeu_si256(index.as_mut_ptr().add(LANES * h).cast(), fast.index8(x0[h]));
                    next_k[h] = _mm512_mask_add_pd(r.k, half(active, h), r.k, one);
                }
                let mut live = active;
                if let Some(skip) = &self.skip {
                    // Lanes in empty cells jump, as the single-sample loop does, and are not
                    // composited this time round.
                    let mut empty = 0;
                    let mut cells = [([one; 3], _mm256_setzero_si256()); HALVES];
                    for (h, &x0) in x0.iter().enumerate() {
                        let e = match &classified {
                            Some(classes) => {
                                cells[h] = cells_of(x0, classes.dims);
                                bit_set(classes.bits, cells[h].1)
                            }
                            None => self.empty_lanes(skip, &mut lanes, h, x0),
                        };
                        empty |= u16::from(e) << (LANES * h);
                    }
                    empty &= active;
                    if empty != 0 {
                        if let Some(FineClasses { distance, .. }) = classified {
                            // Leaps over cubes of empty cells, in registers.
                            for (h, r) in regs.iter().enumerate() {
                                let e = half(empty, h);
                                if e != 0 {
                                    let leap = leaps(&lanes, h, distance, &grid, cells[h], r.k, r.n);
                                    next_k[h] = _mm512_mask_blend_pd(e, next_k[h], leap);
                                }
                            }
                        } else {
                            for (h, r) in regs.iter().enumerate() {
                                store(&mut lanes.k, h, r.k);
                            }
                            self.jump(&mut lanes, skip, empty, x0.map(|x0| bases(x0)));
                            for (h, next_k) in next_k.iter_mut().enumerate() {
                                *next_k = _mm512_mask_blend_pd(half(empty, h), *next_k, load(&lanes.k, h));
                            }
                        }
                        live &= !empty;
                    }
                }
                let mut ended = 0;
                for (h, r) in regs.iter_mut().enumerate() {
                    let lanes_index = index[LANES * h..LANES * (h + 1)].try_into().expect("a half's lanes");
                    let (opacity, colour) = fast.map8(fast.trilinear8(lanes_index, weights[h]));
                    let alpha = if self.correction {
                        let mut alpha = [0.0; LANES];
                        _mm512_storeu_pd(alpha.as_mut_ptr(), opacity);
                        for (alpha, &ell) in alpha.iter_mut().zip(&lanes.ell[LANES * h..]) {
                            *alpha = corrected_opacity(*alpha, ell);
                        }
                        _mm512_loadu_pd(alpha.as_ptr())
                    } else {
                        opacity
                    };
                    // `Rgba::add_sample` in live lanes, then the stopping test of `composite`.
                    let live = half(live, h);
                    let w = _mm512_mul_pd(alpha, _mm512_sub_pd(one, r.acc[3]));
                    for (acc, &c) in r.acc.iter_mut().zip(&colour) {
                        *acc = _mm512_mask_add_pd(*acc, live, *acc, _mm512_mul_pd(c, w));
                    }
                    r.acc[3] = _mm512_mask_add_pd(r.acc[3], live, r.acc[3], w);
                    let front = _mm512_add_pd(r.alpha_in, _mm512_mul_pd(_mm512_sub_pd(one, r.alpha_in), r.acc[3]));
                    let done = live
                        & _mm512_cmp_pd_mask::<_CMP_NEQ_UQ>(alpha, _mm512_setzero_pd())
                        & _mm512_cmp_pd_mask::<_CMP_GE_OQ>(front, r.stop_at);
                    r.samples = _mm512_mask_add_pd(r.samples, live, r.samples, one);
                    r.k = next_k[h];
                    let end = half(active, h) & (done | _mm512_cmp_pd_mask::<_CMP_GE_OQ>(r.k, r.n));
                    ended |= u16::from(end) << (LANES * h);
                }
                if ended != 0 {
                    for (h, r) in regs.iter().enumerate() {
                        r.store(&mut lanes, h);
                    }
                    for l in (0..W).filter(|l| ended >> l & 1 == 1) {
                        let piece = lanes.piece[l].expect("an ended lane was active");
                        let acc = &lanes.acc;
                        out[lines[piece].slot] = PieceResult {
                            rgba: Rgba { colour: [acc[0][l], acc[1][l], acc[2][l]], alpha: acc[3][l] },
                            samples: lanes.samples[l] as u64,
                        };
                        next = self.refill(&mut lanes, l, lines, next);
                    }
                    continue 'refilled;
                }
            }
        }
    }

    /// The lanes of half `h` whose samples, with lower corners `x0`, lie in empty
    /// macrocells, where cells are classified on entry: lane by lane, each lane classifying
    /// a cell when it enters it, as the single-sample loop does.
    #[inline]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
    unsafe fn empty_lanes(&self, skip: &Skipper<'_>, lanes: &mut Lanes, h: usize, x0: [__m512d; 3]) -> __mmask8 {
        let base = bases(x0);
        let mut empty = 0;
        for l in (0..LANES).filter(|&l| lanes.piece[LANES * h + l].is_some()) {
            let c = cell_of([base[0][l], base[1][l], base[2][l]]);
            let lane = LANES * h + l;
            if c != lanes.cell[lane] {
                lanes.cell[lane] = c;
                lanes.empty[lane] = skip.is_empty(&self.interp, Level::Fine, c);
            }
            empty |= u8::from(lanes.empty[lane]) << l;
        }
        empty
    }

    /// Moves each lane of `empty`, whose sample is based at `base` (per half) in an empty
    /// cell, to the next sample that may contribute ([`Jumps::skip`]).
    fn jump(&self, lanes: &mut Lanes, skip: &Skipper<'_>, empty: u16, base: [[[u32; LANES]; 3]; HALVES]) {
        for l in (0..W).filter(|l| empty >> l & 1 == 1) {
            let jumps = lanes.jumps[l].as_ref().expect("a lane of a skipping cast has jumps");
            let [x, y, z] = base[l / LANES].map(|axis| axis[l % LANES]);
            lanes.k[l] = jumps.skip(&self.interp, skip, lanes.k[l] as u64, cell_of([x, y, z])) as f64;
        }
    }

    /// Gives lane `l` the piece `lines[next]`, or leaves it idle when none is left;
    /// returns the next piece to hand out.
    fn refill(&self, lanes: &mut Lanes, l: usize, lines: &[Line], next: usize) -> usize {
        let Some(piece) = lines.get(next) else {
            lanes.piece[l] = None;
            return next;
        };
        let (vc0, delta, inv_n) = piece.line.parts();
        lanes.piece[l] = Some(next);
        for a in 0..3 {
            lanes.vc0[a][l] = vc0[a];
            lanes.delta[a][l] = delta[a];
        }
        lanes.inv_n[l] = inv_n;
        lanes.n[l] = piece.line.len() as f64;
        lanes.alpha_in[l] = piece.alpha_in;
        lanes.stop_at[l] = piece.stop_at;
        lanes.ell[l] = piece.line.ell();
        lanes.k[l] = 0.0;
        for acc in &mut lanes.acc {
            acc[l] = 0.0;
        }
        lanes.samples[l] = 0.0;
        lanes.cell[l] = [u32::MAX; 3];
        lanes.empty[l] = false;
        lanes.jumps[l] = self.skip.as_ref().map(|_| Jumps::new(&self.interp, &piece.line));
        if let Some(jumps) = &lanes.jumps[l] {
            for (lane, part) in lanes.leap.iter_mut().zip(jumps.parts()) {
                for a in 0..3 {
                    lane[a][l] = part[a];
                }
            }
        }
        next + 1
    }
}
