//! Algorithm 2 (paper §3.3) in one process: intersect every ray first, then cast dataset
//! by dataset — each loaded once, every piece of every object that uses it cast while it is
//! resident, then unloaded — and finally composite each ray's pieces front to back.
//!
//! This is the local driver of the [`Scheduler`]: it visits datasets in the scheduler's
//! front-to-back order, and casts each ready wave's batches on rayon threads with one
//! [`BatchCaster`] per dataset. The farm's coordinator drives the same scheduler with
//! workers instead of threads, so the two give the same image byte for byte.
//!
//! Each dataset's turn comes once and waves only run over the dataset that is resident, so
//! early termination never adds a load: under a budget that holds the largest dataset,
//! every voxel is brought in at most once.

use std::time::{Duration, Instant};

use rayon::prelude::*;

use super::intersection::intersect;
use super::schedule::{Batch, Scheduler};
use super::workunit::{BatchCaster, PieceRgba};
use super::{Image, Progress, RenderError, RenderStats, Rendered, VolumeStore};
use crate::scene::Scene;

/// Tasks per batch: large enough to amortise scheduling, small enough to balance two
/// threads over uneven pieces.
const BATCH_TASKS: usize = 256;

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
        loop {
            let wave: Vec<Batch> = std::iter::from_fn(|| scheduler.next_batch(dataset)).collect();
            if wave.is_empty() {
                break;
            }
            let cast: Vec<_> = wave
                .par_iter()
                .map(|batch| {
                    let mut out = vec![PieceRgba::default(); batch.tasks.len()];
                    caster.cast(&batch.tasks, &mut out).map(|samples| (out, samples))
                })
                .collect();
            for (batch, result) in wave.iter().zip(cast) {
                let (out, samples) = result?;
                stats.samples += samples;
                scheduler.record(batch.id, &out)?;
            }
            if let Some(p) = progress {
                let done = scheduler.progress();
                p(h as u64 * (done.cast + done.culled) / done.total.max(1));
            }
        }
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
