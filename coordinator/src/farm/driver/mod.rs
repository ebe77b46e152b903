//! One job, driven to its end: the farm's driver of `trove-core`'s
//! [`Scheduler`](trove_core::render::Scheduler).
//!
//! The image is worked through in *bands* of rows (`trove_core::render::bands`, the shape
//! local mode shares; the image, `trove_core`'s `Raster` as in local mode, fills up band
//! by band from `raster.rs`): the coordinator holds only
//! the pieces of the bands in flight, as many as [`DriverConfig::memory_bound`] and
//! [`DriverConfig::max_bands`] admit, started in an order spread over the image so that
//! many datasets are busy at once. For each band the driver runs the intersection phase
//! (from dataset headers only — it never reads a voxel), hands the scheduler's ready
//! batches to the workers that hold each dataset (`dispatch.rs`, under the policy of
//! `trove_core::render::dispatch`) over one `Cast` stream per worker and dataset, records
//! the results as they come back in any order, and composites the band into the image with
//! the same code as local mode. Datasets stay resident on their workers from band to band.
//!
//! Each band in flight has a thread of its own (`band.rs`) that owns the band's scheduler
//! and does every per-task step: intersection and planning, the fronts and culls of each
//! batch it hands out and their encoding, decoding and recording answers, composition. The
//! job's one task — its event loop — does only per-batch work: everything that happens to
//! the job arrives on one channel of `Event`s (news from a band, an answer, a stream opened
//! or ended), the loop keeps per dataset the batches bands handed out (`Stock`), sends them
//! to workers with room, asks bands for more where there is room, and hands each answer to
//! its band. So a job's per-task work runs on as many cores as it has bands in flight, and
//! its state still needs no locks: the loop owns what is per job, each band's thread what
//! is per band. A dataset is looked at again only when something happened to it.
//!
//! A batch is identified by its wire id (unique in the job) and its attempt (how many times
//! its tasks were given up before); an answer is taken only on the stream the batch went
//! out on and for the attempt it was, so answers to a batch that was given up are dropped.
//! A worker that stops answering (its stream breaks, it misses heartbeats, or a batch
//! outlives [`DriverConfig::batch_deadline`]) has its batches handed to another holder of
//! the dataset, and serves the job again after a rest if it is still alive. Batches go on a
//! stream only once the worker has accepted it (opening it checks the scene and the
//! worker's stream cap), so a worker that refuses a stream as busy costs no batch an
//! attempt: it is asked again later. A job fails only when no holder is left, when a batch
//! has been given up [`DriverConfig::max_attempts`] times, when a worker reports a failure
//! that retrying cannot fix, when it runs past [`DriverConfig::job_deadline`], when a band
//! makes more tasks than the memory bound holds (`intersect_within`), or when a step on a
//! blocking thread panics: each fails this job only.

mod band;
mod config;
mod dispatch;
mod error;
mod raster;
mod shadows;
mod streams;
mod tally;

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet, VecDeque};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::Arc;
use std::time::Instant;

use prost::Message;
use tokio::sync::mpsc;
use tonic::Status;
use trove_core::render::bands::{Bands, Casting};
use trove_core::render::dispatch::{batches_to_ask, Admission};
use trove_core::render::schedule::Progress;
use trove_core::render::{Algorithm, ObjectEffects, Raster};
use trove_core::scene::Scene;
use trove_proto::convert;
use trove_proto::v1 as pb;

use super::jobs::{Job, JobOutput};
use super::registry::{Registry, WorkerHandle};
use band::{News, Ready, ToBand};
#[cfg(debug_assertions)]
pub use config::Fault;
pub use config::{DriverConfig, JobPlan, DEFAULT_BATCH_TASKS};
use dispatch::{Dispatch, InFlight, Rest};
pub use error::JobError;
use tally::Tally;

/// Runs `f` on a blocking thread's stack, turning a panic into the job's error.
fn unwinding<T>(step: &'static str, f: impl FnOnce() -> T) -> Result<T, JobError> {
    catch_unwind(AssertUnwindSafe(f)).map_err(|payload| JobError::Panicked { step, message: panic_message(&*payload) })
}

/// The text of a panic's payload.
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    match (payload.downcast_ref::<&str>(), payload.downcast_ref::<String>()) {
        (Some(s), _) => s.to_string(),
        (_, Some(s)) => s.clone(),
        _ => "a panic without a message".to_string(),
    }
}

/// A `Cast` stream: (worker id, dataset).
type StreamKey = (String, usize);

/// What happens to a job.
enum Event {
    /// News from a band's thread.
    Band {
        band: usize,
        news: News,
    },
    /// The worker accepted stream `serial`: batches may go on it.
    Opened {
        stream: StreamKey,
        serial: u64,
    },
    Answer {
        stream: StreamKey,
        serial: u64,
        response: pb::CastResponse,
        bytes: u64,
    },
    StreamEnded {
        stream: StreamKey,
        serial: u64,
        status: Option<Status>,
    },
    /// A step that ran off the event loop failed; the job cannot go on.
    Failed(JobError),
}

struct Stream {
    tx: mpsc::Sender<pb::CastRequest>,
    worker: WorkerHandle,
    /// Its open carried the scene (the worker did not hold it yet, as far as the job knew).
    carries_scene: bool,
    /// Which opening of its (worker, dataset) pair this is: events of an earlier stream of
    /// the same pair, lost before, are not this one's.
    serial: u64,
}

/// What the job's loop keeps of a band in flight: the band's thread owns its scheduler.
struct BandState {
    bytes: u64,
    progress: Progress,
}

impl Casting for BandState {
    fn heap_bytes(&self) -> u64 {
        self.bytes
    }

    fn progress(&self) -> Progress {
        self.progress
    }
}

struct Driver {
    plan: JobPlan,
    job: Arc<Job>,
    registry: Arc<Registry>,
    config: DriverConfig,
    events: mpsc::Sender<Event>,
    bands: Bands<BandState>,
    /// Each band's thread, from its start until it is composited.
    band_tx: HashMap<usize, mpsc::UnboundedSender<ToBand>>,
    raster: Raster,
    batch_tasks: usize,
    dispatch: Dispatch,
    streams: HashMap<StreamKey, Stream>,
    /// Streams opened and not accepted yet, since when (few: only while streams open).
    opening: Vec<(StreamKey, Instant)>,
    next_serial: u64,
    /// The scene's SHA-256 (`convert::scene_digest`): what names it on streams that do not
    /// carry it.
    scene_digest: Vec<u8>,
    /// The scene's shadow maps (`shadows.rs`), carried with the scene, once its shadow pass
    /// ran: `None` without shadows.
    shadow_maps: Option<Vec<pb::ShadowMap>>,
    /// Workers that accepted a stream of this job carrying the scene: they hold it, and the
    /// job's other streams to them name it by digest alone.
    scene_on: HashSet<String>,
    /// Per dataset: the batches bands handed out that wait for a worker with room, and how
    /// many more are asked for and not yet produced.
    stock: Vec<Stock>,
    /// Datasets with batches in stock or a band that may produce one: the only ones the
    /// dispatch looks at.
    active: BTreeSet<usize>,
    tally: Tally,
}

/// One dataset's side of the job's loop.
#[derive(Default)]
struct Stock {
    ready: VecDeque<Ready>,
    /// Bands (by start order) that may have a batch of the dataset to hand out: a band leaves
    /// when it has nothing ready and comes back when an answer or a lost batch could change
    /// that.
    bands: BTreeSet<(usize, usize)>,
    /// Batches asked of each band (by band) and not produced yet. Per band, because a band
    /// that completes (its last tasks culled or answered) never answers what it was asked.
    asked: BTreeMap<usize, usize>,
}

impl Stock {
    fn asked(&self) -> usize {
        self.asked.values().sum()
    }
}

/// Runs `plan` as `job` until it succeeds, fails or is cancelled, leaving the outcome in the
/// job's status (and its files in the job).
pub async fn run(plan: JobPlan, job: Arc<Job>, registry: Arc<Registry>, config: DriverConfig) {
    let span = tracing::info_span!("job", id = %job.id);
    let _entered = span.enter();
    let started = Instant::now();
    let (events, mut inbox) = mpsc::channel(1024);
    let (w, h) = (plan.scene.image().width, plan.scene.image().height);
    let max_bands = config.max_bands.max(1);
    let band_rows = plan.band_rows;
    // Bands the count kept were intersected then, not here.
    let counting_seconds = if plan.kept.iter().any(Option::is_some) { plan.counting_seconds } else { 0.0 };
    let batch_tasks = match plan.options.batch_tasks {
        0 => DEFAULT_BATCH_TASKS,
        n => (n as usize).min(trove_proto::MAX_BATCH_TASKS),
    };
    let admission = Admission { max_bands, memory_bound: config.memory_bound };
    let metrics = config.metrics.clone();
    let datasets = plan.scene.datasets().len();
    // Without shadow maps: the shadow pass, where there is one, sets it again with them.
    let scene_digest = convert::scene_digest(&plan.scene_toml, &plan.scene_name, &plan.headers, None).to_vec();
    let mut driver = Driver {
        bands: Bands::<BandState>::new(h, band_rows, admission),
        band_tx: HashMap::new(),
        raster: Raster::new(w, h, plan.options.want_pfm),
        dispatch: Dispatch::new(plan.dataset_keys.clone()),
        plan,
        job: job.clone(),
        registry,
        config,
        events,
        batch_tasks,
        streams: Default::default(),
        opening: Vec::new(),
        next_serial: 0,
        scene_digest,
        shadow_maps: None,
        scene_on: HashSet::new(),
        stock: (0..datasets).map(|_| Stock::default()).collect(),
        active: BTreeSet::new(),
        tally: {
            let mut tally = Tally::new(metrics);
            tally.coordinator.intersection += counting_seconds;
            tally.stats.seconds.intersection += counting_seconds;
            tally
        },
    };
    job.update(|s| {
        s.state = pb::JobState::Running as i32;
        s.phase = pb::Phase::Intersection as i32;
        s.rows_total = h;
    });
    let deadline = tokio::time::Instant::now() + driver.config.job_deadline;
    let mut ends = Ends {
        cancelled: job.cancelled(),
        past_deadline: Box::pin(tokio::time::sleep_until(deadline)),
        job_deadline: driver.config.job_deadline,
    };
    // Shadows first (SPEC §6): the other objects' shares, from the workers. Then the bands.
    let outcome = match ends.guard(driver.shadow_pass()).await {
        Ok(()) => driver.cast(&mut inbox, &mut ends).await,
        Err(e) => Err(e),
    };
    // Closing every stream tells the workers to drop what they still hold for this job, and
    // gives back to their load counts, shared with other jobs, what this job still had out.
    let open: Vec<StreamKey> = driver.streams.keys().cloned().collect();
    for stream in &open {
        driver.lose_stream(stream, Rest::Job);
    }
    // Dropping the bands' senders ends their threads.
    driver.band_tx.clear();
    let outcome = match outcome {
        Ok(()) => {
            let job_deadline = driver.config.job_deadline;
            match tokio::time::timeout_at(deadline, driver.finish(started)).await {
                Ok(finished) => finished,
                Err(_) => Err(JobError::DeadlineExceeded { deadline: job_deadline }),
            }
        }
        Err(e) => Err(e),
    };
    if let Err(e) = outcome {
        let state = if e.is_cancel() { pb::JobState::Cancelled } else { pb::JobState::Failed };
        let failure = e.to_failure();
        tracing::warn!(reason = ?failure.reason(), message = %failure.message, "job ended");
        job.update(|s| {
            s.state = state as i32;
            s.failure = Some(failure);
        });
    }
}

/// What ends a job before its work does: a cancel, or its deadline.
struct Ends {
    cancelled: tokio::sync::watch::Receiver<bool>,
    past_deadline: std::pin::Pin<Box<tokio::time::Sleep>>,
    job_deadline: std::time::Duration,
}

impl Ends {
    /// Resolves when the job is cancelled or past its deadline, with that error.
    async fn reached(&mut self) -> JobError {
        tokio::select! {
            _ = self.cancelled.changed() => JobError::Cancelled,
            _ = &mut self.past_deadline => JobError::DeadlineExceeded { deadline: self.job_deadline },
        }
    }

    /// `work`, unless the job ends first.
    async fn guard(&mut self, work: impl std::future::Future<Output = Result<(), JobError>>) -> Result<(), JobError> {
        tokio::select! {
            done = work => done,
            ended = self.reached() => Err(ended),
        }
    }
}

impl Driver {
    fn scene(&self) -> &Arc<Scene> {
        &self.plan.scene
    }

    /// The job's event loop, from the first stream to the last band composited: bands
    /// started as admission allows, batches handed out as workers have room, and every
    /// event handled, until the job is done, fails, is cancelled or runs out of time.
    async fn cast(&mut self, inbox: &mut mpsc::Receiver<Event>, ends: &mut Ends) -> Result<(), JobError> {
        let mut tick = tokio::time::interval(self.config.tick);
        let mut room = self.registry.watch_room();
        self.open_early();
        loop {
            // Whatever room was freed before this point, the dispatch below sees.
            room.borrow_and_update();
            let step = Instant::now();
            let advanced = self.advance();
            self.tally.coordinator.event_loop += step.elapsed().as_secs_f64();
            advanced?;
            if self.bands.is_done() {
                return Ok(());
            }
            tokio::select! {
                event = inbox.recv() => {
                    let Some(event) = event else { return Err(JobError::Internal("the job's event channel closed".into())) };
                    let step = Instant::now();
                    let mut handled = self.handle(event);
                    // Take whatever else has arrived before dispatching again: one dispatch
                    // pass serves many answers when they come quickly.
                    while handled.is_ok() {
                        let Ok(event) = inbox.try_recv() else { break };
                        handled = self.handle(event);
                    }
                    self.tally.coordinator.event_loop += step.elapsed().as_secs_f64();
                    handled?;
                }
                // Another job's answer (or lost stream) freed room on a worker this job may use.
                _ = room.changed() => {}
                ended = ends.reached() => return Err(ended),
                _ = tick.tick() => {
                    let step = Instant::now();
                    self.check_workers();
                    self.tally.coordinator.event_loop += step.elapsed().as_secs_f64();
                }
            }
        }
    }

    /// Before any band has a batch: a stream to each worker that holds a dataset of the job
    /// (for its first such dataset, to the holder the policy picks), carrying the scene, so
    /// that workers parse the scene while the first bands are planned; the job's other
    /// streams to them then open by digest as soon as their batches are ready.
    fn open_early(&mut self) {
        self.dispatch.refresh(&self.registry, false);
        for d in self.scene().used_datasets() {
            let usable = |w: &WorkerHandle| !self.scene_on.contains(&w.id) && !self.scene_on_its_way(&w.id);
            if let Some(worker) = self.dispatch.pick(d, usable).cloned() {
                self.open(&worker, d);
            }
        }
    }

    /// Starts new bands while admission allows, then hands out every batch some worker has
    /// room for.
    fn advance(&mut self) -> Result<(), JobError> {
        while let Some((band, rows)) = self.bands.start_next() {
            let start = band::Start {
                band,
                rows,
                scene: self.scene().clone(),
                kept: self.plan.kept.get_mut(band).and_then(Option::take),
                batch_tasks: self.batch_tasks,
                want_pfm: self.plan.options.want_pfm,
                config: self.config.clone(),
            };
            self.band_tx.insert(band, band::spawn(start, self.events.clone()));
        }
        self.dispatch_ready()
    }

    /// Hands out ready batches to the least loaded holder of their dataset that has room,
    /// and asks bands for more where holders have room the stock does not fill.
    fn dispatch_ready(&mut self) -> Result<(), JobError> {
        self.dispatch.refresh(&self.registry, false);
        let active: Vec<usize> = self.active.iter().copied().collect();
        for d in active {
            if self.dispatch.is_orphaned(d) {
                return Err(JobError::NoHolder { dataset: self.scene().datasets()[d].name().to_string() });
            }
            loop {
                // A worker is usable for `d` unless its stream for `d` is opening, or it has
                // none and the scene is on its way to it on another stream: that one opens
                // once the scene is accepted, naming it by digest alone. Other holders take
                // `d` meanwhile, so a worker that is slow to accept holds nothing up.
                let usable = |w: &WorkerHandle| {
                    let opening = self.opening.iter().any(|((id, od), _)| *od == d && *id == w.id);
                    let waits_for_scene = !self.scene_on.contains(&w.id)
                        && self.scene_on_its_way(&w.id)
                        && !self.streams.contains_key(&(w.id.clone(), d));
                    !opening && !waits_for_scene
                };
                let Some(worker) = self.dispatch.pick(d, usable).cloned() else { break };
                if !self.streams.contains_key(&(worker.id.clone(), d)) {
                    // Its batches wait until the worker accepts the stream.
                    self.open(&worker, d);
                    continue;
                }
                let Some(ready) = self.stock[d].ready.pop_front() else { break };
                if ready.attempt >= self.config.max_attempts {
                    let dataset = self.scene().datasets()[d].name().to_string();
                    return Err(JobError::TooManyAttempts { dataset, attempts: ready.attempt });
                }
                self.send(d, worker, ready);
            }
            self.ask(d);
            let stock = &self.stock[d];
            if stock.ready.is_empty() && stock.bands.is_empty() {
                self.active.remove(&d);
            }
        }
        Ok(())
    }

    /// Asks the bands that may have batches of dataset `d` for as many as its holders have
    /// room for (and one per holder more, so that an answer finds the next batch waiting),
    /// less what is in stock or already asked for; earliest started band first, a share
    /// each, so that several bands' threads make them at once.
    fn ask(&mut self, d: usize) {
        let (room, holders) = self.dispatch.room(d);
        let stock = &mut self.stock[d];
        let asking = batches_to_ask(room, holders, stock.ready.len(), stock.asked(), stock.bands.len());
        let Some((mut want, share)) = asking else { return };
        while want > 0 {
            let Some((seq, band)) = stock.bands.pop_first() else { break };
            let n = share.min(want);
            let Some(tx) = self.band_tx.get(&band) else { continue };
            if tx.send(ToBand::Produce { dataset: d, n }).is_ok() {
                *stock.asked.entry(band).or_default() += n;
                want -= n;
            } else {
                tracing::trace!(band, seq, "band ended before it was asked");
            }
        }
    }

    /// Marks dataset `d` of band `band` as possibly ready.
    fn wake(&mut self, band: usize, d: usize) {
        if let Some((seq, _)) = self.bands.casting(band) {
            self.stock[d].bands.insert((seq, band));
            self.active.insert(d);
        }
    }

    /// Sends batch `ready` of dataset `d` to `worker`'s stream for it, which is open.
    fn send(&mut self, d: usize, worker: WorkerHandle, ready: Ready) {
        let key = (worker.id.clone(), d);
        // A place in the stream's queue first, so that a batch that cannot go stays whole.
        let Some(permit) = self.streams.get(&key).and_then(|s| s.tx.try_reserve().ok()) else {
            // The stream's reader is gone or its queue is full: the batch goes back to the
            // front of the stock, and the stream is lost.
            self.stock[d].ready.push_front(ready);
            self.active.insert(d);
            self.lose_stream(&key, self.rest_lost());
            return;
        };
        let wire = self.dispatch.next_wire();
        let Ready { band, id, attempt, tasks, encoded } = ready;
        let _span = tracing::debug_span!("batch", wire, dataset = d, attempt, worker = %worker.id, tasks).entered();
        let request = pb::CastRequest {
            kind: Some(pb::cast_request::Kind::Batch(pb::CastBatch {
                batch_id: wire,
                attempt,
                tasks: encoded.clone(),
            })),
        };
        self.tally.wire_to += request.encoded_len() as u64;
        permit.send(request);
        let in_flight = InFlight { band, id, dataset: d, attempt, stream: key, tasks, encoded, sent: Instant::now() };
        self.dispatch.sent(wire, &worker, in_flight);
        if self.tally.cast_started.is_none() {
            self.tally.cast_started = Some(Instant::now());
            self.job.update(|s| s.phase = pb::Phase::VolumeRendering as i32);
        }
    }

    /// Whether `serial` is the stream now open for `stream` (events of a lost one are not).
    fn is_current(&self, stream: &StreamKey, serial: u64) -> bool {
        self.streams.get(stream).is_some_and(|s| s.serial == serial)
    }

    /// The rest of a pair whose stream broke or went silent: as long as a silent worker
    /// takes to count as lost, so that a dead one is no longer a holder by then and a live
    /// one (its heartbeats kept coming) serves the job again.
    fn rest_lost(&self) -> Rest {
        Rest::Until(Instant::now() + self.registry.lost_after())
    }

    fn handle(&mut self, event: Event) -> Result<(), JobError> {
        match event {
            Event::Failed(e) => Err(e),
            Event::Band { band, news } => {
                self.heard(band, news);
                Ok(())
            }
            Event::Opened { stream, serial } => {
                if self.is_current(&stream, serial) {
                    self.opening.retain(|(k, _)| *k != stream);
                    if self.streams.get(&stream).is_some_and(|s| s.carries_scene) {
                        self.scene_on.insert(stream.0.clone());
                    }
                    // Batches of its dataset may go on it now.
                    self.active.insert(stream.1);
                }
                Ok(())
            }
            Event::Answer { stream, serial, response, bytes } => {
                self.tally.wire_from += bytes;
                if !self.is_current(&stream, serial) {
                    // A stream lost before: its batches were given back then.
                    return Ok(());
                }
                match response.kind {
                    Some(pb::cast_response::Kind::Result(result)) => {
                        self.answered(&stream, result);
                        Ok(())
                    }
                    Some(pb::cast_response::Kind::Failure(failure)) => self.failed(&stream, failure),
                    None => Ok(()),
                }
            }
            Event::StreamEnded { stream, serial, status } => {
                if !self.is_current(&stream, serial) {
                    return Ok(());
                }
                if let Some(failure) = status.as_ref().and_then(convert::status_failure) {
                    if !failure.retryable {
                        return Err(JobError::Worker { worker: stream.0.clone(), failure: Box::new(failure) });
                    }
                    if failure.reason() == pb::Reason::SceneUnknown {
                        // The worker no longer holds the scene (it restarted, or let it go):
                        // the stream opens again at once, carrying it.
                        tracing::debug!(worker = %stream.0, dataset = stream.1, "scene unknown; sending it again");
                        self.scene_on.remove(&stream.0);
                        self.lose_stream(&stream, Rest::Until(Instant::now()));
                        return Ok(());
                    }
                }
                let code = status.as_ref().map(|s| s.code());
                let rest = if code == Some(tonic::Code::ResourceExhausted) {
                    // The worker serves as many streams as it takes: ask again shortly.
                    tracing::debug!(worker = %stream.0, dataset = stream.1, "worker busy; asking again later");
                    Rest::Until(Instant::now() + self.registry.heartbeat())
                } else {
                    tracing::warn!(worker = %stream.0, dataset = stream.1, status = ?code, "stream ended");
                    self.rest_lost()
                };
                self.lose_stream(&stream, rest);
                Ok(())
            }
        }
    }

    /// What band `band`'s thread reports.
    fn heard(&mut self, band: usize, news: News) {
        match news {
            News::Intersected { datasets, bytes, progress, segments, pieces, seconds, planning } => {
                self.tally.stats.segments += segments;
                self.tally.stats.pieces += pieces;
                self.tally.stats.seconds.intersection += seconds;
                self.tally.coordinator.intersection += seconds - planning;
                self.tally.coordinator.planning += planning;
                self.job.update(|s| s.pieces_total += progress.total);
                self.bands.intersected(band, BandState { bytes, progress });
                for d in datasets {
                    self.wake(band, d);
                }
            }
            News::Produced { dataset, asked, batches, more, progress, seconds } => {
                self.progressed(band, progress, seconds);
                let stock = &mut self.stock[dataset];
                if let Some(left) = stock.asked.get_mut(&band) {
                    *left = left.saturating_sub(asked);
                    if *left == 0 {
                        stock.asked.remove(&band);
                    }
                }
                stock.ready.extend(batches);
                self.active.insert(dataset);
                if more {
                    self.wake(band, dataset);
                }
            }
            News::Refused { id, dataset, stream, why } => {
                // A worker that answers nonsense is not trusted with more of this job. The
                // band gave the batch back; the loop forgot it when it took the answer.
                tracing::warn!(band, id, worker = %stream.0, error = %why, "refused an answer");
                self.wake(band, dataset);
                self.lose_stream(&stream, Rest::Job);
            }
            News::Composited { part, progress, seconds } => {
                self.progressed(band, progress, seconds);
                self.band_tx.remove(&band);
                for stock in &mut self.stock {
                    stock.asked.remove(&band);
                }
                if self.bands.take_complete(band).is_none() {
                    tracing::error!(band, "a band composited before its every task was cast or culled");
                }
                self.raster.place(part.rows.start, &part.raster);
                self.bands.composited(band);
                self.tally.stats.samples_skipped += part.samples_skipped;
                self.tally.stats.seconds.composition += part.seconds;
                self.tally.coordinator.composition += part.seconds;
                let rows_done = self.bands.rows_done();
                self.job.update(|s| {
                    s.phase = pb::Phase::Composition as i32;
                    s.rows_done = rows_done;
                });
                self.tally.publish(&self.job, self.bands.tasks_done());
            }
        }
    }

    /// A band's progress and the time its thread took for it.
    fn progressed(&mut self, band: usize, progress: Progress, seconds: band::Seconds) {
        if let Some((_, state)) = self.bands.casting(band) {
            state.progress = progress;
        }
        let c = &mut self.tally.coordinator;
        c.dispatch += seconds.dispatch;
        c.encoding += seconds.encoding;
        c.decoding += seconds.decoding;
        c.recording += seconds.recording;
    }

    /// A batch's results: handed to its band's thread to decode and record. An answer to a
    /// batch given up, on another stream or for another attempt, is dropped.
    fn answered(&mut self, stream: &StreamKey, result: pb::BatchResult) {
        let worker = self.streams.get(stream).map(|s| s.worker.clone());
        let batch = match self.dispatch.answered(result.batch_id, result.attempt, stream, worker.as_ref()) {
            Ok(batch) => batch,
            Err(why) => {
                tracing::debug!(wire = result.batch_id, worker = %stream.0, ?why, "answer not taken; dropped");
                return;
            }
        };
        self.registry.room_freed();
        self.active.insert(batch.dataset);
        self.tally.answered(&stream.0, batch.tasks, batch.sent.elapsed(), &result);
        if let Some(tx) = self.band_tx.get(&batch.band) {
            let (id, dataset, stream, results) = (batch.id, batch.dataset, stream.clone(), result.results);
            if tx.send(ToBand::Answer { id, dataset, stream, results }).is_ok() {
                // Once recorded, the answer may let the band hand out more of the dataset:
                // asked from now on, the band finds it recorded (it takes its messages in
                // order), so it says nothing back.
                self.wake(batch.band, batch.dataset);
            }
        }
    }

    /// A worker's failure report: a batch it cannot cast, or the stream as a whole.
    fn failed(&mut self, stream: &StreamKey, failure: pb::Failure) -> Result<(), JobError> {
        if failure.reason() == pb::Reason::Busy {
            self.busy(stream, failure.batch_id);
            return Ok(());
        }
        if !failure.retryable {
            return Err(JobError::Worker { worker: stream.0.clone(), failure: Box::new(failure) });
        }
        tracing::warn!(worker = %stream.0, reason = ?failure.reason(), message = %failure.message, "worker failed a batch; retrying elsewhere");
        self.lose_stream(stream, Rest::Job);
        Ok(())
    }

    /// Batch `wire`, refused by the worker of `stream` as busy (other coordinators' or jobs'
    /// batches fill it): back to the front of its dataset's stock as it was, attempt unspent,
    /// for a holder with room — this worker once it has answered one of this job's batches.
    fn busy(&mut self, stream: &StreamKey, wire: u64) {
        let worker = self.streams.get(stream).map(|s| s.worker.clone());
        let batch = match self.dispatch.refused(wire, stream, worker.as_ref()) {
            Ok(batch) => batch,
            Err(why) => {
                tracing::debug!(wire, worker = %stream.0, ?why, "busy refusal of a batch not in flight; ignored");
                return;
            }
        };
        tracing::debug!(wire, worker = %stream.0, dataset = batch.dataset, "worker busy; the batch goes again");
        self.tally.refused += 1;
        let InFlight { band, id, dataset, attempt, tasks, encoded, .. } = batch;
        self.stock[dataset].ready.push_front(Ready { band, id, attempt, tasks, encoded });
        self.active.insert(dataset);
    }

    /// Stops using `stream` for this job, for `rest`: its batches go back to their bands,
    /// to be handed to another holder.
    fn lose_stream(&mut self, stream: &StreamKey, rest: Rest) {
        let worker = self.streams.remove(stream).map(|s| s.worker);
        self.opening.retain(|(k, _)| k != stream);
        let lost = self.dispatch.lose(stream, worker.as_ref(), rest);
        if !lost.is_empty() {
            self.registry.room_freed();
        }
        let mut by_band: BTreeMap<usize, Vec<u64>> = BTreeMap::new();
        for batch in &lost {
            by_band.entry(batch.band).or_default().push(batch.id);
        }
        for (band, ids) in by_band {
            if let Some(tx) = self.band_tx.get(&band) {
                let _ = tx.send(ToBand::Abandon { ids });
            }
        }
        for batch in lost {
            self.wake(batch.band, batch.dataset);
        }
    }

    /// The tick: gives up on workers that missed their heartbeats and on batches past their
    /// deadline, looks holders up again (heartbeats age without the registry changing), and
    /// publishes the job's progress.
    fn check_workers(&mut self) {
        let mut lost = self.dispatch.overdue(self.config.batch_deadline);
        lost.extend(self.streams.keys().filter(|(w, _)| !self.registry.is_alive(w)).cloned());
        let deadline = self.config.batch_deadline;
        lost.extend(self.opening.iter().filter(|(_, since)| since.elapsed() > deadline).map(|(k, _)| k.clone()));
        for stream in lost {
            tracing::warn!(worker = %stream.0, dataset = stream.1, "worker silent; its batches go elsewhere");
            let rest = self.rest_lost();
            self.lose_stream(&stream, rest);
        }
        self.dispatch.refresh(&self.registry, true);
        // A worker that joined, or one that freed room for another job, may take batches
        // that no holder had room for.
        for d in 0..self.stock.len() {
            if !self.stock[d].ready.is_empty() || !self.stock[d].bands.is_empty() {
                self.active.insert(d);
            }
        }
        self.tally.publish(&self.job, self.bands.tasks_done());
    }

    /// Encodes the image and statistics and marks the job succeeded.
    async fn finish(self, started: Instant) -> Result<(), JobError> {
        self.job.update(|s| s.phase = pb::Phase::Encoding as i32);
        let Driver { plan, job, bands, raster, mut tally, config, .. } = self;
        if let Some(cast) = tally.cast_started {
            tally.stats.seconds.volume_rendering =
                (cast.elapsed().as_secs_f64() - tally.stats.seconds.composition).max(0.0);
        }
        let h = plan.scene.image().height;
        let tasks = bands.tasks_composited();
        let encoded = tokio::task::spawn_blocking(move || {
            unwinding("encoding", || {
                config.inject("encoding");
                let started = Instant::now();
                let png = raster.encode_png();
                let pfm = raster.encode_pfm();
                (png, pfm, started.elapsed().as_secs_f64())
            })
        })
        .await
        .map_err(|e| JobError::Internal(format!("encoding the image: {e}")))??;
        tally.coordinator.image_encoding += encoded.2;
        let png = encoded.0.map_err(JobError::Encode)?;
        let pfm = encoded.1;
        let mut stats = std::mem::take(&mut tally.stats);
        stats.effects = ObjectEffects::listed(&plan.scene, Some(0));
        ObjectEffects::add(&mut stats.effects, &tally.shaded);
        stats.finish(&plan.scene, Algorithm::Grouped, &tally.store, None, started.elapsed().as_secs_f64());
        let stats_json = tally.into_stats(stats).to_json();
        job.set_output(JobOutput { png, pfm, stats_json });
        job.update(|s| {
            s.state = pb::JobState::Succeeded as i32;
            s.phase = pb::Phase::Done as i32;
            s.pieces_done = tasks;
            s.rows_done = h;
        });
        tracing::info!(seconds = started.elapsed().as_secs_f64(), "job succeeded");
        Ok(())
    }
}
