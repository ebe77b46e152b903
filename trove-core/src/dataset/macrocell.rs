//! Value ranges per macrocell: the data behind empty-space skipping (issue 10).
//!
//! A dataset's volume is cut into cells of [`MACROCELL`]³ voxels; for each cell the minimum
//! and maximum of the finite values a sample *based* in that cell can read are kept. A
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

/// The channels that get ranges: those an opacity map reads (`voxel` for LUTs, ramps and
/// polynomials, `alpha` for raw opacity, SPEC §3.2). Only opacity decides whether a sample
/// contributes, so colour channels need none.
pub const RANGED_CHANNELS: [ChannelName; 2] = [ChannelName::Voxel, ChannelName::Alpha];

/// log₂ of the macrocell side.
pub const MACROCELL_SHIFT: u32 = 3;
/// Voxels per macrocell side: 8, as a compromise between skipping close to surfaces
/// (smaller cells) and the cost of a jump and the table's size (1/64 of the voxel count,
/// 8 bytes each).
pub const MACROCELL: u32 = 1 << MACROCELL_SHIFT;

/// The empty range: no finite value.
const EMPTY: [f32; 2] = [f32::INFINITY, f32::NEG_INFINITY];

/// Min and max per macrocell of one channel (see the module documentation).
#[derive(Clone, Debug, PartialEq)]
pub struct Macrocells {
    cells: [u32; 3],
    ranges: Vec<[f32; 2]>,
}

impl Macrocells {
    /// Cells along an axis of `n` voxels.
    pub fn cells_along(n: u32) -> u32 {
        n.div_ceil(MACROCELL)
    }

    /// Cells per axis for a dataset of `dims`.
    pub fn cells_of(dims: Dims) -> [u32; 3] {
        dims.as_array().map(Macrocells::cells_along)
    }

    /// Resident bytes of one channel's ranges for a dataset of `dims` (two f32 per cell):
    /// what [`super::DatasetInfo::resident_bytes`] reserves before loading and
    /// [`super::Volume::byte_len`] reports after.
    pub fn byte_len(dims: Dims) -> u64 {
        Macrocells::cells_of(dims).iter().map(|&c| c as u64).product::<u64>() * std::mem::size_of::<[f32; 2]>() as u64
    }

    /// Scans `channel` (of `dims`) once and returns its ranges.
    pub fn compute(channel: &Channel, dims: Dims) -> Macrocells {
        let reader = channel.reader();
        if let Some(v) = U8Voxels::of(reader) {
            scan(v, dims)
        } else if let Some(v) = U16LeVoxels::of(reader) {
            scan(v, dims)
        } else if let Some(v) = F32LeVoxels::of(reader) {
            scan(v, dims)
        } else if let Some(v) = BitVoxels::of(reader) {
            scan(v, dims)
        } else {
            scan::<ChannelReader<'_>>(reader, dims)
        }
    }

    /// Cells per axis.
    pub fn cells(&self) -> [u32; 3] {
        self.cells
    }

    /// `[min, max]` of the finite values a sample based in cell `c` reads; `min > max` when
    /// there is none. `c` must be a valid cell.
    #[inline]
    pub fn range(&self, c: [u32; 3]) -> [f32; 2] {
        let [nx, ny, _] = self.cells;
        self.ranges[c[0] as usize + nx as usize * (c[1] as usize + ny as usize * c[2] as usize)]
    }

    /// The union of the ranges of the cells within `radius` cells of `c` (per axis, clipped
    /// to the grid): what a stencil reaching beyond its base cell can read.
    pub fn range_around(&self, c: [u32; 3], radius: u32) -> [f32; 2] {
        let lo = c.map(|v| v.saturating_sub(radius));
        let hi: [u32; 3] = std::array::from_fn(|a| (c[a] + radius).min(self.cells[a] - 1));
        let mut out = EMPTY;
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    out = union(out, self.range([x, y, z]));
                }
            }
        }
        out
    }
}

#[inline(always)]
fn union(a: [f32; 2], b: [f32; 2]) -> [f32; 2] {
    [a[0].min(b[0]), a[1].max(b[1])]
}

/// The voxel window `[c·B, c·B + B]` of cell `c` along an axis of `n` voxels, clamped.
#[inline]
fn window(c: u32, n: u32) -> (usize, usize) {
    let lo = c * MACROCELL;
    (lo as usize, (lo + MACROCELL).min(n - 1) as usize)
}

/// Separable min/max: along x over every row, then along y over the row results, then
/// along z. Each pass reads its input about (B + 1)/B times, so the whole scan costs little
/// more than reading the channel once.
fn scan<V: Voxels>(v: V, dims: Dims) -> Macrocells {
    let [nx, ny, nz] = dims.as_array();
    let cells = Macrocells::cells_of(dims);
    let [cx, cy, cz] = cells.map(|c| c as usize);
    let (nxu, nyu, nzu) = (nx as usize, ny as usize, nz as usize);

    // Pass 1: x. rows[(k·ny + j)·cx + i] = range of cell i's window in row (j, k).
    let mut rows = vec![EMPTY; cx * nyu * nzu];
    for (row, out) in rows.chunks_exact_mut(cx).enumerate() {
        let base = row * nxu;
        for (i, o) in out.iter_mut().enumerate() {
            let (lo, hi) = window(i as u32, nx);
            let mut r = EMPTY;
            for x in lo..=hi {
                let value = v.get(base + x);
                if value.is_finite() {
                    r = union(r, [value, value]);
                }
            }
            *o = r;
        }
    }

    // Pass 2: y. planes[(k·cy + j)·cx + i].
    let mut planes = vec![EMPTY; cx * cy * nzu];
    for k in 0..nzu {
        for j in 0..cy {
            let (lo, hi) = window(j as u32, ny);
            let out = &mut planes[(k * cy + j) * cx..][..cx];
            for y in lo..=hi {
                let row = &rows[(k * nyu + y) * cx..][..cx];
                for (o, r) in out.iter_mut().zip(row) {
                    *o = union(*o, *r);
                }
            }
        }
    }
    drop(rows);

    // Pass 3: z.
    let mut ranges = vec![EMPTY; cx * cy * cz];
    for k in 0..cz {
        let (lo, hi) = window(k as u32, nz);
        let out = &mut ranges[k * cy * cx..][..cy * cx];
        for z in lo..=hi {
            let plane = &planes[z * cy * cx..][..cy * cx];
            for (o, p) in out.iter_mut().zip(plane) {
                *o = union(*o, *p);
            }
        }
    }
    Macrocells { cells, ranges }
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
            assert_eq!(m.cells(), Macrocells::cells_of(dims));
            for z in 0..m.cells()[2] {
                for y in 0..m.cells()[1] {
                    for x in 0..m.cells()[0] {
                        assert_eq!(m.range([x, y, z]), brute(&ch, dims, [x, y, z]), "{d:?} cell {x} {y} {z}");
                    }
                }
            }
        }
    }

    #[test]
    fn the_apron_reaches_the_first_voxel_of_the_next_cell_only() {
        let dims = Dims::new([24, 1, 1]).unwrap();
        // A single bright voxel at x = 8: cell 0 (window 0..=8) and cell 1 (8..=16) see it,
        // cell 2 (16..=23) does not; at x = 16 it would be cells 1 and 2.
        let ch = channel(dims, |i, _, _| if i == 8 { 9.0 } else { 0.0 });
        let m = Macrocells::compute(&ch, dims);
        assert_eq!(m.range([0, 0, 0]), [0.0, 9.0]);
        assert_eq!(m.range([1, 0, 0]), [0.0, 9.0]);
        assert_eq!(m.range([2, 0, 0]), [0.0, 0.0]);
        assert_eq!(m.range_around([2, 0, 0], 1), [0.0, 9.0]);
        assert_eq!(m.range_around([0, 0, 0], 1), [0.0, 9.0]);
    }

    #[test]
    fn non_finite_voxels_are_left_out_and_an_all_nan_cell_is_empty() {
        let dims = Dims::new([20, 2, 2]).unwrap();
        let ch = channel(dims, |i, _, _| match i {
            0..=8 => f32::NAN,
            9 => f32::INFINITY,
            10 => 4.0,
            _ => -1.0,
        });
        let m = Macrocells::compute(&ch, dims);
        assert_eq!(m.range([0, 0, 0]), EMPTY);
        assert_eq!(m.range([1, 0, 0]), [-1.0, 4.0]);
        assert_eq!(m.range([2, 0, 0]), [-1.0, -1.0]);
    }

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
        for ch in [&u16_le, &u8_ch] {
            assert_eq!(Macrocells::compute(ch, dims), scan::<ChannelReader<'_>>(ch.reader(), dims));
        }
    }

    #[test]
    fn byte_len_counts_two_f32_per_cell() {
        let dims = Dims::new([256, 256, 113]).unwrap();
        assert_eq!(Macrocells::byte_len(dims), 32 * 32 * 15 * 8);
    }
}
