//! An image worked through in bands of rows, the one shape of Algorithm 2's drivers: which
//! band starts next (spread over the image: [`super::dispatch::band_order`]), how many are
//! held at once (within a memory bound: [`super::dispatch::Admission`]), and where each
//! stands. The local renderer holds one band at a time and the farm's coordinator several;
//! both hold only the pieces of the bands in flight, so their memory is bounded by
//! configuration rather than by the image's area. Each driver keeps its own raster (local
//! mode the f64 pixels of its `Image`, the farm its PNG bytes and PFM floats).
//!
//! What a casting band holds is the driver's ([`Casting`]): the local renderer keeps the
//! band's [`Scheduler`] here, while the farm's coordinator gives each band a thread of its
//! own that owns the scheduler, and keeps here only what that thread last reported.

use std::collections::BTreeMap;
use std::ops::Range;

use super::dispatch::{band_order, Admission};
use super::schedule::{Progress, Scheduler};

/// What [`Bands`] needs to know of a casting band: its bytes, for admission, and its
/// progress, to know when it is complete.
pub trait Casting {
    /// Bytes of bookkeeping the band holds ([`Scheduler::heap_bytes`]).
    fn heap_bytes(&self) -> u64;
    /// Its tasks: in all, cast and culled.
    fn progress(&self) -> Progress;
}

impl Casting for Box<Scheduler> {
    fn heap_bytes(&self) -> u64 {
        Scheduler::heap_bytes(self)
    }

    fn progress(&self) -> Progress {
        Scheduler::progress(self)
    }
}

/// Where a band stands.
pub enum Stage<S> {
    /// Its rays are being intersected.
    Intersecting,
    /// Its scheduler hands out batches.
    Casting(S),
    /// Every task is cast or culled; its pixels are being composited.
    Compositing,
}

struct Band<S> {
    seq: usize,
    rows: Range<u32>,
    stage: Stage<S>,
    bytes: u64,
}

/// An image's bands; see the module documentation.
pub struct Bands<S = Box<Scheduler>> {
    rows: Vec<Range<u32>>,
    order: Vec<usize>,
    started: usize,
    live: BTreeMap<usize, Band<S>>,
    admission: Admission,
    held: u64,
    largest: u64,
    rows_done: u32,
    tasks_composited: u64,
}

impl<S: Casting> Bands<S> {
    /// `height` rows in bands of `band_rows` rows, admitted under `admission`.
    pub fn new(height: u32, band_rows: u32, admission: Admission) -> Self {
        let band_rows = band_rows.clamp(1, height.max(1));
        let rows: Vec<Range<u32>> =
            (0..height.div_ceil(band_rows)).map(|b| b * band_rows..((b + 1) * band_rows).min(height)).collect();
        Bands {
            order: band_order(rows.len()),
            rows,
            started: 0,
            live: BTreeMap::new(),
            admission,
            held: 0,
            largest: 0,
            rows_done: 0,
            tasks_composited: 0,
        }
    }

    /// Whether every band is done.
    pub fn is_done(&self) -> bool {
        self.started == self.order.len() && self.live.is_empty()
    }

    /// Rows done so far.
    pub fn rows_done(&self) -> u32 {
        self.rows_done
    }

    /// Tasks of the bands composited or being composited.
    pub fn tasks_composited(&self) -> u64 {
        self.tasks_composited
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
    pub fn intersected(&mut self, band: usize, scheduler: S) {
        let bytes = scheduler.heap_bytes();
        self.held += bytes;
        self.largest = self.largest.max(bytes);
        if let Some(b) = self.live.get_mut(&band) {
            b.bytes = bytes;
            b.stage = Stage::Casting(scheduler);
        }
    }

    /// The band's start order (earlier bands go first) and scheduler, while it casts.
    pub fn casting(&mut self, band: usize) -> Option<(usize, &mut S)> {
        match self.live.get_mut(&band) {
            Some(Band { seq, stage: Stage::Casting(s), .. }) => Some((*seq, s)),
            _ => None,
        }
    }

    /// Every band casting, in band order.
    pub fn casting_bands(&self) -> impl Iterator<Item = (usize, &S)> {
        self.live.iter().filter_map(|(&b, band)| match &band.stage {
            Stage::Casting(s) => Some((b, s)),
            _ => None,
        })
    }

    /// Takes the scheduler of a band whose every task is cast or culled, with its rows, to
    /// composite it; its memory counts until [`Bands::composited`].
    pub fn take_complete(&mut self, band: usize) -> Option<(Range<u32>, S)> {
        let b = self.live.get_mut(&band)?;
        if !matches!(&b.stage, Stage::Casting(s) if s.progress().is_complete()) {
            return None;
        }
        let Stage::Casting(scheduler) = std::mem::replace(&mut b.stage, Stage::Compositing) else { unreachable!() };
        self.tasks_composited += scheduler.progress().total;
        Some((b.rows.clone(), scheduler))
    }

    /// Band `band`'s pixels are in the image: it is forgotten.
    pub fn composited(&mut self, band: usize) {
        if let Some(b) = self.live.remove(&band) {
            self.held -= b.bytes;
            self.rows_done += b.rows.len() as u32;
        }
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
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bands_cover_the_image_once_and_start_spread_out() {
        let mut bands = <Bands>::new(103, 10, Admission { max_bands: 64, memory_bound: u64::MAX });
        let mut seen = Vec::new();
        while let Some((b, rows)) = bands.start_next() {
            seen.push((b, rows));
        }
        assert_eq!(seen.len(), 11);
        assert_eq!(seen[1].0, 8, "the second band starts far from the first");
        let mut rows: Vec<Range<u32>> = seen.into_iter().map(|(_, r)| r).collect();
        rows.sort_by_key(|r| r.start);
        assert_eq!((rows[0].start, rows[10].end), (0, 103));
        assert!(rows.windows(2).all(|w| w[0].end == w[1].start));
    }

    #[test]
    fn admission_caps_the_bands_in_flight() {
        let mut bands = <Bands>::new(40, 1, Admission { max_bands: 3, memory_bound: u64::MAX });
        assert!(bands.start_next().is_some() && bands.start_next().is_some() && bands.start_next().is_some());
        assert_eq!(bands.start_next(), None);
        assert!(!bands.is_done());
        bands.composited(0);
        assert!(bands.start_next().is_some(), "a band done makes room");
    }
}
