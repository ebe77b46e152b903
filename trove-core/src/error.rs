//! The three ways a render can fail: a scene the user wrote wrongly, a dataset file that
//! disagrees with what it claims, and failures while rendering (loading, writing).
//!
//! Every message names the file and, for scenes, the TOML key path, so a user can find the
//! mistake without reading our code.

use std::path::PathBuf;

use thiserror::Error;

/// A scene file that cannot be rendered as written.
#[derive(Debug, Error)]
#[error("{}: {key}: {message}", file.display())]
pub struct SceneError {
    /// The scene file.
    pub file: PathBuf,
    /// TOML path of the offending key, e.g. `objects[3].opacity.bounds`.
    pub key: String,
    /// What was wrong and what was expected.
    pub message: String,
}

impl SceneError {
    /// An error at `key` of `file`.
    pub fn new(file: impl Into<PathBuf>, key: impl Into<String>, message: impl Into<String>) -> Self {
        SceneError { file: file.into(), key: key.into(), message: message.into() }
    }
}

/// A dataset file that cannot be read, or whose header, size and dims disagree.
#[derive(Debug, Error)]
pub enum DatasetError {
    /// The file could not be opened or read.
    #[error("cannot read {}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What the OS said.
        #[source]
        source: std::io::Error,
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
    /// A header is malformed or disagrees with the scene.
    #[error("{}: {message}", path.display())]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

impl DatasetError {
    /// A format error in `path`.
    pub fn format(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        DatasetError::Format { path: path.into(), message: message.into() }
    }

    /// An I/O error on `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        DatasetError::Io { path: path.into(), source }
    }
}
