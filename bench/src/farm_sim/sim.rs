//! The discrete-event model of one farm job, following `coordinator/src/farm/driver.rs`
//! and `worker/src/cast.rs` step by step:
//!
//! * **Coordinator.** The image is worked through in bands of rows, at most
//!   `bands_in_flight` at once. A band is intersected on the blocking threads (in parallel
//!   over rows, then `Scheduler::new` on one thread), cast, then composited on the blocking
//!   threads (in parallel over rays). Everything else happens on the job's one event loop,
//!   one event at a time: after every event it runs `advance` — start bands while there is
//!   room, then for every band being cast, for every dataset not finished, `pick_worker`
//!   (which asks the registry for the dataset's holders) and, while a holder has room,
//!   `next_batch` and `send`. An answer is recorded on the loop, and only then does its
//!   worker's slot free. A dataset's waves go one after the other; datasets are independent.
//! * **Workers.** Each holds some datasets ([`super::placement`]). A batch goes to the
//!   least-loaded holder with fewer than `max(2·threads, 4)` batches in flight. A worker has
//!   one stream per job and dataset: its first batch brings the scene (parsed there), the
//!   dataset is loaded once and stays resident, objects are bound whenever the stream starts
//!   again after running dry, and its batches are cast one after the other, each spread over
//!   the worker's threads in chunks of 256 tasks.
//! * **Network.** Every machine has a link each way; messages queue on the sender's link and
//!   the receiver's, one after the other, with a one-way latency between.
//!
//! `coordinators > 1` models several coordinators, each with its own cores and link, that
//! split the image into tiles of whole bands and share the workers (each counts only its
//! own batches in flight). [`Dispatch::Indexed`] models the driver keeping each dataset's
//! holders and the datasets with ready batches instead of scanning every dataset on every
//! event.

use std::cmp::Ordering;
use std::collections::{BTreeMap, BTreeSet, BinaryHeap, HashMap, VecDeque};
use trove_core::render::dispatch::{band_order, least_loaded, Load};

use super::inputs::Inputs;
use super::pool::{transfer, Link, Pool};
use super::workload::Workload;

/// Tasks per rayon work item in a worker's batch (`CHUNK_TASKS` in `worker/src/cast.rs`).
const CHUNK_TASKS: u64 = 256;
/// Image rows per parallel work item of the intersection (`BAND_ROWS` in
/// `trove-core/src/render/intersection.rs`).
const INTERSECT_ROWS: u64 = 4;

/// How the coordinator finds a worker for a dataset's next batch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Dispatch {
    /// The design as it is: on every event, every unfinished dataset of every band being
    /// cast asks the registry for its holders (a pass over every registered worker).
    Scan,
    /// Holders kept per dataset and a set of datasets with a batch ready: an event costs
    /// only the batches it sends.
    Indexed,
}

/// The farm being simulated.
#[derive(Clone, Debug)]
pub(crate) struct FarmConfig {
    /// Worker machines.
    pub workers: usize,
    /// Cores (rayon threads) per worker.
    pub worker_threads: usize,
    /// Cores of each coordinator: its event loops run on some, the blocking threads on the
    /// rest.
    pub coordinator_cores: usize,
    /// Event loops per coordinator, each owning every `loops`-th band (1: the design as it
    /// is, one loop per job).
    pub loops: usize,
    /// Coordinators, each with a tile of whole bands.
    pub coordinators: usize,
    /// Tasks per batch (the job's `batch_tasks`; the driver's default is 4096).
    pub batch_tasks: u64,
    /// Bands whose pieces a coordinator holds at once (the driver's `BANDS_IN_FLIGHT`),
    /// counting those being intersected and composited.
    pub bands_in_flight: usize,
    pub dispatch: Dispatch,
    /// Order of the bands: top to bottom, or spread over the image as the driver starts
    /// them (`trove_core::render::dispatch::band_order`), so that the bands in flight lie
    /// apart in the image and meet different datasets.
    pub spread_bands: bool,
    /// Intersection tests every ray against every object (as it is), or, projected, walks
    /// a bounding-volume hierarchy: about 2·log₂(objects) boxes plus the objects hit.
    pub bvh: bool,
}

/// Where a coordinator's event loop spent its time, in seconds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct LoopSpent {
    /// Fixed cost of every event.
    pub events: f64,
    /// `pick_worker` for every unfinished dataset on every event (the registry scan).
    pub scan: f64,
    /// Batches handed out: `next_batch`, encoding, choosing the worker, sending.
    pub dispatch: f64,
    /// Streams opened: the scene and headers copied into the `open` message.
    pub open: f64,
    /// Answers recorded.
    pub record: f64,
    /// The job's status rebuilt after every answer.
    pub progress: f64,
}

impl LoopSpent {
    /// Every part.
    pub(crate) fn total(&self) -> f64 {
        self.events + self.scan + self.dispatch + self.open + self.record + self.progress
    }

    fn add(&mut self, o: &LoopSpent) {
        self.events += o.events;
        self.scan += o.scan;
        self.dispatch += o.dispatch;
        self.open += o.open;
        self.record += o.record;
        self.progress += o.progress;
    }
}

/// What a simulated job took.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Outcome {
    /// Wall time of the job, submission to encoded image.
    pub seconds: f64,
    /// The busiest coordinator's event loop: busy time / job time.
    pub loop_busy: f64,
    /// Event-loop time over all coordinators, by part.
    pub spent: LoopSpent,
    /// The busiest coordinator's blocking threads: core-seconds / (cores × job time).
    pub pool_busy: f64,
    /// Core-seconds of intersection (with planning) and of composition, all coordinators.
    pub intersect: f64,
    pub composite: f64,
    /// The busiest coordinator link (either direction): busy time / job time.
    pub link_busy: f64,
    /// The largest fraction of the job during which a coordinator had no band being cast
    /// (its bands in flight were all being intersected or composited).
    pub no_band_cast: f64,
    /// Workers' core-seconds (open, load, bind, cast) / (threads × job time): the mean and
    /// the busiest worker's.
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
    LoopRun(usize, usize),
    /// A job starts on a coordinator's blocking threads.
    Spawn(usize, CoordJob),
    /// Pool completion checks, valid while the pool's version is unchanged.
    CoordPool(usize, u64),
    WorkerPool(usize, u64),
    /// A batch reaches its worker.
    BatchArrives(usize),
    /// A batch's answer reaches its coordinator.
    AnswerArrives(usize),
}

/// What a coordinator's event loop handles.
#[derive(Debug)]
enum LoopEvent {
    Start,
    /// A worker this loop's bands could use has room again.
    Wake,
    Intersected(usize),
    Composited(usize),
    Answer(usize),
}

#[derive(Clone, Copy, Debug)]
enum CoordJob {
    Intersect(usize),
    Plan(usize),
    Composite(usize),
    Png,
}

#[derive(Clone, Copy, Debug)]
enum WorkerJob {
    Open(StreamKey),
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

#[derive(Clone, Debug, Default)]
struct LaneState {
    wave: usize,
    handed: u64,
    outstanding: usize,
    done: bool,
}

enum BandState {
    Intersecting,
    Casting { lanes: Vec<LaneState>, unfinished: usize, unfinished_holders: usize },
    Compositing,
}

/// One event loop of a coordinator: it handles its events one at a time.
#[derive(Default)]
struct EventLoop {
    inbox: VecDeque<LoopEvent>,
    busy_until: f64,
    scheduled: bool,
    spent: LoopSpent,
}

struct Shard {
    bands: Vec<usize>,
    next: usize,
    active: BTreeMap<usize, BandState>,
    /// Lanes that can hand out a batch now: (band, lane).
    ready: BTreeSet<(usize, usize)>,
    /// The event loops; band `bands[i]` belongs to loop `i mod loops.len()`.
    loops: Vec<EventLoop>,
    /// Per band of the image: its loop, if it is this coordinator's.
    loop_of: Vec<usize>,
    pool: Pool<CoordJob>,
    out: Link,
    into: Link,
    in_flight: Vec<usize>,
    answered: Vec<bool>,
    answered_count: usize,
    intersect: f64,
    composite: f64,
    /// Since when no band has been in the casting state, and the total time so.
    idle_since: Option<f64>,
    no_band_cast: f64,
    finished: Option<f64>,
}

#[derive(Default)]
struct Stream {
    /// Batches received and not yet answered, oldest first.
    queue: VecDeque<usize>,
    /// Whether the stream's thread is working (opening, loading, binding or casting).
    running: bool,
    /// Whether the coordinator has sent the `open` message.
    opened: bool,
    /// Whether the worker has parsed the scene.
    parsed: bool,
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
    cast: f64,
    load: f64,
}

struct Sim<'a> {
    work: &'a Workload,
    inputs: &'a Inputs,
    config: &'a FarmConfig,
    holders: &'a [Vec<usize>],
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
        let k = config.coordinators.clamp(1, n.max(1));
        let shards = (0..k).map(|s| Shard::new(config, (s * n / k..(s + 1) * n / k).collect(), n)).collect();
        let workers = (0..config.workers)
            .map(|_| Worker {
                pool: Pool::new(config.worker_threads as f64),
                out: Link::default(),
                into: Link::default(),
                streams: HashMap::new(),
                datasets: HashMap::new(),
                cast: 0.0,
                load: 0.0,
            })
            .collect();
        Sim {
            work,
            inputs,
            config,
            holders,
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
            self.wake_loop(s, 0);
        }
        while let Some(event) = self.queue.pop() {
            self.now = event.time;
            match event.kind {
                EventKind::LoopRun(s, l) => self.loop_run(s, l),
                EventKind::Spawn(s, job) => self.spawn(s, job),
                EventKind::CoordPool(s, v) if v == self.shards[s].pool.version => self.coord_pool(s),
                EventKind::WorkerPool(w, v) if v == self.workers[w].pool.version => self.worker_pool(w),
                EventKind::CoordPool(..) | EventKind::WorkerPool(..) => {}
                EventKind::BatchArrives(b) => self.batch_arrives(b),
                EventKind::AnswerArrives(b) => {
                    let (s, band) = (self.batches[b].shard, self.batches[b].band);
                    self.post(s, band, LoopEvent::Answer(b));
                }
            }
        }
    }

    /// The loop of coordinator `s` that handles band `b`.
    fn loop_of(&self, s: usize, b: usize) -> usize {
        self.shards[s].loop_of[b]
    }

    /// Hands `event` about band `b` to its loop.
    fn post(&mut self, s: usize, b: usize, event: LoopEvent) {
        let l = self.loop_of(s, b);
        self.shards[s].loops[l].inbox.push_back(event);
        self.wake_loop(s, l);
    }

    /// Makes sure loop `l` of coordinator `s` will take its next event.
    fn wake_loop(&mut self, s: usize, l: usize) {
        let lp = &mut self.shards[s].loops[l];
        if !lp.scheduled && !lp.inbox.is_empty() {
            lp.scheduled = true;
            let t = lp.busy_until.max(self.now);
            self.at(t, EventKind::LoopRun(s, l));
        }
    }

    fn outcome(&self) -> Outcome {
        let seconds = self.shards.iter().filter_map(|s| s.finished).fold(0.0, f64::max);
        let t = seconds.max(1e-12);
        let mut spent = LoopSpent::default();
        self.shards.iter().flat_map(|s| &s.loops).for_each(|l| spent.add(&l.spent));
        let threads = self.config.worker_threads as f64;
        let worker_busy: Vec<f64> = self.workers.iter().map(|w| w.pool.busy / (threads * t)).collect();
        Outcome {
            seconds,
            loop_busy: self.shards.iter().flat_map(|s| &s.loops).map(|l| l.spent.total() / t).fold(0.0, f64::max),
            spent,
            pool_busy: self.shards.iter().map(|s| s.pool.busy / (s.pool.capacity() * t)).fold(0.0, f64::max),
            intersect: self.shards.iter().map(|s| s.intersect).sum(),
            composite: self.shards.iter().map(|s| s.composite).sum(),
            link_busy: self.shards.iter().map(|s| s.out.busy.max(s.into.busy) / t).fold(0.0, f64::max),
            no_band_cast: self.shards.iter().map(|s| s.no_band_cast / t).fold(0.0, f64::max),
            worker_mean: worker_busy.iter().sum::<f64>() / worker_busy.len().max(1) as f64,
            worker_max: worker_busy.iter().copied().fold(0.0, f64::max),
            cast: self.workers.iter().map(|w| w.cast).sum(),
            load: self.workers.iter().map(|w| w.load).sum(),
            batches: self.batches.len() as u64,
        }
    }
}

impl Shard {
    /// A coordinator of the image's `bands` bands that works through `tile`, in the order
    /// `config.spread_bands` asks for.
    fn new(config: &FarmConfig, tile: Vec<usize>, bands: usize) -> Shard {
        let loops = config.loops.max(1);
        let order: Vec<usize> =
            if config.spread_bands { band_order(tile.len()).into_iter().map(|i| tile[i]).collect() } else { tile };
        let mut loop_of = vec![0; bands];
        order.iter().enumerate().for_each(|(i, &b)| loop_of[b] = i % loops);
        let start = |l| if l == 0 { VecDeque::from([LoopEvent::Start]) } else { VecDeque::new() };
        Shard {
            bands: order,
            loop_of,
            next: 0,
            active: BTreeMap::new(),
            ready: BTreeSet::new(),
            loops: (0..loops).map(|l| EventLoop { inbox: start(l), ..EventLoop::default() }).collect(),
            pool: Pool::new(config.coordinator_cores.saturating_sub(loops).max(1) as f64),
            out: Link::default(),
            into: Link::default(),
            in_flight: vec![0; config.workers],
            answered: vec![false; config.workers],
            answered_count: 0,
            intersect: 0.0,
            composite: 0.0,
            idle_since: Some(0.0),
            no_band_cast: 0.0,
            finished: None,
        }
    }
}

/// The coordinator side.
impl Sim<'_> {
    /// Handles the next event of loop `l` of coordinator `s`, charging its cost from now on.
    fn loop_run(&mut self, s: usize, l: usize) {
        self.shards[s].loops[l].scheduled = false;
        let Some(event) = self.shards[s].loops[l].inbox.pop_front() else { return };
        let mut clock = self.now;
        self.charge((s, l), &mut clock, |p| &mut p.events, self.inputs.per_event);
        match event {
            LoopEvent::Start | LoopEvent::Wake => {}
            LoopEvent::Intersected(b) => self.intersected(s, b, &clock),
            LoopEvent::Composited(b) => {
                self.shards[s].active.remove(&b);
            }
            LoopEvent::Answer(id) => self.record((s, l), id, &mut clock),
        }
        self.advance((s, l), &mut clock);
        let shard = &mut self.shards[s];
        if shard.finished.is_none() && shard.next == shard.bands.len() && shard.active.is_empty() {
            shard.finished = Some(f64::INFINITY);
            if let Some(since) = shard.idle_since.take() {
                shard.no_band_cast += clock - since;
            }
            self.at(clock, EventKind::Spawn(s, CoordJob::Png));
        }
        self.note_bands(s, clock);
        self.shards[s].loops[l].busy_until = clock;
        self.wake_loop(s, l);
    }

    /// Keeps count of the time coordinator `s` has no band being cast.
    fn note_bands(&mut self, s: usize, clock: f64) {
        let shard = &mut self.shards[s];
        let casting = shard.active.values().any(|b| matches!(b, BandState::Casting { .. }));
        match (casting, shard.idle_since) {
            (true, Some(since)) => {
                shard.no_band_cast += clock - since;
                shard.idle_since = None;
            }
            (false, None) if shard.finished.is_none() => shard.idle_since = Some(clock),
            _ => {}
        }
    }

    /// Spends `seconds` of loop `at` = (coordinator, loop) on the part `part` picks.
    fn charge(&mut self, at: (usize, usize), clock: &mut f64, part: impl Fn(&mut LoopSpent) -> &mut f64, seconds: f64) {
        *part(&mut self.shards[at.0].loops[at.1].spent) += seconds;
        *clock += seconds;
    }

    fn intersected(&mut self, s: usize, b: usize, clock: &f64) {
        let work = self.work;
        let band = &work.bands[b];
        let lanes = vec![LaneState::default(); band.lanes.len()];
        let unfinished_holders = band.lanes.iter().map(|l| self.holders[l.dataset].len()).sum();
        let shard = &mut self.shards[s];
        shard.ready.extend((0..band.lanes.len()).map(|l| (b, l)));
        shard.active.insert(b, BandState::Casting { lanes, unfinished: band.lanes.len(), unfinished_holders });
        if band.lanes.is_empty() {
            self.band_cast(s, b, *clock);
        }
    }

    /// Band `b` is wholly cast: composite it on the blocking threads.
    fn band_cast(&mut self, s: usize, b: usize, clock: f64) {
        self.shards[s].active.insert(b, BandState::Compositing);
        self.at(clock, EventKind::Spawn(s, CoordJob::Composite(b)));
    }

    fn record(&mut self, at: (usize, usize), id: usize, clock: &mut f64) {
        let s = at.0;
        let (band, lane, worker, tasks) = {
            let b = &self.batches[id];
            (b.band, b.lane, b.worker, b.tasks)
        };
        let shard = &mut self.shards[s];
        if !shard.answered[worker] {
            shard.answered[worker] = true;
            shard.answered_count += 1;
        }
        shard.in_flight[worker] -= 1;
        let progress = shard.answered_count as f64 * self.inputs.progress_per_worker;
        self.charge(at, clock, |p| &mut p.record, tasks as f64 * self.inputs.record_per_task);
        self.charge(at, clock, |p| &mut p.progress, progress);
        self.wake_others(at, worker);
        let work = self.work;
        let spec = &work.bands[band].lanes[lane];
        let holders = self.holders[spec.dataset].len();
        let shard = &mut self.shards[s];
        let Some(BandState::Casting { lanes, unfinished, unfinished_holders }) = shard.active.get_mut(&band) else {
            unreachable!("an answer for a band that is not being cast")
        };
        let l = &mut lanes[lane];
        l.outstanding -= 1;
        if l.outstanding > 0 || l.handed < spec.waves[l.wave].tasks {
            return;
        }
        if l.wave + 1 < spec.waves.len() {
            shard.ready.insert((band, lane));
            return;
        }
        l.done = true;
        *unfinished -= 1;
        *unfinished_holders -= holders;
        if *unfinished == 0 {
            self.band_cast(s, band, *clock);
        }
    }

    /// The driver's `advance`: start bands while there is room, then hand out batches.
    fn advance(&mut self, at: (usize, usize), clock: &mut f64) {
        let (s, l) = at;
        loop {
            let shard = &mut self.shards[s];
            if shard.active.len() >= self.config.bands_in_flight || shard.next >= shard.bands.len() {
                break;
            }
            let b = shard.bands[shard.next];
            shard.next += 1;
            shard.active.insert(b, BandState::Intersecting);
            self.at(*clock, EventKind::Spawn(s, CoordJob::Intersect(b)));
        }
        if self.config.dispatch == Dispatch::Scan {
            // Every unfinished dataset of every band being cast calls `pick_worker` once,
            // whatever it then finds.
            let (mut lanes, mut holders) = (0usize, 0usize);
            for (&b, state) in &self.shards[s].active {
                if self.loop_of(s, b) != l {
                    continue;
                }
                if let BandState::Casting { unfinished, unfinished_holders, .. } = state {
                    lanes += unfinished;
                    holders += unfinished_holders;
                }
            }
            let cost = lanes as f64 * self.inputs.holders_per_worker * self.config.workers as f64
                + holders as f64 * self.inputs.pick_per_holder;
            self.charge(at, clock, |p| &mut p.scan, cost);
        }
        let ready: Vec<(usize, usize)> =
            self.shards[s].ready.iter().copied().filter(|&(b, _)| self.loop_of(s, b) == l).collect();
        let work = self.work;
        for (band, lane) in ready {
            while let Some(worker) = self.pick(s, work.bands[band].lanes[lane].dataset) {
                self.send(at, band, lane, worker, clock);
                if !self.shards[s].ready.contains(&(band, lane)) {
                    break;
                }
            }
        }
    }

    /// A slot of `worker` freed on loop `at`: the coordinator's other loops that have a
    /// ready dataset held by it are woken (each loop owns its bands' schedulers; the
    /// workers' counts are shared).
    fn wake_others(&mut self, at: (usize, usize), worker: usize) {
        let (s, l) = at;
        let loops = self.shards[s].loops.len();
        if loops == 1 {
            return;
        }
        let mut wake = vec![false; loops];
        for &(b, lane) in &self.shards[s].ready {
            let other = self.loop_of(s, b);
            if other != l && self.holders[self.work.bands[b].lanes[lane].dataset].contains(&worker) {
                wake[other] = true;
            }
        }
        for (other, _) in wake.iter().enumerate().filter(|(_, w)| **w) {
            let lp = &mut self.shards[s].loops[other];
            if lp.inbox.is_empty() {
                lp.inbox.push_back(LoopEvent::Wake);
                self.wake_loop(s, other);
            }
        }
    }

    /// The holder of dataset `d` that casts its next batch: the driver's own policy
    /// (`trove_core::render::dispatch::least_loaded`), over holders in worker order.
    fn pick(&self, s: usize, d: usize) -> Option<usize> {
        let in_flight = &self.shards[s].in_flight;
        let threads = self.config.worker_threads as u32;
        let loads = self.holders[d].iter().map(|&w| Load { in_flight: in_flight[w] as u64, threads });
        least_loaded(loads).map(|i| self.holders[d][i])
    }

    /// `next_batch` on a ready lane and `send` to `worker`.
    fn send(&mut self, at: (usize, usize), band: usize, lane: usize, worker: usize, clock: &mut f64) {
        let s = at.0;
        let work = self.work;
        let spec = &work.bands[band].lanes[lane];
        let d = spec.dataset;
        let shard = &mut self.shards[s];
        let Some(BandState::Casting { lanes, .. }) = shard.active.get_mut(&band) else { unreachable!("ready lane") };
        let l = &mut lanes[lane];
        if l.handed == spec.waves[l.wave].tasks {
            l.wave += 1;
            l.handed = 0;
        }
        let wave = spec.waves[l.wave];
        let tasks = self.config.batch_tasks.min(wave.tasks - l.handed);
        // The wave's samples, shared out in proportion to tasks, summing exactly.
        let share = |n: u64| (wave.samples as u128 * n as u128 / wave.tasks as u128) as u64;
        let samples = share(l.handed + tasks) - share(l.handed);
        l.handed += tasks;
        l.outstanding += 1;
        if l.handed == wave.tasks {
            shard.ready.remove(&(band, lane));
        }
        shard.in_flight[worker] += 1;
        let pick = match self.config.dispatch {
            Dispatch::Scan => self.inputs.holders_per_worker * self.config.workers as f64,
            Dispatch::Indexed => 0.0,
        } + self.inputs.pick_per_holder * self.holders[d].len() as f64;
        let cost = tasks as f64 * self.inputs.dispatch_per_task + self.inputs.per_send + pick;
        self.charge(at, clock, |p| &mut p.dispatch, cost);
        let stream = self.workers[worker].streams.entry((s, d)).or_default();
        let mut payload = 24.0 * tasks as f64;
        if !stream.opened {
            stream.opened = true;
            payload += self.scene_bytes;
            self.charge(at, clock, |p| &mut p.open, self.scene_bytes * self.inputs.open_per_byte);
        }
        let seconds = self.inputs.wire_seconds(payload);
        let arrival =
            transfer(*clock, seconds, &mut self.shards[s].out, &mut self.workers[worker].into, self.inputs.latency);
        self.batches.push(Batch { shard: s, band, lane, worker, tasks, samples });
        self.at(arrival, EventKind::BatchArrives(self.batches.len() - 1));
    }

    /// A job starts on coordinator `s`'s blocking threads.
    fn spawn(&mut self, s: usize, job: CoordJob) {
        let i = self.inputs;
        let cores = self.shards[s].pool.capacity();
        let (work, cap) = match job {
            CoordJob::Intersect(b) => {
                let band = &self.work.bands[b];
                let rows = band.rays / self.work.width as u64;
                let objects = self.work.objects as f64;
                let tested = if self.config.bvh {
                    (2.0 * objects.log2().max(1.0) + band.tasks() as f64 / band.rays.max(1) as f64).min(objects)
                } else {
                    objects
                };
                let work =
                    band.rays as f64 * tested * i.intersect_per_ray_object + band.tasks() as f64 * i.intersect_per_task;
                (work, cores.min(rows.div_ceil(INTERSECT_ROWS) as f64))
            }
            CoordJob::Plan(b) => (self.work.bands[b].tasks() as f64 * i.plan_per_task, 1.0),
            CoordJob::Composite(b) => {
                let band = &self.work.bands[b];
                (band.rays as f64 * i.composite_per_ray + band.pieces as f64 * i.composite_per_piece, cores)
            }
            CoordJob::Png => {
                let rays: u64 = self.shards[s].bands.iter().map(|&b| self.work.bands[b].rays).sum();
                (rays as f64 * i.png_per_pixel, 1.0)
            }
        };
        match job {
            CoordJob::Intersect(_) | CoordJob::Plan(_) => self.shards[s].intersect += work,
            CoordJob::Composite(_) => self.shards[s].composite += work,
            CoordJob::Png => {}
        }
        self.shards[s].pool.add(self.now, job, work, cap);
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
                CoordJob::Intersect(b) => self.spawn(s, CoordJob::Plan(b)),
                CoordJob::Plan(b) => self.post(s, b, LoopEvent::Intersected(b)),
                CoordJob::Composite(b) => self.post(s, b, LoopEvent::Composited(b)),
                CoordJob::Png => self.shards[s].finished = Some(self.now),
            }
        }
        self.check_coord_pool(s);
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
            if stream.parsed {
                self.prepare(w, key);
            } else {
                stream.parsed = true;
                let work = self.work.objects as f64 * self.inputs.parse_per_object;
                self.worker_job(w, WorkerJob::Open(key), work, 1.0);
            }
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
        let work = self.work.dataset_voxels as f64 * self.inputs.bind_per_voxel;
        self.worker_job(w, WorkerJob::Bind(key), work, 1.0);
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
                WorkerJob::Open(key) => self.prepare(w, key),
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
        let seconds = self.inputs.wire_seconds(16.0 * tasks as f64);
        let arrival =
            transfer(self.now, seconds, &mut self.workers[w].out, &mut self.shards[s].into, self.inputs.latency);
        self.at(arrival, EventKind::AnswerArrives(id));
        self.workers[w].streams.get_mut(&key).expect("the batch's stream").queue.pop_front();
        self.cast_next(w, key);
    }
}

#[cfg(test)]
mod tests {
    use super::super::placement::Placement;
    use super::super::workload::{Band, Lane, Wave};
    use super::*;

    /// Only casting costs anything: no coordinator work, no network, no loads.
    fn cast_only() -> Inputs {
        let mut i = Inputs::recorded();
        i.cast_per_sample = 1e-8;
        i.cast_per_task = 1e-7;
        for zero in [
            &mut i.bind_per_voxel,
            &mut i.load_per_byte,
            &mut i.parse_per_object,
            &mut i.intersect_per_ray_object,
            &mut i.intersect_per_task,
            &mut i.plan_per_task,
            &mut i.composite_per_ray,
            &mut i.composite_per_piece,
            &mut i.png_per_pixel,
            &mut i.dispatch_per_task,
            &mut i.record_per_task,
            &mut i.holders_per_worker,
            &mut i.pick_per_holder,
            &mut i.progress_per_worker,
            &mut i.open_per_byte,
            &mut i.per_event,
            &mut i.per_send,
            &mut i.latency,
            &mut i.message_overhead_bytes,
            &mut i.per_message,
        ] {
            *zero = 0.0;
        }
        i.link_bytes_per_s = f64::INFINITY;
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
                .map(|_| Band { rays: 64 * 64, pieces: 64 * 64, lanes: (0..datasets).map(lane).collect() })
                .collect(),
        }
    }

    fn config(workers: usize, threads: usize) -> FarmConfig {
        FarmConfig {
            workers,
            worker_threads: threads,
            coordinator_cores: 4,
            loops: 1,
            coordinators: 1,
            spread_bands: false,
            batch_tasks: 256 * threads as u64,
            bands_in_flight: 2,
            dispatch: Dispatch::Scan,
            bvh: false,
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
        // Some 5 µs of casting per task: the coordinator's link (24 bytes a task) and loop
        // stay far from busy.
        inputs.cast_per_sample = 1e-7;
        inputs.dispatch_per_task = 2e-9;
        inputs.record_per_task = 1e-9;
        let t8 = run(&work, &inputs, &config(8, 8), 1).seconds;
        let t16 = run(&work, &inputs, &config(16, 8), 1).seconds;
        let t32 = run(&work, &inputs, &config(32, 8), 1).seconds;
        assert!((t8 / t16 - 2.0).abs() < 0.1, "8 → 16 workers: {t8} / {t16}");
        assert!((t16 / t32 - 2.0).abs() < 0.1, "16 → 32 workers: {t16} / {t32}");
    }

    #[test]
    fn a_coordinator_bound_farm_stops_getting_faster() {
        let work = workload(4, 64, &[4096]);
        let mut inputs = cast_only();
        // Handing out a task costs the loop as much as casting it costs one worker core.
        inputs.dispatch_per_task = work.samples() as f64 / work.tasks() as f64 * inputs.cast_per_sample;
        let runs: Vec<Outcome> = [8, 16, 32].iter().map(|&w| run(&work, &inputs, &config(w, 8), 1)).collect();
        let loop_work = work.tasks() as f64 * inputs.dispatch_per_task;
        for out in &runs {
            assert!(out.seconds >= loop_work, "the loop's own work bounds the job");
            assert!(out.loop_busy > 0.9, "loop busy {}", out.loop_busy);
        }
        assert!(runs[2].seconds > 0.9 * runs[0].seconds, "{} vs {}", runs[2].seconds, runs[0].seconds);
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
