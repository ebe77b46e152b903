//! Algorithm 2 (paper §3.3) in one process: intersect every ray first, then cast dataset
//! by dataset — each loaded once, every piece of every object that uses it cast while it is
//! resident, then unloaded — and finally composite each ray's pieces front to back.
//!
//! This is the local driver of the [`Scheduler`]: it visits datasets in the scheduler's
//! front-to-back order, and casts each dataset's batches on as many threads as rayon has,
//! with one [`BatchCaster`] per dataset ([`cast_turn`]). The farm's coordinator drives the same scheduler with
//! workers instead of threads, so the two give the same image byte for byte.
//!
//! Each dataset's turn comes once and waves only run over the dataset that is resident, so
//! early termination never adds a load: under a budget that holds the largest dataset,
//! every voxel is brought in at most once.

use std::sync::{Condvar, Mutex, PoisonError};
use std::time::{Duration, Instant};

use super::intersection::intersect;
use super::schedule::Scheduler;
use super::workunit::{BatchCaster, PieceRgba};
use super::{Image, Progress, RenderError, RenderStats, Rendered, VolumeStore};
use crate::scene::Scene;

/// Tasks per batch: large enough to amortise scheduling and to keep a batch's last pieces,
/// which leave packet lanes idle as they end, a small part of it; small enough to balance
/// two threads over uneven pieces (256 and 2048 were both slower on the peers' scenes).
const BATCH_TASKS: usize = 1024;

/// Renders with Algorithm 2.
pub(super) fn render(scene: &Scene, store: &VolumeStore, progress: Option<&Progress>) -> Result<Rendered, RenderError> {
    let (w, h) = (scene.image().width, scene.image().height);
    let mut stats = RenderStats::default();

    // Phase 1: intersection (object level only).
    let started = Instant::now();
    let inter = intersect(scene, 0..h);
    stats.segments = inter.segments;
    stats.pieces = inter.pieces() as u64;
    stats.seconds.intersection = started.elapsed().as_secs_f64();

    // Phase 2: volume rendering, dataset by dataset, in front-to-back waves.
    let started = Instant::now();
    let mut scheduler = Scheduler::new(scene, inter, BATCH_TASKS)?;
    let mut loading = Duration::ZERO;
    for dataset in scheduler.datasets().to_vec() {
        let info = &scene.datasets()[dataset];
        let load_started = Instant::now();
        let volume = store.get(info)?;
        loading += load_started.elapsed();
        let caster = BatchCaster::for_dataset_turn(scene, dataset, &volume)?;
        stats.samples += cast_turn(&mut scheduler, &caster, dataset, progress, h)?;
        drop(caster);
        drop(volume);
        store.unload(info);
    }
    stats.samples_skipped = scheduler.culled_samples(scene);
    stats.seconds.loading = loading.as_secs_f64();
    stats.seconds.volume_rendering = (started.elapsed() - loading).as_secs_f64();

    // Phase 3: composition, front to back per ray.
    let started = Instant::now();
    let pixels = scheduler.composite_pixels(scene.image().background);
    stats.seconds.composition = started.elapsed().as_secs_f64();
    if let Some(p) = progress {
        p(h as u64);
    }
    Ok(Rendered { image: Image::new(w, h, pixels), stats })
}

/// Casts dataset `d`'s batches until its turn is done, on as many threads as rayon has;
/// returns the samples evaluated. Each thread takes a batch from the scheduler, casts it
/// and records it, so the scheduler's own work (the fronts it decides when it hands a
/// batch out, recording results) overlaps the other threads' casting instead of holding
/// all of them at the end of each wave. A thread that finds no batch ready (the wave is
/// handed out, and the next one waits for its results) sleeps until a result is recorded.
fn cast_turn(
    scheduler: &mut Scheduler,
    caster: &BatchCaster<'_>,
    d: usize,
    progress: Option<&Progress>,
    rows: u32,
) -> Result<u64, RenderError> {
    struct Turn<'s> {
        scheduler: &'s mut Scheduler,
        samples: u64,
        error: Option<RenderError>,
    }
    let turn = Mutex::new(Turn { scheduler, samples: 0, error: None });
    let recorded = Condvar::new();
    let work = || {
        let mut t = turn.lock().unwrap_or_else(PoisonError::into_inner);
        loop {
            if t.error.is_some() || t.scheduler.is_dataset_done(d) {
                return;
            }
            let Some(batch) = t.scheduler.next_batch(d) else {
                // Either the turn is done (its last tasks were culled), or batches are out,
                // whose recording wakes this thread.
                if !t.scheduler.is_dataset_done(d) {
                    t = recorded.wait(t).unwrap_or_else(PoisonError::into_inner);
                }
                continue;
            };
            drop(t);
            let mut out = vec![PieceRgba::default(); batch.tasks.len()];
            let cast = caster.cast(&batch.tasks, &mut out);
            t = turn.lock().unwrap_or_else(PoisonError::into_inner);
            let recorded_ok = cast
                .map_err(RenderError::from)
                .and_then(|samples| Ok(t.scheduler.record(batch.id, &out).map(|()| samples)?));
            match recorded_ok {
                Ok(samples) => t.samples += samples,
                Err(e) => {
                    t.error.get_or_insert(e);
                }
            }
            if let Some(p) = progress {
                let done = t.scheduler.progress();
                p(rows as u64 * (done.cast + done.culled) / done.total.max(1));
            }
            recorded.notify_all();
        }
    };
    let threads = rayon::current_num_threads().max(1);
    if threads == 1 {
        work();
    } else {
        std::thread::scope(|s| {
            for _ in 0..threads {
                s.spawn(work);
            }
        });
    }
    let turn = turn.into_inner().unwrap_or_else(PoisonError::into_inner);
    match turn.error {
        Some(e) => Err(e),
        None => Ok(turn.samples),
    }
}
