//! Where a dataset's voxels come from, validated at scene load, loaded on demand.

use std::collections::BTreeMap;
use std::sync::Arc;

use super::error::DatasetError;
use super::generator::Generator;
use super::macrocell::{Macrocells, RANGED_CHANNELS};
use super::raw::StoredType;
use super::{Channel, ChannelName, DataFile, Dims, Endian, Volume, VoxelType};
use crate::width::VectorWidth;

/// How a file region is encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
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
        file: DataFile,
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
        file: DataFile,
    },
    /// One channel of a PNG/JPEG image, flipped so y points up.
    Image {
        /// The image file.
        file: DataFile,
        /// Which of red, green, blue, alpha.
        channel: ChannelName,
    },
    /// A documented generator.
    Generated(Generator),
}

impl ChannelSource {
    /// Reads, decodes or generates the channel; a [`DataFile::Remote`] source is
    /// [`DatasetError::Remote`].
    pub fn load(&self, dims: Dims) -> Result<Channel, DatasetError> {
        match self {
            ChannelSource::File { file, offset, encoding, stored, endian } => {
                super::raw::load(file.local()?, *offset, *encoding, *stored, *endian, dims)
            }
            ChannelSource::Nifti { file } => super::nifti_file::load(file.local()?, dims),
            ChannelSource::Image { file, channel } => super::image_file::load(file.local()?, *channel, dims),
            ChannelSource::Generated(g) => Ok(g.generate(dims)),
        }
    }
}

/// A dataset as the object level sees it: enough to place and intersect objects (dims,
/// channel types) and to load its voxels when a renderer needs them. Built once, by the
/// scene loader, from sources it checked against the dims.
#[derive(Clone, Debug)]
pub struct DatasetInfo {
    name: String,
    dims: Dims,
    channels: BTreeMap<ChannelName, (VoxelType, ChannelSource)>,
    /// Computed once: a store looks datasets up by it for every cast.
    id: DatasetId,
}

impl DatasetInfo {
    /// A dataset of `dims` whose channels come from `channels` (each checked against `dims`
    /// by whoever built it).
    pub(crate) fn new(
        name: String,
        dims: Dims,
        channels: BTreeMap<ChannelName, (VoxelType, ChannelSource)>,
    ) -> DatasetInfo {
        let id = identity(dims, &channels);
        DatasetInfo { name, dims, channels, id }
    }

    /// Its unique name in the scene.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Voxels per axis.
    pub fn dims(&self) -> Dims {
        self.dims
    }

    /// Each channel's storage type once loaded, and where it comes from.
    pub fn channels(&self) -> &BTreeMap<ChannelName, (VoxelType, ChannelSource)> {
        &self.channels
    }

    /// The files its channels read, each once (none for a generated dataset).
    pub fn files(&self) -> Vec<&DataFile> {
        let mut files: Vec<&DataFile> = Vec::new();
        for (_, source) in self.channels.values() {
            let file = match source {
                ChannelSource::File { file, .. }
                | ChannelSource::Nifti { file }
                | ChannelSource::Image { file, .. } => file,
                ChannelSource::Generated(_) => continue,
            };
            if !files.contains(&file) {
                files.push(file);
            }
        }
        files
    }

    /// The keys (or local paths) of [`DatasetInfo::files`], as text.
    pub fn file_keys(&self) -> Vec<String> {
        self.files().iter().map(|f| f.path().to_string_lossy().into_owned()).collect()
    }

    /// Whether this process can load it: every file it reads is local.
    pub fn is_local(&self) -> bool {
        self.files().iter().all(|f| matches!(f, DataFile::Local(_)))
    }
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

    /// The dataset's identity: what it reads (each channel's file region, or its generator
    /// and parameters) and its dims, not its name. Two scenes that name the same files (or
    /// the same generators) with the same dims give equal ids, so a long-lived store can
    /// keep the voxels between them. Local files compare by path as resolved (a sandboxed
    /// catalog resolves to canonical paths).
    pub fn id(&self) -> &DatasetId {
        &self.id
    }

    /// Loads every channel.
    pub fn load(&self) -> Result<Arc<Volume>, DatasetError> {
        self.load_at(VectorWidth::detect(VectorWidth::Avx512))
    }

    /// [`DatasetInfo::load`], its macrocells scanned at most `width` wide (a render's
    /// configured width: the same ranges at any width).
    pub(crate) fn load_at(&self, width: VectorWidth) -> Result<Arc<Volume>, DatasetError> {
        let mut channels = BTreeMap::new();
        for (name, (_, source)) in &self.channels {
            channels.insert(*name, source.load(self.dims)?);
        }
        Ok(Arc::new(Volume::at_width(self.dims, channels, width)))
    }
}

/// The identity of a dataset of `dims` reading `channels` ([`DatasetInfo::id`]).
fn identity(dims: Dims, channels: &BTreeMap<ChannelName, (VoxelType, ChannelSource)>) -> DatasetId {
    let channels = channels
        .iter()
        .map(|(name, (_, source))| {
            let id = match source {
                ChannelSource::File { file, offset, encoding, stored, endian } => SourceId::File {
                    file: file.clone(),
                    offset: *offset,
                    encoding: *encoding,
                    stored: *stored,
                    endian: *endian,
                },
                ChannelSource::Nifti { file } => SourceId::Nifti(file.clone()),
                ChannelSource::Image { file, channel } => SourceId::Image(file.clone(), *channel),
                ChannelSource::Generated(g) => SourceId::Generated(g.identity()),
            };
            (*name, id)
        })
        .collect();
    DatasetId { dims, channels }
}

/// What a dataset reads, independent of its name in a scene ([`DatasetInfo::id`]): the key a
/// volume store caches voxels by.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct DatasetId {
    dims: Dims,
    channels: Vec<(ChannelName, SourceId)>,
}

/// One channel's source, comparable and hashable (generator parameters by their bits).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
enum SourceId {
    File { file: DataFile, offset: u64, encoding: Encoding, stored: StoredType, endian: Endian },
    Nifti(DataFile),
    Image(DataFile, ChannelName),
    Generated(Vec<u64>),
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use super::*;

    fn dims(n: u64) -> Dims {
        Dims::new([n, n, n]).unwrap()
    }

    fn info(name: &str, n: u64, channels: Vec<(ChannelName, ChannelSource)>) -> DatasetInfo {
        DatasetInfo::new(name.into(), dims(n), channels.into_iter().map(|(c, s)| (c, (VoxelType::U8, s))).collect())
    }

    fn raw(path: &str, offset: u64) -> ChannelSource {
        ChannelSource::File {
            file: DataFile::Local(PathBuf::from(path)),
            offset,
            encoding: Encoding::Raw,
            stored: StoredType::U8,
            endian: Endian::Little,
        }
    }

    fn sphere(radius: f64) -> ChannelSource {
        ChannelSource::Generated(Generator::Sphere {
            centre: [0.5; 3],
            radius,
            value: 255.0,
            profile: Default::default(),
            ty: VoxelType::U8,
        })
    }

    #[test]
    fn ids_follow_sources_and_dims_not_names() {
        use std::collections::HashSet;
        let a = info("a", 4, vec![(ChannelName::Voxel, raw("/d/v.raw", 0))]);
        let same_file_other_name = info("b", 4, vec![(ChannelName::Voxel, raw("/d/v.raw", 0))]);
        assert_eq!(a.id(), same_file_other_name.id());
        let different = [
            info("a", 5, vec![(ChannelName::Voxel, raw("/d/v.raw", 0))]),
            info("a", 4, vec![(ChannelName::Voxel, raw("/d/w.raw", 0))]),
            info("a", 4, vec![(ChannelName::Voxel, raw("/d/v.raw", 8))]),
            info("a", 4, vec![(ChannelName::Grey, raw("/d/v.raw", 0))]),
            info("a", 4, vec![(ChannelName::Voxel, sphere(0.4))]),
        ];
        let mut ids: HashSet<DatasetId> = different.iter().map(|d| d.id().clone()).collect();
        assert_eq!(ids.len(), different.len(), "every difference in source or dims changes the id");
        assert!(ids.insert(a.id().clone()));
        // Generators compare by kind and parameters.
        let g = info("g", 4, vec![(ChannelName::Voxel, sphere(0.4))]);
        assert_eq!(g.id(), info("h", 4, vec![(ChannelName::Voxel, sphere(0.4))]).id());
        assert_ne!(g.id(), info("g", 4, vec![(ChannelName::Voxel, sphere(0.41))]).id());
        let remote = |key: &str| ChannelSource::Nifti { file: DataFile::Remote(key.into()) };
        assert_eq!(
            info("r", 4, vec![(ChannelName::Voxel, remote("k.nii"))]).id(),
            info("s", 4, vec![(ChannelName::Voxel, remote("k.nii"))]).id()
        );
    }

    #[test]
    fn a_remote_source_is_a_typed_error_when_loaded() {
        let source = ChannelSource::File {
            file: DataFile::Remote("data/v.raw".into()),
            offset: 0,
            encoding: Encoding::Raw,
            stored: StoredType::U8,
            endian: Endian::Little,
        };
        let e = source.load(dims(2)).unwrap_err();
        assert!(matches!(&e, DatasetError::Remote { key } if key == "data/v.raw"), "{e:?}");
        assert!(!e.is_retryable());
        let e = info("r", 2, vec![(ChannelName::Red, source)]).load().unwrap_err();
        assert!(matches!(e, DatasetError::Remote { .. }), "{e:?}");
    }
}
