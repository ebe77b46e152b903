//! The discrete-event model of farm jobs, following `coordinator/src/farm/driver/` and
//! `worker/src/cast.rs` step by step, with each coordinator stage's cost and place read from
//! the recorded inputs (the job's event loop, a band's own thread, or the other threads):
//!
//! * **Bands.** The image is worked through in bands of rows started in bit-reversed order
//!   (`trove_core::render::dispatch::band_order`), as many at once as
//!   `trove_core::render::dispatch::Admission` admits: at most `max_bands`, and their
//!   schedulers' bytes within `memory_bound`, a band not yet intersected counted as large as
//!   the largest so far (a fair share of the bound before any) — `render/bands.rs`.
//! * **A thread per band** (`driver/band.rs`). Each band in flight has a thread of its own
//!   that owns its scheduler and does, one step at a time, every per-task step: it
//!   intersects the band (the stages placed [`RunsOn::Parallel`] at [`At::Intersect`], over
//!   the coordinator's cores, one work item per 4 rows) and plans it ([`RunsOn::Band`]);
//!   when the loop asks it for up to `n` batches of a dataset, it hands out what the
//!   scheduler has ready (`next_batch`: the dataset's current wave, batch by batch; its next
//!   wave only once every batch of this one is recorded) and pays the [`At::Send`] stages
//!   on [`RunsOn::Band`] per task; for each answer the loop forwards it pays the
//!   [`At::Answer`] stages on [`RunsOn::Band`] and records it; once every task is recorded it
//!   composites the band (parallel part, then its own part) and reads no more messages. Its
//!   steps are serial; the threads of the bands in flight run side by side on the
//!   coordinator's cores, with rayon's work and the transport.
//! * **The job's event loop** handles one event at a time — news from a band (intersected,
//!   batches produced, an answer recorded, composited), a stream accepted, an answer —
//!   paying only the stages placed on [`RunsOn::EventLoop`] (per batch sent, per answer
//!   taken). It keeps per dataset a stock of the batches bands produced, and for each dataset
//!   that may have work (in dataset order) sends its stock to the least-loaded holder with
//!   room (`trove_core::render::dispatch::least_loaded`, holders kept per job; a holder
//!   without a stream is first sent the scene, and its batches wait until it has parsed it
//!   and accepted the stream); then asks the bands that may have batches of it for
//!   `room + holders − stock − asked` more (`room` from `dispatch::capacity`), earliest
//!   started band first, a share each. A band is asked again when it produced all it was
//!   asked for, or recorded an answer. So a batch goes out only after its band's thread
//!   produced it, and a dataset's next wave waits until its band's thread recorded the last
//!   answer of the previous one. Work placed [`RunsOn::Parallel`] or [`RunsOn::OneThread`]
//!   at a send or an answer (`transport`) loads the coordinator's cores without delaying
//!   anything.
//! * **Workers.** Each holds some datasets ([`super::placement`]). A worker has one stream
//!   per job and dataset: the dataset is loaded once and stays resident, its objects bound
//!   the first time through the store (cells classified and kept) and again, cheaply,
//!   whenever the stream starts after running dry; its batches are cast one after the other,
//!   each over the worker's threads in chunks of 256 tasks.
//! * **Network.** Every machine has a link each way; messages queue on the sender's link and
//!   the receiver's, one after the other, with a one-way latency between.
//!
//! A coordinator of `coordinator_cores` cores runs its event loop on one of them and
//! everything else (the bands' threads, rayon's work, the transport, the image's encoding)
//! on the others, older work first ([`Pool`]).
//!
//! **Layouts.** `coordinators` coordinators of `coordinator_cores` cores each share the
//! workers, each counting only its own batches in flight (each has its own registry): with
//! [`Split::Tiles`] they split one image into tiles of whole bands, one job each; with
//! [`Split::Jobs`] each runs a whole job of its own (the same scene), side by side — the
//! layout the farm runs (`trove-worker --coordinator A,B,…`). A simulated worker queues all
//! its coordinators send; a real one refuses beyond `--max-batches` a job over its fair
//! share as busy (`dispatch::admits`), which is not modelled: every [`Load`] here has
//! `refused: false`.

use std::cmp::Ordering;
use std::collections::{BTreeMap, BTreeSet, BinaryHeap, HashMap, HashSet, VecDeque};

use trove_core::render::dispatch::{band_order, batches_to_ask, capacity, least_loaded, Admission, Load};

use super::inputs::{Inputs, TASK_BYTES_BACK, TASK_BYTES_OUT};
use super::pool::{transfer, Link, Pool};
use super::recorded::{At, RunsOn};
use super::workload::{Lane, Workload};

/// Tasks per rayon work item in a worker's batch (`CHUNK_TASKS` in `worker/src/cast.rs`).
const CHUNK_TASKS: u64 = 256;
/// Image rows per parallel work item of the intersection (`BAND_ROWS` in
/// `trove-core/src/render/intersection.rs`).
const INTERSECT_ROWS: u64 = 4;
/// Bytes of the small messages: a stream accepted.
const SMALL_MESSAGE: f64 = 16.0;

/// How several coordinators share the work.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Split {
    /// Each owns a tile of whole bands of one image.
    Tiles,
    /// Each owns a whole job of its own.
    Jobs,
}

/// The farm being simulated.
#[derive(Clone, Debug)]
pub(crate) struct FarmConfig {
    /// Worker machines.
    pub workers: usize,
    /// Cores (rayon threads) per worker.
    pub worker_threads: usize,
    /// Cores of each coordinator: the job's event loop runs on one; the bands' threads,
    /// rayon's work and the transport share the rest (one at least).
    pub coordinator_cores: usize,
    /// Coordinators sharing the workers.
    pub coordinators: usize,
    pub split: Split,
    /// Tasks per batch (the job's `batch_tasks`; the driver's default is 4096).
    pub batch_tasks: u64,
    /// Bands a job holds at once at most (`DriverConfig::max_bands`).
    pub max_bands: usize,
    /// Bytes of band bookkeeping a job holds at once at most (`DriverConfig::memory_bound`).
    pub memory_bound: u64,
}

/// What a simulated run took.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Outcome {
    /// Wall time, start to the last job's encoded image.
    pub seconds: f64,
    /// The busiest event loop: busy time / run time.
    pub loop_busy: f64,
    /// Event-loop seconds over all coordinators: sending batches, taking answers, the rest.
    pub loop_send: f64,
    pub loop_answer: f64,
    pub loop_other: f64,
    /// The bands' threads: the time they had a step running or waiting for a core over the
    /// time their bands were held, on the coordinator where that is highest. Near 1, the
    /// bands in flight are each as busy as one thread can be.
    pub band_busy: f64,
    /// Core-seconds of the bands' threads over all coordinators: handing out batches
    /// (fronts, culls, encoding), taking answers (decoding, recording), the rest
    /// (intersection, planning, composition).
    pub band_send: f64,
    pub band_answer: f64,
    pub band_other: f64,
    /// The busiest coordinator's other cores: core-seconds / (cores × run time).
    pub pool_busy: f64,
    /// The busiest coordinator link (either direction): busy time / run time.
    pub link_busy: f64,
    /// The largest fraction of the run during which a coordinator had no band being cast.
    pub no_band_cast: f64,
    /// Mean bands a coordinator held at once, over the run.
    pub bands_held: f64,
    /// Workers' core-seconds / (threads × run time): the mean and the busiest worker's.
    pub worker_mean: f64,
    pub worker_max: f64,
    /// Core-seconds workers spent casting, and loading.
    pub cast: f64,
    pub load: f64,
    /// Batches sent.
    pub batches: u64,
}

/// Simulates `work` on the farm `config` whose datasets are held by `holders` (per
/// dataset, its workers), with the costs `inputs`.
pub(crate) fn simulate(work: &Workload, inputs: &Inputs, config: &FarmConfig, holders: &[Vec<usize>]) -> Outcome {
    let mut sim = Sim::new(work, inputs, config, holders);
    sim.run();
    sim.outcome()
}

#[derive(Debug)]
struct Event {
    time: f64,
    seq: u64,
    kind: EventKind,
}

impl PartialEq for Event {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}
impl Eq for Event {}
impl PartialOrd for Event {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Event {
    /// Reversed, so that the heap pops the earliest event; ties go in the order scheduled.
    fn cmp(&self, other: &Self) -> Ordering {
        other.time.total_cmp(&self.time).then(other.seq.cmp(&self.seq))
    }
}

#[derive(Debug)]
enum EventKind {
    /// A coordinator's event loop takes its next event.
    LoopRun(usize),
    /// Band `.1`'s thread on coordinator `.0` takes its next step if it is idle.
    BandRun(usize, usize),
    /// The image's encoding starts on a coordinator's other cores.
    Finish(usize),
    /// Pool completion checks, valid while the pool's version is unchanged.
    CoordPool(usize, u64),
    WorkerPool(usize, u64),
    /// A stream's scene reaches worker `.0` from coordinator `.1` for dataset `.2`.
    OpenArrives(usize, usize, usize),
    /// Worker `.1`'s acceptance of its stream for dataset `.2` reaches coordinator `.0`.
    OpenedArrives(usize, usize, usize),
    /// A batch reaches its worker.
    BatchArrives(usize),
    /// A batch's answer reaches its coordinator.
    AnswerArrives(usize),
}

/// A batch a band's thread handed out, in its dataset's stock until it is sent.
#[derive(Clone, Copy, Debug)]
struct Made {
    band: usize,
    lane: usize,
    tasks: u64,
    samples: u64,
}

/// What a coordinator's event loop handles (`driver/mod.rs`' `Event`, a band's `News`).
#[derive(Debug)]
enum LoopEvent {
    Start,
    /// Band `.0` is intersected and planned.
    Intersected(usize),
    /// Batches of `dataset` a band was asked for: as many as were ready, up to `asked`.
    Produced {
        band: usize,
        dataset: usize,
        asked: usize,
        batches: Vec<Made>,
        more: bool,
    },
    Composited(usize),
    Opened(usize, usize),
    Answer(usize),
}

/// What a band's thread does next (`driver/band.rs`: its own phases, and `ToBand`).
#[derive(Clone, Copy, Debug)]
enum BandStep {
    /// The stages at [`At::Intersect`]: the parallel part, then the band's own.
    Intersect,
    Plan,
    /// `ToBand::Produce`.
    Produce {
        dataset: usize,
        n: usize,
    },
    /// `ToBand::Answer` for batch `.0`.
    Answer(usize),
    /// The stages at [`At::Composite`], likewise.
    Composite,
    CompositeOne,
}

#[derive(Clone, Copy, Debug)]
enum CoordJob {
    /// The step band `.0`'s thread is running.
    Band(usize),
    /// The stages at [`At::Finish`].
    Finish,
    /// Work for a batch sent or answered that nothing waits for: it loads the cores.
    Background,
}

#[derive(Clone, Copy, Debug)]
enum WorkerJob {
    Parse(usize, usize),
    Load(usize),
    Bind(StreamKey),
    Cast(usize),
}

/// A worker's stream: (coordinator, dataset).
type StreamKey = (usize, usize);

struct Batch {
    shard: usize,
    band: usize,
    lane: usize,
    worker: usize,
    tasks: u64,
    samples: u64,
}

/// A dataset's lane of a band's scheduler: the wave it is in, the tasks of that wave
/// handed out, its batches not yet recorded.
#[derive(Clone, Debug, Default)]
struct LaneState {
    wave: usize,
    handed: u64,
    outstanding: usize,
}

impl LaneState {
    /// `Scheduler::next_batch` on this lane: up to `batch_tasks` tasks of the current wave
    /// (as tasks, samples), moving on to the next wave once this one is handed out and
    /// recorded; `None` when the wave waits for answers or the lane is done.
    fn next_batch(&mut self, spec: &Lane, batch_tasks: u64) -> Option<(u64, u64)> {
        loop {
            let wave = *spec.waves.get(self.wave)?;
            if self.handed < wave.tasks {
                let tasks = batch_tasks.min(wave.tasks - self.handed);
                // The wave's samples, shared out in proportion to tasks, summing exactly.
                let share = |n: u64| (wave.samples as u128 * n as u128 / wave.tasks as u128) as u64;
                let samples = share(self.handed + tasks) - share(self.handed);
                self.handed += tasks;
                self.outstanding += 1;
                return Some((tasks, samples));
            }
            if self.outstanding > 0 {
                return None;
            }
            self.wave += 1;
            self.handed = 0;
        }
    }

    /// Records one answer; whether the lane is done (its last wave handed out and recorded).
    fn record(&mut self, spec: &Lane) -> bool {
        self.outstanding -= 1;
        self.outstanding == 0
            && self.wave + 1 >= spec.waves.len()
            && spec.waves.get(self.wave).is_none_or(|w| self.handed == w.tasks)
    }
}

/// A band's thread and the scheduler it owns.
struct BandThread {
    lanes: Vec<LaneState>,
    /// Lanes not yet done.
    unfinished: usize,
    /// Its own next phases, then the loop's messages, in order.
    inbox: VecDeque<BandStep>,
    /// Whether a [`EventKind::BandRun`] is due.
    scheduled: bool,
    /// The step running on the cores, with what it tells the loop when done.
    running: Option<Option<LoopEvent>>,
    /// Every task recorded: it composites and reads no more messages.
    complete: bool,
    /// Composited: its inbox is gone (sending to it fails).
    ended: bool,
}

/// Per dataset, what the loop keeps (`driver/mod.rs`' `Stock`).
#[derive(Default)]
struct Stock {
    /// Batches bands handed out, not yet sent.
    ready: VecDeque<Made>,
    /// (start order, band) of the bands that may have batches of it.
    bands: BTreeSet<(usize, usize)>,
    /// Batches asked of each band and not yet produced.
    asked: BTreeMap<usize, usize>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum StreamState {
    Opening,
    Open,
}

/// One coordinator and its job (its tile of the image, or a whole job).
struct Shard {
    /// Its bands in the order they start.
    bands: Vec<usize>,
    next: usize,
    /// The bands held, as the loop sees them: started, and whether intersected (casting).
    active: BTreeMap<usize, bool>,
    /// The bands' threads, until the loop hears they composited.
    threads: BTreeMap<usize, BandThread>,
    /// Per band of the image: its start order, once started.
    seq: Vec<usize>,
    /// Per dataset.
    stock: Vec<Stock>,
    /// Datasets that may have batches to send or to ask for (`driver/mod.rs`' `active`).
    datasets: BTreeSet<usize>,
    held: u64,
    largest: u64,
    inbox: VecDeque<LoopEvent>,
    busy_until: f64,
    scheduled: bool,
    loop_send: f64,
    loop_answer: f64,
    loop_other: f64,
    band_send: f64,
    band_answer: f64,
    band_other: f64,
    /// Bands' threads with a step running, ∫ of that dt, and when it last changed.
    busy_threads: usize,
    busy_time: f64,
    busy_change: f64,
    pool: Pool<CoordJob>,
    out: Link,
    into: Link,
    /// Per worker: this coordinator's batches in flight.
    in_flight: Vec<usize>,
    streams: HashMap<(usize, usize), StreamState>,
    pixels: u64,
    idle_since: Option<f64>,
    no_band_cast: f64,
    /// ∫ bands held dt.
    held_time: f64,
    last_change: f64,
    finished: Option<f64>,
}

#[derive(Default)]
struct Stream {
    /// Batches received and not yet answered, oldest first.
    queue: VecDeque<usize>,
    /// Whether the stream's thread is working (loading, binding or casting).
    running: bool,
}

#[derive(PartialEq)]
enum Residency {
    Loading(Vec<StreamKey>),
    Resident,
}

struct Worker {
    pool: Pool<WorkerJob>,
    out: Link,
    into: Link,
    streams: HashMap<StreamKey, Stream>,
    datasets: HashMap<usize, Residency>,
    /// Datasets whose cells the store has classified.
    bound: HashSet<usize>,
    cast: f64,
    load: f64,
}

struct Sim<'a> {
    work: &'a Workload,
    inputs: &'a Inputs,
    config: &'a FarmConfig,
    holders: &'a [Vec<usize>],
    admission: Admission,
    now: f64,
    seq: u64,
    queue: BinaryHeap<Event>,
    shards: Vec<Shard>,
    workers: Vec<Worker>,
    batches: Vec<Batch>,
    /// Bytes of the `open` message: the scene's text and the headers of its files.
    scene_bytes: f64,
}

impl<'a> Sim<'a> {
    fn new(work: &'a Workload, inputs: &'a Inputs, config: &'a FarmConfig, holders: &'a [Vec<usize>]) -> Sim<'a> {
        let n = work.bands.len();
        let k = match config.split {
            Split::Tiles => config.coordinators.clamp(1, n.max(1)),
            Split::Jobs => config.coordinators.max(1),
        };
        let shards = (0..k)
            .map(|s| {
                let tile: Vec<usize> = match config.split {
                    Split::Tiles => (s * n / k..(s + 1) * n / k).collect(),
                    Split::Jobs => (0..n).collect(),
                };
                let pixels = tile.iter().map(|&b| work.bands[b].rays).sum();
                Shard::new(config, tile, n, work.datasets, pixels)
            })
            .collect();
        let workers = (0..config.workers)
            .map(|_| Worker {
                pool: Pool::new(config.worker_threads as f64),
                out: Link::default(),
                into: Link::default(),
                streams: HashMap::new(),
                datasets: HashMap::new(),
                bound: HashSet::new(),
                cast: 0.0,
                load: 0.0,
            })
            .collect();
        Sim {
            work,
            inputs,
            config,
            holders,
            admission: Admission { max_bands: config.max_bands.max(1), memory_bound: config.memory_bound },
            now: 0.0,
            seq: 0,
            queue: BinaryHeap::new(),
            shards,
            workers,
            batches: Vec::new(),
            scene_bytes: work.scene_bytes as f64,
        }
    }

    fn at(&mut self, time: f64, kind: EventKind) {
        self.seq += 1;
        self.queue.push(Event { time, seq: self.seq, kind });
    }

    fn run(&mut self) {
        for s in 0..self.shards.len() {
            self.wake_loop(s);
        }
        while let Some(event) = self.queue.pop() {
            self.now = event.time;
            match event.kind {
                EventKind::LoopRun(s) => self.loop_run(s),
                EventKind::BandRun(s, b) => self.band_run(s, b),
                EventKind::Finish(s) => self.finish(s),
                EventKind::CoordPool(s, v) if v == self.shards[s].pool.version => self.coord_pool(s),
                EventKind::WorkerPool(w, v) if v == self.workers[w].pool.version => self.worker_pool(w),
                EventKind::CoordPool(..) | EventKind::WorkerPool(..) => {}
                EventKind::OpenArrives(w, s, d) => {
                    let work = self.work.objects as f64 * self.inputs.parse_per_object;
                    self.worker_job(w, WorkerJob::Parse(s, d), work, 1.0);
                }
                EventKind::OpenedArrives(s, w, d) => self.post(s, LoopEvent::Opened(w, d)),
                EventKind::BatchArrives(b) => self.batch_arrives(b),
                EventKind::AnswerArrives(b) => {
                    let s = self.batches[b].shard;
                    self.post(s, LoopEvent::Answer(b));
                }
            }
        }
    }

    /// Hands `event` to coordinator `s`'s loop.
    fn post(&mut self, s: usize, event: LoopEvent) {
        self.shards[s].inbox.push_back(event);
        self.wake_loop(s);
    }

    /// Makes sure coordinator `s`'s loop will take its next event.
    fn wake_loop(&mut self, s: usize) {
        let shard = &mut self.shards[s];
        if !shard.scheduled && !shard.inbox.is_empty() {
            shard.scheduled = true;
            let t = shard.busy_until.max(self.now);
            self.at(t, EventKind::LoopRun(s));
        }
    }

    fn outcome(&self) -> Outcome {
        let seconds = self.shards.iter().filter_map(|s| s.finished).fold(0.0, f64::max);
        let t = seconds.max(1e-12);
        let threads = self.config.worker_threads as f64;
        let worker_busy: Vec<f64> = self.workers.iter().map(|w| w.pool.busy / (threads * t)).collect();
        let loop_total = |s: &Shard| s.loop_send + s.loop_answer + s.loop_other;
        Outcome {
            seconds,
            loop_busy: self.shards.iter().map(|s| loop_total(s) / t).fold(0.0, f64::max),
            loop_send: self.shards.iter().map(|s| s.loop_send).sum(),
            loop_answer: self.shards.iter().map(|s| s.loop_answer).sum(),
            loop_other: self.shards.iter().map(|s| s.loop_other).sum(),
            band_busy: self.shards.iter().map(|s| s.busy_time / s.held_time.max(1e-12)).fold(0.0, f64::max),
            band_send: self.shards.iter().map(|s| s.band_send).sum(),
            band_answer: self.shards.iter().map(|s| s.band_answer).sum(),
            band_other: self.shards.iter().map(|s| s.band_other).sum(),
            pool_busy: self.shards.iter().map(|s| s.pool.busy / (s.pool.capacity() * t)).fold(0.0, f64::max),
            link_busy: self.shards.iter().map(|s| s.out.busy.max(s.into.busy) / t).fold(0.0, f64::max),
            no_band_cast: self.shards.iter().map(|s| s.no_band_cast / t).fold(0.0, f64::max),
            bands_held: self.shards.iter().map(|s| s.held_time / s.finished.unwrap_or(t).max(1e-12)).sum::<f64>()
                / self.shards.len().max(1) as f64,
            worker_mean: worker_busy.iter().sum::<f64>() / worker_busy.len().max(1) as f64,
            worker_max: worker_busy.iter().copied().fold(0.0, f64::max),
            cast: self.workers.iter().map(|w| w.cast).sum(),
            load: self.workers.iter().map(|w| w.load).sum(),
            batches: self.batches.len() as u64,
        }
    }
}

impl Shard {
    /// A coordinator of an image of `bands` bands and `datasets` datasets that works
    /// through `tile` (its bands, `pixels` pixels) in the driver's spread order.
    fn new(config: &FarmConfig, tile: Vec<usize>, bands: usize, datasets: usize, pixels: u64) -> Shard {
        let order: Vec<usize> = band_order(tile.len()).into_iter().map(|i| tile[i]).collect();
        Shard {
            bands: order,
            next: 0,
            active: BTreeMap::new(),
            threads: BTreeMap::new(),
            seq: vec![usize::MAX; bands],
            stock: (0..datasets).map(|_| Stock::default()).collect(),
            datasets: BTreeSet::new(),
            held: 0,
            largest: 0,
            inbox: VecDeque::from([LoopEvent::Start]),
            busy_until: 0.0,
            scheduled: false,
            loop_send: 0.0,
            loop_answer: 0.0,
            loop_other: 0.0,
            band_send: 0.0,
            band_answer: 0.0,
            band_other: 0.0,
            busy_threads: 0,
            busy_time: 0.0,
            busy_change: 0.0,
            pool: Pool::new(config.coordinator_cores.saturating_sub(1).max(1) as f64),
            out: Link::default(),
            into: Link::default(),
            in_flight: vec![0; config.workers],
            streams: HashMap::new(),
            pixels,
            idle_since: Some(0.0),
            no_band_cast: 0.0,
            held_time: 0.0,
            last_change: 0.0,
            finished: None,
        }
    }

    /// Keeps the time integral of the bands held up to `now`.
    fn note_held(&mut self, now: f64) {
        self.held_time += self.active.len() as f64 * (now - self.last_change).max(0.0);
        self.last_change = self.last_change.max(now);
    }

    /// Keeps the time integral of the bands' threads busy up to `now`.
    fn note_busy(&mut self, now: f64) {
        self.busy_time += self.busy_threads as f64 * (now - self.busy_change).max(0.0);
        self.busy_change = self.busy_change.max(now);
    }
}

/// Where an event-loop cost is counted.
#[derive(Clone, Copy)]
enum Part {
    Send,
    Answer,
    Other,
}

/// The coordinator's event loop.
impl Sim<'_> {
    /// Handles the next event of coordinator `s`'s loop, charging its cost from now on.
    fn loop_run(&mut self, s: usize) {
        self.shards[s].scheduled = false;
        let Some(event) = self.shards[s].inbox.pop_front() else { return };
        let mut clock = self.now;
        match event {
            LoopEvent::Start => {}
            LoopEvent::Intersected(b) => self.intersected(s, b, &mut clock),
            LoopEvent::Produced { band, dataset, asked, batches, more } => {
                let shard = &mut self.shards[s];
                let stock = &mut shard.stock[dataset];
                if let Some(left) = stock.asked.get_mut(&band) {
                    *left = left.saturating_sub(asked);
                    if *left == 0 {
                        stock.asked.remove(&band);
                    }
                }
                stock.ready.extend(batches);
                shard.datasets.insert(dataset);
                if more {
                    self.wake(s, band, dataset);
                }
            }
            LoopEvent::Composited(b) => {
                let pieces = self.work.bands[b].pieces as f64;
                self.charge(s, &mut clock, Part::Other, pieces * self.inputs.cost(At::Composite, RunsOn::EventLoop));
                let shard = &mut self.shards[s];
                shard.note_held(clock);
                shard.active.remove(&b);
                shard.threads.remove(&b);
                shard.stock.iter_mut().for_each(|stock| {
                    stock.asked.remove(&b);
                });
                shard.held -= self.work.bands[b].bytes;
            }
            LoopEvent::Opened(w, d) => {
                self.shards[s].streams.insert((w, d), StreamState::Open);
                self.shards[s].datasets.insert(d);
            }
            LoopEvent::Answer(id) => self.answered(s, id, &mut clock),
        }
        self.advance(s, &mut clock);
        let shard = &mut self.shards[s];
        if shard.finished.is_none() && shard.next == shard.bands.len() && shard.active.is_empty() {
            shard.finished = Some(f64::INFINITY);
            if let Some(since) = shard.idle_since.take() {
                shard.no_band_cast += clock - since;
            }
            let pixels = shard.pixels as f64;
            self.charge(s, &mut clock, Part::Other, pixels * self.inputs.cost(At::Finish, RunsOn::EventLoop));
            self.at(clock, EventKind::Finish(s));
        }
        self.note_bands(s, clock);
        self.shards[s].busy_until = clock;
        self.wake_loop(s);
    }

    /// Keeps count of the time coordinator `s` has no band being cast.
    fn note_bands(&mut self, s: usize, clock: f64) {
        let shard = &mut self.shards[s];
        let casting = shard.active.values().any(|&intersected| intersected);
        match (casting, shard.idle_since) {
            (true, Some(since)) => {
                shard.no_band_cast += clock - since;
                shard.idle_since = None;
            }
            (false, None) if shard.finished.is_none() => shard.idle_since = Some(clock),
            _ => {}
        }
    }

    /// Spends `seconds` of coordinator `s`'s loop.
    fn charge(&mut self, s: usize, clock: &mut f64, part: Part, seconds: f64) {
        let shard = &mut self.shards[s];
        match part {
            Part::Send => shard.loop_send += seconds,
            Part::Answer => shard.loop_answer += seconds,
            Part::Other => shard.loop_other += seconds,
        }
        *clock += seconds;
    }

    /// Work off the loop that nothing waits for: it takes one core of the coordinator's
    /// others while it runs.
    fn background(&mut self, s: usize, clock: f64, seconds: f64) {
        if seconds > 0.0 {
            self.shards[s].pool.add(clock.max(self.now), CoordJob::Background, seconds, 1.0);
            self.check_coord_pool(s);
        }
    }

    fn intersected(&mut self, s: usize, b: usize, clock: &mut f64) {
        let band = &self.work.bands[b];
        self.charge(s, clock, Part::Other, band.pieces as f64 * self.inputs.cost(At::Intersect, RunsOn::EventLoop));
        let shard = &mut self.shards[s];
        shard.held += band.bytes;
        shard.largest = shard.largest.max(band.bytes);
        shard.active.insert(b, true);
        for lane in &band.lanes {
            self.wake(s, b, lane.dataset);
        }
    }

    /// The driver's `wake`: dataset `d` of band `b` may have batches, if the band is being
    /// cast.
    fn wake(&mut self, s: usize, b: usize, d: usize) {
        let shard = &mut self.shards[s];
        if shard.active.get(&b) == Some(&true) {
            shard.stock[d].bands.insert((shard.seq[b], b));
            shard.datasets.insert(d);
        }
    }

    /// The driver's `answered`: the batch's worker has room again, the answer goes to its
    /// band's thread, and the band's dataset may have batches again once it is recorded
    /// (the band takes its messages in order, so a `Produce` after it finds it recorded).
    fn answered(&mut self, s: usize, id: usize, clock: &mut f64) {
        let (band, lane, worker, tasks) = {
            let b = &self.batches[id];
            (b.band, b.lane, b.worker, b.tasks)
        };
        self.shards[s].in_flight[worker] -= 1;
        let i = self.inputs;
        self.charge(s, clock, Part::Answer, tasks as f64 * i.cost(At::Answer, RunsOn::EventLoop));
        let off = i.cost(At::Answer, RunsOn::Parallel) + i.cost(At::Answer, RunsOn::OneThread);
        self.background(s, *clock, tasks as f64 * off);
        let d = self.work.bands[band].lanes[lane].dataset;
        self.shards[s].datasets.insert(d);
        self.tell_band(s, band, BandStep::Answer(id), *clock);
        self.wake(s, band, d);
    }

    /// The driver's `advance`: start bands while admission allows, then `dispatch_ready`.
    fn advance(&mut self, s: usize, clock: &mut f64) {
        loop {
            let shard = &mut self.shards[s];
            let Some(&b) = shard.bands.get(shard.next) else { break };
            let expected = if shard.largest > 0 {
                shard.largest
            } else {
                self.admission.memory_bound / self.admission.max_bands as u64
            };
            if !self.admission.admits(shard.active.len(), shard.held, expected) {
                break;
            }
            shard.note_held(*clock);
            shard.seq[b] = shard.next;
            shard.next += 1;
            shard.active.insert(b, false);
            let lanes = self.work.bands[b].lanes.len();
            shard.threads.insert(
                b,
                BandThread {
                    lanes: vec![LaneState::default(); lanes],
                    unfinished: lanes,
                    inbox: VecDeque::from([BandStep::Intersect, BandStep::Plan]),
                    scheduled: false,
                    running: None,
                    complete: false,
                    ended: false,
                },
            );
            self.schedule_band(s, b, *clock);
        }
        let datasets: Vec<usize> = self.shards[s].datasets.iter().copied().collect();
        for d in datasets {
            while let Some(worker) = self.pick(s, d) {
                if !self.shards[s].streams.contains_key(&(worker, d)) {
                    // Its batches wait until the worker accepts the stream.
                    self.open(s, worker, d, *clock);
                    continue;
                }
                let Some(made) = self.shards[s].stock[d].ready.pop_front() else { break };
                self.send(s, made, worker, clock);
            }
            self.ask(s, d, *clock);
            let shard = &mut self.shards[s];
            let stock = &shard.stock[d];
            if stock.ready.is_empty() && stock.bands.is_empty() {
                shard.datasets.remove(&d);
            }
        }
    }

    /// The holder of dataset `d` that casts its next batch: the driver's own policy over
    /// holders in worker order, passing over those whose stream is still opening.
    fn pick(&self, s: usize, d: usize) -> Option<usize> {
        let shard = &self.shards[s];
        let threads = self.config.worker_threads as u32;
        let usable: Vec<usize> = self.holders[d]
            .iter()
            .copied()
            .filter(|&w| shard.streams.get(&(w, d)) != Some(&StreamState::Opening))
            .collect();
        let loads = usable.iter().map(|&w| Load { in_flight: shard.in_flight[w] as u64, threads, refused: false });
        least_loaded(loads).map(|i| usable[i])
    }

    /// The driver's `ask`: as many batches of dataset `d` as its holders have room for, and
    /// one per holder more, less the stock and what is already asked for; earliest started
    /// band first, a share each.
    fn ask(&mut self, s: usize, d: usize, clock: f64) {
        let shard = &self.shards[s];
        let cap = capacity(self.config.worker_threads as u32) as usize;
        let room: usize = self.holders[d].iter().map(|&w| cap.saturating_sub(shard.in_flight[w])).sum();
        let stock = &shard.stock[d];
        let asked: usize = stock.asked.values().sum();
        let asking = batches_to_ask(room, self.holders[d].len(), stock.ready.len(), asked, stock.bands.len());
        let Some((mut want, share)) = asking else { return };
        while want > 0 {
            let Some((_, band)) = self.shards[s].stock[d].bands.pop_first() else { break };
            let n = share.min(want);
            if !self.shards[s].threads.contains_key(&band) {
                continue;
            }
            if self.tell_band(s, band, BandStep::Produce { dataset: d, n }, clock) {
                *self.shards[s].stock[d].asked.entry(band).or_default() += n;
                want -= n;
            }
        }
    }

    /// Opens a stream to `worker` for dataset `d`: the scene and its headers go first.
    fn open(&mut self, s: usize, worker: usize, d: usize, clock: f64) {
        self.shards[s].streams.insert((worker, d), StreamState::Opening);
        let seconds = self.inputs.wire_seconds(self.scene_bytes);
        let arrival =
            transfer(clock, seconds, &mut self.shards[s].out, &mut self.workers[worker].into, self.inputs.latency);
        self.at(arrival, EventKind::OpenArrives(worker, s, d));
    }

    /// Sends batch `made` to `worker`, whose stream for its dataset is open.
    fn send(&mut self, s: usize, made: Made, worker: usize, clock: &mut f64) {
        let Made { band, lane, tasks, samples } = made;
        self.shards[s].in_flight[worker] += 1;
        let i = self.inputs;
        self.charge(s, clock, Part::Send, tasks as f64 * i.cost(At::Send, RunsOn::EventLoop));
        let off = i.cost(At::Send, RunsOn::Parallel) + i.cost(At::Send, RunsOn::OneThread);
        self.background(s, *clock, tasks as f64 * off);
        let seconds = i.wire_seconds(TASK_BYTES_OUT * tasks as f64);
        let arrival = transfer(*clock, seconds, &mut self.shards[s].out, &mut self.workers[worker].into, i.latency);
        self.batches.push(Batch { shard: s, band, lane, worker, tasks, samples });
        self.at(arrival, EventKind::BatchArrives(self.batches.len() - 1));
    }

    /// The image's encoding, on the coordinator's other cores.
    fn finish(&mut self, s: usize) {
        let i = self.inputs;
        let one = i.cost(At::Finish, RunsOn::OneThread) + i.cost(At::Finish, RunsOn::Band);
        let work = self.shards[s].pixels as f64 * (one + i.cost(At::Finish, RunsOn::Parallel));
        let cap = if one > 0.0 { 1.0 } else { self.shards[s].pool.capacity() };
        self.shards[s].pool.add(self.now, CoordJob::Finish, work, cap);
        self.check_coord_pool(s);
    }

    fn check_coord_pool(&mut self, s: usize) {
        let pool = &self.shards[s].pool;
        if let Some(t) = pool.next_completion() {
            let v = pool.version;
            self.at(t, EventKind::CoordPool(s, v));
        }
    }

    fn coord_pool(&mut self, s: usize) {
        for job in self.shards[s].pool.take_finished(self.now) {
            match job {
                CoordJob::Band(b) => self.band_step_done(s, b),
                CoordJob::Finish => self.shards[s].finished = Some(self.now),
                CoordJob::Background => {}
            }
        }
        self.check_coord_pool(s);
    }
}

/// The bands' threads.
impl Sim<'_> {
    /// Sends `step` to band `b`'s thread at `clock`; whether the send succeeded (a thread
    /// that ended has dropped its inbox; one compositing takes the message and never reads
    /// it).
    fn tell_band(&mut self, s: usize, b: usize, step: BandStep, clock: f64) -> bool {
        let Some(thread) = self.shards[s].threads.get_mut(&b) else { return false };
        if thread.ended {
            return false;
        }
        if !thread.complete {
            thread.inbox.push_back(step);
            self.schedule_band(s, b, clock);
        }
        true
    }

    /// Makes sure band `b`'s thread looks at its inbox at `clock` (or when its step ends).
    fn schedule_band(&mut self, s: usize, b: usize, clock: f64) {
        let Some(thread) = self.shards[s].threads.get_mut(&b) else { return };
        if !thread.scheduled && thread.running.is_none() && !thread.inbox.is_empty() {
            thread.scheduled = true;
            self.at(clock.max(self.now), EventKind::BandRun(s, b));
        }
    }

    /// Band `b`'s thread starts its next step, if it is idle.
    fn band_run(&mut self, s: usize, b: usize) {
        let cores = self.shards[s].pool.capacity();
        let (i, work, band) = (self.inputs, self.work, &self.work.bands[b]);
        let batch_tasks = self.config.batch_tasks;
        let shard = &mut self.shards[s];
        let Some(thread) = shard.threads.get_mut(&b) else { return };
        thread.scheduled = false;
        if thread.running.is_some() {
            return;
        }
        let Some(step) = thread.inbox.pop_front() else { return };
        let pieces = band.pieces as f64;
        let own = |at: At| i.cost(at, RunsOn::Band) + i.cost(at, RunsOn::OneThread);
        let (seconds, cap, news) = match step {
            BandStep::Intersect => {
                let rows = band.rays / work.width as u64;
                let cap = cores.min(rows.div_ceil(INTERSECT_ROWS) as f64);
                shard.band_other += pieces * i.cost(At::Intersect, RunsOn::Parallel);
                (pieces * i.cost(At::Intersect, RunsOn::Parallel), cap, None)
            }
            BandStep::Plan => {
                if thread.unfinished == 0 {
                    thread.complete = true;
                    thread.inbox = VecDeque::from([BandStep::Composite, BandStep::CompositeOne]);
                }
                shard.band_other += pieces * own(At::Intersect);
                (pieces * own(At::Intersect), 1.0, Some(LoopEvent::Intersected(b)))
            }
            BandStep::Produce { dataset, n } => {
                let mut batches = Vec::with_capacity(n.min(64));
                if let Ok(lane) = band.lanes.binary_search_by_key(&dataset, |l| l.dataset) {
                    while batches.len() < n {
                        let Some((tasks, samples)) = thread.lanes[lane].next_batch(&band.lanes[lane], batch_tasks)
                        else {
                            break;
                        };
                        batches.push(Made { band: b, lane, tasks, samples });
                    }
                }
                let more = batches.len() == n;
                let seconds = batches.iter().map(|m| m.tasks).sum::<u64>() as f64 * own(At::Send);
                shard.band_send += seconds;
                (seconds, 1.0, Some(LoopEvent::Produced { band: b, dataset, asked: n, batches, more }))
            }
            BandStep::Answer(id) => {
                let (lane, tasks) = (self.batches[id].lane, self.batches[id].tasks);
                if thread.lanes[lane].record(&band.lanes[lane]) {
                    thread.unfinished -= 1;
                    if thread.unfinished == 0 {
                        // Every task recorded: it composites next and reads nothing more.
                        thread.complete = true;
                        thread.inbox = VecDeque::from([BandStep::Composite, BandStep::CompositeOne]);
                    }
                }
                // An answer recorded needs no reply: the loop woke the dataset as it handed
                // the answer over.
                let seconds = tasks as f64 * own(At::Answer);
                shard.band_answer += seconds;
                (seconds, 1.0, None)
            }
            BandStep::Composite => {
                shard.band_other += pieces * i.cost(At::Composite, RunsOn::Parallel);
                (pieces * i.cost(At::Composite, RunsOn::Parallel), cores, None)
            }
            BandStep::CompositeOne => {
                shard.band_other += pieces * own(At::Composite);
                (pieces * own(At::Composite), 1.0, Some(LoopEvent::Composited(b)))
            }
        };
        thread.running = Some(news);
        shard.note_busy(self.now);
        shard.busy_threads += 1;
        shard.pool.add(self.now, CoordJob::Band(b), seconds, cap);
        self.check_coord_pool(s);
    }

    /// Band `b`'s thread finished its step: it tells the loop, and goes on with its inbox.
    fn band_step_done(&mut self, s: usize, b: usize) {
        let shard = &mut self.shards[s];
        shard.note_busy(self.now);
        shard.busy_threads -= 1;
        let thread = shard.threads.get_mut(&b).expect("a band's thread that ran a step");
        let news = thread.running.take().flatten();
        if matches!(news, Some(LoopEvent::Composited(_))) {
            thread.ended = true;
        }
        if let Some(news) = news {
            self.post(s, news);
        }
        self.schedule_band(s, b, self.now);
    }
}
/// The worker side.
impl Sim<'_> {
    fn batch_arrives(&mut self, id: usize) {
        let (w, key) = {
            let b = &self.batches[id];
            (b.worker, (b.shard, self.work.bands[b.band].lanes[b.lane].dataset))
        };
        let stream = self.workers[w].streams.entry(key).or_default();
        stream.queue.push_back(id);
        if !stream.running {
            stream.running = true;
            self.prepare(w, key);
        }
    }

    /// A stream (re)starts: load its dataset if no stream has, then bind its objects.
    fn prepare(&mut self, w: usize, key: StreamKey) {
        let d = key.1;
        match self.workers[w].datasets.get_mut(&d) {
            Some(Residency::Resident) => self.bind(w, key),
            Some(Residency::Loading(waiting)) => waiting.push(key),
            None => {
                self.workers[w].datasets.insert(d, Residency::Loading(vec![key]));
                let work = self.work.dataset_bytes as f64 * self.inputs.load_per_byte;
                self.workers[w].load += work;
                self.worker_job(w, WorkerJob::Load(d), work, 1.0);
            }
        }
    }

    fn bind(&mut self, w: usize, key: StreamKey) {
        let first = self.workers[w].bound.insert(key.1);
        let per_voxel = if first { self.inputs.bind_per_voxel } else { self.inputs.rebind_per_voxel };
        self.worker_job(w, WorkerJob::Bind(key), self.work.dataset_voxels as f64 * per_voxel, 1.0);
    }

    /// Casts the batch at the head of the stream's queue, or lets the stream run dry.
    fn cast_next(&mut self, w: usize, key: StreamKey) {
        let stream = self.workers[w].streams.get_mut(&key).expect("a stream that ran");
        let Some(&id) = stream.queue.front() else {
            stream.running = false;
            return;
        };
        let b = &self.batches[id];
        let work = b.tasks as f64 * self.inputs.cast_per_task + b.samples as f64 * self.inputs.cast_per_sample;
        let cap = (self.config.worker_threads as u64).min(b.tasks.div_ceil(CHUNK_TASKS)) as f64;
        self.workers[w].cast += work;
        self.worker_job(w, WorkerJob::Cast(id), work, cap);
    }

    fn worker_job(&mut self, w: usize, job: WorkerJob, work: f64, cap: f64) {
        self.workers[w].pool.add(self.now, job, work, cap);
        self.check_worker_pool(w);
    }

    fn check_worker_pool(&mut self, w: usize) {
        let pool = &self.workers[w].pool;
        if let Some(t) = pool.next_completion() {
            let v = pool.version;
            self.at(t, EventKind::WorkerPool(w, v));
        }
    }

    fn worker_pool(&mut self, w: usize) {
        for job in self.workers[w].pool.take_finished(self.now) {
            match job {
                WorkerJob::Parse(s, d) => {
                    let seconds = self.inputs.wire_seconds(SMALL_MESSAGE);
                    let arrival = transfer(
                        self.now,
                        seconds,
                        &mut self.workers[w].out,
                        &mut self.shards[s].into,
                        self.inputs.latency,
                    );
                    self.at(arrival, EventKind::OpenedArrives(s, w, d));
                }
                WorkerJob::Load(d) => {
                    let Some(Residency::Loading(waiting)) = self.workers[w].datasets.insert(d, Residency::Resident)
                    else {
                        unreachable!("a load finished that was not running")
                    };
                    waiting.into_iter().for_each(|key| self.bind(w, key));
                }
                WorkerJob::Bind(key) => self.cast_next(w, key),
                WorkerJob::Cast(id) => self.answer(w, id),
            }
        }
        self.check_worker_pool(w);
    }

    /// Sends batch `id`'s results to its coordinator and goes on with the stream.
    fn answer(&mut self, w: usize, id: usize) {
        let (s, tasks, key) = {
            let b = &self.batches[id];
            (b.shard, b.tasks, (b.shard, self.work.bands[b.band].lanes[b.lane].dataset))
        };
        let seconds = self.inputs.wire_seconds(TASK_BYTES_BACK * tasks as f64);
        let arrival =
            transfer(self.now, seconds, &mut self.workers[w].out, &mut self.shards[s].into, self.inputs.latency);
        self.at(arrival, EventKind::AnswerArrives(id));
        self.workers[w].streams.get_mut(&key).expect("the batch's stream").queue.pop_front();
        self.cast_next(w, key);
    }
}

#[cfg(test)]
mod tests {
    use super::super::inputs::Cost;
    use super::super::placement::Placement;
    use super::super::recorded::tests::sample;
    use super::super::recorded::WorkerRecord;
    use super::super::workload::{Band, Lane, Wave};
    use super::*;

    /// Only casting costs anything: no coordinator work, no network, no loads.
    fn cast_only() -> Inputs {
        Inputs {
            cast_per_sample: 1e-8,
            cast_per_task: 1e-7,
            bind_per_voxel: 0.0,
            rebind_per_voxel: 0.0,
            load_per_byte: 0.0,
            parse_per_object: 0.0,
            stages: Vec::new(),
            link_bytes_per_s: f64::INFINITY,
            latency: 0.0,
            message_overhead_bytes: 0.0,
        }
    }

    fn with_stage(mut i: Inputs, runs_on: RunsOn, at: At, seconds: f64) -> Inputs {
        i.stages.push(Cost { name: "test".into(), runs_on, at, seconds });
        i
    }

    /// `bands` bands, each with the given waves (tasks) for every one of `datasets` datasets.
    fn workload(bands: usize, datasets: usize, waves: &[u64]) -> Workload {
        let lane = |d| Lane { dataset: d, waves: waves.iter().map(|&t| Wave { tasks: t, samples: 50 * t }).collect() };
        Workload {
            width: 64,
            height: 64 * bands as u32,
            datasets,
            objects: datasets,
            dataset_bytes: 1 << 20,
            dataset_voxels: 1 << 18,
            scene_bytes: 1000,
            bands: (0..bands)
                .map(|_| Band {
                    rays: 64 * 64,
                    pieces: 64 * 64,
                    bytes: 1 << 20,
                    lanes: (0..datasets).map(lane).collect(),
                })
                .collect(),
        }
    }

    fn config(workers: usize, threads: usize) -> FarmConfig {
        FarmConfig {
            workers,
            worker_threads: threads,
            coordinator_cores: 4,
            coordinators: 1,
            split: Split::Tiles,
            batch_tasks: 256 * threads as u64,
            max_bands: 2,
            memory_bound: 256 << 20,
        }
    }

    fn run(work: &Workload, inputs: &Inputs, config: &FarmConfig, replicas: usize) -> Outcome {
        let samples: Vec<u64> = work.per_dataset().iter().map(|p| p.1).collect();
        simulate(work, inputs, config, &Placement::round_robin(replicas).holders(config.workers, &samples))
    }

    /// Core-seconds of casting the whole workload.
    fn cast_work(work: &Workload, i: &Inputs) -> f64 {
        work.tasks() as f64 * i.cast_per_task + work.samples() as f64 * i.cast_per_sample
    }

    #[test]
    fn one_worker_takes_the_sum_of_the_casting_costs_over_its_threads() {
        let (work, inputs, config) = (workload(3, 4, &[2048, 4096, 2048]), cast_only(), config(1, 8));
        let out = run(&work, &inputs, &config, 1);
        let expected = cast_work(&work, &inputs) / 8.0;
        assert!((out.seconds / expected - 1.0).abs() < 1e-9, "{} vs {expected}", out.seconds);
        assert!((out.worker_mean - 1.0).abs() < 1e-9);
        assert_eq!(out.batches, 3 * 4 * 4);
        // A dataset's load runs on one thread before its first batch; one dataset alone
        // leaves nothing to overlap it with.
        let mut inputs = inputs;
        inputs.load_per_byte = 1e-9;
        let one = workload(2, 1, &[4096]);
        let out = run(&one, &inputs, &config, 1);
        let expected = (1 << 20) as f64 * 1e-9 + cast_work(&one, &inputs) / 8.0;
        assert!((out.seconds / expected - 1.0).abs() < 1e-9, "{} vs {expected}", out.seconds);
    }

    #[test]
    fn twice_the_workers_take_half_the_time_on_an_embarrassingly_parallel_scene() {
        let work = workload(1, 64, &[64 * 2048]);
        let mut inputs = cast_only().with_link(100.0, 50.0);
        // Some 5 µs of casting per task: the coordinator's link (24 bytes a task), its loop
        // and its band's thread stay far from busy.
        inputs.cast_per_sample = 1e-7;
        let inputs = with_stage(inputs, RunsOn::Band, At::Send, 2e-9);
        let inputs = with_stage(inputs, RunsOn::Band, At::Answer, 1e-9);
        let inputs = with_stage(inputs, RunsOn::EventLoop, At::Answer, 1e-9);
        let t8 = run(&work, &inputs, &config(8, 8), 1).seconds;
        let t16 = run(&work, &inputs, &config(16, 8), 1).seconds;
        let t32 = run(&work, &inputs, &config(32, 8), 1).seconds;
        assert!((t8 / t16 - 2.0).abs() < 0.1, "8 → 16 workers: {t8} / {t16}");
        assert!((t16 / t32 - 2.0).abs() < 0.1, "16 → 32 workers: {t16} / {t32}");
    }

    /// Handing out a task costs as much as casting it costs one worker core.
    fn heavy(work: &Workload, runs_on: RunsOn) -> (Inputs, f64) {
        let per_task = work.samples() as f64 / work.tasks() as f64 * 1e-8 + 1e-7;
        (with_stage(cast_only(), runs_on, At::Send, per_task), work.tasks() as f64 * per_task)
    }

    #[test]
    fn a_farm_bound_by_the_event_loop_stops_getting_faster_and_more_coordinators_lift_it() {
        let work = workload(4, 64, &[4096]);
        let (inputs, loop_work) = heavy(&work, RunsOn::EventLoop);
        let runs: Vec<Outcome> = [8, 16, 32].iter().map(|&w| run(&work, &inputs, &config(w, 8), 1)).collect();
        for out in &runs {
            assert!(out.seconds >= loop_work, "the loop's own work bounds the job");
            assert!(out.loop_busy > 0.9, "loop busy {}", out.loop_busy);
        }
        assert!(runs[2].seconds > 0.9 * runs[0].seconds, "{} vs {}", runs[2].seconds, runs[0].seconds);
        // More cores change nothing: the loop is one.
        let mut wide = config(32, 8);
        wide.coordinator_cores = 33;
        assert!(run(&work, &inputs, &wide, 1).seconds >= loop_work);
        // Four coordinators, each a tile of one band, share the loop's work.
        let mut tiles = config(32, 8);
        tiles.coordinators = 4;
        let t = run(&work, &inputs, &tiles, 1).seconds;
        assert!(t < 0.3 * runs[2].seconds, "4 tiles: {t} vs {}", runs[2].seconds);
    }

    #[test]
    fn per_band_threads_lift_the_event_loops_bound_as_cores_grow() {
        let work = workload(16, 64, &[4096]);
        let (on_loop, serial) = heavy(&work, RunsOn::EventLoop);
        let (on_bands, _) = heavy(&work, RunsOn::Band);
        let mut farm = config(32, 8);
        farm.max_bands = 8;
        let mut runs = Vec::new();
        for cores in [2, 5, 9] {
            farm.coordinator_cores = cores;
            assert!(run(&work, &on_loop, &farm, 1).seconds >= serial, "on the loop, {cores} cores");
            let out = run(&work, &on_bands, &farm, 1);
            // The bands' threads share the cores besides the loop's: their work over those
            // cores bounds the job, and nothing is left on the loop.
            assert!(out.seconds >= serial / (cores - 1) as f64, "{cores} cores: {}", out.seconds);
            assert!(out.loop_busy == 0.0 && (out.band_send - serial).abs() < 1e-9 * serial);
            runs.push(out);
        }
        // One core for eight bands' threads: they wait for it, and the job takes the loop's
        // time; four and eight cores (one per band in flight) take a fourth and an eighth.
        assert!(runs[0].pool_busy > 0.95 && runs[0].seconds < 1.05 * serial, "{:?}", runs[0]);
        assert!(runs[1].seconds < 0.3 * serial, "4 cores: {} vs {serial}", runs[1].seconds);
        assert!(runs[2].seconds < 0.6 * runs[1].seconds, "8 cores: {} vs 4: {}", runs[2].seconds, runs[1].seconds);
        assert!(runs[2].band_busy > 0.9, "each band's thread busy: {}", runs[2].band_busy);
    }

    #[test]
    fn a_one_band_job_is_bound_by_its_bands_thread() {
        let work = workload(1, 64, &[4096]);
        let (inputs, serial) = heavy(&work, RunsOn::Band);
        let mut farm = config(32, 8);
        farm.coordinator_cores = 33;
        let out = run(&work, &inputs, &farm, 1);
        // 32 cores, but the band's steps are one after the other on its thread.
        assert!(out.seconds >= serial && out.seconds < 1.05 * serial, "{} vs {serial}", out.seconds);
        assert!(out.band_busy > 0.95 && out.pool_busy < 0.05, "{out:?}");
        // The same work in four bands (four threads, all in flight) takes about a fourth.
        let four = workload(4, 16, &[4096]);
        farm.max_bands = 4;
        let t = run(&four, &inputs, &farm, 1).seconds;
        assert!(t < 0.3 * out.seconds, "four bands: {t} vs one: {}", out.seconds);
    }

    #[test]
    fn a_datasets_waves_run_one_after_the_other_while_datasets_run_side_by_side() {
        let inputs = cast_only();
        let config = config(2, 8);
        // One dataset on both workers, two waves of one batch each: the second waits.
        let serial = run(&workload(1, 1, &[2048, 2048]), &inputs, &config, 2).seconds;
        // Two datasets, one wave each, one on each worker: side by side.
        let parallel = run(&workload(1, 2, &[2048]), &inputs, &config, 1).seconds;
        assert!((serial / parallel - 2.0).abs() < 1e-9, "{serial} vs {parallel}");
    }

    #[test]
    fn admission_holds_the_bands_within_the_count_and_the_memory_bound() {
        let work = workload(16, 4, &[2048]);
        let mut config = config(4, 8);
        config.max_bands = 8;
        let many = run(&work, &cast_only(), &config, 1);
        assert!(many.bands_held > 2.5 && many.bands_held <= 8.0, "{}", many.bands_held);
        // Each band holds 1 MiB: once one is measured, a bound of 2 MiB admits two at once
        // (before then, a fair share of the bound is expected of each).
        config.memory_bound = 2 << 20;
        let bounded = run(&work, &cast_only(), &config, 1);
        assert!(bounded.bands_held < 0.75 * many.bands_held, "{} vs {}", bounded.bands_held, many.bands_held);
        config.max_bands = 2;
        config.memory_bound = 256 << 20;
        let two = run(&work, &cast_only(), &config, 1);
        assert!(two.bands_held <= 2.0 + 1e-9, "{}", two.bands_held);
    }

    #[test]
    fn whole_jobs_on_two_coordinators_take_twice_the_work_of_one() {
        let work = workload(2, 8, &[4096]);
        let one = run(&work, &cast_only(), &config(1, 8), 1).seconds;
        let mut two = config(1, 8);
        two.coordinators = 2;
        two.split = Split::Jobs;
        let t = run(&work, &cast_only(), &two, 1).seconds;
        assert!((t / one - 2.0).abs() < 1e-9, "{t} vs {one}");
    }

    /// The recorded sample's inputs reproduce a case worked out by hand: one band of one
    /// dataset, one batch, one worker of 8 threads, a free and instant network.
    #[test]
    fn inputs_from_a_record_give_the_time_worked_out_by_hand() {
        let worker = WorkerRecord {
            processor: String::new(),
            simd: String::new(),
            commit: String::new(),
            cast_per_sample: 1e-8,
            cast_per_task: 1e-7,
            bind_per_voxel: 0.0,
            rebind_per_voxel: 0.0,
            load_per_byte: 0.0,
            parse_per_object: 0.0,
        };
        let mut inputs = Inputs::from_records(&sample(), &worker);
        inputs.link_bytes_per_s = f64::INFINITY;
        inputs.latency = 0.0;
        // 64×64 pixels, 4096 pieces, one wave of 2048 tasks of 50 samples each.
        let work = workload(1, 1, &[2048]);
        let mut config = config(1, 8);
        config.coordinator_cores = 5; // 4 cores besides the loop
        let out = run(&work, &inputs, &config, 1);
        // The sample, per piece: intersection 40 ns (parallel: 64 rows in 16 items, on 4
        // cores), planning 10 ns (the band's thread), composition 15 ns (4 cores); per task
        // (half a task a piece): dispatch 40 ns on the band's thread before the batch goes
        // out, 10 ns on the loop for the answer, then recording 20 ns on the band's thread;
        // per pixel (2 pieces a pixel): the image 10 ns.
        let pieces = 4096.0;
        let expected = pieces * 40e-9 / 4.0
            + pieces * 10e-9
            + 2048.0 * 40e-9
            + (2048.0 * 1e-7 + 2048.0 * 50.0 * 1e-8) / 8.0
            + 2048.0 * 10e-9
            + 2048.0 * 20e-9
            + pieces * 15e-9 / 4.0
            + 4096.0 * 10e-9;
        assert!((out.seconds / expected - 1.0).abs() < 1e-9, "{} vs {expected}", out.seconds);
        assert!((out.band_send - 2048.0 * 40e-9).abs() < 1e-15 && (out.band_answer - 2048.0 * 20e-9).abs() < 1e-15);
        assert!(out.loop_send == 0.0 && (out.loop_answer - 2048.0 * 10e-9).abs() < 1e-15);
    }

    #[test]
    fn the_same_farm_gives_the_same_outcome() {
        let work = workload(3, 16, &[3000, 500, 7000]);
        let inputs = cast_only().with_link(10.0, 50.0);
        let mut config = config(8, 4);
        config.batch_tasks = 1000;
        let a = run(&work, &inputs, &config, 2);
        assert_eq!(a, run(&work, &inputs, &config, 2));
        assert!(a.seconds > 0.0 && a.batches > 0);
    }
}
