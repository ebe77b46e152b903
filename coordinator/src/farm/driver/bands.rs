//! A job's image as bands of rows: which band starts next (spread over the image, within
//! the job's memory bound: [`trove_core::render::dispatch`]), where each band stands
//! (intersecting, casting, compositing), and the image as it fills up. The coordinator
//! holds only the pieces of the bands in flight, so its memory is bounded by configuration,
//! not by the image's area.

use std::collections::BTreeMap;
use std::ops::Range;

use trove_core::render::dispatch::{band_order, Admission};
use trove_core::render::Scheduler;

/// Pixels per band when the job does not say: some tens of thousands of pieces in most
/// scenes, a few megabytes of bookkeeping. Small enough that a 512² image makes four bands,
/// so that intersecting and compositing one band overlap casting another (with 2¹⁸ a 512²
/// render was one band, each stage waiting for the last: `trove-bench farm`, Fig. 1 through
/// 2 workers, went from 1.72× to 1.20× local mode's time).
pub const BAND_PIXELS: u32 = 1 << 16;

/// Where a band stands.
pub(super) enum Stage {
    Intersecting,
    Casting(Box<Scheduler>),
    Compositing,
}

/// A band in flight.
pub(super) struct Band {
    /// Its place in the start order: earlier bands are dispatched first.
    pub seq: usize,
    pub rows: Range<u32>,
    pub stage: Stage,
    /// What its scheduler holds on the heap, once intersected.
    bytes: u64,
}

/// A band's share of the image, composited.
pub(super) struct Composited {
    pub rows: Range<u32>,
    pub rgb8: Vec<u8>,
    pub rgb32f: Option<Vec<f32>>,
    pub samples_skipped: u64,
    pub seconds: f64,
}

/// The job's bands and its image.
pub(super) struct Bands {
    rows: Vec<Range<u32>>,
    order: Vec<usize>,
    started: usize,
    live: BTreeMap<usize, Band>,
    admission: Admission,
    held: u64,
    largest: u64,
    width: u32,
    rgb8: Vec<u8>,
    rgb32f: Option<Vec<f32>>,
    /// Rows composited into the image.
    pub rows_done: u32,
    /// Tasks of the bands composited or being composited (all cast or culled).
    pub tasks_composited: u64,
}

impl Bands {
    /// An image of `width × height` pixels in bands of `band_rows` rows.
    pub fn new(width: u32, height: u32, band_rows: u32, admission: Admission, want_pfm: bool) -> Bands {
        let band_rows = band_rows.clamp(1, height.max(1));
        let rows: Vec<Range<u32>> =
            (0..height.div_ceil(band_rows)).map(|b| b * band_rows..((b + 1) * band_rows).min(height)).collect();
        let pixels = width as usize * height as usize * 3;
        Bands {
            order: band_order(rows.len()),
            rows,
            started: 0,
            live: BTreeMap::new(),
            admission,
            held: 0,
            largest: 0,
            width,
            rgb8: vec![0; pixels],
            rgb32f: want_pfm.then(|| vec![0.0; pixels]),
            rows_done: 0,
            tasks_composited: 0,
        }
    }

    /// The rows of a band per the job's options (0: [`BAND_PIXELS`] worth of rows).
    pub fn rows_per_band(asked: u32, width: u32, height: u32) -> u32 {
        match asked {
            0 => (BAND_PIXELS / width.max(1)).clamp(1, height.max(1)),
            n => n.min(height.max(1)),
        }
    }

    /// Whether every band is composited into the image.
    pub fn is_done(&self) -> bool {
        self.started == self.order.len() && self.live.is_empty()
    }

    /// The next band to intersect, if admission allows another: its index and rows. A band
    /// not yet measured is expected to be as large as the largest so far (a fair share of
    /// the bound before any is measured).
    pub fn start_next(&mut self) -> Option<(usize, Range<u32>)> {
        let &band = self.order.get(self.started)?;
        let expected = if self.largest > 0 {
            self.largest
        } else {
            self.admission.memory_bound / self.admission.max_bands.max(1) as u64
        };
        if !self.admission.admits(self.live.len(), self.held, expected) {
            return None;
        }
        let rows = self.rows[band].clone();
        self.live.insert(band, Band { seq: self.started, rows: rows.clone(), stage: Stage::Intersecting, bytes: 0 });
        self.started += 1;
        Some((band, rows))
    }

    /// Band `band`'s scheduler is ready: it casts from now on.
    pub fn intersected(&mut self, band: usize, scheduler: Box<Scheduler>) {
        let bytes = scheduler.heap_bytes();
        self.held += bytes;
        self.largest = self.largest.max(bytes);
        if let Some(b) = self.live.get_mut(&band) {
            b.bytes = bytes;
            b.stage = Stage::Casting(scheduler);
        }
    }

    /// The band's start order and scheduler, while it casts.
    pub fn casting(&mut self, band: usize) -> Option<(usize, &mut Scheduler)> {
        match self.live.get_mut(&band) {
            Some(Band { seq, stage: Stage::Casting(s), .. }) => Some((*seq, s)),
            _ => None,
        }
    }

    /// Every band casting, in band order.
    pub fn casting_bands(&self) -> impl Iterator<Item = (usize, &Scheduler)> {
        self.live.iter().filter_map(|(&b, band)| match &band.stage {
            Stage::Casting(s) => Some((b, &**s)),
            _ => None,
        })
    }

    /// Takes the scheduler of a band whose every task is cast or culled, to composite it;
    /// the band's memory is counted until [`Bands::place`].
    pub fn take_complete(&mut self, band: usize) -> Option<(Range<u32>, Box<Scheduler>)> {
        let b = self.live.get_mut(&band)?;
        if !matches!(&b.stage, Stage::Casting(s) if s.is_complete()) {
            return None;
        }
        let Stage::Casting(scheduler) = std::mem::replace(&mut b.stage, Stage::Compositing) else { unreachable!() };
        self.tasks_composited += scheduler.progress().total;
        Some((b.rows.clone(), scheduler))
    }

    /// Copies a composited band into the image and forgets it.
    pub fn place(&mut self, band: usize, part: &Composited) {
        if let Some(b) = self.live.remove(&band) {
            self.held -= b.bytes;
        }
        let row_len = self.width as usize * 3;
        let start = part.rows.start as usize * row_len;
        self.rgb8[start..start + part.rgb8.len()].copy_from_slice(&part.rgb8);
        if let (Some(all), Some(band)) = (&mut self.rgb32f, &part.rgb32f) {
            all[start..start + band.len()].copy_from_slice(band);
        }
        self.rows_done += part.rows.len() as u32;
    }

    /// Tasks done so far: composited bands' and the casting bands' cast or culled ones.
    pub fn tasks_done(&self) -> u64 {
        let casting: u64 = self
            .casting_bands()
            .map(|(_, s)| {
                let p = s.progress();
                p.cast + p.culled
            })
            .sum();
        self.tasks_composited + casting
    }

    /// The finished image: 8-bit, and floats when the job asked for a PFM.
    pub fn into_image(self) -> (Vec<u8>, Option<Vec<f32>>) {
        (self.rgb8, self.rgb32f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bands_cover_the_image_once_and_start_spread_out() {
        let mut bands = Bands::new(10, 103, 10, Admission { max_bands: 64, memory_bound: u64::MAX }, false);
        let mut seen = Vec::new();
        while let Some((b, rows)) = bands.start_next() {
            seen.push((b, rows));
        }
        assert_eq!(seen.len(), 11);
        assert_eq!(seen[1].0, 8, "the second band starts far from the first");
        let mut rows: Vec<Range<u32>> = seen.into_iter().map(|(_, r)| r).collect();
        rows.sort_by_key(|r| r.start);
        assert_eq!(rows.first().unwrap().start, 0);
        assert_eq!(rows.last().unwrap().end, 103);
        assert!(rows.windows(2).all(|w| w[0].end == w[1].start));
    }

    #[test]
    fn admission_caps_the_bands_in_flight() {
        let mut bands = Bands::new(4, 40, 1, Admission { max_bands: 3, memory_bound: u64::MAX }, false);
        assert!(bands.start_next().is_some() && bands.start_next().is_some() && bands.start_next().is_some());
        assert_eq!(bands.start_next(), None);
        assert!(!bands.is_done());
    }
}
