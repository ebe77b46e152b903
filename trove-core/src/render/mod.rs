//! Rendering a validated scene to an image, with the statistics of the paper's Table 1.
//!
//! [`per_ray`] is Algorithm 1 (paper §3.1): each ray intersects every object, then casts
//! its pieces front to back, loading datasets as it meets them. Both this and any other
//! algorithm use [`crate::sampling::ObjectCaster`] and [`crate::composite::Rgba`], so they
//! render the same image up to early termination (SPEC §4.4).

mod image;
mod per_ray;
mod stats;
mod store;

use std::sync::Arc;

pub use image::Image;
pub use stats::{RenderStats, Seconds};
pub use store::VolumeStore;

use crate::scene::Scene;
use crate::RenderError;

/// Which ray-casting algorithm renders the scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Algorithm {
    /// Algorithm 1 (paper §3.1): rays in scanline order, datasets in ray order.
    #[default]
    PerRay,
}

impl Algorithm {
    /// The command line's and the statistics' name.
    pub fn name(self) -> &'static str {
        match self {
            Algorithm::PerRay => "per-ray",
        }
    }
}

/// Called with the number of image rows finished so far (from any thread).
pub type Progress = Arc<dyn Fn(u64) + Send + Sync>;

/// How to render.
#[derive(Clone, Default)]
pub struct RenderOptions {
    /// The algorithm.
    pub algorithm: Algorithm,
    /// Progress callback.
    pub progress: Option<Progress>,
}

/// An image and how it was made.
#[derive(Clone, Debug)]
pub struct Rendered {
    /// The final linear RGB image.
    pub image: Image,
    /// Counts and timings.
    pub stats: RenderStats,
}

/// Renders `scene` with the chosen algorithm.
pub fn render(scene: &Scene, options: &RenderOptions) -> Result<Rendered, RenderError> {
    let started = std::time::Instant::now();
    let store = VolumeStore::new(scene);
    let mut rendered = match options.algorithm {
        Algorithm::PerRay => per_ray::render(scene, &store, options.progress.as_ref())?,
    };
    rendered.stats.finish(scene, options.algorithm, &store, started.elapsed().as_secs_f64());
    Ok(rendered)
}
