//! How the driver treats workers and how much of an image it holds ([`DriverConfig`]), and
//! what a job brings to it once validated ([`JobPlan`]): the checks a submission makes
//! before a job is queued live here, so that `SubmitJob` and the job-request fuzz target
//! run the same ones.

use std::sync::Arc;
use std::time::Duration;

use trove_core::render::intersection::Intersections;
use trove_core::render::limits::{check_pfm, LimitError, Work, MAX_PFM_PIXELS};
use trove_core::scene::Scene;
use trove_proto::v1 as pb;

use super::super::metrics::FarmMetrics;
use super::raster;

/// Tasks per batch when the job does not say.
pub const DEFAULT_BATCH_TASKS: usize = 4096;

/// How the driver treats workers and how much of an image it holds.
#[derive(Clone, Debug)]
pub struct DriverConfig {
    /// A batch not answered within this is given up and handed to another holder.
    pub batch_deadline: Duration,
    /// Bands whose pieces a job holds at once, at most.
    pub max_bands: usize,
    /// Bytes of band bookkeeping (tasks, results, fronts) a job holds at once, at most; one
    /// band is always admitted, and bands are made small enough that this holds
    /// [`DriverConfig::max_bands`] of them. The image itself is not counted.
    pub memory_bound: u64,
    /// Dispatches of one batch before the job fails.
    pub max_attempts: u32,
    /// Longest a job may run (from leaving the queue to its files); past it the job fails
    /// with `DEADLINE_EXCEEDED`, so no job stays RUNNING forever.
    pub job_deadline: Duration,
    /// Most pixels of a job that asks for a PFM (the coordinator holds its floats and the
    /// file's bytes): a larger one is refused at submission.
    pub max_pfm_pixels: u64,
    /// How often the driver looks for silent workers and overdue batches, looks holders up
    /// again and publishes progress. Nothing else waits for it: batches are handed out as
    /// answers, new workers and room freed by other jobs arrive.
    pub tick: Duration,
    /// Where every job of the coordinator records its counters (`--metrics-listen`).
    pub metrics: Arc<FarmMetrics>,
    /// Debug builds only, for tests: a blocking step that panics in every job, to show that
    /// a panic fails its job only.
    #[cfg(debug_assertions)]
    pub fault: Option<Fault>,
}

/// A step made to panic (debug builds only): [`DriverConfig::fault`].
#[cfg(debug_assertions)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fault {
    /// Intersecting a band.
    Intersection,
    /// Compositing a band.
    Composition,
    /// Encoding the image.
    Encoding,
}

impl Default for DriverConfig {
    fn default() -> Self {
        DriverConfig {
            batch_deadline: Duration::from_secs(120),
            max_bands: 8,
            memory_bound: 256 << 20,
            max_attempts: 5,
            job_deadline: Duration::from_secs(3600),
            max_pfm_pixels: MAX_PFM_PIXELS,
            tick: Duration::from_millis(250),
            metrics: Arc::new(FarmMetrics::new()),
            #[cfg(debug_assertions)]
            fault: None,
        }
    }
}

impl DriverConfig {
    /// Rows per band of a job of `scene` with `options`, whose work is `work`: as the job
    /// asks, else sized from the exact count so that [`DriverConfig::max_bands`] bands fit
    /// the memory bound. The submission check sizes bands here once and hands the result
    /// to the driver in its [`JobPlan`], so a scene refused for a band over its limit is
    /// refused before it runs.
    pub fn band_rows(&self, scene: &Scene, work: &Work, options: &pb::JobOptions) -> Result<u32, LimitError> {
        let (w, h) = (scene.image().width, scene.image().height);
        let within = work.rows_within(self.memory_bound / self.max_bands.max(1) as u64)?;
        Ok(raster::rows_per_band(options.band_rows, w, h, within))
    }

    /// The work a job of `scene` with `options` would take, checked before it is queued:
    /// its PFM capped, its tasks counted without storing one, its bands sized
    /// ([`DriverConfig::band_rows`]) and each checked against the memory bound. Returns the
    /// count and the rows per band; `SubmitJob` calls it, and so does the job-request fuzz
    /// target, so that what is fuzzed is what a submission runs.
    ///
    /// The count intersects the image in the bands the driver will most likely use and
    /// keeps them when they fit a quarter of the memory bound ([`Work::count_keeping`]), so
    /// that the driver does not intersect the image a second time; the third value is those
    /// bands, one per band of the returned rows, or none.
    pub fn check_work(
        &self,
        scene: &Scene,
        options: &pb::JobOptions,
    ) -> Result<(Work, u32, Vec<Intersections>), LimitError> {
        let (w, h) = (scene.image().width, scene.image().height);
        if options.want_pfm {
            check_pfm(w, h, self.max_pfm_pixels)?;
        }
        // The rows a band has unless the memory bound narrows it (it rarely does).
        let likely = raster::rows_per_band(options.band_rows, w, h, h);
        let (work, kept) = Work::count_keeping(scene, likely, self.memory_bound / 4)?;
        let band_rows = self.band_rows(scene, &work, options)?;
        work.check_bands(band_rows, self.memory_bound)?;
        let kept = if band_rows == likely { kept } else { Vec::new() };
        Ok((work, band_rows, kept))
    }

    /// Panics if this step is the configured fault (debug builds only).
    #[cfg_attr(not(debug_assertions), allow(unused_variables))]
    pub(super) fn inject(&self, step: &'static str) {
        #[cfg(debug_assertions)]
        {
            let fault = match step {
                "intersection" => Fault::Intersection,
                "composition" => Fault::Composition,
                _ => Fault::Encoding,
            };
            if self.fault == Some(fault) {
                panic!("injected fault in {step}");
            }
        }
    }
}

/// A validated job, ready to run.
pub struct JobPlan {
    /// The scene, validated against the workers' headers.
    pub scene: Arc<Scene>,
    /// Its text and name, sent to each worker once per stream.
    pub scene_toml: String,
    /// The scene file's name, for messages.
    pub scene_name: String,
    /// The client's options.
    pub options: pb::JobOptions,
    /// The registrations of every file the scene names.
    pub headers: Vec<pb::DatasetFile>,
    /// Per dataset: the keys of its files (empty for generated datasets).
    pub dataset_keys: Vec<Vec<String>>,
    /// Rows per band ([`DriverConfig::band_rows`]), checked against the band limit.
    pub band_rows: u32,
    /// Bands the submission's count intersected and kept ([`DriverConfig::check_work`]),
    /// each taken by the driver when the band starts (at most a quarter of the memory bound
    /// per running job, on top of the bands in flight); none for a job that waited in the
    /// queue (they are dropped so that waiting jobs hold no pieces).
    pub kept: Vec<Option<Intersections>>,
    /// Seconds the submission's count took ([`DriverConfig::check_work`]): the kept bands'
    /// intersection, charged to the job's intersection stage when it runs.
    pub counting_seconds: f64,
}
