//! The farm job's bands and their share of the image. The image is `trove_core`'s
//! [`Raster`] (the PNG's bytes, and floats for a PFM when the job asked for one), local
//! mode's too: each band's pixels are composited on a blocking thread with the one
//! composition step, [`Raster::composite_rows`], into a band-sized raster, and placed into
//! the job's as it arrives.

use std::ops::Range;

use trove_core::render::{Raster, Scheduler};
use trove_core::scene::Scene;

/// Pixels per band when the job does not say: some tens of thousands of pieces in most
/// scenes, a few megabytes of bookkeeping. Small enough that a 512² image makes four bands,
/// so that intersecting and compositing one band overlap casting another (with 2¹⁸ a 512²
/// render was one band, each stage waiting for the last: `trove-bench farm`, Fig. 1 through
/// 2 workers, went from 1.72× to 1.20× local mode's time).
pub const BAND_PIXELS: u32 = 1 << 16;

/// The rows of a band: as the job asks, else [`BAND_PIXELS`] worth of rows, and never more
/// than `within` (what the memory bound allows a band).
pub fn rows_per_band(asked: u32, width: u32, height: u32, within: u32) -> u32 {
    let rows = match asked {
        0 => (BAND_PIXELS / width.max(1)).min(within),
        n => n,
    };
    rows.clamp(1, height.max(1))
}

/// A band's share of the image, composited: its rows as a [`Raster`] as wide as the image,
/// for [`Raster::place`] on the event loop, and the band's statistics.
pub(super) struct Composited {
    pub rows: Range<u32>,
    pub raster: Raster,
    pub samples_skipped: u64,
    pub seconds: f64,
}

impl Composited {
    /// Composites the band of `rows` whose every task `scheduler` has cast or culled, with
    /// the composition step local mode uses ([`Raster::composite_rows`]).
    pub fn of(scene: &Scene, rows: Range<u32>, scheduler: &Scheduler, want_pfm: bool) -> Composited {
        let started = std::time::Instant::now();
        let mut raster = Raster::new(scene.image().width, rows.len() as u32, want_pfm);
        raster.composite_rows(0, scheduler, scene.image().background);
        let samples_skipped = scheduler.culled_samples(scene);
        Composited { rows, raster, samples_skipped, seconds: started.elapsed().as_secs_f64() }
    }
}
