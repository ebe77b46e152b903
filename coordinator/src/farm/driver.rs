//! One job, driven to its end: the farm's driver of `trove-core`'s [`Scheduler`].
//!
//! The image is worked through in *bands* of rows, so the coordinator holds only the pieces
//! of the bands in flight (at most [`BANDS_IN_FLIGHT`]) and never the whole image's: its
//! memory grows with the image's width, not its area. For each band the driver runs the
//! intersection phase (from dataset headers only — it never reads a voxel), hands the
//! scheduler's ready batches to the workers that hold each dataset, least loaded first, over
//! one `Cast` stream per worker and dataset, records the results as they come back in any
//! order, and composites the band into the image with the same code as local mode. Datasets
//! stay resident on their workers from band to band.
//!
//! Everything that happens to a job arrives on one channel of [`Event`]s — a band
//! intersected or composited (on blocking threads), an answer or the end of a stream — and
//! is handled by this one task, so the job's state needs no locks.
//!
//! A batch is identified by its wire id (unique in the job) and attempt; answers to a batch
//! that was given up are recognised and dropped. A worker that stops answering (its stream
//! breaks, it misses heartbeats, or a batch outlives [`DriverConfig::batch_deadline`]) has
//! its batches handed to another holder of the dataset; a job fails only when no holder is
//! left, or when a worker reports a failure that retrying cannot fix.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::ops::Range;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use prost::Message;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Status;
use trove_core::render::intersection::intersect;
use trove_core::render::wire::{decode_results, encode_tasks};
use trove_core::render::{quantize, Algorithm, RenderStats, Scheduler, StoreStats};
use trove_core::scene::Scene;
use trove_proto::convert::{self, JOB_HEADER};
use trove_proto::v1 as pb;
use trove_proto::v1::worker_client::WorkerClient;

use super::jobs::{Job, JobOutput};
use super::registry::{Registry, WorkerHandle};
use super::stats::{FarmStats, WorkerStats};

/// Why a job ended early; boxed because it travels up through every step of the
/// driver and is rare.
type Failed = Box<pb::Failure>;

/// Bands whose pieces the coordinator holds at once: one being cast while the next is
/// intersected or the last composited keeps workers busy between bands.
pub const BANDS_IN_FLIGHT: usize = 2;

/// Pixels per band when the job does not say: some tens of thousands of pieces in most
/// scenes, a few megabytes of bookkeeping. Small enough that a 512² image makes four bands,
/// so that intersecting and compositing one band overlap casting another (with 2¹⁸ a 512²
/// render was one band, each stage waiting for the last: `trove-bench farm`, Fig. 1 through
/// 2 workers, went from 1.72× to 1.20× local mode's time).
const BAND_PIXELS: u32 = 1 << 16;

/// Tasks per batch when the job does not say.
pub const DEFAULT_BATCH_TASKS: usize = 4096;

/// How the driver treats workers.
#[derive(Clone, Debug)]
pub struct DriverConfig {
    /// A batch not answered within this is given up and handed to another holder.
    pub batch_deadline: Duration,
}

impl Default for DriverConfig {
    fn default() -> Self {
        DriverConfig { batch_deadline: Duration::from_secs(120) }
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
}

type StreamKey = (String, usize);

/// What happens to a job.
enum Event {
    Intersected {
        band: usize,
        rows: Range<u32>,
        scheduler: Box<Scheduler>,
        seconds: f64,
    },
    Composited {
        band: usize,
        part: Box<Composited>,
    },
    Answer {
        stream: StreamKey,
        response: pb::CastResponse,
        bytes: u64,
    },
    StreamEnded {
        stream: StreamKey,
        status: Option<Status>,
    },
    /// A step that ran off the event loop failed; the job cannot go on.
    Failed(Failed),
}

/// A band's share of the image and statistics.
struct Composited {
    rows: Range<u32>,
    rgb8: Vec<u8>,
    rgb32f: Option<Vec<f32>>,
    samples_skipped: u64,
    seconds: f64,
}

enum Band {
    Intersecting,
    Casting { rows: Range<u32>, scheduler: Box<Scheduler> },
    Compositing,
}

struct Stream {
    tx: mpsc::Sender<pb::CastRequest>,
    worker: WorkerHandle,
}

struct InFlight {
    band: usize,
    id: u64,
    stream: StreamKey,
    sent: Instant,
}

/// The image as it fills up, band by band: the PNG's bytes, and floats for a PFM.
struct Raster {
    rgb8: Vec<u8>,
    rgb32f: Option<Vec<f32>>,
}

struct Driver {
    plan: JobPlan,
    job: Arc<Job>,
    registry: Arc<Registry>,
    config: DriverConfig,
    events: mpsc::Sender<Event>,
    bands: BTreeMap<usize, Band>,
    band_rows: u32,
    next_row: u32,
    next_band: usize,
    rows_done: u32,
    batch_tasks: usize,
    streams: HashMap<StreamKey, Stream>,
    unusable: HashSet<StreamKey>,
    in_flight: HashMap<u64, InFlight>,
    next_wire: u64,
    raster: Raster,
    stats: RenderStats,
    store: StoreStats,
    batches: u64,
    wire_to: u64,
    wire_from: u64,
    workers: BTreeMap<String, WorkerStats>,
    cast_started: Option<Instant>,
    /// Tasks of the bands handed to composition (all cast or culled).
    tasks_composited: u64,
}

/// Runs `plan` as `job` until it succeeds, fails or is cancelled, leaving the outcome in the
/// job's status (and its files in the job).
pub async fn run(plan: JobPlan, job: Arc<Job>, registry: Arc<Registry>, config: DriverConfig) {
    let span = tracing::info_span!("job", id = %job.id);
    let _entered = span.enter();
    let started = Instant::now();
    let (events, mut inbox) = mpsc::channel(1024);
    let (w, h) = (plan.scene.image().width, plan.scene.image().height);
    let band_rows = match plan.options.band_rows {
        0 => (BAND_PIXELS / w).clamp(1, h),
        n => n.min(h),
    };
    let batch_tasks = match plan.options.batch_tasks {
        0 => DEFAULT_BATCH_TASKS,
        n => (n as usize).min(trove_proto::MAX_BATCH_TASKS),
    };
    let pixels = w as usize * h as usize * 3;
    let raster = Raster { rgb8: vec![0; pixels], rgb32f: plan.options.want_pfm.then(|| vec![0.0; pixels]) };
    let mut driver = Driver {
        plan,
        job: job.clone(),
        registry,
        config,
        events,
        bands: BTreeMap::new(),
        band_rows,
        next_row: 0,
        next_band: 0,
        rows_done: 0,
        batch_tasks,
        streams: HashMap::new(),
        unusable: HashSet::new(),
        in_flight: HashMap::new(),
        next_wire: 1,
        raster,
        stats: RenderStats::default(),
        store: StoreStats::default(),
        batches: 0,
        wire_to: 0,
        wire_from: 0,
        workers: BTreeMap::new(),
        cast_started: None,
        tasks_composited: 0,
    };
    job.update(|s| {
        s.state = pb::JobState::Running as i32;
        s.phase = pb::Phase::Intersection as i32;
        s.rows_total = h;
    });
    let mut cancelled = job.cancelled();
    let mut tick = tokio::time::interval(Duration::from_millis(250));
    let outcome = loop {
        if let Err(f) = driver.advance() {
            break Err(f);
        }
        if driver.is_done() {
            break Ok(());
        }
        tokio::select! {
            event = inbox.recv() => {
                let Some(event) = event else { break Err(convert::failure(pb::Reason::Internal, true, "the job's event channel closed".into()).into()) };
                if let Err(f) = driver.handle(event) {
                    break Err(f);
                }
            }
            _ = cancelled.changed() => {
                break Err(convert::failure(pb::Reason::Cancelled, false, "the job was cancelled".into()).into());
            }
            _ = tick.tick() => {
                if let Err(f) = driver.check_workers() {
                    break Err(f);
                }
            }
        }
    };
    // Closing every stream tells the workers to drop what they still hold for this job, and
    // gives back to their load counts, shared with other jobs, what this job still had out.
    let open: Vec<StreamKey> = driver.streams.keys().cloned().collect();
    for stream in &open {
        driver.lose_stream(stream);
    }
    match outcome {
        Ok(()) => driver.finish(started).await,
        Err(failure) => {
            let state =
                if failure.reason() == pb::Reason::Cancelled { pb::JobState::Cancelled } else { pb::JobState::Failed };
            tracing::warn!(reason = ?failure.reason(), message = %failure.message, "job ended");
            job.update(|s| {
                s.state = state as i32;
                s.failure = Some(*failure);
            });
        }
    }
}

impl Driver {
    fn scene(&self) -> &Arc<Scene> {
        &self.plan.scene
    }

    fn is_done(&self) -> bool {
        self.next_row >= self.scene().image().height && self.bands.is_empty()
    }

    /// Starts intersecting new bands while there is room, then hands out every batch some
    /// worker has room for.
    fn advance(&mut self) -> Result<(), Failed> {
        let h = self.scene().image().height;
        while self.bands.len() < BANDS_IN_FLIGHT && self.next_row < h {
            let rows = self.next_row..(self.next_row + self.band_rows).min(h);
            self.next_row = rows.end;
            let band = self.next_band;
            self.next_band += 1;
            self.bands.insert(band, Band::Intersecting);
            let (scene, events, batch_tasks) = (self.scene().clone(), self.events.clone(), self.batch_tasks);
            tokio::task::spawn_blocking(move || {
                let started = Instant::now();
                let inter = intersect(&scene, rows.clone());
                let event = match Scheduler::new(&scene, inter, batch_tasks) {
                    Ok(scheduler) => {
                        let seconds = started.elapsed().as_secs_f64();
                        Event::Intersected { band, rows, scheduler: Box::new(scheduler), seconds }
                    }
                    // A band of at most BAND_PIXELS rays holds far fewer tasks than the
                    // scheduler's limit; should it not, the job fails rather than waits.
                    Err(e) => {
                        Event::Failed(Box::new(convert::failure(pb::Reason::LimitExceeded, false, e.to_string())))
                    }
                };
                let _ = events.blocking_send(event);
            });
        }
        self.dispatch()
    }

    /// Hands out ready batches, earliest band first, each to the least loaded holder of its
    /// dataset that has room; then composites every band that asking for batches completed
    /// (its last tasks can be culled rather than cast, so no answer would complete it).
    fn dispatch(&mut self) -> Result<(), Failed> {
        let band_ids: Vec<usize> = self.bands.keys().copied().collect();
        for &band in &band_ids {
            let Some(Band::Casting { scheduler, .. }) = self.bands.get(&band) else { continue };
            let datasets = scheduler.datasets().to_vec();
            for d in datasets {
                while let Some(Band::Casting { scheduler, .. }) = self.bands.get_mut(&band) {
                    if scheduler.is_dataset_done(d) {
                        break;
                    }
                    let Some(worker) = self.pick_worker(d)? else { break };
                    let Some(Band::Casting { scheduler, .. }) = self.bands.get_mut(&band) else { break };
                    let Some(batch) = scheduler.next_batch(d) else { break };
                    self.send(band, worker, batch)?;
                }
            }
        }
        for band in band_ids {
            if let Some(Band::Casting { scheduler, .. }) = self.bands.get(&band) {
                if scheduler.is_complete() {
                    if let Some(Band::Casting { rows, scheduler }) = self.bands.remove(&band) {
                        self.composite(band, rows, scheduler);
                    }
                }
            }
        }
        Ok(())
    }

    /// The alive holder of dataset `d` with the fewest batches in flight that has room for
    /// another, opening its stream if needed; `None` when all are busy. Fails the job when no
    /// holder is left at all.
    fn pick_worker(&mut self, d: usize) -> Result<Option<WorkerHandle>, Failed> {
        let holders: Vec<WorkerHandle> = self
            .registry
            .holders(&self.plan.dataset_keys[d])
            .into_iter()
            .filter(|w| !self.unusable.contains(&(w.clone(), d)))
            .filter_map(|w| self.registry.handle(&w))
            .collect();
        if holders.is_empty() {
            let name = self.scene().datasets()[d].name().to_string();
            let mut f = convert::failure(
                pb::Reason::WorkerLost,
                true,
                format!("no worker that holds dataset `{name}` is left to cast it"),
            );
            f.dataset = name;
            return Err(f.into());
        }
        let best = holders
            .into_iter()
            .filter(|w| w.in_flight.load(Ordering::Relaxed) < capacity(w))
            .min_by_key(|w| (w.in_flight.load(Ordering::Relaxed), w.id.clone()));
        Ok(best)
    }

    /// Sends `batch` of band `band` to `worker`'s stream for its dataset.
    fn send(&mut self, band: usize, worker: WorkerHandle, batch: trove_core::render::Batch) -> Result<(), Failed> {
        let key = (worker.id.clone(), batch.dataset);
        if !self.streams.contains_key(&key) {
            self.open(&worker, batch.dataset);
        }
        let wire = self.next_wire;
        self.next_wire += 1;
        let _span = tracing::debug_span!("batch", wire, dataset = batch.dataset, worker = %worker.id, tasks = batch.tasks.len()).entered();
        let request = pb::CastRequest {
            kind: Some(pb::cast_request::Kind::Batch(pb::CastBatch {
                batch_id: wire,
                attempt: 0,
                tasks: encode_tasks(&batch.tasks),
            })),
        };
        self.wire_to += request.encoded_len() as u64;
        let stream = self.streams.get(&key).expect("opened above");
        if stream.tx.try_send(request).is_err() {
            // The stream's reader is gone or its queue is full: give the batch back.
            if let Some(Band::Casting { scheduler, .. }) = self.bands.get_mut(&band) {
                let _ = scheduler.abandon(batch.id);
            }
            self.lose_stream(&key);
            return Ok(());
        }
        worker.in_flight.fetch_add(1, Ordering::Relaxed);
        self.in_flight.insert(wire, InFlight { band, id: batch.id, stream: key, sent: Instant::now() });
        self.cast_started.get_or_insert_with(Instant::now);
        self.job.update(|s| s.phase = pb::Phase::VolumeRendering as i32);
        Ok(())
    }

    /// Opens the `Cast` stream to `worker` for dataset `d`: the scene first, then batches.
    fn open(&mut self, worker: &WorkerHandle, d: usize) {
        let (tx, rx) = mpsc::channel(256);
        let open = pb::CastRequest {
            kind: Some(pb::cast_request::Kind::Open(pb::CastOpen {
                job_id: self.job.id.clone(),
                scene_toml: self.plan.scene_toml.clone(),
                scene_name: self.plan.scene_name.clone(),
                dataset: d as u32,
                headers: self.plan.headers.clone(),
            })),
        };
        self.wire_to += open.encoded_len() as u64;
        let _ = tx.try_send(open);
        let key = (worker.id.clone(), d);
        let mut client = WorkerClient::new(worker.channel.clone())
            .max_decoding_message_size(trove_proto::MAX_MESSAGE_BYTES)
            .max_encoding_message_size(trove_proto::MAX_MESSAGE_BYTES);
        let mut request = tonic::Request::new(ReceiverStream::new(rx));
        if let Ok(value) = self.job.id.parse() {
            request.metadata_mut().insert(JOB_HEADER, value);
        }
        let events = self.events.clone();
        let stream_key = key.clone();
        tokio::spawn(async move {
            let status = match client.cast(request).await {
                Ok(response) => {
                    let mut inbound = response.into_inner();
                    loop {
                        match inbound.message().await {
                            Ok(Some(response)) => {
                                let bytes = response.encoded_len() as u64;
                                let stream = stream_key.clone();
                                if events.send(Event::Answer { stream, response, bytes }).await.is_err() {
                                    return;
                                }
                            }
                            Ok(None) => break None,
                            Err(status) => break Some(status),
                        }
                    }
                }
                Err(status) => Some(status),
            };
            let _ = events.send(Event::StreamEnded { stream: stream_key, status }).await;
        });
        self.streams.insert(key, Stream { tx, worker: worker.clone() });
    }

    fn handle(&mut self, event: Event) -> Result<(), Failed> {
        match event {
            Event::Failed(failure) => Err(failure),
            Event::Intersected { band, rows, scheduler, seconds } => {
                let inter = scheduler.intersections();
                self.stats.segments += inter.segments;
                self.stats.pieces += inter.pieces() as u64;
                self.stats.seconds.intersection += seconds;
                let total = scheduler.progress().total;
                self.job.update(|s| s.pieces_total += total);
                if scheduler.is_complete() {
                    self.composite(band, rows, scheduler);
                } else {
                    self.bands.insert(band, Band::Casting { rows, scheduler });
                }
                Ok(())
            }
            Event::Composited { band, part } => {
                self.bands.remove(&band);
                self.place(&part);
                self.rows_done += part.rows.len() as u32;
                self.stats.samples_skipped += part.samples_skipped;
                self.stats.seconds.composition += part.seconds;
                let rows_done = self.rows_done;
                self.job.update(|s| s.rows_done = rows_done);
                Ok(())
            }
            Event::Answer { stream, response, bytes } => {
                self.wire_from += bytes;
                match response.kind {
                    Some(pb::cast_response::Kind::Result(result)) => self.record(&stream, result),
                    Some(pb::cast_response::Kind::Failure(failure)) => self.failed(&stream, failure),
                    None => Ok(()),
                }
            }
            Event::StreamEnded { stream, status } => {
                if let Some(failure) = status.as_ref().and_then(convert::status_failure) {
                    if !failure.retryable {
                        return Err(failure.into());
                    }
                }
                if self.streams.contains_key(&stream) || self.in_flight.values().any(|b| b.stream == stream) {
                    tracing::warn!(worker = %stream.0, dataset = stream.1, status = ?status.map(|s| s.code()), "stream ended");
                    self.lose_stream(&stream);
                }
                Ok(())
            }
        }
    }

    /// A batch's results: recorded in its band's scheduler; the band is composited once
    /// complete. An answer to a batch given up is dropped.
    fn record(&mut self, stream: &StreamKey, result: pb::BatchResult) -> Result<(), Failed> {
        let Some(batch) = self.in_flight.remove(&result.batch_id) else {
            tracing::debug!(wire = result.batch_id, "answer to a batch given up; dropped");
            return Ok(());
        };
        let _span = tracing::debug_span!("batch", wire = result.batch_id, worker = %stream.0).entered();
        if let Some(s) = self.streams.get(stream) {
            s.worker.in_flight.fetch_sub(1, Ordering::Relaxed);
            s.worker.done.fetch_add(1, Ordering::Relaxed);
        }
        let Some(Band::Casting { scheduler, .. }) = self.bands.get_mut(&batch.band) else {
            return Ok(());
        };
        // Either refusal is only logged: the batch is given to another worker.
        let recorded = match decode_results(&result.results) {
            Ok(results) => {
                scheduler.record(batch.id, &results).map(|()| results.len() as u64).map_err(|e| e.to_string())
            }
            Err(e) => Err(format!("undecodable results: {e}")),
        };
        let tasks = match recorded {
            Ok(n) => n,
            Err(e) => {
                // A worker that answers nonsense is not trusted with more of this job.
                tracing::warn!(worker = %stream.0, error = %e, "refused an answer");
                let _ = scheduler.abandon(batch.id);
                self.lose_stream(stream);
                return Ok(());
            }
        };
        self.batches += 1;
        self.stats.samples += result.samples;
        if result.bytes_loaded > 0 {
            self.store.loads += 1;
            self.store.bytes_loaded += result.bytes_loaded;
        }
        self.store.loading_seconds += result.loading_nanos as f64 * 1e-9;
        let w = self.workers.entry(stream.0.clone()).or_insert_with(|| WorkerStats::new(&stream.0));
        w.batches += 1;
        w.tasks += tasks;
        w.samples += result.samples;
        let complete = scheduler.is_complete();
        self.update_progress();
        if complete {
            if let Some(Band::Casting { rows, scheduler }) = self.bands.remove(&batch.band) {
                self.composite(batch.band, rows, scheduler);
            }
        }
        Ok(())
    }

    /// A worker's failure report: a batch it cannot cast, or the stream as a whole.
    fn failed(&mut self, stream: &StreamKey, mut failure: pb::Failure) -> Result<(), Failed> {
        failure.worker_id = stream.0.clone();
        if !failure.retryable {
            return Err(failure.into());
        }
        tracing::warn!(worker = %stream.0, reason = ?failure.reason(), message = %failure.message, "worker failed a batch; retrying elsewhere");
        self.lose_stream(stream);
        Ok(())
    }

    /// Stops using `stream` for this job: its batches go back to their schedulers, to be
    /// handed to another holder.
    fn lose_stream(&mut self, stream: &StreamKey) {
        if let Some(s) = self.streams.remove(stream) {
            let lost: Vec<u64> =
                self.in_flight.iter().filter(|(_, b)| b.stream == *stream).map(|(&wire, _)| wire).collect();
            for wire in lost {
                let batch = self.in_flight.remove(&wire).expect("listed above");
                s.worker.in_flight.fetch_sub(1, Ordering::Relaxed);
                if let Some(Band::Casting { scheduler, .. }) = self.bands.get_mut(&batch.band) {
                    let _ = scheduler.abandon(batch.id);
                }
            }
        }
        self.unusable.insert(stream.clone());
    }

    /// Gives up on workers that missed their heartbeats and on batches past their deadline.
    fn check_workers(&mut self) -> Result<(), Failed> {
        let deadline = self.config.batch_deadline;
        let mut lost: HashSet<StreamKey> =
            self.in_flight.values().filter(|b| b.sent.elapsed() > deadline).map(|b| b.stream.clone()).collect();
        lost.extend(self.streams.keys().filter(|(w, _)| !self.registry.is_alive(w)).cloned());
        for stream in lost {
            tracing::warn!(worker = %stream.0, dataset = stream.1, "worker silent; its batches go elsewhere");
            self.lose_stream(&stream);
        }
        Ok(())
    }

    fn update_progress(&self) {
        let done: u64 = self
            .bands
            .values()
            .filter_map(|b| match b {
                Band::Casting { scheduler, .. } => {
                    let p = scheduler.progress();
                    Some(p.cast + p.culled)
                }
                _ => None,
            })
            .sum();
        let workers: Vec<pb::WorkerCount> = self.workers.values().map(WorkerStats::to_proto).collect();
        let composited = self.tasks_composited;
        self.job.update(|s| {
            s.pieces_done = composited + done;
            s.workers = workers;
        });
    }

    /// Composites a finished band on a blocking thread.
    fn composite(&mut self, band: usize, rows: Range<u32>, scheduler: Box<Scheduler>) {
        self.bands.insert(band, Band::Compositing);
        self.tasks_composited += scheduler.progress().total;
        self.job.update(|s| s.phase = pb::Phase::Composition as i32);
        let (scene, events, want_pfm) = (self.scene().clone(), self.events.clone(), self.plan.options.want_pfm);
        tokio::task::spawn_blocking(move || {
            let started = Instant::now();
            let pixels = scheduler.composite_pixels(scene.image().background);
            let rgb8 = pixels.iter().flat_map(|p| p.map(quantize)).collect();
            let rgb32f = want_pfm.then(|| pixels.iter().flat_map(|p| p.map(|c| c as f32)).collect());
            let samples_skipped = scheduler.culled_samples(&scene);
            let part = Composited { rows, rgb8, rgb32f, samples_skipped, seconds: started.elapsed().as_secs_f64() };
            let _ = events.blocking_send(Event::Composited { band, part: Box::new(part) });
        });
    }

    /// Copies a composited band into the image.
    fn place(&mut self, part: &Composited) {
        let row_len = self.scene().image().width as usize * 3;
        let start = part.rows.start as usize * row_len;
        self.raster.rgb8[start..start + part.rgb8.len()].copy_from_slice(&part.rgb8);
        if let (Some(all), Some(band)) = (&mut self.raster.rgb32f, &part.rgb32f) {
            all[start..start + band.len()].copy_from_slice(band);
        }
    }

    /// Encodes the image and statistics and marks the job succeeded.
    async fn finish(mut self, started: Instant) {
        self.job.update(|s| s.phase = pb::Phase::Encoding as i32);
        if let Some(cast) = self.cast_started {
            self.stats.seconds.volume_rendering =
                (cast.elapsed().as_secs_f64() - self.stats.seconds.composition).max(0.0);
        }
        let (w, h) = (self.scene().image().width, self.scene().image().height);
        let raster = std::mem::replace(&mut self.raster, Raster { rgb8: Vec::new(), rgb32f: None });
        let encoded = tokio::task::spawn_blocking(move || {
            let png = trove_core::render::encode_png(w, h, &raster.rgb8);
            let pfm = raster.rgb32f.map(|f| trove_core::render::encode_pfm(w, h, &f));
            (png, pfm)
        })
        .await;
        let (png, pfm) = match encoded {
            Ok((Ok(png), pfm)) => (png, pfm),
            Ok((Err(e), _)) => {
                return self.fail(convert::failure(pb::Reason::Internal, false, format!("encoding the PNG: {e}")))
            }
            Err(e) => return self.fail(convert::failure(pb::Reason::Internal, true, format!("encoding the PNG: {e}"))),
        };
        let mut stats = std::mem::take(&mut self.stats);
        stats.finish(self.scene(), Algorithm::Grouped, &self.store, None, started.elapsed().as_secs_f64());
        let farm =
            FarmStats::new(stats, self.batches, self.wire_to, self.wire_from, self.workers.into_values().collect());
        let stats_json = farm.to_json();
        let output = JobOutput { png, pfm, stats_json };
        self.job.set_output(output);
        let tasks = self.tasks_composited;
        self.job.update(|s| {
            s.state = pb::JobState::Succeeded as i32;
            s.phase = pb::Phase::Done as i32;
            s.pieces_done = tasks;
            s.rows_done = h;
        });
        tracing::info!(seconds = started.elapsed().as_secs_f64(), "job succeeded");
    }

    fn fail(&self, failure: pb::Failure) {
        self.job.update(|s| {
            s.state = pb::JobState::Failed as i32;
            s.failure = Some(failure);
        });
    }
}

/// Batches a worker may have in flight at once: enough to keep its threads busy while
/// answers travel, few enough that late culling still saves work.
fn capacity(w: &WorkerHandle) -> u64 {
    (2 * w.threads as u64).max(4)
}
