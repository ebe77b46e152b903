//! One band of a farm job, on a thread of its own: the band's intersection and plan, its
//! [`Scheduler`], every per-task step of casting it — deciding fronts and culls and encoding
//! the batches it hands out, decoding and recording the answers — and its composition.
//!
//! The job's event loop ([`super`]) does only per-batch work: it asks a band for batches of
//! a dataset when workers have room for them ([`ToBand::Produce`]), sends them, and hands
//! each accepted answer to its band ([`ToBand::Answer`]). So a job's per-task work runs on
//! as many threads as it has bands in flight, not on one, and a coordinator's throughput
//! grows with its cores. The band tells the loop what changed as [`News`], on the job's one
//! event channel.
//!
//! An answer recorded needs no reply: the loop counts the dataset as possibly ready again
//! as it hands the answer over, and the band takes its messages in order, so a `Produce`
//! sent after an `Answer` finds it recorded, often on the same wake-up. The band's progress
//! and the time its answers took ride on its next `Produced`, or on `Composited`. (A reply
//! per answer cost each batch two more wake-ups, one of the band's thread and one of the
//! loop: 15% of the coordinator's context switches, BENCHMARKS.md.)
//!
//! A band's thread is a blocking thread of the runtime. It ends when the band is
//! composited, when a step fails (the job then fails: [`News`] never carries a panic out,
//! [`super::unwinding`] turns it into the job's error), or when the job's loop drops its
//! sender (the job ended).

use std::ops::Range;
use std::sync::Arc;
use std::time::Instant;

use tokio::sync::mpsc;
use trove_core::render::intersection::{intersect_within, recycle, Intersections};
use trove_core::render::limits::max_band_tasks;
use trove_core::render::schedule::Progress;
use trove_core::render::wire::{decode_results, TaskWriter};
use trove_core::render::Scheduler;
use trove_core::scene::Scene;

use super::raster::Composited;
use super::{unwinding, DriverConfig, Event, JobError, StreamKey};

/// What the job's loop asks of a band.
pub(super) enum ToBand {
    /// Hand out up to `n` batches of dataset `dataset`, encoded for the wire.
    Produce { dataset: usize, n: usize },
    /// The answer to batch `id` (the scheduler's id), taken on the stream and for the attempt
    /// it went out as: its results in `render::wire` form.
    Answer { id: u64, dataset: usize, stream: StreamKey, results: Vec<u8> },
    /// Batches given up (their worker was lost): handed out again later, with new ids.
    Abandon { ids: Vec<u64> },
}

/// A batch a band handed out, ready to go on a stream.
pub(super) struct Ready {
    pub band: usize,
    /// The scheduler's id.
    pub id: u64,
    pub attempt: u32,
    pub tasks: u64,
    /// The tasks in `render::wire` form (shared, not copied, with the request that carries
    /// them, so a batch a busy worker refuses goes again as it was).
    pub encoded: prost::bytes::Bytes,
}

/// What a band tells the job's loop.
pub(super) enum News {
    /// Intersected and planned: it casts from now on.
    Intersected {
        /// Datasets with tasks in the band, front to back.
        datasets: Vec<usize>,
        bytes: u64,
        progress: Progress,
        segments: u64,
        pieces: u64,
        seconds: f64,
        /// Of `seconds`, what `Scheduler::new` took.
        planning: f64,
    },
    /// Batches of `dataset` asked for with [`ToBand::Produce`]: as many as were ready, up to
    /// the number asked; `more` when that many were, so that another may be.
    Produced { dataset: usize, asked: usize, batches: Vec<Ready>, more: bool, progress: Progress, seconds: Seconds },
    /// An answer that did not decode or record (the batch was given back): the worker that
    /// sent it is not trusted with more of the job.
    Refused { id: u64, dataset: usize, stream: StreamKey, why: String },
    /// Every task is cast or culled, and the band's pixels are composited; `seconds`: what
    /// recording the last answers took, not told before.
    Composited { part: Box<Composited>, progress: Progress, seconds: Seconds },
}

/// A band's own time by step, in seconds, for the job's statistics.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Seconds {
    /// Handing batches out (`next_batch`: fronts and culls).
    pub dispatch: f64,
    pub encoding: f64,
    pub decoding: f64,
    pub recording: f64,
}

/// What a band needs to run.
pub(super) struct Start {
    pub band: usize,
    pub rows: Range<u32>,
    pub scene: Arc<Scene>,
    /// The band as the submission's count intersected it, if it kept it.
    pub kept: Option<Intersections>,
    pub batch_tasks: usize,
    pub want_pfm: bool,
    pub config: DriverConfig,
}

/// Starts band `start.band` on a blocking thread; returns the sender its loop listens on.
pub(super) fn spawn(start: Start, events: mpsc::Sender<Event>) -> mpsc::UnboundedSender<ToBand> {
    let (tx, inbox) = mpsc::unbounded_channel();
    tokio::task::spawn_blocking(move || {
        let band = start.band;
        if let Err(e) = run(start, inbox, &events) {
            let _ = events.blocking_send(Event::Failed(e));
        }
        tracing::trace!(band, "band thread ended");
    });
    tx
}

/// The band's life; `Ok` also when the job ended first (its loop dropped the sender).
fn run(start: Start, mut inbox: mpsc::UnboundedReceiver<ToBand>, events: &mpsc::Sender<Event>) -> Result<(), JobError> {
    let Start { band, rows, scene, kept, batch_tasks, want_pfm, config } = start;
    let tell = |news: News| events.blocking_send(Event::Band { band, news }).is_ok();
    let started = Instant::now();
    let (mut scheduler, planned) = unwinding("intersection", || {
        config.inject("intersection");
        // The band's share of the bound: a band denser than its sizing expected is refused
        // as it is intersected, before its tasks are stored.
        let bound = config.memory_bound;
        let inter = match kept {
            Some(inter) => inter,
            None => intersect_within(&scene, rows.clone(), max_band_tasks(bound), bound)?,
        };
        let planned = Instant::now();
        Scheduler::new(&scene, inter, batch_tasks)
            .map(|s| (s, planned))
            .map_err(|source| JobError::Band { rows: rows.clone(), source })
    })??;
    let inter = scheduler.intersections();
    let intersected = News::Intersected {
        datasets: scheduler.datasets().to_vec(),
        bytes: scheduler.heap_bytes(),
        progress: scheduler.progress(),
        segments: inter.segments,
        pieces: inter.pieces() as u64,
        seconds: started.elapsed().as_secs_f64(),
        planning: planned.elapsed().as_secs_f64(),
    };
    if !tell(intersected) {
        return Ok(());
    }
    // Time spent on answers, told with the next news.
    let mut untold = Seconds::default();
    while !scheduler.is_complete() {
        let Some(message) = inbox.blocking_recv() else { return Ok(()) };
        let news = unwinding("casting", || step(&mut scheduler, band, message, &mut untold))?;
        if let Some(news) = news {
            if !tell(news) {
                return Ok(());
            }
        }
    }
    let part = unwinding("composition", || {
        config.inject("composition");
        Composited::of(&scene, rows, &scheduler, want_pfm)
    })?;
    let progress = scheduler.progress();
    // Its buffers go to the next band's intersection, which then writes memory that is
    // already paged in.
    recycle(scheduler.into_intersections());
    tell(News::Composited { part: Box::new(part), progress, seconds: untold });
    Ok(())
}

/// Handles one message of the job's loop; returns what to tell it. Time spent on an answer
/// recorded is added to `untold`, and told with the next batches produced.
fn step(scheduler: &mut Scheduler, band: usize, message: ToBand, untold: &mut Seconds) -> Option<News> {
    match message {
        ToBand::Produce { dataset, n } => {
            let mut seconds = std::mem::take(untold);
            let mut batches = Vec::with_capacity(n);
            while batches.len() < n {
                let asked = Instant::now();
                // Each task is encoded as it is decided (`next_batch_encoded`), so the
                // dispatch time includes the encoding; what is left of encoding is the
                // hand-over of the bytes.
                let mut writer = TaskWriter::with_capacity(0);
                let next = scheduler.next_batch_encoded(dataset, &mut writer);
                let encoding = Instant::now();
                seconds.dispatch += (encoding - asked).as_secs_f64();
                let Some(batch) = next else { break };
                let (bytes, start) = writer.finish();
                let encoded = prost::bytes::Bytes::from(bytes).slice(start..);
                seconds.encoding += encoding.elapsed().as_secs_f64();
                batches.push(Ready { band, id: batch.id, attempt: batch.attempt, tasks: batch.tasks as u64, encoded });
            }
            let more = batches.len() == n;
            Some(News::Produced { dataset, asked: n, batches, more, progress: scheduler.progress(), seconds })
        }
        ToBand::Answer { id, dataset, stream, results } => {
            let decoding = Instant::now();
            let decoded = decode_results(&results);
            let recording = Instant::now();
            let recorded = match decoded {
                Ok(results) => scheduler.record(id, &results).map_err(|e| e.to_string()),
                Err(e) => Err(format!("undecodable results: {e}")),
            };
            untold.decoding += (recording - decoding).as_secs_f64();
            untold.recording += recording.elapsed().as_secs_f64();
            match recorded {
                Ok(()) => None,
                Err(why) => {
                    let _ = scheduler.abandon(id);
                    Some(News::Refused { id, dataset, stream, why })
                }
            }
        }
        ToBand::Abandon { ids } => {
            for id in ids {
                let _ = scheduler.abandon(id);
            }
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use trove_core::render::intersection::intersect;
    use trove_core::render::wire::{decode_tasks, encode_results};
    use trove_core::render::{BatchCaster, PieceRgba, VolumeStore};

    use super::*;

    /// A generated ball's scheduler over its whole 24² image, in batches of 10 tasks, and
    /// the scene.
    fn ball() -> (Arc<Scene>, Scheduler) {
        let scene = Arc::new(Scene::parse(&trove_tests::scenes::ball(24, ""), "ball.toml").unwrap());
        let inter = intersect(&scene, 0..24);
        let scheduler = Scheduler::new(&scene, inter, 10).unwrap();
        (scene, scheduler)
    }

    fn stream() -> StreamKey {
        ("w".to_string(), 0)
    }

    /// Casts a produced batch as a worker would, from its wire form; returns its answer.
    fn cast(scene: &Scene, ready: &Ready) -> Vec<u8> {
        let tasks = decode_tasks(&ready.encoded).unwrap();
        let store = VolumeStore::new(None);
        let volume = store.get(&scene.datasets()[0]).unwrap();
        let caster = BatchCaster::new(scene, 0, &volume).unwrap();
        let mut out = vec![PieceRgba::default(); tasks.len()];
        caster.cast(&tasks, &mut out).unwrap();
        encode_results(&out)
    }

    #[test]
    fn a_band_hands_out_at_most_what_it_is_asked_and_says_when_it_may_have_more() {
        let mut untold = Seconds::default();
        let (_, mut scheduler) = ball();
        let total = scheduler.progress().total;
        assert!(total > 30, "the test needs several batches: {total} tasks");
        let Some(News::Produced { batches, more, asked, .. }) =
            step(&mut scheduler, 3, ToBand::Produce { dataset: 0, n: 2 }, &mut untold)
        else {
            panic!("a produce request is answered with batches")
        };
        assert_eq!((batches.len(), asked, more), (2, 2, true));
        assert!(batches.iter().all(|b| b.band == 3 && b.attempt == 0 && b.tasks == 10));
        assert_eq!(decode_tasks(&batches[0].encoded).unwrap().len(), 10, "the tasks go encoded for the wire");
        // Asked for more than the wave holds: all of it, and no more to come until answers.
        let Some(News::Produced { batches: rest, more, .. }) =
            step(&mut scheduler, 3, ToBand::Produce { dataset: 0, n: 1000 }, &mut untold)
        else {
            panic!()
        };
        assert!(!more, "a band that could not fill the request says it has nothing more now");
        let handed: u64 = batches.iter().chain(&rest).map(|b| b.tasks).sum();
        assert!(handed <= total);
    }

    #[test]
    fn answers_are_recorded_until_the_band_is_complete_and_nonsense_is_refused_and_given_back() {
        let mut untold = Seconds::default();
        let (scene, mut scheduler) = ball();
        let mut rounds = 0;
        while !scheduler.is_complete() {
            rounds += 1;
            assert!(rounds < 100, "the band never completes");
            let Some(News::Produced { batches, .. }) =
                step(&mut scheduler, 0, ToBand::Produce { dataset: 0, n: 1000 }, &mut untold)
            else {
                panic!()
            };
            let mut answered = false;
            for (i, ready) in batches.iter().enumerate() {
                if i == 0 && rounds == 1 {
                    // A worker answering with bytes that do not decode: the band gives the
                    // batch back and names the stream, and it is handed out again.
                    let answer = ToBand::Answer { id: ready.id, dataset: 0, stream: stream(), results: vec![7] };
                    let refused = step(&mut scheduler, 0, answer, &mut untold);
                    assert!(
                        matches!(refused, Some(News::Refused { id, stream: s, .. }) if id == ready.id && s == stream())
                    );
                    continue;
                }
                let results = cast(&scene, ready);
                let answer = ToBand::Answer { id: ready.id, dataset: 0, stream: stream(), results };
                let news = step(&mut scheduler, 0, answer, &mut untold);
                assert!(news.is_none(), "an answer recorded needs no reply");
                answered = true;
            }
            if answered && !scheduler.is_complete() {
                // The time the answers took rides on the next batches handed out.
                let Some(News::Produced { seconds, .. }) =
                    step(&mut scheduler, 0, ToBand::Produce { dataset: 0, n: 0 }, &mut untold)
                else {
                    panic!()
                };
                assert!(seconds.recording > 0.0 && seconds.decoding > 0.0, "{seconds:?}");
                assert_eq!(untold.recording, 0.0, "told once");
            }
        }
        assert!(rounds >= 2, "the refused batch was handed out again");
        let p = scheduler.progress();
        assert_eq!(p.cast + p.culled, p.total);
    }

    #[test]
    fn abandoned_batches_are_handed_out_again_as_a_later_attempt() {
        let mut untold = Seconds::default();
        let (_, mut scheduler) = ball();
        let Some(News::Produced { batches, .. }) =
            step(&mut scheduler, 0, ToBand::Produce { dataset: 0, n: 2 }, &mut untold)
        else {
            panic!()
        };
        let ids: Vec<u64> = batches.iter().map(|b| b.id).collect();
        assert!(step(&mut scheduler, 0, ToBand::Abandon { ids: ids.clone() }, &mut untold).is_none());
        let Some(News::Produced { batches: again, .. }) =
            step(&mut scheduler, 0, ToBand::Produce { dataset: 0, n: 2 }, &mut untold)
        else {
            panic!()
        };
        assert!(again.iter().all(|b| b.attempt == 1 && !ids.contains(&b.id)), "new ids, one attempt more");
    }
}
