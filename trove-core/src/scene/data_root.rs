//! The data root: the folder under which a local render resolves a scene's dataset keys.
//!
//! A scene names its dataset files by key (`file = "cthead.nhdr"`, see [`crate::dataset`]'s
//! catalog). Locally the keys are paths under one folder, chosen by the rule every TROVE
//! command follows: `--data-root DIR` if given, else the `TROVE_DATA` environment variable,
//! else the scene file's own folder (SPEC §1: "relative to the scene file's folder"). A farm
//! worker resolves the same keys under its own `--data-root`, so one scene text renders the
//! same here (with `--data-root D`) and through workers whose data root is a copy of `D`.
//!
//! The rule lives here rather than in the command line so that every front end follows the
//! same one, and so that a key that names no file can say where it was looked for and why
//! there ([`SceneErrorKind::DataNotFound`]). The library never reads the environment itself:
//! callers pass the variable's value to [`DataRoot::choose`], and tests never depend on it.

use std::ffi::OsString;
use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use super::error::{SceneError, SceneErrorKind};
use crate::dataset::{Catalog, DatasetError, FileInfo, FileKind, FsCatalog};

/// The environment variable that names the data root when `--data-root` is not given.
pub const DATA_ROOT_ENV: &str = "TROVE_DATA";

/// Where a local render resolves dataset keys, and who chose it (for messages).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DataRoot {
    /// The scene file's folder: no root was given (SPEC §1).
    SceneFolder,
    /// A folder given explicitly: `--data-root DIR`, or a caller's own choice (tests).
    Given(PathBuf),
    /// A folder named by the [`DATA_ROOT_ENV`] environment variable.
    Environment(PathBuf),
}

impl DataRoot {
    /// The rule: `given` (`--data-root`) if any, else `environment` (the value of
    /// [`DATA_ROOT_ENV`], ignored when empty, as an unset variable), else the scene's folder.
    pub fn choose(given: Option<PathBuf>, environment: Option<OsString>) -> DataRoot {
        match (given, environment) {
            (Some(dir), _) => DataRoot::Given(dir),
            (None, Some(env)) if !env.is_empty() => DataRoot::Environment(PathBuf::from(env)),
            _ => DataRoot::SceneFolder,
        }
    }

    /// The folder keys of the scene file `scene` resolve under.
    pub fn dir(&self, scene: &Path) -> PathBuf {
        match self {
            DataRoot::SceneFolder => scene.parent().map(Path::to_path_buf).unwrap_or_default(),
            DataRoot::Given(dir) | DataRoot::Environment(dir) => dir.clone(),
        }
    }
}

/// Says where keys were looked for and how to look elsewhere: the end of a
/// [`SceneErrorKind::DataNotFound`] message.
impl fmt::Display for DataRoot {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DataRoot::SceneFolder => write!(
                f,
                "keys resolve in the scene file's folder when no data root is given; \
                 pass --data-root DIR or set {DATA_ROOT_ENV}=DIR to name the folder that holds the data \
                 (docs/data.md)"
            ),
            DataRoot::Given(dir) => write!(f, "the data root is {} (--data-root)", dir.display()),
            DataRoot::Environment(dir) => {
                write!(f, "the data root is {} (from {DATA_ROOT_ENV}; --data-root overrides it)", dir.display())
            }
        }
    }
}

/// A trusting catalog over the data root that remembers the last key whose own file does not
/// exist, so that the scene loader's error (which names the file, not the key) can become a
/// [`SceneErrorKind::DataNotFound`]. A missing file that a header refers to (an NHDR's `data
/// file`) is not a key's own file and stays a [`DatasetError::Io`].
struct LocalCatalog {
    files: FsCatalog,
    missing: Mutex<Option<(String, PathBuf)>>,
}

impl Catalog for LocalCatalog {
    fn describe(&self, key: &str, kind: FileKind) -> Result<FileInfo, DatasetError> {
        let result = self.files.describe(key, kind);
        if let Err(DatasetError::Io { path, source }) = &result {
            if source.kind() == std::io::ErrorKind::NotFound && *path == self.files.root().join(key) {
                *self.missing.lock().unwrap_or_else(|p| p.into_inner()) = Some((key.to_string(), path.clone()));
            }
        }
        result
    }
}

/// Parses scene text read from `path` with its keys under `root` (see [`super::Scene::parse_in`]).
pub(super) fn parse_in(text: &str, path: &Path, root: &DataRoot) -> Result<super::Scene, SceneError> {
    let catalog = LocalCatalog { files: FsCatalog::trusting(root.dir(path)), missing: Mutex::new(None) };
    super::load::scene(text, path, &catalog).map_err(|mut e| {
        let missing = catalog.missing.lock().unwrap_or_else(|p| p.into_inner()).take();
        if let (SceneErrorKind::Dataset(DatasetError::Io { path: file, .. }), Some((key, looked_for))) =
            (&e.kind, missing)
        {
            if *file == looked_for {
                e.kind = SceneErrorKind::DataNotFound { key, looked_for, root: Box::new(root.clone()) };
            }
        }
        e
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_option_wins_then_the_environment_then_the_scene_folder() {
        let env = || Some(OsString::from("/env/data"));
        assert_eq!(DataRoot::choose(Some("flag".into()), env()), DataRoot::Given("flag".into()));
        assert_eq!(DataRoot::choose(None, env()), DataRoot::Environment("/env/data".into()));
        assert_eq!(DataRoot::choose(None, Some(OsString::new())), DataRoot::SceneFolder);
        assert_eq!(DataRoot::choose(None, None), DataRoot::SceneFolder);
        let scene = Path::new("scenes/a.toml");
        assert_eq!(DataRoot::SceneFolder.dir(scene), Path::new("scenes"));
        assert_eq!(DataRoot::SceneFolder.dir(Path::new("a.toml")), Path::new(""));
        assert_eq!(DataRoot::Given("d".into()).dir(scene), Path::new("d"));
        assert_eq!(DataRoot::Environment("e".into()).dir(scene), Path::new("e"));
    }
}
