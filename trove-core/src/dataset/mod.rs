//! The voxel level (paper §2.2, §2.3.1): raw datasets, each stored once and shared (via
//! `Arc`) by every object that names it.
//!
//! A dataset is described at scene load by a [`DatasetInfo`] (name, dims, channel types and
//! where the bytes come from), which is enough for the intersection phase and is validated
//! in full: header, dims and byte counts agree before any ray is cast. Its voxels are a
//! [`Volume`], produced by [`DatasetInfo::load`] when a renderer needs them, so a
//! memory-budgeted store can drop and reload them.

mod catalog;
mod channel;
mod error;
pub(crate) mod generator;
pub(crate) mod image_file;
pub(crate) mod macrocell;
mod mmap;
pub(crate) mod nifti_file;
pub(crate) mod nrrd;
pub(crate) mod raw;
mod source;
mod volume;

pub use catalog::{Catalog, DataFile, FileInfo, FileKind, FsCatalog, VolumeFormat};
pub use channel::{
    BitVoxels, Channel, ChannelName, ChannelReader, ChannelSizeError, Endian, F32LeVoxels, U16LeVoxels, U8Voxels,
    VoxelBytes, VoxelType, Voxels,
};
pub use error::{DatasetError, KeyProblem};
pub use generator::{Generator, GeneratorError};
pub use raw::StoredType;
pub use source::{ChannelSource, DatasetId, DatasetInfo, Encoding};
pub use volume::{Dims, DimsError, Volume};
