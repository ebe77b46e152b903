//! TROVE core: the two-level scene model of Leu & Chen (1997) and the ray casting that
//! renders it, with no networking and no protocol types (the farm translates at its edge).
//!
//! The data flow of one render is visible in the modules, in order:
//! [`scene`] (TOML → validated model) → [`geometry`] (camera rays → per-object segments →
//! pieces) → `sampling` (interpolate a dataset's channels, map to colour and opacity,
//! composite one object over one piece) → `composite` (co-located media, front to back,
//! background) → [`render`] (Algorithm 1 per ray; Algorithm 2 as three stages —
//! intersection into wire-shaped work units, volume rendering dataset by dataset in
//! front-to-back waves, composition — over a volume store with a memory budget; the image
//! and statistics they yield).
//! [`dataset`] is the voxel level: channels stored once and shared by every object that
//! names them.
#![deny(missing_docs)]

pub(crate) mod composite;
pub mod dataset;
pub mod error;
pub mod geometry;
pub(crate) mod interp;
pub mod mapping;
pub mod render;
pub(crate) mod sampling;
pub mod scene;
#[cfg(test)]
mod testing;
pub(crate) mod width;

// The sampler's and compositor's internals stay inside the crate; these are what callers
// (the farm, the tests that hold the sampler to closed forms) need of them.
pub use composite::Rgba;
pub use error::{DatasetError, SceneError};
pub use interp::Interpolation;
pub use render::RenderError;
pub use sampling::{corrected_opacity, CastOptions, ObjectCaster, SimdError, SimdPath};
