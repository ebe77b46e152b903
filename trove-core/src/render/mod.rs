//! Rendering a validated scene to an image, with the statistics of the paper's Table 1.
//!
//! Both algorithms are built from the same three stages, and differ only in when they run:
//!
//! 1. **Intersection** ([`intersection`]): rays → segments → pieces → [`PieceTask`]s.
//!    Object-level data only: placements and dataset dims, never a voxel.
//! 2. **Volume rendering**: casting a task with [`crate::sampling::ObjectCaster::cast`], the
//!    only sampler, while its dataset is resident in the [`VolumeStore`]; for Algorithm 2,
//!    batches of tasks handed out by the [`Scheduler`] and cast by a [`BatchCaster`].
//! 3. **Composition**: a ray's pieces front to back with [`crate::composite::Rgba`]
//!    (co-located objects combined first, SPEC §4.4).
//!
//! `per_ray` is Algorithm 1 (paper §3.1): each ray runs all three stages before the next
//! ray starts, loading datasets in the order the ray meets them, so under a short memory
//! budget it thrashes — the paper's point. `grouped` is Algorithm 2 (§3.3): each stage
//! runs over all rays before the next, and volume rendering visits each dataset once, in
//! front-to-back waves that recover early termination; it is the in-process driver of the
//! [`Scheduler`], which the farm drives with workers instead. Both algorithms render the
//! same image up to early termination (SPEC §4.4).

pub mod bands;
pub mod dispatch;
#[cfg(test)]
mod effects_tests;
mod error;
mod grouped;
mod image;
pub mod intersection;
mod kept;
pub mod limits;
mod per_ray;
mod raster;
pub mod schedule;
pub mod shadow;
#[cfg(test)]
mod shadow_tests;
mod stats;
mod store;
pub mod wire;
pub mod workunit;

use std::sync::Arc;

pub use error::{CastError, OutputError, RenderError, ScheduleError, StoreError};
pub use image::{encode_pfm, encode_png, quantize, Image};
pub use raster::Raster;
pub use schedule::{Batch, Scheduler};
pub use stats::{ObjectEffects, RenderStats, Seconds};
pub use store::{Pinned, StoreStats, VolumeStore};
pub use workunit::{BatchCaster, BindTarget, PieceRgba, PieceTask};

use crate::sampling::SimdPath;
use crate::scene::Scene;
use crate::width::VectorWidth;
use raster::Canvas;

/// The width of a render's loops that give the same bits at any width (the intersection's
/// slab tests, the macrocell scan when a dataset loads): the widest the processor has, but
/// no wider than the sampler's configured path, so `TROVE_SIMD=scalar` keeps a whole render
/// on the baseline.
pub(crate) fn vector_width() -> VectorWidth {
    let cap = match SimdPath::configured() {
        Ok(SimdPath::Avx512) => VectorWidth::Avx512,
        Ok(SimdPath::Avx2) => VectorWidth::Avx2,
        _ => VectorWidth::Baseline,
    };
    VectorWidth::detect(cap)
}

/// Which ray-casting algorithm renders the scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Algorithm {
    /// Algorithm 1 (paper §3.1): rays in scanline order, datasets in ray order.
    PerRay,
    /// Algorithm 2 (paper §3.3): all intersections, then dataset by dataset, then
    /// composition — with early termination recovered by front-to-back waves.
    #[default]
    Grouped,
}

impl Algorithm {
    /// The command line's and the statistics' name.
    pub fn name(self) -> &'static str {
        match self {
            Algorithm::PerRay => "per-ray",
            Algorithm::Grouped => "grouped",
        }
    }
}

/// Called with the number of image rows finished so far (from any thread); the grouped
/// algorithm reports the same fraction of its work in rows.
pub type Progress = Arc<dyn Fn(u64) + Send + Sync>;

/// How to render.
#[derive(Clone, Default)]
pub struct RenderOptions {
    /// The algorithm.
    pub algorithm: Algorithm,
    /// Most bytes of voxel data kept resident at once (`None`: no limit). It must hold the
    /// largest dataset the scene uses (datasets are loaded whole).
    pub memory_budget: Option<u64>,
    /// Progress callback.
    pub progress: Option<Progress>,
    /// Most bytes of Algorithm 2's band bookkeeping (pieces, results, fronts) held at once
    /// (`None`: [`DEFAULT_BAND_MEMORY`]). An image whose pieces need more is rendered in
    /// bands of rows, each dataset then loaded once per band unless the budget keeps it.
    pub band_memory: Option<u64>,
    /// A store to render through, kept by the caller across renders (the frames of a
    /// sequence, repeated renders in one process): the datasets it holds stay resident after
    /// the render, and with them the macrocell classifications binding kept (`render::store`),
    /// so the next render over the same data loads and classifies nothing again unless an
    /// opacity map's zero set, a channel or an interpolation changed. Its own budget
    /// applies, and `memory_budget` is not read. `None`: a store for this render alone,
    /// emptied as the render goes.
    pub store: Option<VolumeStore>,
}

/// Local Algorithm 2's band memory when the options do not say: a 4096² render of the
/// paper's Fig. 1 fits one band, so everyday scenes load each dataset once, and an 8192²
/// one takes a few bands instead of 5.6 GiB of pieces.
pub const DEFAULT_BAND_MEMORY: u64 = 1 << 30;

/// An image and how it was made: linear values ([`render`]) or a file's compact form
/// ([`render_raster`]).
#[derive(Clone, Debug)]
pub struct Rendered<I = Image> {
    /// The final image.
    pub image: I,
    /// Counts and timings.
    pub stats: RenderStats,
}

/// Renders `scene` with the chosen algorithm, to linear values: 24 bytes a pixel, for the
/// callers that read them. A render to a file uses [`render_raster`].
pub fn render(scene: &Scene, options: &RenderOptions) -> Result<Rendered, RenderError> {
    render_onto(scene, options, false)
}

/// Renders `scene` with the chosen algorithm into a [`Raster`]: the same bytes as
/// [`render`]'s image quantised (and, when `linear`, its values as f32 for a PFM), holding
/// 3 bytes a pixel (15 with `linear`) instead of 24. Algorithm 2 composites each band into
/// it as the band is done, so an image of any size renders within the band memory plus
/// the raster.
pub fn render_raster(scene: &Scene, options: &RenderOptions, linear: bool) -> Result<Rendered<Raster>, RenderError> {
    render_onto(scene, options, linear)
}

/// Renders onto a canvas of type `C` (`linear`: a raster keeps f32 values).
fn render_onto<C: Canvas>(scene: &Scene, options: &RenderOptions, linear: bool) -> Result<Rendered<C>, RenderError> {
    let started = std::time::Instant::now();
    let kept_store = options.store.is_some();
    let store = options.store.clone().unwrap_or_else(|| VolumeStore::new(options.memory_budget));
    store.check_budget(scene)?;
    // A kept store's counts cover every render through it; this render's are the difference.
    let before = store.stats();
    // The work the geometry makes, counted before any is stored (limits.rs); Algorithm 2's
    // bands are sized from that exact count, so each fits the band memory. For Algorithm 2
    // the count intersects the image as one band and keeps it where it fits a quarter of
    // the band memory: an image that is then one band is intersected once, not counted and
    // intersected again (the farm's coordinator keeps its count's bands the same way).
    let band_memory = options.band_memory.unwrap_or(DEFAULT_BAND_MEMORY);
    let counting = std::time::Instant::now();
    // (An image too large to keep stops count_keeping at its first rows: its rays' index alone
    // leaves no room for a task.)
    let (work, kept) = match options.algorithm {
        Algorithm::Grouped => limits::Work::count_keeping(scene, scene.image().height, band_memory / 4)?,
        Algorithm::PerRay => (limits::Work::count(scene)?, Vec::new()),
    };
    let counting_seconds = counting.elapsed().as_secs_f64();
    // Shadows first (SPEC §6): one visit of each dataset for the other objects' shares.
    let (scene, shadow_seconds) = shadow::attach(scene, &store)?;
    let scene: &Scene = &scene;
    let mut rendered = match options.algorithm {
        Algorithm::PerRay => {
            let Rendered { image, stats } = per_ray::render(scene, &store, options.progress.as_ref())?;
            Rendered { image: C::from_image(image, linear), stats }
        }
        Algorithm::Grouped => {
            let band_rows = work.rows_within(band_memory)?;
            let (w, h) = (scene.image().width, scene.image().height);
            let canvas = C::blank(w, h, linear);
            let whole = kept.into_iter().next().filter(|_| band_rows >= h);
            let counted_whole = whole.is_some();
            let bands = (band_rows, band_memory);
            let mut rendered =
                grouped::render(scene, &store, !kept_store, options.progress.as_ref(), bands, canvas, whole)?;
            // The count was the intersection, as on the farm.
            if counted_whole {
                rendered.stats.seconds.intersection += counting_seconds;
            }
            rendered
        }
    };
    let total = started.elapsed().as_secs_f64();
    rendered.stats.seconds.shadows = shadow_seconds;
    rendered.stats.finish(scene, options.algorithm, &store.stats().since(&before), store.budget(), total);
    Ok(rendered)
}
