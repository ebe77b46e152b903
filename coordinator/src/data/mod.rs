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
//!
//! `manifest` says what each file must be; `verify` checks a folder against it; `fetch` fills
//! one, rebuilding each file with `rebuild`'s steps from what `download` brings and `archive`
//! unpacks. Only [`DataCommand::run`] prints.

mod archive;
mod download;
mod fetch;
mod manifest;
mod rebuild;
#[cfg(test)]
mod test_support;
mod verify;

use std::error::Error;
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use trove_core::scene::{DataRoot, DATA_ROOT_ENV};

use download::Curl;
use fetch::{fetch, Fetched};
use manifest::Manifest;
use verify::{verify, Status};

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
        let manifest = Manifest::builtin().context("data/manifest.toml (compiled into trove)")?;
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
                    Err(e) => println!("FAILED   {name}: {}", one_line(e)),
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

/// `e` and its causes on one line, as `main` prints the error that ends a command, so that a
/// file's FAILED line says as much. A cause is left out where its error's text already ends
/// with it (some libraries' errors repeat their source).
fn one_line(e: &dyn Error) -> String {
    let mut line = e.to_string();
    for cause in std::iter::successors(e.source(), |&c| c.source()) {
        let text = cause.to_string();
        if !line.ends_with(&text) {
            line = format!("{line}: {text}");
        }
    }
    line
}

#[cfg(test)]
mod tests {
    use std::io;

    use super::archive::ArchiveError;
    use super::download::{DownloadError, DownloadFailure};
    use super::fetch::FetchError;
    use super::*;

    #[test]
    fn a_failed_line_names_the_source_and_every_cause_once() {
        let download = FetchError::from(DownloadError {
            url: "https://h/x.raw".into(),
            reason: DownloadFailure::Curl("The requested URL returned error: 404".into()),
        });
        assert_eq!(one_line(&download), "downloading https://h/x.raw: The requested URL returned error: 404");
        let damaged = FetchError::Archive {
            url: "https://h/p.whl".into(),
            member: "p/a.png".into(),
            source: ArchiveError::Unreadable(zip::result::ZipError::Io(io::Error::other("disk on fire"))),
        };
        assert_eq!(
            one_line(&damaged),
            "taking p/a.png out of https://h/p.whl: not a zip archive that trove can read: i/o error: disk on fire"
        );
    }
}
