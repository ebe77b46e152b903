//! The lossless steps that rebuild a data file from its source: download it whole, join
//! numbered parts, take a member out of an archive, swap 16-bit words, or write its text.

use std::collections::HashMap;
use std::fs::{self, File};
use std::io::{BufReader, Write};
use std::path::{Path, PathBuf};

use super::archive::zip_member;
use super::download::{Download, DownloadError};
use super::fetch::FetchError;
use super::manifest::Entry;

/// Writes the file `entry` describes to `out`, unchecked: `fetch` checks it before it is kept.
/// `archives` holds what each archive's download gave, so a wheel several files come out of
/// is downloaded (or fails) once.
pub(super) fn build(
    entry: &Entry,
    out: &Path,
    scratch: &Path,
    source: &dyn Download,
    archives: &mut HashMap<String, Result<PathBuf, DownloadError>>,
) -> Result<(), FetchError> {
    let Some(url) = &entry.url else {
        return fs::write(out, entry.text.as_deref().unwrap_or_default()).map_err(FetchError::write(out));
    };
    let swap = |mut bytes: Vec<u8>, from: &str| -> Result<Vec<u8>, FetchError> {
        if entry.swap16 {
            if !bytes.len().is_multiple_of(2) {
                return Err(FetchError::OddLength { url: from.to_string(), bytes: bytes.len() as u64 });
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
                    let got = source.download(url, &path).map(|()| path);
                    archives.insert(url.clone(), got.clone());
                    got
                }
            }?;
            let file = File::open(&archive).map_err(FetchError::read(&archive))?;
            let bytes = zip_member(BufReader::new(file), member).map_err(|source| FetchError::Archive {
                url: url.clone(),
                member: member.clone(),
                source,
            })?;
            fs::write(out, swap(bytes, url)?).map_err(FetchError::write(out))?;
        }
        (None, Some([first, last])) => {
            let mut file = File::create(out).map_err(FetchError::write(out))?;
            let part = scratch.join("part");
            for n in first..=last {
                let part_url = url.replace("{n}", &n.to_string());
                source.download(&part_url, &part)?;
                let bytes = fs::read(&part).map_err(FetchError::read(&part))?;
                file.write_all(&swap(bytes, &part_url)?).map_err(FetchError::write(out))?;
            }
            let _ = fs::remove_file(&part);
        }
        (None, None) => {
            source.download(url, out)?;
            if entry.swap16 {
                let bytes = swap(fs::read(out).map_err(FetchError::read(out))?, url)?;
                fs::write(out, bytes).map_err(FetchError::write(out))?;
            }
        }
    }
    Ok(())
}
