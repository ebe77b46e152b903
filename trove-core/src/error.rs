//! The three ways a render can fail: a scene the user wrote wrongly, a dataset file that
//! disagrees with what it claims, and failures while rendering (loading, writing).
//!
//! Every message names the file and, for scenes, the TOML key path, so a user can find the
//! mistake without reading our code.

pub use crate::dataset::DatasetError;
pub use crate::scene::{SceneError, SceneErrorKind};

/// `error: cause: its cause…` on one line, as anyhow's `{:#}` prints a chain: for code that
/// has to keep an error as text. Each error displays only its own level and names the rest as
/// its source, so this shows every level once.
pub fn with_causes(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        text.push_str(": ");
        text.push_str(&c.to_string());
        cause = c.source();
    }
    text
}
