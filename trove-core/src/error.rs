//! The three ways a render can fail: a scene the user wrote wrongly, a dataset file that
//! disagrees with what it claims, and failures while rendering (loading, writing).
//!
//! Every message names the file and, for scenes, the TOML key path, so a user can find the
//! mistake without reading our code.

use std::path::PathBuf;

use thiserror::Error;

pub use crate::dataset::DatasetError;
pub use crate::scene::{SceneError, SceneErrorKind};

/// `error: cause: its cause…` on one line, as anyhow's `{:#}` prints a chain: for code that
/// has to keep an error as text. Each error displays only its own level and names the rest as
/// its source, so this shows every level once.
pub(crate) fn with_causes(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        text.push_str(": ");
        text.push_str(&c.to_string());
        cause = c.source();
    }
    text
}

/// A failure while rendering a valid scene.
#[derive(Debug, Error)]
pub enum RenderError {
    /// Loading a dataset's voxels failed (the file changed since the scene was validated,
    /// or a budget cannot hold it).
    #[error("dataset `{name}`: {source}")]
    Dataset {
        /// The dataset's name in the scene.
        name: String,
        /// Why.
        #[source]
        source: DatasetError,
    },
    /// A memory budget too small for what must be resident at once.
    #[error("memory budget of {budget} bytes cannot hold dataset `{name}` ({needed} bytes); raise --memory-budget")]
    BudgetTooSmall {
        /// The dataset.
        name: String,
        /// Its resident size.
        needed: u64,
        /// The budget.
        budget: u64,
    },
    /// An object could not be bound to the volume loaded for its dataset.
    #[error("object `{object}`: {source}")]
    Bind {
        /// The object's name.
        object: String,
        /// Why.
        #[source]
        source: crate::sampling::BindError,
    },
    /// Writing the output failed.
    #[error("cannot write {}: {message}", path.display())]
    Output {
        /// The output file.
        path: PathBuf,
        /// Why.
        message: String,
    },
}
