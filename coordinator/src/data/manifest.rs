//! `data/manifest.toml`, compiled into `trove`: what each data file must be (name, size,
//! SHA-256) and the one way to rebuild it from its source, checked when it is parsed.

use std::collections::HashMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use serde::Deserialize;

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
}
