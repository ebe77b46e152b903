//! The volume-rendering phase of Algorithm 2 as a scheduler: it knows which piece tasks are
//! ready, hands them out in batches of one dataset, takes results back in any order, and
//! composites the image once every task is cast or culled. It does no IO and knows no
//! threads or sockets, so one copy serves every driver: the local renderer casts its batches
//! on rayon threads while one dataset at a time is resident (`render::grouped`); the farm's
//! coordinator sends them to the workers that hold each dataset, several datasets at once.
//!
//! # Waves
//! A dataset's tasks are split into *waves* by their rank along their ray: wave k holds,
//! for every ray, the tasks of the k-th piece of that ray that the dataset covers. A wave is
//! handed out only once the dataset's previous wave is wholly recorded; waves of different
//! datasets are independent, so any number of datasets can be in flight at once.
//!
//! # Early termination that does not depend on timing
//! Two things use what is known of the ray in front of a piece, and they obey different
//! rules, because the image must be the same bytes whatever order results arrive in:
//!
//! * **Culling** a whole task uses every result that has arrived: leaving the missing ones
//!   out gives a *lower bound* on the opacity in front (opacity only grows). A task whose
//!   bound has reached the termination threshold (plus [`CULL_MARGIN`], which absorbs the
//!   rounding of the bound) is dropped. Whether a task is culled depends on timing, but the
//!   image does not: composition stops at the first piece in front of which the ray is
//!   opaque, which lies in front of every task that could ever be culled.
//! * **Stopping early inside a piece** changes the piece's result, so its front must be the
//!   same in every schedule. It is the composite of the pieces in front that belong wholly
//!   to the same dataset: they lie in the dataset's earlier waves, which are always recorded
//!   before this wave is handed out. It is a lower bound on the true front, so a cast that
//!   stops on it stops no earlier than Algorithm 1 would (SPEC §4.4 allows the difference).
//!
//! Both the local renderer and the farm therefore produce identical images; what timing
//! changes is only how many samples are saved. In a scene of one dataset the rule loses
//! nothing; with several, a piece behind another dataset's translucent piece casts until its
//! own opacity reaches termination instead of the ray's (BENCHMARKS.md measures the cost).
//!
//! # Datasets in front-to-back order
//! [`Scheduler::datasets`] lists the datasets in an order that follows the rays front to
//! back where the scene allows it (a greedy order of the graph "dataset A is met just before
//! dataset B on n rays", Eades–Lin–Smyth, exact when that graph has no cycle). A driver
//! that visits datasets in that order (the local renderer does) culls the most.

use std::collections::HashMap;

use super::error::ScheduleError;
use super::intersection::{Intersections, INDEX_BYTES};
use super::kept;
use super::wire::TaskWriter;
use super::workunit::{PieceRgba, PieceTask};
use crate::composite::Rgba;
use crate::scene::Scene;

/// How far above the termination threshold a lower bound on the opacity in front must be
/// before a task is culled. The bound is computed with the same arithmetic as composition,
/// but with pieces left out, and floating-point compositing is monotone only to within a few
/// ulps per piece: the margin keeps "culled" a proof that composition stops in front.
pub const CULL_MARGIN: f64 = 1e-9;

/// A batch of tasks of one dataset, ready to cast. Results must come back in task order,
/// through [`Scheduler::record`] with the batch's id.
#[derive(Clone, Debug, PartialEq)]
pub struct Batch {
    /// Unique within its scheduler; a batch handed out again after [`Scheduler::abandon`]
    /// gets a new one, so a late answer to the old one is recognised and refused.
    pub id: u64,
    /// The dataset index in the scene; every task's object uses it.
    pub dataset: usize,
    /// How many times these tasks were handed out before and given up ([`Scheduler::abandon`]):
    /// 0 for a first dispatch. A driver sends it with the batch, checks it on the answer, and
    /// can fail a job whose batch every worker gives up on.
    pub attempt: u32,
    /// The tasks, each with its front opacity set.
    pub tasks: Vec<PieceTask>,
}

/// A batch handed out by [`Scheduler::next_batch_encoded`], its tasks in the writer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct EncodedBatch {
    /// As [`Batch::id`].
    pub id: u64,
    /// As [`Batch::dataset`].
    pub dataset: usize,
    /// As [`Batch::attempt`].
    pub attempt: u32,
    /// How many tasks it holds.
    pub tasks: usize,
}

/// Where a batch's tasks go as they are decided: a list, or their wire form.
trait TaskSink {
    fn reserve(&mut self, tasks: usize);
    fn push(&mut self, task: &PieceTask);
}

impl TaskSink for Vec<PieceTask> {
    fn reserve(&mut self, tasks: usize) {
        self.reserve_exact(tasks);
    }

    #[inline]
    fn push(&mut self, task: &PieceTask) {
        Vec::push(self, *task);
    }
}

impl TaskSink for TaskWriter {
    fn reserve(&mut self, tasks: usize) {
        TaskWriter::reserve(self, tasks);
    }

    #[inline]
    fn push(&mut self, task: &PieceTask) {
        TaskWriter::push(self, task);
    }
}

/// Where a task stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Status {
    /// Not handed out, or handed out and not answered yet.
    Pending,
    /// Cast; its result is in `results`.
    Done,
    /// Dropped: the ray was known to be opaque in front of it.
    Culled,
}

/// What the scheduler decides for a task when it hands it out.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Decision {
    /// Cast it, stopping inside the piece on this front opacity.
    Cast(f64),
    /// The ray is opaque in front of it.
    Cull,
}

/// One dataset's progress through its waves, which lie in the scheduler's `queue`.
#[derive(Debug, Default)]
struct Lane {
    /// Where each wave starts in the queue, then where the last one ends (empty for a
    /// dataset without tasks).
    waves: Vec<u32>,
    /// The wave being handed out.
    wave: usize,
    /// The queue position of that wave's next task to hand out.
    cursor: usize,
    /// Task lists of abandoned batches of that wave, with the attempt they were, to hand
    /// out again first.
    retry: Vec<(Vec<u32>, u32)>,
    /// Batches of the current wave handed out and not yet recorded.
    outstanding: usize,
}

impl Lane {
    fn wave_count(&self) -> usize {
        self.waves.len().saturating_sub(1)
    }

    /// Where wave `k` ends in the queue.
    fn end_of(&self, k: usize) -> usize {
        self.waves[k + 1] as usize
    }
}

struct InFlight {
    dataset: usize,
    attempt: u32,
    tasks: Vec<u32>,
}

/// How far a scheduler has got, in tasks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Progress {
    /// Every task of the region.
    pub total: u64,
    /// Tasks recorded.
    pub cast: u64,
    /// Tasks culled.
    pub culled: u64,
}

impl Progress {
    /// Whether every task is recorded or culled.
    pub fn is_complete(&self) -> bool {
        self.cast + self.culled == self.total
    }
}

/// The volume-rendering phase of one region of the image (the whole image, or a tile of
/// rows): see the module documentation.
pub struct Scheduler {
    inter: Intersections,
    dataset_of_object: Vec<u32>,
    /// Per object, how far a lit colour may exceed the opacity it is premultiplied by
    /// ([`crate::scene::Object::colour_gain`]; 1 unlit); empty when no object is lit, so
    /// an unlit scene's results are checked without looking their objects up.
    gain_of_object: Vec<f32>,
    termination: f64,
    batch_tasks: usize,
    status: Vec<Status>,
    /// Each task's result as [r, g, b, α] (a `PieceRgba`'s fields), read only once its
    /// status is `Done`: until then it holds whatever a kept list held
    /// ([`kept::for_overwrite`]), or zeros.
    results: Vec<[f32; 4]>,
    order: Vec<usize>,
    /// Every task once, dataset by dataset and wave by wave ([`Plan::queue`]).
    queue: Vec<Queued>,
    lanes: Vec<Lane>,
    in_flight: HashMap<u64, InFlight>,
    next_id: u64,
    progress: Progress,
    /// Per region ray: its leading pieces whose every task is cast, composited. Statuses
    /// only move from pending to done or culled, so this prefix only grows, and the bound a
    /// task's cull test needs starts from it instead of from the ray's first piece: the
    /// same `over` operations in the same order, so the same bound to the bit.
    ///
    /// Held packed ([`KnownFront::pack`]), zero the clear front: a new list is then
    /// allocated zeroed, and its pages are faulted in only for the rays it is written for.
    /// Only a task that does not lead its ray reads or writes it, so on a scene where each
    /// ray meets one object (the CT head) none is; as `KnownFront`s, filling the list
    /// faulted in 16 bytes a ray on the planning thread (a thousand faults at 512², about
    /// 4 ms on a VM that takes 4 µs a fault; BENCHMARKS.md).
    known: Vec<PackedFront>,
}

/// A ray's leading pieces that are wholly cast: how many, and their composite's opacity.
/// Opacity is all that culling and in-piece fronts read, and compositing computes it
/// without the colour (`Rgba::over`, `Rgba::colocated`: the same operations on the
/// opacities alone), so the colour is not kept: 16 bytes a ray instead of 40.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct KnownFront {
    pieces: u32,
    alpha: f64,
}

impl KnownFront {
    /// The front in 16 bytes, all zero for the clear front (no piece, opacity `+0.0`).
    fn pack(self) -> PackedFront {
        u128::from(self.pieces) | u128::from(self.alpha.to_bits()) << 64
    }

    /// The front [`KnownFront::pack`] packed, bit for bit.
    fn unpack(bits: PackedFront) -> KnownFront {
        KnownFront { pieces: bits as u32, alpha: f64::from_bits((bits >> 64) as u64) }
    }
}

/// A [`KnownFront`] as the scheduler holds it: the piece count in the low 32 bits, the
/// opacity's bits in the high 64. An integer, so that a new list of them is allocated zeroed.
type PackedFront = u128;

/// [`super::limits::BYTES_PER_BAND_RAY`] counts a known front as 16 bytes.
const _: () = assert!(std::mem::size_of::<PackedFront>() == 16);

impl Scheduler {
    /// A scheduler for the tasks of `inter` (a region of `scene`'s image), handing out
    /// batches of at most `batch_tasks` tasks.
    pub fn new(scene: &Scene, inter: Intersections, batch_tasks: usize) -> Result<Scheduler, ScheduleError> {
        let n = inter.tasks.len();
        if n > Queued::MAX_TASKS {
            return Err(ScheduleError::TooManyTasks { tasks: n as u64, max: Queued::MAX_TASKS as u64 });
        }
        let dataset_of_object: Vec<u32> = scene.objects().iter().map(|o| o.dataset() as u32).collect();
        let gains: Vec<f32> = scene.objects().iter().map(|o| o.colour_gain() as f32).collect();
        let gain_of_object = if gains.iter().all(|&g| g == 1.0) { Vec::new() } else { gains };
        let Plan { order, queue, waves } = plan(&inter, &dataset_of_object, scene.datasets().len());
        let lanes: Vec<Lane> = waves
            .into_iter()
            .map(|waves| Lane { cursor: waves.first().map_or(0, |&s| s as usize), waves, ..Lane::default() })
            .collect();
        Ok(Scheduler {
            known: kept::filled(inter.rays(), KnownFront::default().pack()),
            status: kept::filled(n, Status::Pending),
            results: kept::for_overwrite(n),
            progress: Progress { total: n as u64, ..Progress::default() },
            inter,
            dataset_of_object,
            gain_of_object,
            termination: scene.render().termination,
            batch_tasks: batch_tasks.max(1),
            order,
            queue,
            lanes,
            in_flight: HashMap::new(),
            next_id: 0,
        })
    }

    /// The region's rays, pieces and tasks.
    pub fn intersections(&self) -> &Intersections {
        &self.inter
    }

    /// The region's intersections, given back (to [`super::intersection::recycle`] them
    /// once the region is composited); the scheduler's own lists are kept for the next
    /// scheduler (`kept.rs`).
    pub fn into_intersections(self) -> Intersections {
        kept::keep(self.known);
        kept::keep(self.status);
        kept::keep(self.results);
        kept::keep(self.queue);
        self.inter
    }

    /// The datasets that have tasks, front to back as far as the scene allows.
    pub fn datasets(&self) -> &[usize] {
        &self.order
    }

    /// Tasks cast, culled, and in all.
    pub fn progress(&self) -> Progress {
        self.progress
    }

    /// Bytes this scheduler holds on the heap: its intersections, the tasks' statuses,
    /// results and waves. What a driver's memory bound ([`super::dispatch::Admission`])
    /// counts; the few in-flight lists are left out (they are at most the waves again).
    pub fn heap_bytes(&self) -> u64 {
        use std::mem::size_of;
        let inter = self.inter.tasks.capacity() * size_of::<PieceTask>()
            + (self.inter.piece_start.capacity() + self.inter.ray_start.capacity()) * INDEX_BYTES as usize;
        let per_task = self.status.capacity() * size_of::<Status>() + self.results.capacity() * size_of::<[f32; 4]>();
        let waves: usize =
            (self.queue.capacity() + self.lanes.iter().map(|l| l.waves.capacity()).sum::<usize>()) * size_of::<u32>();
        (inter + per_task + waves + self.known.capacity() * size_of::<PackedFront>()) as u64
    }

    /// Whether every task is recorded or culled.
    pub fn is_complete(&self) -> bool {
        self.progress.is_complete()
    }

    /// Whether dataset `d` has nothing left to hand out or wait for.
    pub fn is_dataset_done(&self, d: usize) -> bool {
        self.lanes.get(d).is_none_or(|l| {
            l.wave >= l.wave_count()
                || (l.wave + 1 == l.wave_count()
                    && l.cursor >= l.end_of(l.wave)
                    && l.outstanding == 0
                    && l.retry.is_empty())
        })
    }

    /// The next batch of dataset `d`, or `None` when none is ready: either the dataset is
    /// done, or its current wave is wholly handed out and batches of it are still
    /// unanswered (the next wave needs their results). Tasks whose ray is known to be opaque
    /// in front are culled here and never handed out.
    pub fn next_batch(&mut self, d: usize) -> Option<Batch> {
        self.next_batch_of(d, self.batch_tasks)
    }

    /// [`Scheduler::next_batch`] with at most `max` candidate tasks (and at most the
    /// scheduler's batch size): a driver that casts the waves itself can cut a wave's last
    /// tasks into smaller batches ([`Scheduler::wave_left`]), so that its threads end the
    /// wave together instead of one casting a whole batch while the others wait. Which tasks
    /// go together never changes a result.
    pub fn next_batch_of(&mut self, d: usize, max: usize) -> Option<Batch> {
        let mut tasks = Vec::new();
        let (id, attempt) = self.hand_out(d, &mut tasks, max.clamp(1, self.batch_tasks))?;
        Some(Batch { id, dataset: d, attempt, tasks })
    }

    /// The tasks of dataset `d`'s current wave not handed out yet (retried batches left
    /// out): what a driver splits among its threads before the wave ends.
    pub fn wave_left(&self, d: usize) -> usize {
        self.lanes.get(d).filter(|l| l.wave < l.wave_count()).map_or(0, |l| l.end_of(l.wave).saturating_sub(l.cursor))
    }

    /// [`Scheduler::next_batch`] with its tasks written straight into their wire form
    /// ([`super::wire::encode_tasks`]'s bytes) as they are decided, never held as a list of
    /// tasks: the same batch, the same bytes. `writer` is cleared first.
    pub fn next_batch_encoded(&mut self, d: usize, writer: &mut TaskWriter) -> Option<EncodedBatch> {
        writer.clear();
        let (id, attempt) = self.hand_out(d, writer, self.batch_tasks)?;
        Some(EncodedBatch { id, dataset: d, attempt, tasks: writer.len() })
    }

    /// The next batch of dataset `d`, of at most `max` candidates, its tasks given to
    /// `sink`: its id and attempt.
    fn hand_out(&mut self, d: usize, sink: &mut impl TaskSink, max: usize) -> Option<(u64, u32)> {
        loop {
            let lane = self.lanes.get_mut(d)?;
            if lane.wave >= lane.wave_count() {
                return None;
            }
            let first_wave = lane.wave == 0;
            let end = lane.end_of(lane.wave);
            let (retry, attempt) = if let Some((retry, attempt)) = lane.retry.pop() {
                (Some(retry), attempt + 1)
            } else if lane.cursor < end {
                (None, 0)
            } else if lane.outstanding > 0 {
                return None;
            } else {
                lane.wave += 1;
                if lane.wave < lane.wave_count() {
                    lane.cursor = lane.waves[lane.wave] as usize;
                }
                continue;
            };
            // The candidates are read in place from the queue (or the retried list), which
            // is moved out for the loop so that deciding may update the scheduler.
            let queue = std::mem::take(&mut self.queue);
            let chunk: &[Queued] = match &retry {
                Some(_) => &[],
                None => &queue[lane.cursor..(lane.cursor + max).min(end)],
            };
            lane.cursor += chunk.len();
            let n = retry.as_ref().map_or(chunk.len(), Vec::len);
            let mut cast = Vec::with_capacity(n);
            sink.reserve(n);
            // A retried batch's tasks come without their flags: each is decided in full.
            for &t in retry.iter().flatten() {
                self.take(t, false, first_wave, sink, &mut cast);
            }
            for (i, q) in chunk.iter().enumerate() {
                if let Some(ahead) = chunk.get(i + PREFETCH_AHEAD) {
                    prefetch(&self.inter.tasks[ahead.task() as usize]);
                }
                self.take(q.task(), q.leads(), first_wave, sink, &mut cast);
            }
            self.queue = queue;
            if cast.is_empty() {
                continue;
            }
            let id = self.next_id;
            self.next_id += 1;
            self.lanes[d].outstanding += 1;
            self.in_flight.insert(id, InFlight { dataset: d, attempt, tasks: cast });
            return Some((id, attempt));
        }
    }

    /// Decides task `t` ([`Scheduler::decide`]) and culls it, or writes it to `sink` and
    /// `cast`.
    #[inline(always)]
    fn take(&mut self, t: u32, leads: bool, first_wave: bool, sink: &mut impl TaskSink, cast: &mut Vec<u32>) {
        match self.decide(t as usize, first_wave, leads) {
            Decision::Cull => {
                self.status[t as usize] = Status::Culled;
                self.progress.culled += 1;
            }
            Decision::Cast(front) => {
                let mut task = self.inter.tasks[t as usize];
                // A task is intersected with a clear front (or as whole), which is what
                // setting 0 would write: most tasks skip the rounding.
                if front > 0.0 {
                    task.set_front_alpha(front);
                }
                sink.push(&task);
                cast.push(t);
            }
        }
    }

    /// Stores the results of batch `id`, in the batch's task order. Refuses an unknown (or
    /// already recorded, or abandoned) batch, a wrong count, and results that are not
    /// premultiplied colours and opacities in [0, 1] (a lit object's colour may exceed its
    /// opacity by its [`crate::scene::Object::colour_gain`]).
    pub fn record(&mut self, id: u64, results: &[PieceRgba]) -> Result<(), ScheduleError> {
        let Some(batch) = self.in_flight.get(&id) else {
            return Err(ScheduleError::UnknownBatch { id });
        };
        if batch.tasks.len() != results.len() {
            return Err(ScheduleError::ResultCount { id, expected: batch.tasks.len(), got: results.len() });
        }
        let bad = if self.gain_of_object.is_empty() {
            results.iter().position(|r| !plausible(r, 1.0))
        } else {
            let gain = |i: usize| self.gain_of_object[self.inter.tasks[batch.tasks[i] as usize].object as usize];
            (0..results.len()).find(|&i| !plausible(&results[i], gain(i)))
        };
        if let Some(i) = bad {
            return Err(ScheduleError::BadResult { id, index: i });
        }
        let batch = self.in_flight.remove(&id).expect("looked up above");
        for (&t, r) in batch.tasks.iter().zip(results) {
            self.status[t as usize] = Status::Done;
            self.results[t as usize] = [r.colour[0], r.colour[1], r.colour[2], r.alpha];
        }
        self.progress.cast += batch.tasks.len() as u64;
        self.lanes[batch.dataset].outstanding -= 1;
        Ok(())
    }

    /// Gives batch `id` up (its worker was lost or refused it): its tasks will be handed out
    /// again, in a batch with a new id, and any late answer to this one is refused.
    pub fn abandon(&mut self, id: u64) -> Result<(), ScheduleError> {
        let batch = self.in_flight.remove(&id).ok_or(ScheduleError::UnknownBatch { id })?;
        let lane = &mut self.lanes[batch.dataset];
        lane.outstanding -= 1;
        lane.retry.push((batch.tasks, batch.attempt));
        Ok(())
    }

    /// Region ray `r`'s colour and opacity: its pieces front to back (co-located objects
    /// combined first, SPEC §4.4) until it is opaque. Call once [`Scheduler::is_complete`].
    #[inline]
    pub fn composite_ray(&self, r: usize) -> Rgba {
        debug_assert!(self.is_complete(), "composite before every task is cast");
        let (acc, _) =
            self.front_to_back(Rgba::CLEAR, self.inter.pieces_of(r), self.termination, |p| self.piece_rgba(p));
        acc
    }

    /// Every ray of the intersections composited over `background`, in ray order (rayon):
    /// the pixels of the rows they cover. The one composition step of every driver.
    pub fn composite_pixels(&self, background: [f64; 3]) -> Vec<[f64; 3]> {
        use rayon::prelude::*;
        (0..self.inter.rays()).into_par_iter().map(|r| self.composite_ray(r).with_background(background)).collect()
    }

    /// The sample positions of the culled tasks (`samples_skipped`: never cast).
    pub fn culled_samples(&self, scene: &Scene) -> u64 {
        use rayon::prelude::*;
        let culled: Vec<&PieceTask> = self.culled().collect();
        culled.par_iter().map(|t| super::intersection::task_sample_positions(scene, t)).sum()
    }

    /// The tasks that were culled (for statistics: their sample positions were never cast).
    pub fn culled(&self) -> impl Iterator<Item = &PieceTask> {
        self.inter.tasks.iter().zip(&self.status).filter(|(_, s)| **s == Status::Culled).map(|(t, _)| t)
    }

    /// The ray's pieces `pieces` laid front to back until the accumulated opacity reaches
    /// `stop_at` (SPEC §4.4 with the scene's termination); `rgba(p)` is piece `p`'s
    /// contribution, `None` when the piece was culled (the ray is opaque in front of it).
    /// Returns the accumulation and whether it stopped before the last piece. The one
    /// front-to-back loop of the scheduler: composition, culling bounds and deterministic
    /// fronts all use it.
    fn front_to_back(
        &self,
        mut acc: Rgba,
        pieces: std::ops::Range<usize>,
        stop_at: f64,
        mut rgba: impl FnMut(usize) -> Option<Rgba>,
    ) -> (Rgba, bool) {
        for p in pieces {
            if acc.alpha >= stop_at {
                return (acc, true);
            }
            match rgba(p) {
                Some(c) => acc.over(c),
                None => return (acc, true),
            }
        }
        (acc, false)
    }

    /// Piece `p`'s contribution from what is recorded: its one task's result, or the
    /// co-located combination of its tasks' results (SPEC §4.4), tasks not yet cast left out
    /// (a lower bound on its opacity). `None` when a task of the piece was culled.
    fn piece_rgba(&self, p: usize) -> Option<Rgba> {
        let tasks = self.inter.tasks_of(p);
        if tasks.len() == 1 {
            return match self.status[tasks.start] {
                Status::Done => Some(self.result(tasks.start).into()),
                Status::Pending => Some(Rgba::CLEAR),
                Status::Culled => None,
            };
        }
        if tasks.clone().any(|t| self.status[t] == Status::Culled) {
            return None;
        }
        Some(Rgba::colocated(tasks.filter(|&t| self.status[t] == Status::Done).map(|t| self.result(t).into())))
    }

    /// Task `t`'s recorded result.
    fn result(&self, t: usize) -> PieceRgba {
        let [r, g, b, alpha] = self.results[t];
        PieceRgba { colour: [r, g, b], alpha }
    }

    /// Whether every task of piece `p` belongs to dataset `d`.
    fn piece_is_of(&self, p: usize, d: u32) -> bool {
        self.inter.tasks_of(p).all(|t| self.dataset_of_object[self.inter.tasks[t].object as usize] == d)
    }

    /// [`Scheduler::piece_rgba`]'s opacity alone, computed as `Rgba::colocated` computes it
    /// (the colour never enters it), so the same bits.
    fn piece_alpha(&self, p: usize) -> Option<f64> {
        let tasks = self.inter.tasks_of(p);
        if tasks.len() == 1 {
            return match self.status[tasks.start] {
                Status::Done => Some(f64::from(self.results[tasks.start][3])),
                Status::Pending => Some(0.0),
                Status::Culled => None,
            };
        }
        let mut transmittance = 1.0;
        for t in tasks {
            match self.status[t] {
                Status::Done => transmittance *= 1.0 - f64::from(self.results[t][3]),
                Status::Pending => {}
                Status::Culled => return None,
            }
        }
        Some(1.0 - transmittance)
    }

    /// Whether every task of piece `p` is cast.
    fn piece_is_cast(&self, p: usize) -> bool {
        self.inter.tasks_of(p).all(|t| self.status[t] == Status::Done)
    }

    /// Cull task `t`, or cast it with the deterministic front (module documentation).
    /// `first_wave`: `t` is in its dataset's first wave, so no piece in front is the
    /// dataset's and that front is clear without looking. `leads`: `t`'s piece is its ray's
    /// first ([`Queued::leads`]), so nothing lies in front: cast with a clear front, without
    /// reading the ray's pieces (three dependent reads per task, which missed the cache on a
    /// coordinator's bands).
    ///
    /// Both use opacities only, laid over each other as `Rgba::over` lays them
    /// ([`over_alpha`]), so they are the bits the full composite would give.
    ///
    /// Inlined into both of `hand_out`'s instances: called from two, the compiler kept it
    /// out of line, a call per task.
    #[inline(always)]
    fn decide(&mut self, t: usize, first_wave: bool, leads: bool) -> Decision {
        if leads {
            return Decision::Cast(0.0);
        }
        let task = &self.inter.tasks[t];
        let r = self.inter.local_ray(task.ray);
        let ray_start = self.inter.ray_start[r] as usize;
        let cull_at = self.termination + CULL_MARGIN;
        // The wholly cast pieces in front, from where the last decision on this ray left
        // them (no piece of the known prefix holds a pending task, so `t` lies behind it);
        // then the rest of the bound as `front_to_back` would go on. A piece lies in front
        // of `t` when its tasks end at or before `t`.
        let KnownFront { pieces, mut alpha } = KnownFront::unpack(self.known[r]);
        let mut p = ray_start + pieces as usize;
        let in_front = |p: usize| self.inter.piece_start[p + 1] as usize <= t;
        debug_assert!(self.inter.piece_start[p] as usize <= t, "a pending task's piece lies behind the known pieces");
        while alpha < cull_at && in_front(p) && self.piece_is_cast(p) {
            alpha = over_alpha(alpha, self.piece_alpha(p).expect("a cast piece has an opacity"));
            p += 1;
        }
        if p > ray_start + pieces as usize {
            self.known[r] = KnownFront { pieces: (p - ray_start) as u32, alpha }.pack();
        }
        while in_front(p) {
            if alpha >= cull_at {
                return Decision::Cull;
            }
            match self.piece_alpha(p) {
                Some(a) => alpha = over_alpha(alpha, a),
                None => return Decision::Cull,
            }
            p += 1;
        }
        if alpha >= cull_at {
            return Decision::Cull;
        }
        let task = &self.inter.tasks[t];
        if task.is_whole() || first_wave {
            return Decision::Cast(0.0);
        }
        // Pieces wholly of this dataset are in its earlier waves: all recorded, none culled
        // (a culled one would have stopped the bound above).
        let d = self.dataset_of_object[task.object as usize];
        let mut front = 0.0;
        for q in ray_start..p {
            if front >= self.termination {
                break;
            }
            if self.piece_is_of(q, d) {
                front = over_alpha(front, self.piece_alpha(q).expect("no piece in front is culled"));
            }
        }
        Decision::Cast(front)
    }
}

/// How many candidates ahead [`Scheduler::hand_out`] asks for a task's line.
const PREFETCH_AHEAD: usize = 8;

/// Asks the processor to start loading `x`'s cache line. A wave's tasks are spread over the
/// band's list (other datasets' tasks lie between them) and the band was intersected long
/// before, so the first read of each task in `decide` waited on memory: a fifth of
/// `next_batch_encoded`'s time (BENCHMARKS.md, issue 21). A hint only: it changes no value.
#[inline(always)]
fn prefetch<T>(x: &T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        // SAFETY: SSE is in x86-64's baseline, and a prefetch reads nothing a program can
        // see and never faults, whatever the address.
        unsafe { _mm_prefetch::<_MM_HINT_T0>((x as *const T).cast()) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = x;
}

/// The opacity of `behind` laid behind an accumulation of opacity `front`: `Rgba::over`'s
/// opacity, the same operations.
#[inline]
fn over_alpha(front: f64, behind: f64) -> f64 {
    front + behind * (1.0 - front)
}

/// A result a cast can produce: finite, opacity in [0, 1], colour premultiplied by it (each
/// component at most the opacity times the object's `gain`, up to f32 rounding).
fn plausible(r: &PieceRgba, gain: f32) -> bool {
    let a = r.alpha;
    (0.0..=1.0).contains(&a) && r.colour.iter().all(|&c| (0.0..=a * gain * (1.0 + 1e-5) + 1e-7).contains(&c))
}

/// Every task of a region once, dataset by dataset and wave by wave, and the datasets' order:
/// what [`plan`] works out for [`Scheduler::new`].
struct Plan {
    /// The datasets that have tasks, front to back as far as the scene allows.
    order: Vec<usize>,
    /// Every task once: the datasets in `order`, each one's waves in turn, each wave in task
    /// (so ray) order. One flat list instead of a list per wave, so that planning makes
    /// three allocations whatever the number of waves, and needs no merge.
    queue: Vec<Queued>,
    /// Per dataset (scene index): where each of its waves starts in `queue`, then where the
    /// last one ends; empty for a dataset without tasks.
    waves: Vec<Vec<u32>>,
}

/// Orders datasets front to back as far as the scene allows, and splits each dataset's
/// tasks into waves by their rank along their ray.
///
/// Rays are independent, so chunks of them are surveyed in parallel ([`Survey`]): each
/// writes every task's (dataset, rank) key and counts them. The counts give every wave's
/// place in one flat list, which one pass over the keys then fills in task order (a
/// counting sort, stable): the same waves in the same order as sorting the tasks by
/// (dataset, rank, index), and the votes and depths are the same numbers, summed in the same
/// order, as one pass over the rays would give.
fn plan(inter: &Intersections, dataset_of_object: &[u32], datasets: usize) -> Plan {
    use rayon::prelude::*;
    const RAYS_PER_SURVEY: usize = 8192;
    let rays = inter.rays();
    let n = inter.tasks.len();
    // Each chunk's rays, and its tasks' keys: chunks of rays own disjoint runs of tasks.
    let mut keys = kept::for_overwrite::<u32>(n);
    let mut chunks = Vec::with_capacity(rays.div_ceil(RAYS_PER_SURVEY));
    let mut rest = keys.as_mut_slice();
    for first in (0..rays).step_by(RAYS_PER_SURVEY) {
        let chunk = first..(first + RAYS_PER_SURVEY).min(rays);
        let tasks = inter.tasks_of_rays(chunk.clone()).len();
        let (head, tail) = std::mem::take(&mut rest).split_at_mut(tasks);
        chunks.push((chunk, head));
        rest = tail;
    }
    let surveys: Vec<Survey> = chunks
        .into_par_iter()
        .map(|(chunk, keys)| Survey::of(inter, dataset_of_object, datasets, chunk, keys))
        .collect();
    let mut all = Survey::empty(datasets);
    for survey in surveys {
        all.merge(survey);
    }
    let used: Vec<usize> = (0..datasets).filter(|&d| all.count[d] > 0).collect();
    let mean_depth: Vec<f64> =
        (0..datasets).map(|d| if all.count[d] > 0 { all.depth_sum[d] / all.count[d] as f64 } else { 0.0 }).collect();
    let order = greedy_order(&used, &all.votes, &mean_depth);
    // Every wave's start in the queue, datasets in `order`; `next` is the same, flat, as the
    // cursor each wave is filled from, found at `slot[d] + rank`.
    let mut waves: Vec<Vec<u32>> = vec![Vec::new(); datasets];
    let mut slot = vec![0u32; datasets];
    let mut next: Vec<u32> = Vec::new();
    let mut at = 0u32;
    for &d in &order {
        slot[d] = next.len() as u32;
        let starts = &mut waves[d];
        for &size in &all.waves[d] {
            starts.push(at);
            next.push(at);
            at += size;
        }
        starts.push(at);
    }
    debug_assert_eq!(at as usize, n, "every task is in one wave");
    let mut queue = kept::for_overwrite::<Queued>(n);
    for (t, &key) in keys.iter().enumerate() {
        let cursor = &mut next[(slot[(key >> RANK_BITS) as usize] + (key & RANK_MASK)) as usize];
        queue[*cursor as usize] = Queued::new(t as u32, key & LEADS != 0);
        *cursor += 1;
    }
    kept::keep(keys);
    Plan { order, queue, waves }
}

/// A task's key in [`plan`]'s counting sort: its dataset above [`RANK_BITS`] bits, which hold
/// its rank and, in the top one, whether it [`Queued::leads`]. A scene holds at most
/// [`crate::scene::MAX_OBJECTS`] (4096) objects, so datasets fit the upper 16 bits, and a ray
/// crosses at most 4096 segments, which make at most 8191 pieces: a rank fits 15 bits.
const RANK_BITS: u32 = 16;
const LEADS: u32 = 1 << (RANK_BITS - 1);
const RANK_MASK: u32 = LEADS - 1;
const _: () = assert!(2 * crate::scene::MAX_OBJECTS < LEADS as usize);

/// A task in a scheduler's queue: its index, and whether its piece is its ray's first
/// ([`Queued::leads`]), in the top bit. Which is why a region holds at most
/// [`Queued::MAX_TASKS`] tasks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Queued(u32);

impl Queued {
    const LEADS: u32 = 1 << 31;
    /// The most tasks a region may hold.
    const MAX_TASKS: usize = Queued::LEADS as usize;

    fn new(task: u32, leads: bool) -> Queued {
        debug_assert!((task as usize) < Queued::MAX_TASKS);
        Queued(task | if leads { Queued::LEADS } else { 0 })
    }

    /// The task's index.
    fn task(self) -> u32 {
        self.0 & !Queued::LEADS
    }

    /// Whether the task's piece is the first of its ray: nothing lies in front of it, so it
    /// is never culled and its front is clear.
    fn leads(self) -> bool {
        self.0 & Queued::LEADS != 0
    }
}

/// What a chunk of rays tells [`plan`], per dataset: how many of its tasks each wave holds
/// (wave k: the tasks of the k-th piece of a ray that the dataset covers), how many tasks
/// there are and the sum of their depths; and the votes for the dataset order: each ray
/// votes "A before B" for each pair of datasets it meets one right after the other (first
/// appearances along the ray), which [`greedy_order`] orders (when that graph has no cycle
/// every ray meets datasets in their turn order; ties go to the smaller mean depth).
struct Survey {
    waves: Vec<Vec<u32>>,
    count: Vec<u64>,
    depth_sum: Vec<f64>,
    votes: HashMap<(usize, usize), u64>,
}

impl Survey {
    fn empty(datasets: usize) -> Survey {
        Survey {
            waves: vec![Vec::new(); datasets],
            count: vec![0; datasets],
            depth_sum: vec![0.0; datasets],
            votes: HashMap::new(),
        }
    }

    /// Surveys rays `rays`, writing each of their tasks' key ([`RANK_BITS`]) into `keys`,
    /// which holds exactly their tasks.
    fn of(
        inter: &Intersections,
        dataset_of_object: &[u32],
        datasets: usize,
        rays: std::ops::Range<usize>,
        keys: &mut [u32],
    ) -> Survey {
        let mut survey = Survey::empty(datasets);
        let first_task = inter.tasks_of_rays(rays.clone()).start;
        // Per ray: (dataset, pieces of it so far, last piece) — a handful of datasets per ray,
        // in the order the ray first meets them.
        let mut seen: Vec<(usize, usize, usize)> = Vec::new();
        // Neighbouring rays mostly meet the same datasets in the same order: their votes are
        // counted once per run of such rays rather than hashed ray by ray.
        let (mut run, mut run_len): (Vec<usize>, u64) = (Vec::new(), 0);
        for r in rays {
            seen.clear();
            let pieces = inter.pieces_of(r);
            let first = pieces.start;
            for p in pieces {
                let leads = if p == first { LEADS } else { 0 };
                for t in inter.tasks_of(p) {
                    let task = &inter.tasks[t];
                    let d = dataset_of_object[task.object as usize] as usize;
                    survey.depth_sum[d] += task.t0;
                    survey.count[d] += 1;
                    let rank = match seen.iter_mut().find(|s| s.0 == d) {
                        Some(s) if s.2 == p => s.1 - 1,
                        Some(s) => {
                            s.1 += 1;
                            s.2 = p;
                            s.1 - 1
                        }
                        None => {
                            seen.push((d, 1, p));
                            0
                        }
                    };
                    keys[t - first_task] = (d as u32) << RANK_BITS | leads | rank as u32;
                    let lane = &mut survey.waves[d];
                    if lane.len() <= rank {
                        lane.resize(rank + 1, 0);
                    }
                    lane[rank] += 1;
                }
            }
            if run.len() == seen.len() && run.iter().zip(&seen).all(|(&a, b)| a == b.0) {
                run_len += 1;
            } else {
                survey.vote(&run, run_len);
                run.clear();
                run.extend(seen.iter().map(|s| s.0));
                run_len = 1;
            }
        }
        survey.vote(&run, run_len);
        survey
    }

    /// `rays` votes of rays that met datasets `met`, in that order.
    fn vote(&mut self, met: &[usize], rays: u64) {
        for pair in met.windows(2) {
            *self.votes.entry((pair[0], pair[1])).or_insert(0) += rays;
        }
    }

    /// Adds `later`, a survey of the rays after these.
    fn merge(&mut self, later: Survey) {
        for (waves, later) in self.waves.iter_mut().zip(later.waves) {
            if waves.len() < later.len() {
                waves.resize(later.len(), 0);
            }
            for (wave, later) in waves.iter_mut().zip(later) {
                *wave += later;
            }
        }
        for d in 0..self.count.len() {
            self.count[d] += later.count[d];
            self.depth_sum[d] += later.depth_sum[d];
        }
        for (pair, v) in later.votes {
            *self.votes.entry(pair).or_insert(0) += v;
        }
    }
}

/// The Eades–Lin–Smyth greedy ordering of `nodes` under weighted edges `votes[(a, b)]`
/// ("a before b"): sinks go last, sources first, otherwise the node with the largest
/// out-minus-in weight goes next. Exact (a topological order) on an acyclic graph. Ties go
/// to the smaller `depth`, then the lower index.
fn greedy_order(nodes: &[usize], votes: &HashMap<(usize, usize), u64>, depth: &[f64]) -> Vec<usize> {
    let n = depth.len();
    let mut out_edges: Vec<Vec<(usize, u64)>> = vec![Vec::new(); n];
    let mut in_edges: Vec<Vec<(usize, u64)>> = vec![Vec::new(); n];
    for (&(a, b), &v) in votes {
        if a != b && v > 0 {
            out_edges[a].push((b, v));
            in_edges[b].push((a, v));
        }
    }
    let mut remaining = vec![false; n];
    nodes.iter().for_each(|&d| remaining[d] = true);
    let weight = |edges: &[(usize, u64)], remaining: &[bool]| -> u64 {
        edges.iter().filter(|(o, _)| remaining[*o]).map(|(_, v)| v).sum()
    };
    let nearer = |a: &usize, b: &usize| depth[*a].total_cmp(&depth[*b]).then(a.cmp(b));
    let (mut front, mut back) = (Vec::new(), Vec::new());
    for _ in 0..nodes.len() {
        let alive: Vec<usize> = nodes.iter().copied().filter(|&d| remaining[d]).collect();
        let sinks = alive.iter().filter(|&&d| weight(&out_edges[d], &remaining) == 0);
        // The farthest sink goes to the very back.
        let pick = if let Some(&sink) = sinks.max_by(|a, b| nearer(a, b)) {
            back.push(sink);
            sink
        } else {
            let sources = alive.iter().filter(|&&d| weight(&in_edges[d], &remaining) == 0);
            let net = |d: usize| weight(&out_edges[d], &remaining) as i128 - weight(&in_edges[d], &remaining) as i128;
            let best = sources
                .min_by(|a, b| nearer(a, b))
                .or_else(|| alive.iter().min_by(|a, b| net(**b).cmp(&net(**a)).then_with(|| nearer(a, b))));
            let Some(&best) = best else { break };
            front.push(best);
            best
        };
        remaining[pick] = false;
    }
    front.extend(back.into_iter().rev());
    front
}

#[cfg(test)]
mod tests;
