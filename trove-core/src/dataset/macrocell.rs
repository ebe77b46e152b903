//! Value ranges per macrocell: the data behind empty-space skipping (issue 10).
//!
//! A dataset's volume is cut into cells of B³ voxels (B = [`MACROCELL`]); for each cell the
//! minimum and maximum of the finite values a sample *based* in that cell can read are kept,
//! and the same for coarse blocks of 8³ cells (their union), over which a ray crosses wide
//! empty regions in few steps. A
//! sample is based in cell `c` along an axis when its interpolation's base voxel index (the
//! nearest voxel, or trilinear's and the cubic's lower cell corner `x0`, SPEC §3.3) lies in
//! `[c·B, c·B + B − 1]`. Nearest then reads voxels up to `c·B + B − 1`, trilinear and nonlinear
//! up to `x0 + 1 = c·B + B`, so each range covers the voxels `[c·B, c·B + B]` (one voxel of
//! apron above, clamped to the dataset). The cubic's 32-point stencil reaches one voxel below
//! and two above `x0`; the sampler takes the union of the neighbouring cells' ranges for it.
//!
//! Non-finite voxels are left out of the ranges: any sample that reads one is non-finite and
//! contributes nothing (SPEC §3.2, §4.5), whatever the ranges say. A cell with no finite voxel
//! in reach has the empty range `[+∞, −∞]`.
//!
//! The ranges are computed once per dataset when it is loaded ([`Macrocells::compute`]),
//! are carried by its [`super::Volume`] and shared by every object that uses it; their
//! bytes count towards the memory budget ([`Macrocells::byte_len`]). Each object classifies
//! cells through its own opacity map when it casts (see `sampling`).

use super::{BitVoxels, Channel, ChannelName, ChannelReader, Dims, F32LeVoxels, U16LeVoxels, U8Voxels, Voxels};
use crate::width::VectorWidth;

/// The channels that get ranges: those an opacity map reads (`voxel` for LUTs, ramps and
/// polynomials, `alpha` for raw opacity, SPEC §3.2). Only opacity decides whether a sample
/// contributes, so colour channels need none.
pub const RANGED_CHANNELS: [ChannelName; 2] = [ChannelName::Voxel, ChannelName::Alpha];

/// log₂ of the macrocell side.
pub const MACROCELL_SHIFT: u32 = 2;
/// Voxels per macrocell side: 4, like VTK's min-max blocks, so that skipping reaches close
/// to surfaces; the coarse level lets a ray cross wide empty regions in few steps.
pub const MACROCELL: u32 = 1 << MACROCELL_SHIFT;
/// log₂ of the side of a coarse block, in voxels (32: 8³ macrocells).
pub const COARSE_SHIFT: u32 = 5;

/// A level of the two-level grid.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Level {
    /// Macrocells of [`MACROCELL`]³ voxels.
    Fine = 0,
    /// Blocks of 2^[`COARSE_SHIFT`] voxels a side, each the union of its macrocells.
    Coarse = 1,
}

impl Level {
    /// log₂ of the cell side in voxels.
    pub fn shift(self) -> u32 {
        match self {
            Level::Fine => MACROCELL_SHIFT,
            Level::Coarse => COARSE_SHIFT,
        }
    }
}

/// The empty range: no finite value.
const EMPTY: [f32; 2] = [f32::INFINITY, f32::NEG_INFINITY];

/// Min and max per macrocell of one channel (see the module documentation), and per coarse
/// block (the union of its macrocells).
#[derive(Clone, Debug, PartialEq)]
pub struct Macrocells {
    cells: [u32; 3],
    ranges: Vec<[f32; 2]>,
    coarse_cells: [u32; 3],
    coarse: Vec<[f32; 2]>,
}

impl Macrocells {
    /// Cells of `level` along an axis of `n` voxels.
    pub fn cells_along(n: u32, level: Level) -> u32 {
        n.div_ceil(1 << level.shift())
    }

    /// Cells of `level` per axis for a dataset of `dims`.
    pub fn cells_of(dims: Dims, level: Level) -> [u32; 3] {
        dims.as_array().map(|n| Macrocells::cells_along(n, level))
    }

    /// Resident bytes of one channel's ranges for a dataset of `dims` (two f32 per cell of
    /// either level): what [`super::DatasetInfo::resident_bytes`] reserves before loading and
    /// [`super::Volume::byte_len`] reports after.
    pub fn byte_len(dims: Dims) -> u64 {
        let count = |level| Macrocells::cells_of(dims, level).iter().map(|&c| c as u64).product::<u64>();
        (count(Level::Fine) + count(Level::Coarse)) * std::mem::size_of::<[f32; 2]>() as u64
    }

    /// Scans `channel` (of `dims`) once and returns its ranges.
    pub fn compute(channel: &Channel, dims: Dims) -> Macrocells {
        Macrocells::compute_at(channel, dims, VectorWidth::detect(VectorWidth::Avx512))
    }

    /// [`Macrocells::compute`], the scan at most `width` wide (the same ranges at any width).
    pub(crate) fn compute_at(channel: &Channel, dims: Dims, width: VectorWidth) -> Macrocells {
        let reader = channel.reader();
        if let Some(v) = U8Voxels::of(reader) {
            scan_at(v, dims, width)
        } else if let Some(v) = U16LeVoxels::of(reader) {
            scan_at(v, dims, width)
        } else if let Some(v) = F32LeVoxels::of(reader) {
            scan_at(v, dims, width)
        } else if let Some(v) = BitVoxels::of(reader) {
            scan_at(v, dims, width)
        } else {
            scan::<ChannelReader<'_>>(reader, dims)
        }
    }

    /// Cells of `level` per axis.
    pub fn cells(&self, level: Level) -> [u32; 3] {
        match level {
            Level::Fine => self.cells,
            Level::Coarse => self.coarse_cells,
        }
    }

    /// `[min, max]` of the finite values a sample based in cell `c` of `level` reads;
    /// `min > max` when there is none. `c` must be a valid cell.
    #[inline]
    pub fn range(&self, level: Level, c: [u32; 3]) -> [f32; 2] {
        let ([nx, ny, _], ranges) = match level {
            Level::Fine => (self.cells, &self.ranges),
            Level::Coarse => (self.coarse_cells, &self.coarse),
        };
        ranges[c[0] as usize + nx as usize * (c[1] as usize + ny as usize * c[2] as usize)]
    }

    /// `[min, max]` of the channel's finite values (`None` if it has none).
    pub fn value_range(&self) -> Option<[f64; 2]> {
        let [lo, hi] = self.coarse.iter().fold(EMPTY, |all, &cell| union(all, cell));
        (lo <= hi).then_some([f64::from(lo), f64::from(hi)])
    }

    /// The union of the ranges of the cells of `level` within `radius` cells of `c` (per
    /// axis, clipped to the grid): what a stencil reaching beyond its base cell can read.
    pub fn range_around(&self, level: Level, c: [u32; 3], radius: u32) -> [f32; 2] {
        let cells = self.cells(level);
        let lo = c.map(|v| v.saturating_sub(radius));
        let hi: [u32; 3] = std::array::from_fn(|a| (c[a] + radius).min(cells[a] - 1));
        let mut out = EMPTY;
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    out = union(out, self.range(level, [x, y, z]));
                }
            }
        }
        out
    }
}

/// `acc[i] = min(acc[i], x[i])` (no NaN: sentinels stand for non-finite values).
#[inline(always)]
fn fold_min(acc: &mut [f32], x: &[f32]) {
    for (a, &x) in acc.iter_mut().zip(x) {
        *a = if x < *a { x } else { *a };
    }
}

/// `acc[i] = max(acc[i], x[i])`.
#[inline(always)]
fn fold_max(acc: &mut [f32], x: &[f32]) {
    for (a, &x) in acc.iter_mut().zip(x) {
        *a = if x > *a { x } else { *a };
    }
}

/// The union of two ranges (neither holds NaN: empty is [+∞, −∞]).
#[inline(always)]
fn union(a: [f32; 2], b: [f32; 2]) -> [f32; 2] {
    [if b[0] < a[0] { b[0] } else { a[0] }, if b[1] > a[1] { b[1] } else { a[1] }]
}

/// The voxel window `[c·B, c·B + B]` of cell `c` along an axis of `n` voxels, clamped.
#[inline]
fn window(c: u32, n: u32) -> (usize, usize) {
    let lo = c * MACROCELL;
    (lo as usize, (lo + MACROCELL).min(n - 1) as usize)
}

/// [`scan`], compiled for AVX2 where `width` allows it (AVX-512 adds nothing here). The
/// scan is element-wise conversions, minima and maxima over whole planes, which the
/// baseline x86-64 target compiles to four-lane SSE2; eight lanes halve its instructions,
/// and it was a fifth of the instructions of a one-shot render of the 15-volume scene
/// (BENCHMARKS.md, issue 19). The ranges are the same to the bit at every width: a
/// conversion, a minimum and a maximum are exact.
fn scan_at<V: Voxels>(v: V, dims: Dims, width: VectorWidth) -> Macrocells {
    match width {
        #[cfg(target_arch = "x86_64")]
        VectorWidth::Avx2 | VectorWidth::Avx512 => {
            // SAFETY: `VectorWidth::detect` gives these widths only where the processor has
            // AVX2.
            unsafe { scan_avx2(v, dims) }
        }
        _ => scan(v, dims),
    }
}

/// [`scan`] with AVX2 enabled for the body inlined into it.
///
/// # Safety
/// The processor must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn scan_avx2<V: Voxels>(v: V, dims: Dims) -> Macrocells {
    scan(v, dims)
}

/// Separable min/max, z first: for each layer of cells along z, the slices of its window
/// are decoded (non-finite values replaced by sentinels that min and max pass over) and
/// folded element-wise into one plane; its rows are folded the same way over each y
/// window; and only those few rows are reduced along x, cell by cell. Element-wise minima
/// over whole planes vectorise, so the scan costs about what copying the channel costs.
/// Always inlined, so that [`scan_avx2`]'s instructions reach its loops.
#[inline(always)]
fn scan<V: Voxels>(v: V, dims: Dims) -> Macrocells {
    let [nx, ny, nz] = dims.as_array();
    let cells = Macrocells::cells_of(dims, Level::Fine);
    let [cx, cy, cz] = cells.map(|c| c as usize);
    let (nxu, nyu) = (nx as usize, ny as usize);
    let plane = nxu * nyu;
    let b = MACROCELL as usize;

    let mut ranges = vec![EMPTY; cx * cy * cz];
    let (mut slice, mut slice_hi) = (vec![0.0f32; plane], vec![0.0f32; plane]);
    let (mut lo, mut hi) = (vec![0.0f32; plane], vec![0.0f32; plane]);
    let (mut row_lo, mut row_hi) = (vec![0.0f32; nxu], vec![0.0f32; nxu]);
    for k in 0..cz {
        // z: fold the slices of layer k's window into (lo, hi).
        let (z0, z1) = window(k as u32, nz);
        for z in z0..=z1 {
            // The window's first slice is decoded straight into the planes it starts.
            let (low, high) = if z == z0 { (&mut lo, &mut hi) } else { (&mut slice, &mut slice_hi) };
            v.decode(z * plane, low);
            if V::ALWAYS_FINITE {
                if z == z0 {
                    high.copy_from_slice(low);
                }
            } else {
                for (l, h) in low.iter_mut().zip(high.iter_mut()) {
                    let finite = l.is_finite();
                    *h = if finite { *l } else { f32::NEG_INFINITY };
                    *l = if finite { *l } else { f32::INFINITY };
                }
            }
            if z != z0 {
                fold_min(&mut lo, &slice);
                fold_max(&mut hi, if V::ALWAYS_FINITE { &slice } else { &slice_hi });
            }
        }
        for j in 0..cy {
            // y: fold the rows of cell row j's window.
            let (y0, y1) = window(j as u32, ny);
            row_lo.copy_from_slice(&lo[y0 * nxu..][..nxu]);
            row_hi.copy_from_slice(&hi[y0 * nxu..][..nxu]);
            for y in y0 + 1..=y1 {
                fold_min(&mut row_lo, &lo[y * nxu..][..nxu]);
                fold_max(&mut row_hi, &hi[y * nxu..][..nxu]);
            }
            // x: each cell's own voxels, then its apron (the first voxel of the next cell).
            let out = &mut ranges[(k * cy + j) * cx..][..cx];
            for (i, ((o, l), h)) in out.iter_mut().zip(row_lo.chunks(b)).zip(row_hi.chunks(b)).enumerate() {
                let apron = ((i + 1) * b).min(nxu - 1);
                let low = l.iter().fold(row_lo[apron], |m, &x| if x < m { x } else { m });
                let high = h.iter().fold(row_hi[apron], |m, &x| if x > m { x } else { m });
                *o = [low, high];
            }
        }
    }

    // Coarse blocks: the union of the macrocells they hold.
    let coarse_cells = Macrocells::cells_of(dims, Level::Coarse);
    let per = 1usize << (COARSE_SHIFT - MACROCELL_SHIFT);
    let mut coarse = vec![EMPTY; coarse_cells.iter().map(|&c| c as usize).product()];
    let [ccx, ccy, _] = coarse_cells.map(|c| c as usize);
    for z in 0..cz {
        for y in 0..cy {
            for x in 0..cx {
                let block = x / per + ccx * (y / per + ccy * (z / per));
                coarse[block] = union(coarse[block], ranges[x + cx * (y + cy * z)]);
            }
        }
    }
    Macrocells { cells, ranges, coarse_cells, coarse }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn channel(dims: Dims, f: impl Fn(usize, usize, usize) -> f32) -> Channel {
        let [nx, ny, nz] = dims.as_array().map(|n| n as usize);
        let mut v = Vec::new();
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    v.push(f(i, j, k));
                }
            }
        }
        Channel::from_f32(&v, dims).unwrap()
    }

    /// The definition, voxel by voxel.
    fn brute(ch: &Channel, dims: Dims, c: [u32; 3]) -> [f32; 2] {
        let n = dims.as_array();
        let mut r = EMPTY;
        let w: [(usize, usize); 3] = std::array::from_fn(|a| window(c[a], n[a]));
        for k in w[2].0..=w[2].1 {
            for j in w[1].0..=w[1].1 {
                for i in w[0].0..=w[0].1 {
                    let v = ch.value(dims.index(i, j, k));
                    if v.is_finite() {
                        r = union(r, [v, v]);
                    }
                }
            }
        }
        r
    }

    #[test]
    fn ranges_cover_each_cell_and_one_voxel_above_clamped_at_borders() {
        // Sizes that are and are not multiples of the cell, and single-voxel axes.
        for d in [[17, 9, 8], [8, 1, 3], [1, 1, 1], [16, 24, 9]] {
            let dims = Dims::new(d).unwrap();
            let ch = channel(dims, |i, j, k| ((i * 7 + j * 13 + k * 29) % 23) as f32 - 5.0);
            let m = Macrocells::compute(&ch, dims);
            assert_eq!(m.cells(Level::Fine), Macrocells::cells_of(dims, Level::Fine));
            for z in 0..m.cells(Level::Fine)[2] {
                for y in 0..m.cells(Level::Fine)[1] {
                    for x in 0..m.cells(Level::Fine)[0] {
                        assert_eq!(
                            m.range(Level::Fine, [x, y, z]),
                            brute(&ch, dims, [x, y, z]),
                            "{d:?} cell {x} {y} {z}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn the_apron_reaches_the_first_voxel_of_the_next_cell_only() {
        let dims = Dims::new([12, 1, 1]).unwrap();
        // A single bright voxel at x = 4: cell 0 (window 0..=4) and cell 1 (4..=8) see it,
        // cell 2 (8..=11) does not, nor would cell 1 if it sat at x = 9.
        let ch = channel(dims, |i, _, _| if i == 4 { 9.0 } else { 0.0 });
        let m = Macrocells::compute(&ch, dims);
        assert_eq!(m.range(Level::Fine, [0, 0, 0]), [0.0, 9.0]);
        assert_eq!(m.range(Level::Fine, [1, 0, 0]), [0.0, 9.0]);
        assert_eq!(m.range(Level::Fine, [2, 0, 0]), [0.0, 0.0]);
        assert_eq!(m.range_around(Level::Fine, [2, 0, 0], 1), [0.0, 9.0]);
        assert_eq!(m.range_around(Level::Fine, [0, 0, 0], 1), [0.0, 9.0]);
        assert_eq!(m.cells(Level::Coarse), [1, 1, 1]);
        assert_eq!(m.range(Level::Coarse, [0, 0, 0]), [0.0, 9.0]);
    }

    #[test]
    fn coarse_blocks_are_the_union_of_their_macrocells() {
        let dims = Dims::new([70, 33, 5]).unwrap();
        let ch = channel(dims, |i, j, k| ((i * 5 + j * 11 + k * 3) % 17) as f32 * if i > 40 { 2.0 } else { 1.0 });
        let m = Macrocells::compute(&ch, dims);
        assert_eq!(m.cells(Level::Coarse), [3, 2, 1]);
        let per = 1 << (COARSE_SHIFT - MACROCELL_SHIFT);
        for bz in 0..1 {
            for by in 0..2 {
                for bx in 0..3 {
                    let mut want = EMPTY;
                    let f = m.cells(Level::Fine);
                    for z in bz * per..((bz + 1) * per).min(f[2]) {
                        for y in by * per..((by + 1) * per).min(f[1]) {
                            for x in bx * per..((bx + 1) * per).min(f[0]) {
                                want = union(want, m.range(Level::Fine, [x, y, z]));
                            }
                        }
                    }
                    assert_eq!(m.range(Level::Coarse, [bx, by, bz]), want);
                }
            }
        }
    }

    #[test]
    fn non_finite_voxels_are_left_out_and_an_all_nan_cell_is_empty() {
        let dims = Dims::new([12, 2, 2]).unwrap();
        let ch = channel(dims, |i, _, _| match i {
            0..=4 => f32::NAN,
            5 => f32::INFINITY,
            6 => 4.0,
            _ => -1.0,
        });
        let m = Macrocells::compute(&ch, dims);
        assert_eq!(m.range(Level::Fine, [0, 0, 0]), EMPTY);
        assert_eq!(m.range(Level::Fine, [1, 0, 0]), [-1.0, 4.0]);
        assert_eq!(m.range(Level::Fine, [2, 0, 0]), [-1.0, -1.0]);
    }

    /// Each typed scan, at every width the processor has ([`scan_at`]), gives the generic
    /// reader's plain scan to the bit, non-finite f32 voxels included.
    #[test]
    fn typed_scans_agree_with_the_generic_reader() {
        let dims = Dims::new([19, 10, 11]).unwrap();
        let bytes: Vec<u8> = (0..dims.voxel_count() as usize * 2).map(|i| (i * 31 % 251) as u8).collect();
        let u16_le = Channel::new(
            super::super::VoxelType::U16,
            super::super::Endian::Little,
            super::super::VoxelBytes::Owned(std::sync::Arc::new(bytes.clone())),
            dims,
        )
        .unwrap();
        let u8_ch = Channel::from_u8(bytes[..dims.voxel_count() as usize].to_vec(), dims).unwrap();
        let f32_ch = channel(dims, |i, j, k| match (i * 3 + j * 5 + k * 7) % 11 {
            0 => f32::NAN,
            1 => f32::INFINITY,
            2 => f32::NEG_INFINITY,
            n => n as f32 * 0.75 - 4.0,
        });
        for ch in [&u16_le, &u8_ch, &f32_ch] {
            let plain = scan::<ChannelReader<'_>>(ch.reader(), dims);
            for width in [VectorWidth::Baseline, VectorWidth::Avx2] {
                assert_eq!(Macrocells::compute_at(ch, dims, VectorWidth::detect(width)), plain, "{width:?}");
            }
        }
    }

    #[test]
    fn byte_len_counts_two_f32_per_cell_of_both_levels() {
        let dims = Dims::new([256, 256, 113]).unwrap();
        assert_eq!(Macrocells::byte_len(dims), (64 * 64 * 29 + 8 * 8 * 4) * 8);
    }
}
