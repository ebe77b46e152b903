//! What the crate's unit tests share: scratch folders for tests that write files (fresh,
//! unique to the process and the name, and removed when the test is done with them, so
//! that test runs do not pile folders up in the temp dir; a failing test's folder stays, to
//! look at), and a generator of many cases that are the same on every run.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU32, Ordering};

/// A fresh folder under the system temp folder, removed on drop unless dropped while its
/// thread panics.
#[must_use = "the folder is removed when this is dropped"]
pub(crate) struct TempDir(PathBuf);

impl TempDir {
    /// A fresh, empty folder whose name holds `name`.
    pub(crate) fn new(name: &str) -> TempDir {
        static N: AtomicU32 = AtomicU32::new(0);
        let n = N.fetch_add(1, Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("trove-core-{}-{n}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("create temp folder");
        TempDir(dir)
    }
}

impl std::ops::Deref for TempDir {
    type Target = Path;

    fn deref(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// A generator of numbers below `n`, from `seed`: a linear congruential one, since the tests
/// need many cases, the same every run, and no statistical quality.
pub(crate) fn numbers(seed: u64) -> impl FnMut(u64) -> u64 {
    let mut state = seed;
    move |n| {
        state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        (state >> 33) % n
    }
}
