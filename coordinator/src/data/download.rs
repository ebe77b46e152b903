//! Putting the bytes at a URL into a file: the `Download` trait, and `curl` behind it.

use std::io;
use std::path::Path;
use std::process::Command;
use std::sync::Arc;

use thiserror::Error;

/// Something that puts the bytes at a URL into a file; a trait so that the fetch tests can
/// count what is asked for.
pub(crate) trait Download {
    /// Writes what `url` holds to `to`.
    fn download(&self, url: &str, to: &Path) -> Result<(), DownloadError>;
}

/// A download that failed. Cloned, because an archive that cannot be downloaded fails every
/// data file taken out of it, and is asked for only once.
#[derive(Clone, Debug, Error)]
#[error("downloading {url}")]
pub(crate) struct DownloadError {
    /// The URL asked for, after the mirror was applied: the one to try by hand.
    pub(crate) url: String,
    /// Why.
    #[source]
    pub(crate) reason: DownloadFailure,
}

/// Why a download failed.
#[derive(Clone, Debug, Error)]
pub(crate) enum DownloadFailure {
    /// There is no `curl` to run.
    #[error("curl was not found; install curl (or download the files by hand, see docs/data.md)")]
    NoCurl,
    /// `curl` is there but cannot be started.
    #[error("cannot run curl")]
    Spawn(#[source] Arc<io::Error>),
    /// `curl` ran and failed (network, HTTP status): what it said last, else its exit status.
    #[error("{0}")]
    Curl(String),
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
    fn download(&self, url: &str, to: &Path) -> Result<(), DownloadError> {
        let url = self.locate(url);
        tracing::info!(%url, "downloading");
        let out = Command::new("curl")
            .args(["--fail", "--location", "--silent", "--show-error", "--retry", "3", "--connect-timeout", "30"])
            .arg("--output")
            .arg(to)
            .arg(&url)
            .output();
        let reason = match out {
            Err(e) if e.kind() == io::ErrorKind::NotFound => DownloadFailure::NoCurl,
            Err(e) => DownloadFailure::Spawn(Arc::new(e)),
            Ok(out) if out.status.success() => return Ok(()),
            Ok(out) => {
                // curl repeats its message once per retry: the last line says it.
                let stderr = String::from_utf8_lossy(&out.stderr);
                let said = stderr.lines().rev().map(str::trim).find(|l| !l.is_empty());
                DownloadFailure::Curl(said.map_or_else(|| out.status.to_string(), String::from))
            }
        };
        Err(DownloadError { url, reason })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mirrors_take_host_and_path() {
        let c = Curl { mirror: Some("file:///srv/m/".into()) };
        assert_eq!(c.locate("https://raw.example.org/a/b.raw"), "file:///srv/m/raw.example.org/a/b.raw");
        assert_eq!(Curl { mirror: None }.locate("https://h/x"), "https://h/x");
    }
}
