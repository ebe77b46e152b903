//! Dataset keys and what they name.
//!
//! A scene names its dataset files by **key**: the path as written (`file = "a/b.nhdr"`,
//! `image = ...`, a channel's `raw = ...` or `nrrd = ...`). The scene loader never opens a
//! file itself; it asks a [`Catalog`] what a key holds, and the catalog answers from the
//! file's header alone. That is the seam between the scene and where the bytes are:
//!
//! * [`FsCatalog::trusting`] — local mode: keys are paths relative to a folder (the scene's,
//!   SPEC §1), `..` and absolute paths allowed, as a user expects of their own files.
//! * [`FsCatalog::sandboxed`] — a farm worker serving the files under its data root (SPEC
//!   §5): a key must stay inside the root, symbolic links and an NHDR's `data file`
//!   included, checked on canonical paths.
//! * A farm coordinator implements [`Catalog`] over the headers its workers registered; its
//!   sources are [`DataFile::Remote`], which the coordinator never loads.

use std::fmt;
use std::path::{Component, Path, PathBuf};

use super::{image_file, nifti_file, nrrd, ChannelName, ChannelSource, DatasetError, Dims, KeyProblem, VoxelType};

/// Answers what file a key names, from its header only (never its voxels).
pub trait Catalog: Send + Sync {
    /// What file `key` holds, read from its header only (never voxels). `kind` is what the
    /// scene expects there; an answer of another kind is the catalog's error.
    fn describe(&self, key: &str, kind: FileKind) -> Result<FileInfo, DatasetError>;
}

/// What a scene expects a key to name.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum FileKind {
    /// A volume with a header: NRRD (`.nrrd`, `.nhdr`) or NIfTI-1 (`.nii`, `.nii.gz`), told
    /// by the key's extension ([`VolumeFormat::of_key`]).
    Volume,
    /// A PNG or JPEG picture (`image = ...`).
    Image,
    /// A headerless voxel file (a channel's `raw = ...`); the scene gives its layout.
    Raw,
}

impl fmt::Display for FileKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            FileKind::Volume => "a volume (NRRD or NIfTI)",
            FileKind::Image => "an image (PNG or JPEG)",
            FileKind::Raw => "a raw voxel file",
        })
    }
}

/// What a catalog found under a key.
#[derive(Clone, Debug)]
pub enum FileInfo {
    /// A volume: one channel (`voxel`) of `dims` voxels, of type `ty` once loaded.
    Volume {
        /// Voxels per axis.
        dims: Dims,
        /// The channel's type once loaded (types TROVE does not store natively become f32).
        ty: VoxelType,
        /// Where its voxels are; sizes were checked against the header.
        source: ChannelSource,
    },
    /// A picture: dims `[w, h, 1]` and its channels (red, green, blue, and alpha if it has
    /// one), each u8.
    Image {
        /// `[w, h, 1]`.
        dims: Dims,
        /// The channels and where each comes from.
        channels: Vec<(ChannelName, ChannelSource)>,
    },
    /// A headerless file: its length, for the scene loader to check against the layout the
    /// scene gives.
    Raw {
        /// The file's length in bytes.
        bytes: u64,
        /// Where it is.
        file: DataFile,
    },
}

impl FileInfo {
    /// The kind of file this describes.
    pub fn kind(&self) -> FileKind {
        match self {
            FileInfo::Volume { .. } => FileKind::Volume,
            FileInfo::Image { .. } => FileKind::Image,
            FileInfo::Raw { .. } => FileKind::Raw,
        }
    }
}

/// Where a source's bytes are: a local file, or a key held by another process (a farm
/// coordinator never reads voxels; loading a `Remote` source is a typed error).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub enum DataFile {
    /// A file this process can read.
    Local(PathBuf),
    /// A key another process (a farm worker) resolves.
    Remote(String),
}

impl DataFile {
    /// The local path, or [`DatasetError::Remote`] for a file this process cannot read.
    pub fn local(&self) -> Result<&Path, DatasetError> {
        match self {
            DataFile::Local(path) => Ok(path),
            DataFile::Remote(key) => Err(DatasetError::Remote { key: key.clone() }),
        }
    }

    /// The path or key, for messages.
    pub fn path(&self) -> &Path {
        match self {
            DataFile::Local(path) => path,
            DataFile::Remote(key) => Path::new(key),
        }
    }
}

/// The volume formats TROVE reads, told by a key's extension (any case).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VolumeFormat {
    /// `.nrrd` (attached header) or `.nhdr` (detached).
    Nrrd,
    /// `.nii` or `.nii.gz`.
    Nifti,
}

impl VolumeFormat {
    /// The format a key's extension names, if any.
    pub fn of_key(key: &str) -> Option<VolumeFormat> {
        let lower = key.to_ascii_lowercase();
        if lower.ends_with(".nrrd") || lower.ends_with(".nhdr") {
            Some(VolumeFormat::Nrrd)
        } else if lower.ends_with(".nii") || lower.ends_with(".nii.gz") {
            Some(VolumeFormat::Nifti)
        } else {
            None
        }
    }
}

/// Keys as paths under a root folder.
#[derive(Clone, Debug)]
pub struct FsCatalog {
    root: PathBuf,
    sandboxed: bool,
}

impl FsCatalog {
    /// Local mode: `key` is `root.join(key)`, whatever it says (`..`, absolute paths and
    /// symbolic links are the user's own business).
    pub fn trusting(root: impl Into<PathBuf>) -> FsCatalog {
        FsCatalog { root: root.into(), sandboxed: false }
    }

    /// A farm worker's view of its data root: keys are relative paths of plain components
    /// (no absolute paths, `..`, empty components or backslashes), and every file read —
    /// the key's, and a detached NRRD header's `data file` — must canonicalise (following
    /// symbolic links) to a path inside the canonical root.
    ///
    /// The check is made when a key is described, and sources name the canonical path. A
    /// process that can rename directories inside the root between that check and a later
    /// load could still redirect a read; the root is meant to be the worker's own data.
    pub fn sandboxed(root: impl AsRef<Path>) -> Result<FsCatalog, DatasetError> {
        let root = root.as_ref();
        let root = root.canonicalize().map_err(|e| DatasetError::io(root, e))?;
        Ok(FsCatalog { root, sandboxed: true })
    }

    /// The root folder (canonical when sandboxed).
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Refuses, in a sandbox, a key that is not a plain relative path.
    fn check(&self, key: &str) -> Result<(), DatasetError> {
        if self.sandboxed {
            check_key(key).map_err(|problem| DatasetError::InvalidKey { key: key.to_string(), problem })?;
        }
        Ok(())
    }

    /// The path `key` names, checked against the sandbox.
    fn resolve(&self, key: &str) -> Result<PathBuf, DatasetError> {
        self.check(key)?;
        if !self.sandboxed {
            return Ok(self.root.join(key));
        }
        let joined = self.root.join(key);
        let canonical = joined.canonicalize().map_err(|e| DatasetError::io(&joined, e))?;
        if !canonical.starts_with(&self.root) {
            return Err(DatasetError::OutsideRoot { key: key.to_string() });
        }
        Ok(canonical)
    }

    /// Where a detached NRRD header's `data file` is (`joined`: the value joined to the
    /// header's folder), checked against the sandbox.
    fn locate_data_file(&self, header: &Path, value: &str, joined: PathBuf) -> Result<PathBuf, DatasetError> {
        if !self.sandboxed {
            return Ok(joined);
        }
        let canonical = joined.canonicalize().map_err(|e| DatasetError::io(&joined, e))?;
        if !canonical.starts_with(&self.root) {
            return Err(DatasetError::DataFileOutsideRoot {
                header: header.to_path_buf(),
                data_file: value.to_string(),
            });
        }
        Ok(canonical)
    }
}

/// What a sandboxed catalog refuses in a key before looking at the file system.
fn check_key(key: &str) -> Result<(), KeyProblem> {
    if key.is_empty() {
        return Err(KeyProblem::Empty);
    }
    if key.contains('\\') {
        return Err(KeyProblem::Backslash);
    }
    if key.starts_with('/') || Path::new(key).has_root() || Path::new(key).is_absolute() {
        return Err(KeyProblem::Absolute);
    }
    for part in key.split('/') {
        match part {
            "" => return Err(KeyProblem::EmptyComponent),
            ".." => return Err(KeyProblem::ParentComponent),
            _ => {}
        }
    }
    // A prefix (`C:` on Windows) is absolute in all but name.
    if Path::new(key).components().any(|c| matches!(c, Component::Prefix(_))) {
        return Err(KeyProblem::Absolute);
    }
    Ok(())
}

impl Catalog for FsCatalog {
    fn describe(&self, key: &str, kind: FileKind) -> Result<FileInfo, DatasetError> {
        self.check(key)?;
        match kind {
            FileKind::Volume => {
                let format =
                    VolumeFormat::of_key(key).ok_or_else(|| DatasetError::UnknownFormat { key: key.into() })?;
                let path = self.resolve(key)?;
                let opened = match format {
                    VolumeFormat::Nrrd => {
                        nrrd::open_in(&path, &|value, joined| self.locate_data_file(&path, value, joined))?
                    }
                    VolumeFormat::Nifti => nifti_file::open(&path)?,
                };
                Ok(FileInfo::Volume { dims: opened.dims, ty: opened.ty, source: opened.source })
            }
            FileKind::Image => {
                let (dims, channels) = image_file::open(&self.resolve(key)?)?;
                Ok(FileInfo::Image { dims, channels })
            }
            FileKind::Raw => {
                let path = self.resolve(key)?;
                let bytes = std::fs::metadata(&path).map_err(|e| DatasetError::io(&path, e))?.len();
                Ok(FileInfo::Raw { bytes, file: DataFile::Local(path) })
            }
        }
    }
}

#[cfg(test)]
mod tests;
