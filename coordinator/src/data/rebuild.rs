//! The lossless steps that rebuild a data file from its source: download it whole, join
//! numbered parts, take a member out of an archive, swap 16-bit words, or write its text.

use std::collections::HashMap;
use std::fs::{self, File};
use std::io::{BufReader, Write};
use std::path::{Path, PathBuf};

use super::archive::zip_member;
use super::download::Download;
use super::fetch::FetchError;
use super::manifest::Entry;

/// Writes the file `entry` describes to `out` (unchecked).
pub(super) fn build(
    entry: &Entry,
    out: &Path,
    scratch: &Path,
    source: &dyn Download,
    archives: &mut HashMap<String, Result<PathBuf, String>>,
) -> Result<(), FetchError> {
    let Some(url) = &entry.url else {
        fs::write(out, entry.text.as_deref().unwrap_or_default())?;
        return Ok(());
    };
    let swap = |mut bytes: Vec<u8>, from: &str| -> Result<Vec<u8>, FetchError> {
        if entry.swap16 {
            if !bytes.len().is_multiple_of(2) {
                return Err(FetchError::Download {
                    url: from.to_string(),
                    reason: format!("{} bytes cannot be read as 16-bit words", bytes.len()),
                });
            }
            for pair in bytes.chunks_exact_mut(2) {
                pair.swap(0, 1);
            }
        }
        Ok(bytes)
    };
    match (&entry.member, entry.parts) {
        (Some(member), _) => {
            let archive = match archives.get(url) {
                Some(known) => known.clone(),
                None => {
                    let path = scratch.join(format!("archive-{}", archives.len()));
                    let got = source.download(url, &path).map(|()| path).map_err(|e| e.to_string());
                    archives.insert(url.clone(), got.clone());
                    got
                }
            };
            let archive = archive.map_err(|reason| FetchError::Download { url: url.clone(), reason })?;
            let bytes = zip_member(BufReader::new(File::open(&archive)?), member).map_err(|e| FetchError::Archive {
                url: url.clone(),
                reason: match std::error::Error::source(&e) {
                    Some(cause) => format!("{e}: {cause}"),
                    None => e.to_string(),
                },
            })?;
            fs::write(out, swap(bytes, url)?)?;
        }
        (None, Some([first, last])) => {
            let mut file = File::create(out)?;
            let part = scratch.join("part");
            for n in first..=last {
                let part_url = url.replace("{n}", &n.to_string());
                source.download(&part_url, &part)?;
                file.write_all(&swap(fs::read(&part)?, &part_url)?)?;
            }
            let _ = fs::remove_file(&part);
        }
        (None, None) => {
            source.download(url, out)?;
            if entry.swap16 {
                let bytes = swap(fs::read(out)?, url)?;
                fs::write(out, bytes)?;
            }
        }
    }
    Ok(())
}
