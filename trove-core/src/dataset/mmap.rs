//! The one place that memory-maps a file.

use std::fs::File;
use std::path::Path;
use std::sync::Arc;

use memmap2::Mmap;

use super::error::DatasetError;

/// Maps `path` read-only.
///
/// # Safety argument
/// A mapping is only sound while nobody truncates or rewrites the file under us. Dataset
/// files are inputs that TROVE never writes, and the renderer checks the mapping's length
/// against the header before any voxel is read, so the worst a concurrent writer can do is
/// change voxel values (a wrong image, never memory unsafety on our side) or shrink the file
/// (SIGBUS — the same contract every mmap-based reader, ripgrep included, accepts).
pub(crate) fn map_file(path: &Path) -> Result<Arc<Mmap>, DatasetError> {
    let file = File::open(path).map_err(|e| DatasetError::io(path, e))?;
    // SAFETY: see the function's safety argument above.
    let map = unsafe { Mmap::map(&file) }.map_err(|e| DatasetError::io(path, e))?;
    Ok(Arc::new(map))
}
