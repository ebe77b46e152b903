//! `trove data verify`: a folder's files against the manifest's sizes and SHA-256 sums.

use std::fs::File;
use std::io::{self, Read};
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};
use thiserror::Error;

use super::manifest::{Entry, Manifest};

/// What `verify` found for one file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) enum Status {
    /// Present with the right size and SHA-256.
    Ok,
    /// Not in the folder.
    Missing,
    /// Present but different: its size, and its SHA-256 when the size was right.
    Corrupt {
        /// The file's size.
        bytes: u64,
        /// Its SHA-256 (computed only when the size matches).
        sha256: Option<String>,
    },
}

impl Status {
    pub(super) fn label(&self) -> &'static str {
        match self {
            Status::Ok => "ok",
            Status::Missing => "MISSING",
            Status::Corrupt { .. } => "CORRUPT",
        }
    }
}

/// Why a folder could not be checked at all (as opposed to a file that fails the check).
#[derive(Debug, Error)]
pub(crate) enum VerifyError {
    /// Nothing to check: every file would be missing, which says less than this.
    #[error("{} is not a folder; `trove data fetch --data-root {}` creates and fills it", dir.display(), dir.display())]
    NotAFolder {
        /// The folder given.
        dir: PathBuf,
    },
    /// A file is there but cannot be read, so it is neither right nor wrong.
    #[error("cannot read {}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// What the OS said.
        #[source]
        source: io::Error,
    },
}

/// Checks every file of `manifest` in `dir`. Files the manifest does not name are ignored.
pub(crate) fn verify(manifest: &Manifest, dir: &Path) -> Result<Vec<Status>, VerifyError> {
    if !dir.is_dir() {
        return Err(VerifyError::NotAFolder { dir: dir.to_path_buf() });
    }
    manifest
        .files
        .iter()
        .map(|e| {
            let path = dir.join(&e.name);
            check(e, &path).map_err(|source| VerifyError::Read { path, source })
        })
        .collect()
}

/// One file against its entry; I/O errors other than "not found" are errors, not verdicts.
pub(super) fn check(entry: &Entry, path: &Path) -> io::Result<Status> {
    let file = match File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(Status::Missing),
        Err(e) => return Err(e),
    };
    let bytes = file.metadata()?.len();
    if bytes != entry.bytes {
        return Ok(Status::Corrupt { bytes, sha256: None });
    }
    let sum = sha256_of(file)?;
    Ok(if sum == entry.sha256 { Status::Ok } else { Status::Corrupt { bytes, sha256: Some(sum) } })
}

/// SHA-256 of everything `r` yields, as lowercase hex.
pub(super) fn sha256_of(mut r: impl Read) -> io::Result<String> {
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = r.read(&mut buf)?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
    }
    Ok(hex(&hasher.finalize()))
}

pub(super) fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use std::fs;

    use trove_tests::{scratch, shared_data};

    use super::*;
    use crate::data::test_support::{entry, sha};

    #[test]
    fn verify_tells_ok_missing_and_corrupt_files_apart() {
        let dir = scratch("data-verify");
        let (a, b, c, d) = (b"first".as_slice(), b"second".as_slice(), b"third".as_slice(), b"fourth".as_slice());
        let text = [("a.raw", a), ("b.raw", b), ("c.raw", c), ("d.raw", d)]
            .iter()
            .map(|(n, bytes)| entry(n, bytes) + "url = \"https://h/x\"\n")
            .collect::<String>();
        let manifest = Manifest::parse(&text).unwrap();
        fs::write(dir.join("a.raw"), a).unwrap();
        fs::write(dir.join("b.raw"), b"sEcond").unwrap(); // same size, other bytes
        fs::write(dir.join("c.raw"), b"thirdd").unwrap(); // other size
        fs::write(dir.join("unrelated.txt"), b"ignored").unwrap();
        let report = verify(&manifest, &dir).unwrap();
        assert_eq!(report[0], Status::Ok);
        assert_eq!(report[1], Status::Corrupt { bytes: 6, sha256: Some(sha(b"sEcond")) });
        assert_eq!(report[2], Status::Corrupt { bytes: 6, sha256: None });
        assert_eq!(report[3], Status::Missing);
        assert!(
            matches!(verify(&manifest, &dir.join("absent")), Err(VerifyError::NotAFolder { .. })),
            "a missing folder is an error, not four verdicts"
        );
    }

    #[test]
    fn the_shared_data_matches_the_manifest() {
        let Some(data) = shared_data() else { return };
        let manifest = Manifest::builtin().unwrap();
        let report = verify(&manifest, &data).unwrap();
        for (e, status) in manifest.files.iter().zip(&report) {
            assert_eq!(*status, Status::Ok, "{}", e.name);
        }
    }
}
