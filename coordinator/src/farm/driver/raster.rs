//! The farm job's image as it fills up, band by band: the PNG's bytes, and floats for a
//! PFM when the job asked for one. Each band's pixels are composited on a blocking thread
//! with the scheduler's one composition step and placed here.

use std::ops::Range;

use trove_core::render::{quantize, Scheduler};
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

/// A band's share of the image, composited.
pub(super) struct Composited {
    pub rows: Range<u32>,
    pub rgb8: Vec<u8>,
    pub rgb32f: Option<Vec<f32>>,
    pub samples_skipped: u64,
    pub seconds: f64,
}

impl Composited {
    /// Composites the band of `rows` whose every task `scheduler` has cast or culled.
    pub fn of(scene: &Scene, rows: Range<u32>, scheduler: &Scheduler, want_pfm: bool) -> Composited {
        let started = std::time::Instant::now();
        let pixels = scheduler.composite_pixels(scene.image().background);
        let rgb8 = pixels.iter().flat_map(|p| p.map(quantize)).collect();
        let rgb32f = want_pfm.then(|| pixels.iter().flat_map(|p| p.map(|c| c as f32)).collect());
        let samples_skipped = scheduler.culled_samples(scene);
        Composited { rows, rgb8, rgb32f, samples_skipped, seconds: started.elapsed().as_secs_f64() }
    }
}

/// The image: 8-bit, and floats when the job asked for a PFM.
pub(super) struct Raster {
    width: u32,
    pub rgb8: Vec<u8>,
    pub rgb32f: Option<Vec<f32>>,
}

impl Raster {
    pub fn new(width: u32, height: u32, want_pfm: bool) -> Raster {
        let pixels = width as usize * height as usize * 3;
        Raster { width, rgb8: vec![0; pixels], rgb32f: want_pfm.then(|| vec![0.0; pixels]) }
    }

    /// Copies a composited band into the image.
    pub fn place(&mut self, part: &Composited) {
        let row_len = self.width as usize * 3;
        let start = part.rows.start as usize * row_len;
        self.rgb8[start..start + part.rgb8.len()].copy_from_slice(&part.rgb8);
        if let (Some(all), Some(band)) = (&mut self.rgb32f, &part.rgb32f) {
            all[start..start + band.len()].copy_from_slice(band);
        }
    }
}
