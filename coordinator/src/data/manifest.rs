//! `data/manifest.toml`, compiled into `trove`: what each data file must be (name, size,
//! SHA-256) and the one way to rebuild it from its source, checked when it is parsed.

use std::collections::HashMap;
use std::path::Path;

use serde::Deserialize;
use thiserror::Error;

/// The manifest, as kept in the repository.
const MANIFEST: &str = include_str!("../../../data/manifest.toml");

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

/// Why a manifest was refused.
#[derive(Debug, Error)]
pub(crate) enum ManifestError {
    /// Not TOML of the manifest's shape: a syntax error, an unknown or missing key, a wrong type.
    #[error("not valid manifest TOML")]
    Toml(#[from] toml::de::Error),
    /// One entry breaks a rule that TOML's shape cannot state.
    #[error("file[{index}] ({name})")]
    Entry {
        /// Its place in the manifest, from 0.
        index: usize,
        /// Its `name`.
        name: String,
        /// The rule it breaks.
        #[source]
        problem: EntryProblem,
    },
}

/// The rule an entry breaks, named by its key; checked when the manifest is parsed, so that
/// `fetch` never starts on an entry it could not finish.
#[derive(Debug, Error, PartialEq, Eq)]
pub(crate) enum EntryProblem {
    /// The file would land outside the data folder, or hidden in it.
    #[error("`name` must be a plain file name (no folder, not starting with '.')")]
    Name,
    /// Two entries for one file.
    #[error("`name` is already file[{first}]'s")]
    Duplicate {
        /// The entry that has it first.
        first: usize,
    },
    /// The sums are compared as text, so only one spelling may match.
    #[error("`sha256` must be 64 lowercase hex digits")]
    Sha256,
    /// Nothing, or two things, to rebuild the file from.
    #[error("give exactly one of `url` or `text`")]
    Source,
    /// Steps that apply only to downloads.
    #[error("`text` takes no `parts`, `member` or `swap16`")]
    TextWithSteps,
    /// The text is not the file the sums describe.
    #[error("`text` has {text} bytes, but `bytes` = {bytes}")]
    TextSize {
        /// The text's length.
        text: u64,
        /// The entry's `bytes`.
        bytes: u64,
    },
    /// Parts are numbered into the URL: one without the other cannot be downloaded.
    #[error("`parts` and a `{{n}}` in `url` go together")]
    PartsWithoutNumber,
    /// No parts to download.
    #[error("`parts` must be [first, last] with first ≤ last, not [{first}, {last}]")]
    PartsBackwards {
        /// The first part.
        first: u32,
        /// The last part.
        last: u32,
    },
    /// Two ways to read the download.
    #[error("give `parts` or `member`, not both")]
    PartsAndMember,
    /// 16-bit words cannot cover an odd number of bytes.
    #[error("`swap16` needs an even `bytes`, not {bytes}")]
    OddSwap {
        /// The entry's `bytes`.
        bytes: u64,
    },
}

impl Manifest {
    /// The manifest compiled into this binary.
    pub(crate) fn builtin() -> Result<Manifest, ManifestError> {
        Manifest::parse(MANIFEST)
    }

    /// Parses and checks a manifest: every entry has a plain, unique name, a well-formed
    /// checksum and exactly one consistent way to rebuild it.
    pub(crate) fn parse(text: &str) -> Result<Manifest, ManifestError> {
        let manifest: Manifest = toml::from_str(text)?;
        let mut seen = HashMap::new();
        for (index, e) in manifest.files.iter().enumerate() {
            let first = seen.insert(e.name.as_str(), index);
            if let Some(problem) = e.problem(first) {
                return Err(ManifestError::Entry { index, name: e.name.clone(), problem });
            }
        }
        Ok(manifest)
    }
}

impl Entry {
    /// The first rule this entry breaks; `first` is the entry that already has its name.
    fn problem(&self, first: Option<usize>) -> Option<EntryProblem> {
        if self.name.is_empty()
            || self.name.starts_with('.')
            || self.name.contains(['/', '\\'])
            || Path::new(&self.name).file_name().is_none_or(|n| n != self.name.as_str())
        {
            return Some(EntryProblem::Name);
        }
        if let Some(first) = first {
            return Some(EntryProblem::Duplicate { first });
        }
        if self.sha256.len() != 64 || !self.sha256.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b)) {
            return Some(EntryProblem::Sha256);
        }
        match (&self.url, &self.text) {
            (Some(_), Some(_)) | (None, None) => Some(EntryProblem::Source),
            (None, Some(_)) if self.parts.is_some() || self.member.is_some() || self.swap16 => {
                Some(EntryProblem::TextWithSteps)
            }
            (None, Some(t)) if t.len() as u64 != self.bytes => {
                Some(EntryProblem::TextSize { text: t.len() as u64, bytes: self.bytes })
            }
            (None, Some(_)) => None,
            (Some(url), None) => match self.parts {
                _ if url.contains("{n}") != self.parts.is_some() => Some(EntryProblem::PartsWithoutNumber),
                Some([first, last]) if first > last => Some(EntryProblem::PartsBackwards { first, last }),
                Some(_) if self.member.is_some() => Some(EntryProblem::PartsAndMember),
                _ if self.swap16 && !self.bytes.is_multiple_of(2) => Some(EntryProblem::OddSwap { bytes: self.bytes }),
                _ => None,
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use std::fs;

    use super::*;
    use crate::data::test_support::{entry, sha};

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
        // `None`: refused as TOML, before any rule is checked.
        for (what, text, problem) in [
            ("folder in name", entry("d/a.raw", b"ab") + "url = \"https://h/a\"\n", Some(EntryProblem::Name)),
            ("dot name", entry("..", b"ab") + "url = \"https://h/a\"\n", Some(EntryProblem::Name)),
            ("no source", entry("a.raw", b"ab"), Some(EntryProblem::Source)),
            (
                "two sources",
                entry("a.raw", b"ab") + "url = \"https://h/a\"\ntext = \"ab\"\n",
                Some(EntryProblem::Source),
            ),
            (
                "steps on text",
                entry("a.txt", b"ab") + "text = \"ab\"\nswap16 = true\n",
                Some(EntryProblem::TextWithSteps),
            ),
            (
                "parts without {n}",
                entry("a.raw", b"ab") + "url = \"https://h/a\"\nparts = [1, 2]\n",
                Some(EntryProblem::PartsWithoutNumber),
            ),
            (
                "{n} without parts",
                entry("a.raw", b"ab") + "url = \"https://h/a.{n}\"\n",
                Some(EntryProblem::PartsWithoutNumber),
            ),
            (
                "parts backwards",
                entry("a.raw", b"ab") + "url = \"https://h/a.{n}\"\nparts = [3, 2]\n",
                Some(EntryProblem::PartsBackwards { first: 3, last: 2 }),
            ),
            (
                "parts and member",
                entry("a.raw", b"ab") + "url = \"https://h/a.{n}\"\nparts = [1, 2]\nmember = \"a\"\n",
                Some(EntryProblem::PartsAndMember),
            ),
            (
                "odd swap",
                entry("a.raw", b"abc") + "url = \"https://h/a\"\nswap16 = true\n",
                Some(EntryProblem::OddSwap { bytes: 3 }),
            ),
            (
                "text size",
                entry("a.txt", b"abc") + "text = \"ab\"\n",
                Some(EntryProblem::TextSize { text: 2, bytes: 3 }),
            ),
            ("unknown key", entry("a.raw", b"ab") + "url = \"https://h/a\"\nmd5 = \"x\"\n", None),
            ("duplicate", ok.clone() + &ok, Some(EntryProblem::Duplicate { first: 0 })),
            ("uppercase checksum", ok.replace(&sha(b"abcd"), &sha(b"abcd").to_uppercase()), Some(EntryProblem::Sha256)),
        ] {
            match (Manifest::parse(&text), problem) {
                (Err(ManifestError::Entry { problem: got, .. }), Some(expected)) => assert_eq!(got, expected, "{what}"),
                (Err(ManifestError::Toml(_)), None) => {}
                (other, _) => panic!("{what}: {other:?}"),
            }
        }
    }
}
