//! Putting the bytes at a URL into a file: the `Download` trait, and `curl` behind it.

use std::io;
use std::path::Path;
use std::process::Command;

use super::fetch::FetchError;

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
