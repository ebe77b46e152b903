//! TROVE core (partial, in progress).
pub mod dataset;
pub mod error;
pub use error::{DatasetError, RenderError, SceneError};
