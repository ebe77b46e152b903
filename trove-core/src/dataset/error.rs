//! Why a dataset file cannot be used: it cannot be read, its header, size and dims disagree,
//! or (through a sandboxed [`Catalog`](super::Catalog)) its key reaches outside the data root.
//!
//! Every variant names the file (or the key) it is about, and I/O errors keep their
//! [`std::io::Error`] as the source, so a farm can tell a transient failure from a permanent
//! one ([`DatasetError::is_retryable`]) and put that in its protocol.

use std::io;
use std::path::PathBuf;

use thiserror::Error;

use super::{DimsError, FileKind};

/// A dataset file that cannot be read, or whose header, size and dims disagree.
///
/// Display shows this level only; the cause (the OS error of [`DatasetError::Io`], the dims
/// rule of [`DatasetError::Dims`]) is the [`source`](std::error::Error::source), so that a
/// chain printed with `{:#}` (anyhow) names each once.
#[derive(Debug, Error)]
pub enum DatasetError {
    /// The file could not be opened or read.
    #[error("cannot read {}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What the OS (or the decompressor) said.
        #[source]
        source: io::Error,
    },
    /// The byte count differs from what dims × type need.
    #[error("{} holds {actual} bytes of voxel data but {what} needs exactly {expected} bytes", path.display())]
    SizeMismatch {
        /// The file.
        path: PathBuf,
        /// Bytes the header/dims call for.
        expected: u64,
        /// Bytes actually present.
        actual: u64,
        /// What makes the expectation, e.g. `dims [256, 256, 113] of u16`.
        what: String,
    },
    /// The file is shorter than the bytes said to precede its voxels (a raw `offset`).
    #[error("{}: the file has {len} bytes, fewer than the {offset} bytes that precede the voxel data", path.display())]
    ShorterThanOffset {
        /// The file.
        path: PathBuf,
        /// Its length.
        len: u64,
        /// Bytes before the voxels.
        offset: u64,
    },
    /// A header is malformed, uses what TROVE does not read, or disagrees with the scene.
    #[error("{}: {message}", path.display())]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong, naming the header field.
        message: String,
    },
    /// A header's sizes that [`Dims`](super::Dims) refuses.
    #[error("{}: {field}", path.display())]
    Dims {
        /// The file.
        path: PathBuf,
        /// The header field that gives the sizes, e.g. ``field `sizes` ``.
        field: &'static str,
        /// Which rule the sizes break.
        #[source]
        source: DimsError,
    },
    /// A volume file whose extension names no format TROVE reads.
    #[error("\"{key}\": expected a .nrrd, .nhdr, .nii or .nii.gz file")]
    UnknownFormat {
        /// The key as written.
        key: String,
    },
    /// A key a sandboxed catalog refuses before touching the file system.
    #[error("dataset key \"{key}\" is refused: {problem}")]
    InvalidKey {
        /// The key as written.
        key: String,
        /// What is wrong with it.
        problem: KeyProblem,
    },
    /// A key that resolves (through symbolic links) to a file outside the data root.
    #[error("dataset key \"{key}\" resolves to a file outside the data root")]
    OutsideRoot {
        /// The key as written.
        key: String,
    },
    /// A detached NRRD header whose `data file` resolves outside the data root.
    #[error("{}: its `data file` \"{data_file}\" resolves outside the data root", header.display())]
    DataFileOutsideRoot {
        /// The header.
        header: PathBuf,
        /// The `data file` value as written.
        data_file: String,
    },
    /// A catalog described a key as another kind of file than the scene expects there.
    #[error("dataset key \"{key}\" names {found}, not {expected}")]
    WrongKind {
        /// The key as written.
        key: String,
        /// What the scene expects.
        expected: FileKind,
        /// What the catalog found.
        found: FileKind,
    },
    /// A key no process that could read it holds: no farm worker registered it (or, on a
    /// worker, neither it nor the coordinator's headers know it).
    #[error("no worker holds dataset file \"{key}\"")]
    NotHeld {
        /// The key as written.
        key: String,
    },
    /// A source held by another process (a farm coordinator describes datasets from the
    /// headers its workers registered and never reads voxels itself).
    #[error("dataset file \"{key}\" is held by another process; its voxels cannot be loaded here")]
    Remote {
        /// The key.
        key: String,
    },
}

/// What a sandboxed catalog refuses in a key, before resolving it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Error)]
pub enum KeyProblem {
    /// The key is empty.
    #[error("it is empty")]
    Empty,
    /// An absolute path: keys are relative to the data root.
    #[error("it is an absolute path; keys are relative to the data root")]
    Absolute,
    /// A `..` component, which could climb out of the root.
    #[error("it has a `..` component")]
    ParentComponent,
    /// An empty component (`a//b`, or a leading or trailing `/`).
    #[error("it has an empty component")]
    EmptyComponent,
    /// A backslash, which is a separator on some systems and a file name character on others.
    #[error("it contains a backslash")]
    Backslash,
}

impl DatasetError {
    /// A format error in `path`.
    pub fn format(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        DatasetError::Format { path: path.into(), message: message.into() }
    }

    /// A key no worker holds.
    pub fn not_held(key: impl Into<String>) -> Self {
        DatasetError::NotHeld { key: key.into() }
    }

    /// An I/O error on `path`.
    pub fn io(path: impl Into<PathBuf>, source: io::Error) -> Self {
        DatasetError::Io { path: path.into(), source }
    }

    /// Whether trying again may succeed: only I/O interrupted, timed out or refused as "would
    /// block". A missing file, a denied permission, a malformed header or a size mismatch
    /// stays what it is until someone changes the file or the scene.
    pub fn is_retryable(&self) -> bool {
        match self {
            DatasetError::Io { source, .. } => {
                matches!(
                    source.kind(),
                    io::ErrorKind::Interrupted | io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock
                )
            }
            _ => false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_transient_io_is_retryable() {
        let io = |kind| DatasetError::io("/d/v.raw", io::Error::from(kind));
        for kind in [io::ErrorKind::Interrupted, io::ErrorKind::TimedOut, io::ErrorKind::WouldBlock] {
            assert!(io(kind).is_retryable(), "{kind:?}");
        }
        for kind in [io::ErrorKind::NotFound, io::ErrorKind::PermissionDenied, io::ErrorKind::InvalidData] {
            assert!(!io(kind).is_retryable(), "{kind:?}");
        }
        let permanent = [
            DatasetError::SizeMismatch { path: "v.raw".into(), expected: 8, actual: 7, what: "dims".into() },
            DatasetError::format("h.nhdr", "missing required field `sizes`"),
            DatasetError::OutsideRoot { key: "link".into() },
            DatasetError::Remote { key: "v.raw".into() },
        ];
        assert!(permanent.iter().all(|e| !e.is_retryable()));
    }

    #[test]
    fn io_errors_keep_the_os_error_as_their_source() {
        let e = DatasetError::io("/d/v.raw", io::Error::from(io::ErrorKind::NotFound));
        assert_eq!(e.to_string(), "cannot read /d/v.raw");
        let source = std::error::Error::source(&e).expect("a source");
        assert_eq!(source.downcast_ref::<io::Error>().map(io::Error::kind), Some(io::ErrorKind::NotFound));
    }
}
