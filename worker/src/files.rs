//! The dataset files under a worker's data root: found once at start, registered with the
//! coordinator by key (path under the root, `/`-separated), and opened only through the
//! sandboxed catalog, which refuses absolute keys, `..`, and anything — a symlink, an NHDR's
//! `data file` — that resolves outside the root.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use thiserror::Error;
use trove_core::dataset::{Catalog, FileKind, FsCatalog};
use trove_proto::convert;
use trove_proto::v1 as pb;

/// Why the data root cannot be served.
#[derive(Debug, Error)]
pub enum ScanError {
    /// The root is not a readable folder.
    #[error("data root {}: {source}", root.display())]
    Root {
        /// The folder given.
        root: PathBuf,
        /// What the OS said.
        #[source]
        source: std::io::Error,
    },
    /// The sandbox cannot be set up over the root.
    #[error("data root {}", root.display())]
    Sandbox {
        /// The folder given.
        root: PathBuf,
        /// Why.
        #[source]
        source: trove_core::DatasetError,
    },
}

/// The files a worker holds.
pub struct DataFiles {
    root: PathBuf,
    catalog: FsCatalog,
    files: BTreeMap<String, pb::DatasetFile>,
}

impl DataFiles {
    /// Walks `root` (blocking): every regular file, and every symlink whose target stays
    /// inside the root, with its size and, for NRRD, NIfTI, PNG and JPEG files, its header.
    /// Symlinked folders are not followed, so the walk cannot loop or leave the root.
    pub fn scan(root: &Path) -> Result<DataFiles, ScanError> {
        let canonical = root.canonicalize().map_err(|source| ScanError::Root { root: root.to_path_buf(), source })?;
        let catalog = FsCatalog::sandboxed(&canonical)
            .map_err(|source| ScanError::Sandbox { root: root.to_path_buf(), source })?;
        let mut files = BTreeMap::new();
        let mut folders = vec![canonical.clone()];
        while let Some(folder) = folders.pop() {
            let entries = match std::fs::read_dir(&folder) {
                Ok(e) => e,
                Err(e) => {
                    tracing::warn!(folder = %folder.display(), error = %e, "cannot list folder; skipped");
                    continue;
                }
            };
            for entry in entries.flatten() {
                let path = entry.path();
                let Ok(kind) = entry.file_type() else { continue };
                if entry.file_name().to_string_lossy().starts_with('.') {
                    continue;
                }
                if kind.is_dir() {
                    folders.push(path);
                    continue;
                }
                let Some(key) = key_of(&canonical, &path) else { continue };
                match describe(&catalog, &key) {
                    Some(file) => {
                        files.insert(key, file);
                    }
                    None => tracing::warn!(key, "not registered: it resolves outside the data root"),
                }
            }
        }
        Ok(DataFiles { root: canonical, catalog, files })
    }

    /// The root, canonicalised.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// What the worker registers: every file with its size and header.
    pub fn registration(&self) -> Vec<pb::DatasetFile> {
        self.files.values().cloned().collect()
    }

    /// Whether the worker holds `key`.
    pub fn holds(&self, key: &str) -> bool {
        self.files.contains_key(key)
    }

    /// The sandboxed catalog over the root.
    pub fn catalog(&self) -> &FsCatalog {
        &self.catalog
    }

    /// How many files, and their total bytes.
    pub fn totals(&self) -> (usize, u64) {
        (self.files.len(), self.files.values().map(|f| f.bytes).sum())
    }
}

/// `path`'s key under `root`: its components joined by `/`; `None` when not valid UTF-8.
fn key_of(root: &Path, path: &Path) -> Option<String> {
    let rel = path.strip_prefix(root).ok()?;
    let parts: Option<Vec<&str>> = rel.components().map(|c| c.as_os_str().to_str()).collect();
    Some(parts?.join("/"))
}

/// A file's registration: its size, and its header where its format has one and the header
/// reads (a file whose header does not read is still registered, as raw bytes: a scene may
/// name it as a raw channel). `None` when the sandbox refuses it.
fn describe(catalog: &FsCatalog, key: &str) -> Option<pb::DatasetFile> {
    let raw = catalog.describe(key, FileKind::Raw).ok()?;
    let mut file = convert::dataset_file(key, &raw);
    let lower = key.to_ascii_lowercase();
    let kind = if [".nrrd", ".nhdr", ".nii", ".nii.gz"].iter().any(|e| lower.ends_with(e)) {
        Some(FileKind::Volume)
    } else if [".png", ".jpg", ".jpeg"].iter().any(|e| lower.ends_with(e)) {
        Some(FileKind::Image)
    } else {
        None
    };
    if let Some(kind) = kind {
        match catalog.describe(key, kind) {
            Ok(info) => file.header = convert::dataset_file(key, &info).header,
            Err(e) => tracing::warn!(key, error = %e, "header unreadable; registered as raw bytes"),
        }
    }
    Some(file)
}
