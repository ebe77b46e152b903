//! Where a dataset's voxels come from, validated at scene load, loaded on demand.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;

use super::generator::Generator;
use super::macrocell::{Macrocells, RANGED_CHANNELS};
use super::raw::StoredType;
use super::{Channel, ChannelName, Dims, Endian, Volume, VoxelType};
use crate::DatasetError;

/// How a file region is encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    /// Plain bytes: memory-mapped, zero copy, when no conversion is needed.
    Raw,
    /// A gzip stream, inflated on load.
    Gzip,
}

/// How to produce one channel's bytes. Every variant was checked against the dataset's
/// dims when it was built (file sizes, headers), so a load fails only if a file changed
/// since.
#[derive(Clone, Debug)]
pub enum ChannelSource {
    /// A region of a file (raw files, NRRD data): `stored` numbers from byte `offset`.
    File {
        /// The data file.
        path: PathBuf,
        /// Bytes to skip (an attached header, NRRD `byte skip`).
        offset: u64,
        /// Raw or gzip.
        encoding: Encoding,
        /// The numbers as stored; types TROVE does not store natively become f32.
        stored: StoredType,
        /// Byte order of the stored numbers.
        endian: Endian,
    },
    /// A NIfTI-1 volume (`.nii`, `.nii.gz`), decoded whole.
    Nifti {
        /// The file.
        path: PathBuf,
    },
    /// One channel of a PNG/JPEG image, flipped so y points up.
    Image {
        /// The image file.
        path: PathBuf,
        /// Which of red, green, blue, alpha.
        channel: ChannelName,
    },
    /// A documented generator.
    Generated(Generator),
}

impl ChannelSource {
    /// Reads, decodes or generates the channel.
    pub fn load(&self, dims: Dims) -> Result<Channel, DatasetError> {
        match self {
            ChannelSource::File { path, offset, encoding, stored, endian } => {
                super::raw::load(path, *offset, *encoding, *stored, *endian, dims)
            }
            ChannelSource::Nifti { path } => super::nifti_file::load(path, dims),
            ChannelSource::Image { path, channel } => super::image_file::load(path, *channel, dims),
            ChannelSource::Generated(g) => Ok(g.generate(dims)),
        }
    }
}

/// A dataset as the object level sees it: enough to place and intersect objects (dims,
/// channel types) and to load its voxels when a renderer needs them.
#[derive(Clone, Debug)]
pub struct DatasetInfo {
    /// Unique name in the scene.
    pub name: String,
    /// Voxels per axis.
    pub dims: Dims,
    /// Each channel's storage type once loaded, and where it comes from.
    pub channels: BTreeMap<ChannelName, (VoxelType, ChannelSource)>,
}

impl DatasetInfo {
    /// Whether the dataset has `channel`.
    pub fn has(&self, channel: ChannelName) -> bool {
        self.channels.contains_key(&channel)
    }

    /// Bytes the dataset occupies once loaded (what a memory budget counts): its channels
    /// and the macrocell ranges [`Volume::new`] computes for `voxel` and `alpha`.
    pub fn resident_bytes(&self) -> u64 {
        let ranged = RANGED_CHANNELS.iter().filter(|c| self.has(**c)).count() as u64;
        self.channels
            .values()
            .map(|(ty, _)| ty.byte_len(self.dims.voxel_count()).unwrap_or(u64::MAX))
            .fold(ranged * Macrocells::byte_len(self.dims), u64::saturating_add)
    }

    /// Loads every channel.
    pub fn load(&self) -> Result<Arc<Volume>, DatasetError> {
        let mut channels = BTreeMap::new();
        for (name, (_, source)) in &self.channels {
            channels.insert(*name, source.load(self.dims)?);
        }
        Ok(Arc::new(Volume::new(self.dims, channels)))
    }
}
