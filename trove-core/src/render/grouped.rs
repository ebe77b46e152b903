//! Algorithm 2 (paper §3.3) in one process: intersect every ray first, then cast dataset
//! by dataset — each loaded once, every piece of every object that uses it cast while it is
//! resident, then unloaded — and finally composite each ray's pieces front to back. An
//! image whose pieces do not fit the band memory is worked through in bands of rows, each
//! band as above ([`crate::render::bands`], the shape the farm's driver shares), and each
//! band is composited into the canvas as soon as it is cast, its pieces then dropped: a
//! [`super::Raster`] of 8-bit values for a file, so that the image costs what the file
//! holds, or an [`super::Image`] of linear values for the library.
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

use super::bands::Bands;
use super::dispatch::Admission;
use super::intersection::{intersect, recycle, Intersections};
use super::raster::Canvas;
use super::schedule::Scheduler;
use super::workunit::{BatchCaster, PieceRgba};
use super::{ObjectEffects, Progress, RenderError, RenderStats, Rendered, VolumeStore};
use crate::scene::Scene;

/// Tasks per batch: large enough to amortise scheduling and to keep a batch's last pieces,
/// which leave packet lanes idle as they end, a small part of it; small enough to balance
/// two threads over uneven pieces (256 and 2048 were both slower on the peers' scenes).
const BATCH_TASKS: usize = 1024;

/// The smallest batch a wave's last tasks are cut into ([`cast_turn`]).
const MIN_SHARED_BATCH: usize = 64;

/// Renders with Algorithm 2, in bands of rows whose bookkeeping stays within
/// `band_memory` bytes ([`Bands`], the shape the farm's driver shares): one band, and so
/// each dataset loaded once, for any image whose pieces fit; more for larger images, which
/// then render in bounded memory instead of holding every piece at once. Each band is
/// composited into `canvas` before the next one starts. `unload`: each dataset is unloaded
/// after its turn in the last band (false when the caller keeps `store` for later renders).
/// `whole`: the whole image's intersections, where the count kept them and the image is one
/// band, so that it is not intersected again.
pub(super) fn render<C: Canvas>(
    scene: &Scene,
    store: &VolumeStore,
    unload: bool,
    progress: Option<&Progress>,
    (band_rows, band_memory): (u32, u64),
    mut canvas: C,
    mut whole: Option<Intersections>,
) -> Result<Rendered<C>, RenderError> {
    let h = scene.image().height;
    let mut stats = RenderStats { effects: ObjectEffects::listed(scene, Some(0)), ..RenderStats::default() };
    let mut shaded = vec![0; scene.objects().len()];
    let mut bands = <Bands>::new(h, band_rows, Admission { max_bands: 1, memory_bound: band_memory });
    let mut loading = Duration::ZERO;
    let mut casting = Duration::ZERO;
    while let Some((band, rows)) = bands.start_next() {
        // Phase 1: intersection (object level only).
        let started = Instant::now();
        let inter = match whole.take() {
            Some(inter) if rows == (0..h) => inter,
            _ => intersect(scene, rows.clone()),
        };
        stats.segments += inter.segments;
        stats.pieces += inter.pieces() as u64;
        bands.intersected(band, Box::new(Scheduler::new(scene, inter, BATCH_TASKS)?));
        stats.seconds.intersection += started.elapsed().as_secs_f64();

        // Phase 2: volume rendering, dataset by dataset, in front-to-back waves. Datasets
        // stay resident from band to band (the store evicts under its budget) and are
        // unloaded after their turn in the last band, unless the caller keeps the store.
        let started = Instant::now();
        let before = bands.rows_done();
        let last = unload && before + rows.len() as u32 == h;
        let (_, scheduler) = bands.casting(band).expect("just intersected");
        let band_progress = progress.map(|p| (p, before as u64, rows.len() as u64));
        let mut band_loading = Duration::ZERO;
        for dataset in scheduler.datasets().to_vec() {
            let info = &scene.datasets()[dataset];
            let load_started = Instant::now();
            let volume = store.get(info)?;
            band_loading += load_started.elapsed();
            let caster = BatchCaster::for_dataset_turn(scene, dataset, &volume)?;
            stats.samples += cast_turn(scheduler, &caster, dataset, band_progress, &mut shaded)?;
            drop(caster);
            drop(volume);
            if last {
                store.unload(info);
            }
        }
        stats.samples_skipped += scheduler.culled_samples(scene);
        loading += band_loading;
        casting += started.elapsed() - band_loading;

        // Phase 3: composition, front to back per ray.
        let started = Instant::now();
        let (rows, scheduler) = bands.take_complete(band).expect("every task of the band is cast or culled");
        canvas.composite_rows(rows.start, &scheduler, scene.image().background);
        // Its lists go to the next band's intersection, or to the next render's in this
        // process, which then writes them without the kernel's page faults of fresh memory
        // (as the farm's bands hand theirs back).
        recycle(scheduler.into_intersections());
        bands.composited(band);
        stats.seconds.composition += started.elapsed().as_secs_f64();
    }
    ObjectEffects::add(&mut stats.effects, &shaded);
    stats.seconds.loading = loading.as_secs_f64();
    stats.seconds.volume_rendering = casting.as_secs_f64();
    if let Some(p) = progress {
        p(h as u64);
    }
    Ok(Rendered { image: canvas, stats })
}

/// Casts dataset `d`'s batches until its turn is done, on the calling thread and as many
/// more of rayon's as make rayon's number (no turn waits for new threads to be started and
/// spread over the processors, nor for a thread to wake while the caller sleeps);
/// returns the samples evaluated, and adds the samples shaded per object to `shaded`. Each
/// thread takes a batch from the scheduler, casts it and records it, so the scheduler's own
/// work (the fronts it decides when it hands a batch out, recording results) overlaps the
/// other threads' casting instead of holding all of them at the end of each wave. A wave's
/// last tasks are cut into even shares ([`Scheduler::wave_left`]), so that the threads end
/// it together: on a scene of many small datasets, whose waves are a few batches each, one
/// thread otherwise cast a wave's last batch while the others waited. A thread that finds
/// no batch ready (the wave is handed out, and the next one waits for its results) sleeps
/// until a result is recorded; it never waits on a task that is not running, since a batch
/// is out only while a thread casts it. The cast itself never uses rayon.
fn cast_turn(
    scheduler: &mut Scheduler,
    caster: &BatchCaster<'_>,
    d: usize,
    progress: Option<(&Progress, u64, u64)>,
    shaded: &mut [u64],
) -> Result<u64, RenderError> {
    struct Turn<'s> {
        scheduler: &'s mut Scheduler,
        samples: u64,
        shaded: &'s mut [u64],
        error: Option<RenderError>,
    }
    let objects = shaded.len();
    let turn = Mutex::new(Turn { scheduler, samples: 0, shaded, error: None });
    let recorded = Condvar::new();
    let threads = rayon::current_num_threads().max(1);
    let work = || {
        let mut batch_shaded = vec![0; objects];
        let mut t = turn.lock().unwrap_or_else(PoisonError::into_inner);
        loop {
            if t.error.is_some() || t.scheduler.is_dataset_done(d) {
                return;
            }
            // A wave's last tasks are shared out: no batch larger than an even share of
            // what is left of the wave, down to a floor below which a batch's set-up would
            // cost more than the threads' waiting.
            let share = t.scheduler.wave_left(d).div_ceil(threads).max(MIN_SHARED_BATCH);
            let Some(batch) = t.scheduler.next_batch_of(d, share) else {
                // Either the turn is done (its last tasks were culled), or batches are out,
                // whose recording wakes this thread.
                if !t.scheduler.is_dataset_done(d) {
                    t = recorded.wait(t).unwrap_or_else(PoisonError::into_inner);
                }
                continue;
            };
            drop(t);
            let mut out = vec![PieceRgba::default(); batch.tasks.len()];
            batch_shaded.fill(0);
            let cast = caster.cast_counting(&batch.tasks, &mut out, &mut batch_shaded);
            t = turn.lock().unwrap_or_else(PoisonError::into_inner);
            let recorded_ok = cast
                .map_err(RenderError::from)
                .and_then(|samples| Ok(t.scheduler.record(batch.id, &out).map(|()| samples)?));
            match recorded_ok {
                Ok(samples) => {
                    t.samples += samples;
                    for (total, n) in t.shaded.iter_mut().zip(&batch_shaded) {
                        *total += n;
                    }
                }
                Err(e) => {
                    t.error.get_or_insert(e);
                }
            }
            if let Some((p, before, rows)) = progress {
                let done = t.scheduler.progress();
                p(before + rows * (done.cast + done.culled) / done.total.max(1));
            }
            recorded.notify_all();
        }
    };
    if threads == 1 {
        work();
    } else {
        rayon::scope(|s| {
            for _ in 1..threads {
                s.spawn(|_| work());
            }
            work();
        });
    }
    let turn = turn.into_inner().unwrap_or_else(PoisonError::into_inner);
    match turn.error {
        Some(e) => Err(e),
        None => Ok(turn.samples),
    }
}
