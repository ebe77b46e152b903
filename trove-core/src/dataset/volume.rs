//! Dataset dimensions and the resident voxels of one dataset.

use std::collections::BTreeMap;
use std::fmt;
use std::sync::Arc;

use thiserror::Error;

use super::macrocell::{Macrocells, RANGED_CHANNELS};
use super::{Channel, ChannelName};
use crate::width::VectorWidth;

/// Why [`Dims::new`] refused three sizes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Error)]
pub enum DimsError {
    /// An axis of size 0.
    #[error("dims {dims:?}: every axis must be at least 1")]
    ZeroAxis {
        /// The sizes given.
        dims: [u64; 3],
    },
    /// An axis beyond `i32::MAX` voxels (indices are computed in signed arithmetic).
    #[error("dims {dims:?}: an axis exceeds {}", i32::MAX)]
    AxisTooLarge {
        /// The sizes given.
        dims: [u64; 3],
    },
    /// More than [`Dims::MAX_VOXELS`] voxels in all.
    #[error("dims {dims:?}: more than {} voxels", Dims::MAX_VOXELS)]
    TooManyVoxels {
        /// The sizes given.
        dims: [u64; 3],
    },
}

/// Voxels per axis, each ≥ 1, with a total that indexes safely in `usize` and whose bytes
/// fit in `u64` for every channel type. Established once, in [`Dims::new`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Dims([u32; 3]);

impl Dims {
    /// Largest voxel count accepted (2^40, one TiB of u8 voxels).
    pub const MAX_VOXELS: u64 = 1 << 40;

    /// Checked constructor.
    pub fn new(d: [u64; 3]) -> Result<Dims, DimsError> {
        if d.contains(&0) {
            return Err(DimsError::ZeroAxis { dims: d });
        }
        if d.iter().any(|&n| n > i32::MAX as u64) {
            return Err(DimsError::AxisTooLarge { dims: d });
        }
        let total = d[0].checked_mul(d[1]).and_then(|v| v.checked_mul(d[2]));
        match total {
            Some(t) if t <= Dims::MAX_VOXELS => Ok(Dims([d[0] as u32, d[1] as u32, d[2] as u32])),
            _ => Err(DimsError::TooManyVoxels { dims: d }),
        }
    }

    /// Voxels along `axis` (0 = x, 1 = y, 2 = z).
    #[inline]
    pub fn axis(&self, axis: usize) -> u32 {
        self.0[axis]
    }

    /// The three sizes.
    pub fn as_array(&self) -> [u32; 3] {
        self.0
    }

    /// Total voxel count.
    pub fn voxel_count(&self) -> u64 {
        self.0.iter().map(|&n| n as u64).product()
    }

    /// Linear index of voxel (i, j, k): x fastest, then y, then z.
    #[inline(always)]
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.0[0] as usize * (j + self.0[1] as usize * k)
    }
}

impl fmt::Display for Dims {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "[{}, {}, {}]", self.0[0], self.0[1], self.0[2])
    }
}

/// The resident voxels of one dataset: every channel it declares, each exactly `dims`, and
/// the macrocell ranges of the channels opacity maps read (for empty-space skipping).
#[derive(Clone, Debug)]
pub struct Volume {
    dims: Dims,
    channels: BTreeMap<ChannelName, Channel>,
    macrocells: BTreeMap<ChannelName, Arc<Macrocells>>,
}

impl Volume {
    /// Assembles a volume and scans its `voxel` and `alpha` channels for macrocell ranges;
    /// each channel was already checked against `dims` by [`Channel::new`].
    pub fn new(dims: Dims, channels: BTreeMap<ChannelName, Channel>) -> Volume {
        Volume::at_width(dims, channels, VectorWidth::detect(VectorWidth::Avx512))
    }

    /// [`Volume::new`], its macrocells scanned at most `width` wide (the same ranges at any
    /// width).
    pub(crate) fn at_width(dims: Dims, channels: BTreeMap<ChannelName, Channel>, width: VectorWidth) -> Volume {
        let macrocells = RANGED_CHANNELS
            .iter()
            .filter_map(|name| channels.get(name).map(|ch| (*name, Arc::new(Macrocells::compute_at(ch, dims, width)))))
            .collect();
        Volume { dims, channels, macrocells }
    }

    /// Dimensions.
    pub fn dims(&self) -> Dims {
        self.dims
    }

    /// A channel, if the dataset has it.
    pub fn channel(&self, name: ChannelName) -> Option<&Channel> {
        self.channels.get(&name)
    }

    /// All channels.
    pub fn channels(&self) -> impl Iterator<Item = (ChannelName, &Channel)> {
        self.channels.iter().map(|(n, c)| (*n, c))
    }

    /// The macrocell ranges of `name`, for the channels in `RANGED_CHANNELS` the dataset has.
    pub fn macrocells(&self, name: ChannelName) -> Option<&Macrocells> {
        self.macrocells.get(&name).map(|m| &**m)
    }

    /// The same volume with every channel in owned memory (see [`Channel::owned_copy`]);
    /// the macrocell ranges are owned already and shared.
    pub fn owned_copy(&self) -> Volume {
        Volume {
            dims: self.dims,
            channels: self.channels.iter().map(|(n, c)| (*n, c.owned_copy())).collect(),
            macrocells: self.macrocells.clone(),
        }
    }

    /// Resident bytes (what a memory budget counts): the channels and their macrocell
    /// ranges. Equal to [`super::DatasetInfo::resident_bytes`] of the dataset it was loaded from.
    pub fn byte_len(&self) -> u64 {
        let ranges = self.macrocells.len() as u64 * Macrocells::byte_len(self.dims);
        self.channels.values().map(|c| c.byte_len() as u64).sum::<u64>() + ranges
    }
}
