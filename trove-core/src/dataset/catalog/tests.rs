//! The catalog against a real folder tree: what each kind of key describes, and what a
//! sandboxed catalog refuses — bad keys before any file is touched, then (with real symbolic
//! links) anything that resolves outside the root.

use std::io;
use std::path::{Path, PathBuf};

use super::*;
use crate::dataset::Encoding;
use crate::testing::TempDir;

/// `base/root/` (the data root) holding `data/v.raw` (8 bytes), `data/v.nhdr` (detached,
/// data `v.raw`) and `photo.png` (3×2 RGB); and beside the root, `base/outside/secret.raw`
/// (8 bytes) and `base/outside/secret.nhdr`.
fn tree(name: &str) -> (TempDir, PathBuf) {
    let base = TempDir::new(name);
    let root = base.join("root");
    std::fs::create_dir_all(root.join("data")).unwrap();
    std::fs::create_dir_all(base.join("outside")).unwrap();
    std::fs::write(root.join("data/v.raw"), [7u8; 8]).unwrap();
    std::fs::write(root.join("data/v.nhdr"), nhdr("v.raw")).unwrap();
    std::fs::write(base.join("outside/secret.raw"), [1u8; 8]).unwrap();
    std::fs::write(base.join("outside/secret.nhdr"), nhdr("secret.raw")).unwrap();
    let rgb: Vec<u8> = (0..18).collect();
    image::save_buffer(root.join("photo.png"), &rgb, 3, 2, image::ExtendedColorType::Rgb8).unwrap();
    (base, root)
}

/// A detached header for 2×2×2 u8 voxels in `data_file`.
fn nhdr(data_file: &str) -> String {
    format!("NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\ndata file: {data_file}\n")
}

fn canonical(p: &Path) -> PathBuf {
    p.canonicalize().unwrap()
}

#[test]
fn describes_each_kind_from_headers_and_lengths() {
    let (_base, root) = tree("kinds");
    for catalog in [FsCatalog::trusting(&root), FsCatalog::sandboxed(&root).unwrap()] {
        match catalog.describe("data/v.raw", FileKind::Raw).unwrap() {
            FileInfo::Raw { bytes: 8, file: DataFile::Local(p) } => {
                assert_eq!(canonical(&p), canonical(&root.join("data/v.raw")))
            }
            other => panic!("{other:?}"),
        }
        match catalog.describe("data/v.nhdr", FileKind::Volume).unwrap() {
            FileInfo::Volume {
                dims,
                ty: VoxelType::U8,
                source: ChannelSource::File { file, encoding: Encoding::Raw, .. },
            } => {
                assert_eq!(dims.as_array(), [2, 2, 2]);
                assert_eq!(canonical(file.local().unwrap()), canonical(&root.join("data/v.raw")));
            }
            other => panic!("{other:?}"),
        }
        match catalog.describe("photo.png", FileKind::Image).unwrap() {
            FileInfo::Image { dims, channels } => {
                assert_eq!(dims.as_array(), [3, 2, 1]);
                let names: Vec<_> = channels.iter().map(|c| c.0).collect();
                assert_eq!(names, [ChannelName::Red, ChannelName::Green, ChannelName::Blue]);
            }
            other => panic!("{other:?}"),
        }
        let e = catalog.describe("data/v.mha", FileKind::Volume).unwrap_err();
        assert!(matches!(&e, DatasetError::UnknownFormat { key } if key == "data/v.mha"), "{e:?}");
        let e = catalog.describe("data/absent.raw", FileKind::Raw).unwrap_err();
        let missing = |p: &PathBuf| p.ends_with("data/absent.raw");
        assert!(
            matches!(&e, DatasetError::Io { path, source } if missing(path) && source.kind() == io::ErrorKind::NotFound),
            "{e:?}"
        );
    }
}

#[test]
fn a_sandboxed_root_that_does_not_exist_is_an_error() {
    let base = TempDir::new("no-root");
    let e = FsCatalog::sandboxed(base.join("absent")).unwrap_err();
    assert!(matches!(e, DatasetError::Io { .. }), "{e:?}");
}

#[test]
fn sandboxed_keys_are_plain_relative_paths() {
    let (_base, root) = tree("keys");
    let catalog = FsCatalog::sandboxed(&root).unwrap();
    for (key, problem) in [
        ("", KeyProblem::Empty),
        ("/etc/passwd", KeyProblem::Absolute),
        ("../outside/secret.raw", KeyProblem::ParentComponent),
        ("data/../../outside/secret.raw", KeyProblem::ParentComponent),
        ("data/..", KeyProblem::ParentComponent),
        ("data//v.raw", KeyProblem::EmptyComponent),
        ("data/v.raw/", KeyProblem::EmptyComponent),
        ("data\\v.raw", KeyProblem::Backslash),
        ("..\\outside\\secret.raw", KeyProblem::Backslash),
    ] {
        for kind in [FileKind::Raw, FileKind::Volume, FileKind::Image] {
            let e = catalog.describe(key, kind).unwrap_err();
            assert!(
                matches!(&e, DatasetError::InvalidKey { key: k, problem: p } if k == key && *p == problem),
                "{key:?} as {kind:?}: {e:?}"
            );
            assert!(!e.is_retryable());
        }
    }
    // `.` components are harmless, and the same file.
    assert!(matches!(catalog.describe("./data/./v.raw", FileKind::Raw), Ok(FileInfo::Raw { bytes: 8, .. })));
}

#[test]
fn trusting_catalogs_take_any_path() {
    let (base, root) = tree("trusting");
    let catalog = FsCatalog::trusting(&root);
    assert!(matches!(catalog.describe("../outside/secret.raw", FileKind::Raw), Ok(FileInfo::Raw { bytes: 8, .. })));
    let absolute = base.join("outside/secret.nhdr");
    assert!(matches!(catalog.describe(absolute.to_str().unwrap(), FileKind::Volume), Ok(FileInfo::Volume { .. })));
}

#[cfg(unix)]
mod symlinks {
    use std::os::unix::fs::symlink;

    use super::*;

    #[test]
    fn links_inside_the_root_are_followed_links_out_are_refused() {
        let (base, root) = tree("links");
        symlink("data/v.raw", root.join("inside.raw")).unwrap();
        symlink("data", root.join("inside-dir")).unwrap();
        symlink("../outside/secret.raw", root.join("out.raw")).unwrap();
        symlink(base.join("outside/secret.raw"), root.join("out-absolute.raw")).unwrap();
        symlink("../outside", root.join("out-dir")).unwrap();
        symlink("../outside/secret.nhdr", root.join("out.nhdr")).unwrap();
        symlink("../out.raw", root.join("data/chain.raw")).unwrap();
        let catalog = FsCatalog::sandboxed(&root).unwrap();

        for key in ["inside.raw", "inside-dir/v.raw"] {
            match catalog.describe(key, FileKind::Raw).unwrap() {
                // The source names the canonical file, so it compares equal however it was reached.
                FileInfo::Raw { bytes: 8, file } => {
                    assert_eq!(file, DataFile::Local(canonical(&root.join("data/v.raw"))))
                }
                other => panic!("{key}: {other:?}"),
            }
        }
        for (key, kind) in [
            ("out.raw", FileKind::Raw),
            ("out-absolute.raw", FileKind::Raw),
            ("out-dir/secret.raw", FileKind::Raw),
            ("data/chain.raw", FileKind::Raw),
            ("out.nhdr", FileKind::Volume),
            ("out-dir/secret.nhdr", FileKind::Volume),
        ] {
            let e = catalog.describe(key, kind).unwrap_err();
            assert!(matches!(&e, DatasetError::OutsideRoot { key: k } if k == key), "{key}: {e:?}");
        }
        // A trusting catalog follows the same links.
        assert!(FsCatalog::trusting(&root).describe("out-dir/secret.raw", FileKind::Raw).is_ok());
    }

    #[test]
    fn an_nhdr_data_file_outside_the_root_is_refused() {
        let (base, root) = tree("data-file");
        let outside = base.join("outside/secret.raw");
        symlink("../../outside/secret.raw", root.join("data/link.raw")).unwrap();
        std::fs::write(root.join("climbs.nhdr"), nhdr("../outside/secret.raw")).unwrap();
        std::fs::write(root.join("absolute.nhdr"), nhdr(outside.to_str().unwrap())).unwrap();
        std::fs::write(root.join("data/linked.nhdr"), nhdr("link.raw")).unwrap();
        // Climbing out and back in is fine: only where the file is counts.
        std::fs::write(root.join("data/round-trip.nhdr"), nhdr("../data/v.raw")).unwrap();
        let catalog = FsCatalog::sandboxed(&root).unwrap();

        for (key, data_file) in [
            ("climbs.nhdr", "../outside/secret.raw"),
            ("absolute.nhdr", outside.to_str().unwrap()),
            ("data/linked.nhdr", "link.raw"),
        ] {
            let e = catalog.describe(key, FileKind::Volume).unwrap_err();
            assert!(
                matches!(&e, DatasetError::DataFileOutsideRoot { header, data_file: d }
                    if *header == canonical(&root.join(key)) && d == data_file),
                "{key}: {e:?}"
            );
        }
        assert!(matches!(catalog.describe("data/round-trip.nhdr", FileKind::Volume), Ok(FileInfo::Volume { .. })));
        // Local mode reads them all.
        let trusting = FsCatalog::trusting(&root);
        for key in ["climbs.nhdr", "absolute.nhdr", "data/linked.nhdr"] {
            assert!(trusting.describe(key, FileKind::Volume).is_ok(), "{key}");
        }
    }
}
