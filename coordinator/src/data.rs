//! `trove data`: the public datasets the example scenes and the data tests read.
//!
//! Six of the example scenes, and the tests of the file readers, read real data (a CT head, an
//! engine CT, photographs, ...) by key from a data root (`../shared/data` beside the
//! repository, given as `--data-root`).
//! Those files are not in the repository, so a user needs a way to get exactly them:
//! `data/manifest.toml` (embedded in the binary) names each file with its SHA-256 and says how
//! to rebuild it, byte for byte, from its original public source with lossless steps only.
//!
//! * `trove data verify [--data-root DIR]` checks a folder against those sums, offline.
//! * `trove data fetch [--data-root DIR]` downloads the sources with the `curl` program (shipped with
//!   macOS, Windows 10 and later and most Linux systems, so no HTTP or TLS stack is compiled
//!   into `trove`), repeats the steps, and keeps a file only when its
//!   size and SHA-256 match — so what a user renders is what the team tested, and a moved or
//!   changed source is an error, never a quietly different picture.

use std::collections::HashMap;
use std::fmt;
use std::fs::{self, File};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context, Result};
use serde::Deserialize;
use sha2::{Digest, Sha256};
use trove_core::scene::{DataRoot, DATA_ROOT_ENV};

/// The manifest, as kept in the repository.
const MANIFEST: &str = include_str!("../../data/manifest.toml");

/// The data folder when neither `--data-root` nor `TROVE_DATA` names one: where the README's
/// commands, run from the repository root, give the example scenes their data.
const DEFAULT_DIR: &str = "../shared/data";

/// `trove data ...`
#[derive(clap::Subcommand)]
pub(crate) enum DataCommand {
    /// Check a data folder against the SHA-256 sums kept in the repository (offline).
    Verify {
        /// The data folder (default: TROVE_DATA, else ../shared/data).
        #[arg(long, value_name = "DIR")]
        data_root: Option<PathBuf>,
    },
    /// Download the data from its original public sources (needs curl), rebuild each file
    /// with its documented lossless steps, and keep it only if its SHA-256 matches. Files
    /// already present and correct are not downloaded again.
    Fetch {
        /// The data folder to fill, created if needed (default: TROVE_DATA, else
        /// ../shared/data).
        #[arg(long, value_name = "DIR")]
        data_root: Option<PathBuf>,
        /// Download `https://HOST/PATH` from `MIRROR/HOST/PATH` instead, e.g. a local copy
        /// (`file:///srv/mirror`) or a proxy (`http://cache:8080`). The checksums still apply.
        #[arg(long, value_name = "URL")]
        mirror: Option<String>,
    },
    /// List the files with their sizes, what they are, where they come from and their licences.
    List,
}

impl DataCommand {
    /// Runs the command, printing one line per file.
    pub(crate) fn run(self) -> Result<()> {
        let manifest = Manifest::builtin()?;
        match self {
            DataCommand::List => {
                for e in &manifest.files {
                    println!("{} ({} bytes)\n    {}\n    licence: {}\n", e.name, e.bytes, e.about, e.licence);
                }
                Ok(())
            }
            DataCommand::Verify { data_root } => {
                let dir = data_dir(data_root);
                let report = verify(&manifest, &dir)?;
                let mut bad = 0;
                for (entry, status) in manifest.files.iter().zip(&report) {
                    println!("{:<8} {}", status.label(), entry.name);
                    if let Status::Corrupt { bytes, sha256 } = status {
                        bad += 1;
                        println!("         {bytes} bytes, expected {}", entry.bytes);
                        if let Some(sum) = sha256 {
                            println!("         sha256 {sum}\n         expected {}", entry.sha256);
                        }
                    } else if *status == Status::Missing {
                        bad += 1;
                    }
                }
                if bad > 0 {
                    bail!(
                        "{bad} of {} files in {} are missing or differ from data/manifest.toml; \
                         `trove data fetch --data-root {}` downloads them again",
                        report.len(),
                        dir.display(),
                        dir.display()
                    );
                }
                println!("all {} files in {} match data/manifest.toml", report.len(), dir.display());
                Ok(())
            }
            DataCommand::Fetch { data_root, mirror } => {
                let dir = data_dir(data_root);
                let curl = Curl { mirror };
                let outcomes = fetch(&manifest, &dir, &curl, &mut |name, outcome| match outcome {
                    Ok(Fetched::AlreadyThere) => println!("ok       {name} (already there)"),
                    Ok(Fetched::Downloaded) => println!("fetched  {name}"),
                    Err(e) => println!("FAILED   {name}: {e}"),
                })?;
                let failed = outcomes.iter().filter(|o| o.is_err()).count();
                if failed > 0 {
                    bail!(
                        "{failed} of {} files could not be fetched into {} (see above); \
                         docs/data.md says where each one comes from",
                        outcomes.len(),
                        dir.display()
                    );
                }
                println!("all {} files in {} match data/manifest.toml", outcomes.len(), dir.display());
                Ok(())
            }
        }
    }
}

/// The data folder, by the rule a local render follows (`--data-root`, else `TROVE_DATA`),
/// except that with neither there is no scene folder to fall back on: [`DEFAULT_DIR`].
fn data_dir(given: Option<PathBuf>) -> PathBuf {
    match DataRoot::choose(given, std::env::var_os(DATA_ROOT_ENV)) {
        DataRoot::Given(dir) | DataRoot::Environment(dir) => dir,
        _ => PathBuf::from(DEFAULT_DIR),
    }
}

/// The parsed `data/manifest.toml`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct Manifest {
    /// Every file, in the manifest's order.
    #[serde(rename = "file")]
    pub(crate) files: Vec<Entry>,
}

/// One file of the data folder: what it must be and how to rebuild it.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct Entry {
    /// File name inside the data folder (no folders).
    pub(crate) name: String,
    /// Exact size.
    pub(crate) bytes: u64,
    /// SHA-256, lowercase hex.
    pub(crate) sha256: String,
    /// What the file is and where it comes from, for people.
    pub(crate) about: String,
    /// Its licence, as far as the source states one.
    pub(crate) licence: String,
    /// Where to download it (or its parts, or the archive holding it).
    pub(crate) url: Option<String>,
    /// `[first, last]`: `url` holds `{n}`; parts first..=last are concatenated in order.
    pub(crate) parts: Option<[u32; 2]>,
    /// The member of the zip archive at `url` that is the file.
    pub(crate) member: Option<String>,
    /// Swap the bytes of every 16-bit word (the source is big-endian, the file little).
    #[serde(default)]
    pub(crate) swap16: bool,
    /// The whole file, for headers written for this collection.
    pub(crate) text: Option<String>,
}

impl Manifest {
    /// The manifest compiled into this binary.
    pub(crate) fn builtin() -> Result<Manifest> {
        Manifest::parse(MANIFEST).context("data/manifest.toml (compiled into trove)")
    }

    /// Parses and checks a manifest: every entry has a plain, unique name, a well-formed
    /// checksum and exactly one consistent way to rebuild it.
    pub(crate) fn parse(text: &str) -> Result<Manifest> {
        let manifest: Manifest = toml::from_str(text)?;
        let mut seen = HashMap::new();
        for (i, e) in manifest.files.iter().enumerate() {
            let at = || format!("file[{i}] ({})", e.name);
            if e.name.is_empty()
                || e.name.starts_with('.')
                || e.name.contains(['/', '\\'])
                || Path::new(&e.name).file_name().is_none_or(|n| n != e.name.as_str())
            {
                bail!("{}: name must be a plain file name", at());
            }
            if let Some(j) = seen.insert(e.name.as_str(), i) {
                bail!("{}: the same name as file[{j}]", at());
            }
            if e.sha256.len() != 64 || !e.sha256.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b)) {
                bail!("{}: sha256 must be 64 lowercase hex digits", at());
            }
            match (&e.url, &e.text) {
                (Some(_), Some(_)) | (None, None) => bail!("{}: give exactly one of `url` or `text`", at()),
                (None, Some(t)) => {
                    if e.parts.is_some() || e.member.is_some() || e.swap16 {
                        bail!("{}: `text` takes no `parts`, `member` or `swap16`", at());
                    }
                    if t.len() as u64 != e.bytes {
                        bail!("{}: `text` has {} bytes, but `bytes` = {}", at(), t.len(), e.bytes);
                    }
                }
                (Some(url), None) => {
                    if url.contains("{n}") != e.parts.is_some() {
                        bail!("{}: `parts` and a `{{n}}` in `url` go together", at());
                    }
                    if e.parts.is_some_and(|[a, b]| a > b) {
                        bail!("{}: `parts` must be [first, last] with first ≤ last", at());
                    }
                    if e.parts.is_some() && e.member.is_some() {
                        bail!("{}: give `parts` or `member`, not both", at());
                    }
                    if e.swap16 && e.bytes % 2 != 0 {
                        bail!("{}: `swap16` needs an even byte count", at());
                    }
                }
            }
        }
        Ok(manifest)
    }
}

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
    fn label(&self) -> &'static str {
        match self {
            Status::Ok => "ok",
            Status::Missing => "MISSING",
            Status::Corrupt { .. } => "CORRUPT",
        }
    }
}

/// Checks every file of `manifest` in `dir`. Files the manifest does not name are ignored.
pub(crate) fn verify(manifest: &Manifest, dir: &Path) -> Result<Vec<Status>> {
    if !dir.is_dir() {
        bail!(
            "{} is not a folder; `trove data fetch --data-root {}` creates and fills it",
            dir.display(),
            dir.display()
        );
    }
    manifest
        .files
        .iter()
        .map(|e| check(e, &dir.join(&e.name)).with_context(|| format!("reading {}", dir.join(&e.name).display())))
        .collect()
}

/// One file against its entry; I/O errors other than "not found" are errors, not verdicts.
fn check(entry: &Entry, path: &Path) -> io::Result<Status> {
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
fn sha256_of(mut r: impl Read) -> io::Result<String> {
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

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Why one file could not be fetched.
#[derive(Debug)]
pub(crate) enum FetchError {
    /// The download itself failed (network, HTTP status, no curl).
    Download {
        /// The URL asked for (after the mirror was applied).
        url: String,
        /// What the downloader said.
        reason: String,
    },
    /// The archive at `url` is not a zip we can read, or lacks the member.
    Archive {
        /// The archive's URL.
        url: String,
        /// What is wrong.
        reason: String,
    },
    /// The rebuilt file is not the file the manifest names.
    Checksum {
        /// Its size.
        bytes: u64,
        /// Its SHA-256.
        sha256: String,
    },
    /// Reading or writing the data folder failed.
    Io(io::Error),
}

impl fmt::Display for FetchError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FetchError::Download { url, reason } => write!(f, "downloading {url}: {reason}"),
            FetchError::Archive { url, reason } => write!(f, "archive {url}: {reason}"),
            FetchError::Checksum { bytes, sha256 } => write!(
                f,
                "the rebuilt file ({bytes} bytes, sha256 {sha256}) is not the one in data/manifest.toml; \
                 the source may have changed, so nothing was kept"
            ),
            FetchError::Io(e) => write!(f, "{e}"),
        }
    }
}

impl std::error::Error for FetchError {}

impl From<io::Error> for FetchError {
    fn from(e: io::Error) -> Self {
        FetchError::Io(e)
    }
}

/// What `fetch` did with a file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Fetched {
    /// It was already there with the right checksum; nothing was downloaded.
    AlreadyThere,
    /// It was downloaded, rebuilt and checked.
    Downloaded,
}

/// Something that puts the bytes at a URL into a file.
pub(crate) trait Download {
    /// Writes what `url` holds to `to`.
    fn download(&self, url: &str, to: &Path) -> Result<(), FetchError>;
}

/// Downloads with the `curl` program, optionally through a mirror.
pub(crate) struct Curl {
    /// See `trove data fetch --mirror`.
    pub(crate) mirror: Option<String>,
}

impl Curl {
    /// `url` as seen through the mirror: `https://HOST/PATH` → `MIRROR/HOST/PATH`.
    fn locate(&self, url: &str) -> String {
        match &self.mirror {
            None => url.to_string(),
            Some(m) => {
                let rest = url.split_once("://").map_or(url, |(_, r)| r);
                format!("{}/{rest}", m.trim_end_matches('/'))
            }
        }
    }
}

impl Download for Curl {
    fn download(&self, url: &str, to: &Path) -> Result<(), FetchError> {
        let url = self.locate(url);
        tracing::info!(%url, "downloading");
        let out = Command::new("curl")
            .args(["--fail", "--location", "--silent", "--show-error", "--retry", "3", "--connect-timeout", "30"])
            .arg("--output")
            .arg(to)
            .arg(&url)
            .output()
            .map_err(|e| FetchError::Download {
                url: url.clone(),
                reason: if e.kind() == io::ErrorKind::NotFound {
                    "curl was not found; install curl (or download the files by hand, see docs/data.md)".into()
                } else {
                    format!("cannot run curl: {e}")
                },
            })?;
        if !out.status.success() {
            // curl repeats its message once per retry: the last line says it.
            let stderr = String::from_utf8_lossy(&out.stderr);
            let said = stderr.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or_default().trim().to_string();
            return Err(FetchError::Download {
                url,
                reason: if said.is_empty() { out.status.to_string() } else { said },
            });
        }
        Ok(())
    }
}

/// Fills `dir` with every file of `manifest`, calling `progress` after each one. Files already
/// correct are kept; others are rebuilt in a temporary file and renamed into place only when
/// their size and SHA-256 match, so an interrupted or failed fetch never leaves a wrong file
/// under a right name. Every file is attempted; the result holds each one's outcome.
pub(crate) fn fetch(
    manifest: &Manifest,
    dir: &Path,
    source: &dyn Download,
    progress: &mut dyn FnMut(&str, &Result<Fetched, FetchError>),
) -> Result<Vec<Result<Fetched, FetchError>>> {
    fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let scratch = dir.join(".trove-fetch");
    fs::create_dir_all(&scratch).with_context(|| format!("creating {}", scratch.display()))?;
    // Archives already downloaded in this run (several files come out of one wheel).
    let mut archives: HashMap<String, Result<PathBuf, String>> = HashMap::new();
    let mut outcomes = Vec::with_capacity(manifest.files.len());
    for entry in &manifest.files {
        let outcome = fetch_one(entry, dir, &scratch, source, &mut archives);
        progress(&entry.name, &outcome);
        outcomes.push(outcome);
    }
    let _ = fs::remove_dir_all(&scratch);
    Ok(outcomes)
}

fn fetch_one(
    entry: &Entry,
    dir: &Path,
    scratch: &Path,
    source: &dyn Download,
    archives: &mut HashMap<String, Result<PathBuf, String>>,
) -> Result<Fetched, FetchError> {
    let target = dir.join(&entry.name);
    if check(entry, &target)? == Status::Ok {
        return Ok(Fetched::AlreadyThere);
    }
    let partial = scratch.join(format!("{}.partial", entry.name));
    let result = build(entry, &partial, scratch, source, archives).and_then(|()| {
        let file = File::open(&partial)?;
        let bytes = file.metadata()?.len();
        let sha256 = sha256_of(file)?;
        if bytes != entry.bytes || sha256 != entry.sha256 {
            return Err(FetchError::Checksum { bytes, sha256 });
        }
        fs::rename(&partial, &target)?;
        Ok(Fetched::Downloaded)
    });
    if result.is_err() {
        let _ = fs::remove_file(&partial);
    }
    result
}

/// Writes the file `entry` describes to `out` (unchecked).
fn build(
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
            let zip = fs::read(&archive)?;
            let bytes = zip_member(&zip, member).map_err(|reason| FetchError::Archive { url: url.clone(), reason })?;
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

/// The bytes of member `name` of the zip archive `zip` (stored or deflated; no zip64, no
/// encryption — a Python wheel is plain zip). Sizes and CRC-32 are checked; malformed input
/// is an error, never a panic.
pub(crate) fn zip_member(zip: &[u8], name: &str) -> Result<Vec<u8>, String> {
    let truncated = || "truncated or not a zip archive".to_string();
    let u16_at = |at: usize| -> Result<usize, String> {
        zip.get(at..at + 2).map(|b| u16::from_le_bytes([b[0], b[1]]) as usize).ok_or_else(truncated)
    };
    let u32_at = |at: usize| -> Result<u32, String> {
        zip.get(at..at + 4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]])).ok_or_else(truncated)
    };
    // The end-of-central-directory record: 22 bytes plus a comment of at most 65535.
    let last = zip.len().checked_sub(22).ok_or_else(truncated)?;
    let eocd = (last.saturating_sub(65_535)..=last)
        .rev()
        .find(|&i| u32_at(i) == Ok(0x0605_4b50))
        .ok_or_else(|| "no end-of-central-directory record: not a zip archive".to_string())?;
    let entries = u16_at(eocd + 10)?;
    let mut at = u32_at(eocd + 16)? as usize;
    if entries == 0xffff || at == 0xffff_ffff {
        return Err("zip64 archives are not supported".into());
    }
    for _ in 0..entries {
        if u32_at(at)? != 0x0201_4b50 {
            return Err("damaged central directory".into());
        }
        let flags = u16_at(at + 8)?;
        let method = u16_at(at + 10)?;
        let crc = u32_at(at + 16)?;
        let packed = u32_at(at + 20)? as usize;
        let size = u32_at(at + 24)? as usize;
        let (name_len, extra_len, comment_len) = (u16_at(at + 28)?, u16_at(at + 30)?, u16_at(at + 32)?);
        let local = u32_at(at + 42)? as usize;
        let this = zip.get(at + 46..at + 46 + name_len).ok_or_else(truncated)?;
        at += 46 + name_len + extra_len + comment_len;
        if this != name.as_bytes() {
            continue;
        }
        if flags & 1 != 0 {
            return Err(format!("{name} is encrypted"));
        }
        if u32_at(local)? != 0x0403_4b50 {
            return Err(format!("{name}: damaged local header"));
        }
        let start = local + 30 + u16_at(local + 26)? + u16_at(local + 28)?;
        let data = zip.get(start..start + packed).ok_or_else(truncated)?;
        let bytes = match method {
            0 => data.to_vec(),
            8 => {
                let mut out = Vec::with_capacity(size);
                // Read one byte past the stated size, so a member longer than it says is caught.
                flate2::read::DeflateDecoder::new(data)
                    .take(size as u64 + 1)
                    .read_to_end(&mut out)
                    .map_err(|e| format!("{name}: {e}"))?;
                out
            }
            m => return Err(format!("{name}: compression method {m} is not supported (only stored and deflate)")),
        };
        if bytes.len() != size {
            return Err(format!("{name}: {} bytes, but the archive says {size}", bytes.len()));
        }
        let mut sum = flate2::Crc::new();
        sum.update(&bytes);
        if sum.sum() != crc {
            return Err(format!("{name}: CRC-32 mismatch"));
        }
        return Ok(bytes);
    }
    Err(format!("no member named {name}"))
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;
    use std::io::{BufRead, BufReader};
    use std::net::TcpListener;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;

    use trove_tests::{scratch, shared_data, skip};

    use super::*;

    /// A zip archive of `members` (name, bytes, deflated?), as a wheel is laid out.
    fn zip(members: &[(&str, &[u8], bool)]) -> Vec<u8> {
        let (mut out, mut central) = (Vec::new(), Vec::new());
        for &(name, data, deflate) in members {
            let mut crc = flate2::Crc::new();
            crc.update(data);
            let packed = if deflate {
                let mut e = flate2::write::DeflateEncoder::new(Vec::new(), flate2::Compression::default());
                e.write_all(data).unwrap();
                e.finish().unwrap()
            } else {
                data.to_vec()
            };
            let offset = out.len() as u32;
            let method: u16 = if deflate { 8 } else { 0 };
            let common = |v: &mut Vec<u8>| {
                v.extend_from_slice(&20u16.to_le_bytes()); // version needed
                v.extend_from_slice(&0u16.to_le_bytes()); // flags
                v.extend_from_slice(&method.to_le_bytes());
                v.extend_from_slice(&[0; 4]); // time, date
                v.extend_from_slice(&crc.sum().to_le_bytes());
                v.extend_from_slice(&(packed.len() as u32).to_le_bytes());
                v.extend_from_slice(&(data.len() as u32).to_le_bytes());
                v.extend_from_slice(&(name.len() as u16).to_le_bytes());
                v.extend_from_slice(&0u16.to_le_bytes()); // extra
            };
            out.extend_from_slice(&0x0403_4b50u32.to_le_bytes());
            common(&mut out);
            out.extend_from_slice(name.as_bytes());
            out.extend_from_slice(&packed);
            central.extend_from_slice(&0x0201_4b50u32.to_le_bytes());
            central.extend_from_slice(&20u16.to_le_bytes()); // version made by
            common(&mut central);
            central.extend_from_slice(&[0; 10]); // comment length, disk, internal and external attributes
            central.extend_from_slice(&offset.to_le_bytes());
            central.extend_from_slice(name.as_bytes());
        }
        let (cd_offset, cd_size) = (out.len() as u32, central.len() as u32);
        out.extend_from_slice(&central);
        out.extend_from_slice(&0x0605_4b50u32.to_le_bytes());
        out.extend_from_slice(&[0; 4]);
        out.extend_from_slice(&(members.len() as u16).to_le_bytes());
        out.extend_from_slice(&(members.len() as u16).to_le_bytes());
        out.extend_from_slice(&cd_size.to_le_bytes());
        out.extend_from_slice(&cd_offset.to_le_bytes());
        out.extend_from_slice(b"\x07\x00comment"); // a comment, as some archivers write
        out
    }

    /// A tiny HTTP/1.1 server on 127.0.0.1 serving `root`, counting requests: the
    /// downloads go through curl exactly as they would to the real hosts.
    struct Server {
        base: String,
        requests: Arc<AtomicUsize>,
    }

    fn serve(root: PathBuf) -> Server {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind 127.0.0.1");
        let base = format!("http://{}", listener.local_addr().unwrap());
        let requests = Arc::new(AtomicUsize::new(0));
        let count = requests.clone();
        std::thread::spawn(move || {
            for stream in listener.incoming() {
                let Ok(mut stream) = stream else { continue };
                count.fetch_add(1, Ordering::SeqCst);
                let mut reader = BufReader::new(stream.try_clone().unwrap());
                let mut request = String::new();
                let _ = reader.read_line(&mut request);
                let mut header = String::new();
                while reader.read_line(&mut header).is_ok_and(|n| n > 2) {
                    header.clear();
                }
                let path = request.split_whitespace().nth(1).unwrap_or("/").trim_start_matches('/');
                let body = if path.contains("..") { None } else { fs::read(root.join(path)).ok() };
                let (status, body) = match body {
                    Some(b) => ("200 OK", b),
                    None => ("404 Not Found", b"not found".to_vec()),
                };
                let head = format!("HTTP/1.1 {status}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n", body.len());
                let _ = stream.write_all(head.as_bytes()).and_then(|()| stream.write_all(&body));
            }
        });
        Server { base, requests }
    }

    /// Where a mirror rooted at `root` keeps `url` (see `Curl::locate`).
    fn mirror_path(root: &Path, url: &str) -> PathBuf {
        let path = root.join(url.split_once("://").expect("an absolute URL").1);
        fs::create_dir_all(path.parent().unwrap()).unwrap();
        path
    }

    fn curl_available() -> bool {
        let ok = Command::new("curl").arg("--version").output().is_ok_and(|o| o.status.success());
        if !ok {
            skip("curl, which `trove data fetch` downloads with, is not installed");
        }
        ok
    }

    fn sha(bytes: &[u8]) -> String {
        hex(&Sha256::digest(bytes))
    }

    fn entry(name: &str, bytes: &[u8]) -> String {
        format!(
            "[[file]]\nname = \"{name}\"\nbytes = {}\nsha256 = \"{}\"\nabout = \"x\"\nlicence = \"x\"\n",
            bytes.len(),
            sha(bytes)
        )
    }

    fn fetch_quietly(m: &Manifest, dir: &Path, mirror: &str) -> Vec<Result<Fetched, FetchError>> {
        fetch(m, dir, &Curl { mirror: Some(mirror.into()) }, &mut |_, _| {}).unwrap()
    }

    #[test]
    fn the_manifest_names_every_data_file_the_example_scenes_read() {
        let manifest = Manifest::builtin().unwrap();
        let named: HashMap<&str, &Entry> = manifest.files.iter().map(|e| (e.name.as_str(), e)).collect();
        let scenes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
        let mut used = 0;
        for file in fs::read_dir(&scenes).unwrap() {
            let path = file.unwrap().path();
            if path.extension().is_none_or(|e| e != "toml") {
                continue;
            }
            let scene: toml::Table = toml::from_str(&fs::read_to_string(&path).unwrap()).unwrap();
            let datasets = scene.get("datasets").and_then(|d| d.as_array()).cloned().unwrap_or_default();
            for d in datasets {
                let mut keys: Vec<String> =
                    ["file", "image"].iter().filter_map(|k| d.get(*k)?.as_str().map(String::from)).collect();
                for c in d.get("channels").and_then(|c| c.as_table()).into_iter().flat_map(|t| t.values()) {
                    keys.extend(["raw", "nrrd"].iter().filter_map(|k| c.get(*k)?.as_str().map(String::from)));
                }
                // Every key of an example scene is a file in the data root (the README renders
                // them with `--data-root ../shared/data`).
                for name in &keys {
                    let e = named
                        .get(name.as_str())
                        .unwrap_or_else(|| panic!("{}: {name} is not in data/manifest.toml", path.display()));
                    used += 1;
                    // A detached header's data file must come with it.
                    if let Some(text) = &e.text {
                        let data = text.lines().find_map(|l| l.strip_prefix("data file: ")).unwrap();
                        assert!(named.contains_key(data), "{name} names {data}, which is not in the manifest");
                    }
                }
            }
        }
        assert!(used >= 6, "the example scenes read only {used} data files");
    }

    #[test]
    fn docs_data_md_describes_every_file() {
        let doc = fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/data.md")).unwrap();
        for e in Manifest::builtin().unwrap().files {
            // Headers are listed with their data file: `x.raw` + `.nhdr`.
            let stem = e.name.split('.').next().unwrap();
            assert!(doc.contains(&format!("`{stem}.")), "docs/data.md does not mention {}", e.name);
        }
    }

    #[test]
    fn the_manifest_refuses_inconsistent_entries() {
        let ok = entry("a.raw", b"abcd") + "url = \"https://h/a.raw\"\n";
        Manifest::parse(&ok).unwrap();
        for (what, text) in [
            ("folder in name", entry("d/a.raw", b"ab") + "url = \"https://h/a\"\n"),
            ("dot name", entry("..", b"ab") + "url = \"https://h/a\"\n"),
            ("no source", entry("a.raw", b"ab")),
            ("two sources", entry("a.raw", b"ab") + "url = \"https://h/a\"\ntext = \"ab\"\n"),
            ("parts without {n}", entry("a.raw", b"ab") + "url = \"https://h/a\"\nparts = [1, 2]\n"),
            ("{n} without parts", entry("a.raw", b"ab") + "url = \"https://h/a.{n}\"\n"),
            ("parts backwards", entry("a.raw", b"ab") + "url = \"https://h/a.{n}\"\nparts = [3, 2]\n"),
            ("odd swap", entry("a.raw", b"abc") + "url = \"https://h/a\"\nswap16 = true\n"),
            ("text size", entry("a.txt", b"abc") + "text = \"ab\"\n"),
            ("unknown key", entry("a.raw", b"ab") + "url = \"https://h/a\"\nmd5 = \"x\"\n"),
            ("duplicate", ok.clone() + &ok),
        ] {
            assert!(Manifest::parse(&text).is_err(), "{what} was accepted");
        }
        let mut bad_sum = ok.clone();
        bad_sum = bad_sum.replace(&sha(b"abcd"), &sha(b"abcd").to_uppercase());
        assert!(Manifest::parse(&bad_sum).is_err(), "an uppercase checksum was accepted");
    }

    #[test]
    fn zip_members_come_out_whole_and_damage_is_an_error() {
        let big: Vec<u8> = (0..100_000u32).map(|i| (i * 7 % 251) as u8).collect();
        let archive = zip(&[("a/stored.txt", b"hello", false), ("b/deflated.bin", &big, true)]);
        assert_eq!(zip_member(&archive, "a/stored.txt").unwrap(), b"hello");
        assert_eq!(zip_member(&archive, "b/deflated.bin").unwrap(), big);
        assert!(zip_member(&archive, "b/missing.bin").unwrap_err().contains("no member"));
        // Every truncation and every flipped byte is an error or the right answer, never a panic
        // or wrong bytes (the CRC-32 guards the data).
        for cut in (0..archive.len()).step_by(97) {
            let _ = zip_member(&archive[..cut], "b/deflated.bin");
        }
        for at in (0..archive.len()).step_by(13) {
            let mut damaged = archive.clone();
            damaged[at] ^= 0x5a;
            if let Ok(bytes) = zip_member(&damaged, "b/deflated.bin") {
                assert_eq!(bytes, big, "flipping byte {at} changed the member");
            }
        }
        assert!(zip_member(b"not a zip at all, just some text", "x").is_err());
    }

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
        assert!(verify(&manifest, &dir.join("absent")).is_err(), "a missing folder is an error, not four verdicts");
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

    #[test]
    fn mirrors_take_host_and_path() {
        let c = Curl { mirror: Some("file:///srv/m/".into()) };
        assert_eq!(c.locate("https://raw.example.org/a/b.raw"), "file:///srv/m/raw.example.org/a/b.raw");
        assert_eq!(Curl { mirror: None }.locate("https://h/x"), "https://h/x");
    }

    #[test]
    fn fetch_rebuilds_every_kind_of_source_over_http() {
        if !curl_available() {
            return;
        }
        let root = scratch("data-fetch-http");
        let mirror = root.join("mirror");
        let dir = root.join("data");
        // Two big-endian parts, swapped and concatenated.
        let be: Vec<u8> = (0..64u16).flat_map(|v| (v * 1000).to_be_bytes()).collect();
        let le: Vec<u8> = (0..64u16).flat_map(|v| (v * 1000).to_le_bytes()).collect();
        fs::write(mirror_path(&mirror, "https://example.org/vol/slice.1"), &be[..64]).unwrap();
        fs::write(mirror_path(&mirror, "https://example.org/vol/slice.2"), &be[64..]).unwrap();
        // Two members of one archive: downloaded once.
        let photo = b"\x89PNG pretend".to_vec();
        let notes: Vec<u8> = b"notes ".repeat(500);
        fs::write(
            mirror_path(&mirror, "https://pkg.example.org/w/pkg-1.0-py3-none-any.whl"),
            zip(&[("pkg/data/photo.png", &photo, false), ("pkg/data/notes.txt", &notes, true)]),
        )
        .unwrap();
        // A file as it is.
        let plain = b"plain bytes".to_vec();
        fs::write(mirror_path(&mirror, "https://example.org/plain.raw"), &plain).unwrap();
        let manifest = Manifest::parse(&format!(
            "{}text = '''\nNRRD0004\ndata file: vol.raw\n'''\n\n{}url = \"https://example.org/vol/slice.{{n}}\"\nparts = [1, 2]\nswap16 = true\n\n\
             {}url = \"https://pkg.example.org/w/pkg-1.0-py3-none-any.whl\"\nmember = \"pkg/data/photo.png\"\n\n\
             {}url = \"https://pkg.example.org/w/pkg-1.0-py3-none-any.whl\"\nmember = \"pkg/data/notes.txt\"\n\n\
             {}url = \"https://example.org/plain.raw\"\n",
            entry("vol.nhdr", b"NRRD0004\ndata file: vol.raw\n"),
            entry("vol.raw", &le),
            entry("photo.png", &photo),
            entry("notes.txt", &notes),
            entry("plain.raw", &plain),
        ))
        .unwrap();
        let server = serve(mirror.clone());
        let outcomes = fetch_quietly(&manifest, &dir, &server.base);
        assert!(outcomes.iter().all(|o| matches!(o, Ok(Fetched::Downloaded))), "{outcomes:?}");
        assert_eq!(server.requests.load(Ordering::SeqCst), 2 + 1 + 1, "two parts, one archive, one file");
        assert_eq!(fs::read(dir.join("vol.raw")).unwrap(), le);
        assert!(verify(&manifest, &dir).unwrap().iter().all(|s| *s == Status::Ok));
        assert!(!dir.join(".trove-fetch").exists(), "the scratch folder is removed");

        // A second run downloads nothing.
        let outcomes = fetch_quietly(&manifest, &dir, &server.base);
        assert!(outcomes.iter().all(|o| matches!(o, Ok(Fetched::AlreadyThere))), "{outcomes:?}");
        assert_eq!(server.requests.load(Ordering::SeqCst), 4);

        // A changed source is refused and leaves nothing behind; a missing one names its URL;
        // the other files are still fetched.
        fs::remove_file(dir.join("plain.raw")).unwrap();
        fs::remove_file(dir.join("vol.raw")).unwrap();
        fs::remove_file(dir.join("notes.txt")).unwrap();
        fs::write(mirror_path(&mirror, "https://example.org/plain.raw"), b"plain bytez").unwrap();
        fs::remove_file(mirror_path(&mirror, "https://example.org/vol/slice.2")).unwrap();
        let outcomes = fetch_quietly(&manifest, &dir, &server.base);
        assert!(
            matches!(&outcomes[1], Err(FetchError::Download { url, .. }) if url.ends_with("/example.org/vol/slice.2"))
        );
        assert!(matches!(&outcomes[3], Ok(Fetched::Downloaded)));
        assert!(
            matches!(&outcomes[4], Err(FetchError::Checksum { bytes: 11, sha256 }) if *sha256 == sha(b"plain bytez"))
        );
        assert!(!dir.join("plain.raw").exists() && !dir.join("vol.raw").exists());
        let report = verify(&manifest, &dir).unwrap();
        assert_eq!(report, [Status::Ok, Status::Missing, Status::Ok, Status::Ok, Status::Missing]);
    }

    /// Lays out, under `root`, what the manifest's sources would serve, rebuilt from the data
    /// files by undoing each step (split parts, swap back, pack archives).
    fn mirror_from(manifest: &Manifest, data: &Path, root: &Path) {
        let mut archives: BTreeMap<&str, Vec<(&str, Vec<u8>)>> = BTreeMap::new();
        for e in &manifest.files {
            let Some(url) = &e.url else { continue };
            let mut bytes = fs::read(data.join(&e.name)).unwrap();
            if e.swap16 {
                bytes.chunks_exact_mut(2).for_each(|p| p.swap(0, 1));
            }
            match (&e.member, e.parts) {
                (Some(member), _) => archives.entry(url).or_default().push((member, bytes)),
                (None, Some([first, last])) => {
                    let n = (last - first + 1) as usize;
                    assert_eq!(bytes.len() % n, 0, "{}: parts of equal size", e.name);
                    for (i, part) in bytes.chunks(bytes.len() / n).enumerate() {
                        let part_url = url.replace("{n}", &(first as usize + i).to_string());
                        fs::write(mirror_path(root, &part_url), part).unwrap();
                    }
                }
                (None, None) => fs::write(mirror_path(root, url), bytes).unwrap(),
            }
        }
        for (url, members) in archives {
            let members: Vec<_> = members.iter().map(|(m, b)| (*m, b.as_slice(), true)).collect();
            fs::write(mirror_path(root, url), zip(&members)).unwrap();
        }
    }

    #[test]
    fn fetch_rebuilds_the_real_data_from_a_mirror_and_repairs_a_damaged_folder() {
        let Some(data) = shared_data() else { return };
        if !curl_available() {
            return;
        }
        let manifest = Manifest::builtin().unwrap();
        let root = scratch("data-fetch-real");
        mirror_from(&manifest, &data, &root.join("mirror"));
        let server = serve(root.join("mirror"));
        let dir = root.join("data");
        let outcomes = fetch_quietly(&manifest, &dir, &server.base);
        for (e, o) in manifest.files.iter().zip(&outcomes) {
            assert!(matches!(o, Ok(Fetched::Downloaded)), "{}: {o:?}", e.name);
        }
        assert!(verify(&manifest, &dir).unwrap().iter().all(|s| *s == Status::Ok));

        // Corrupt one photograph, delete one header and one volume: verify names exactly those,
        // and a second fetch downloads only what they need.
        let coffee = dir.join("photo_coffee.png");
        let mut bytes = fs::read(&coffee).unwrap();
        bytes[1000] ^= 1;
        fs::write(&coffee, &bytes).unwrap();
        fs::remove_file(dir.join("engine_256x256x128_uint8.nhdr")).unwrap();
        fs::remove_file(dir.join("engine_256x256x128_uint8.raw.gz")).unwrap();
        let report = verify(&manifest, &dir).unwrap();
        for (e, status) in manifest.files.iter().zip(&report) {
            let expected = match e.name.as_str() {
                "photo_coffee.png" => Status::Corrupt { bytes: e.bytes, sha256: Some(sha(&bytes)) },
                "engine_256x256x128_uint8.nhdr" | "engine_256x256x128_uint8.raw.gz" => Status::Missing,
                _ => Status::Ok,
            };
            assert_eq!(*status, expected, "{}", e.name);
        }
        let before = server.requests.load(Ordering::SeqCst);
        let outcomes = fetch_quietly(&manifest, &dir, &server.base);
        assert_eq!(outcomes.iter().filter(|o| matches!(o, Ok(Fetched::Downloaded))).count(), 3);
        assert_eq!(server.requests.load(Ordering::SeqCst) - before, 2, "the wheel and the engine volume");
        assert!(verify(&manifest, &dir).unwrap().iter().all(|s| *s == Status::Ok));
    }
}
