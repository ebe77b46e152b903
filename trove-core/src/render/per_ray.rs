//! Algorithm 1 (paper §3.1): for each ray, intersect every object, order the pieces, and
//! cast them front to back until the ray is opaque. Threads take bands of scanlines, so
//! rays are visited in scanline order within each band, as the paper's loop does, and
//! datasets are asked for in the order each ray meets them: under a memory budget that
//! cannot hold them all, that is what makes it thrash. A thread holds one dataset at a time
//! (the pin is dropped after each cast), so two threads can never wait on each other.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use rayon::prelude::*;

use super::intersection::{sample_positions, segments_of, Reach};
use super::{CastError, Image, ObjectEffects, Pinned, Progress, RenderError, RenderStats, Rendered, VolumeStore};
use crate::composite::Rgba;
use crate::geometry::{split_into_pieces, Piece, PieceScratch, Ray, Segment};
use crate::sampling::ObjectCaster;
use crate::scene::Scene;

/// Rows per parallel work item.
const BAND_ROWS: usize = 4;

/// Per-thread scratch space and counters.
#[derive(Default)]
struct Band {
    segments: Vec<Segment>,
    scratch: PieceScratch,
    pieces: Vec<Piece>,
    cover: Vec<u32>,
    parts: Vec<Rgba>,
    n_segments: u64,
    n_pieces: u64,
    samples: u64,
    samples_skipped: u64,
    /// Samples shaded, per object (empty until one is).
    shaded: Vec<u64>,
    intersection_nanos: u64,
    /// Casting, loading included.
    casting_nanos: u64,
    /// Time in [`VolumeStore::get`]: loading, and waiting for room under a budget.
    loading_nanos: u64,
}

/// Adds `n` shaded samples to object `o`'s count in `shaded` (a band's, empty until then).
#[inline]
fn count_shaded(shaded: &mut Vec<u64>, o: u32, n: u64, scene: &Scene) {
    if n > 0 {
        if shaded.is_empty() {
            *shaded = vec![0; scene.objects().len()];
        }
        shaded[o as usize] += n;
    }
}

/// Renders with Algorithm 1.
pub(super) fn render(scene: &Scene, store: &VolumeStore, progress: Option<&Progress>) -> Result<Rendered, RenderError> {
    let (w, h) = (scene.image().width, scene.image().height);
    let mut pixels = vec![[0.0; 3]; w as usize * h as usize];
    let rows_done = AtomicU64::new(0);
    let started = Instant::now();
    let reach = Reach::new(scene);
    let bands: Vec<Result<Band, RenderError>> = pixels
        .par_chunks_mut(w as usize * BAND_ROWS)
        .enumerate()
        .map(|(band_index, out)| {
            let mut band = Band::default();
            for (i, px) in out.iter_mut().enumerate() {
                let row = (band_index * BAND_ROWS + i / w as usize) as u32;
                let col = (i % w as usize) as u32;
                let ray = scene.camera().ray(col, row, w, h);
                *px =
                    trace(scene, store, &reach, (col, row), &ray, &mut band)?.with_background(scene.image().background);
                if col + 1 == w {
                    let done = rows_done.fetch_add(1, Ordering::Relaxed) + 1;
                    if let Some(p) = progress {
                        p(done);
                    }
                }
            }
            Ok(band)
        })
        .collect();
    let wall = started.elapsed().as_secs_f64();

    let mut stats = RenderStats { effects: ObjectEffects::listed(scene, Some(0)), ..RenderStats::default() };
    let (mut inter, mut cast, mut load) = (0u64, 0u64, 0u64);
    for band in bands {
        let band = band?;
        ObjectEffects::add(&mut stats.effects, &band.shaded);
        stats.segments += band.n_segments;
        stats.pieces += band.n_pieces;
        stats.samples += band.samples;
        stats.samples_skipped += band.samples_skipped;
        inter += band.intersection_nanos;
        cast += band.casting_nanos;
        load += band.loading_nanos.min(band.casting_nanos);
    }
    // Split the parallel section's wall time by thread time; loading happened inside
    // casting, so it is taken out of the casting share.
    let thread_total = (inter + cast).max(1) as f64;
    let s = &mut stats.seconds;
    s.intersection = wall * inter as f64 / thread_total;
    s.loading = wall * load as f64 / thread_total;
    s.volume_rendering = wall * (cast - load) as f64 / thread_total;
    Ok(Rendered { image: Image::new(w, h, pixels), stats })
}

/// One ray: segments → pieces → front-to-back casting with early termination.
fn trace(
    scene: &Scene,
    store: &VolumeStore,
    reach: &Reach,
    pixel: (u32, u32),
    ray: &Ray,
    band: &mut Band,
) -> Result<Rgba, RenderError> {
    let t = Instant::now();
    segments_of(scene, reach, pixel, ray, &mut band.segments);
    band.n_segments += band.segments.len() as u64;
    split_into_pieces(&band.segments, &mut band.scratch, &mut band.pieces, &mut band.cover);
    band.n_pieces += band.pieces.len() as u64;
    let t_cast = Instant::now();
    band.intersection_nanos += (t_cast - t).as_nanos() as u64;

    let termination = scene.render().termination;
    let correction = scene.render().opacity_correction;
    let mut acc = Rgba::CLEAR;
    for (i, piece) in band.pieces.iter().enumerate() {
        if acc.alpha >= termination {
            band.samples_skipped += skipped_samples(scene, ray, &band.pieces[i..], &band.cover);
            break;
        }
        let cover = &band.cover[piece.cover.0 as usize..piece.cover.1 as usize];
        if let [only] = cover {
            let object = &scene.objects()[*only as usize];
            let volume = get(store, scene, object.dataset(), &mut band.loading_nanos)?;
            let r = bind(object, &volume, correction)?.cast(ray, piece.t0, piece.t1, acc.alpha, termination);
            band.samples += r.samples;
            count_shaded(&mut band.shaded, *only, r.shaded, scene);
            acc.over(r.rgba);
        } else {
            band.parts.clear();
            for &o in cover {
                let object = &scene.objects()[o as usize];
                let volume = get(store, scene, object.dataset(), &mut band.loading_nanos)?;
                let r = bind(object, &volume, correction)?.cast(ray, piece.t0, piece.t1, 0.0, f64::INFINITY);
                band.samples += r.samples;
                count_shaded(&mut band.shaded, o, r.shaded, scene);
                band.parts.push(r.rgba);
            }
            acc.over(Rgba::colocated(band.parts.iter().copied()));
        }
    }
    band.casting_nanos += t_cast.elapsed().as_nanos() as u64;
    Ok(acc)
}

/// The caster of `object` over its own dataset's volume. The scene guarantees the volume
/// has the channels the object's maps read, so this fails only if a file changed since.
fn bind<'a>(
    object: &'a crate::scene::Object,
    volume: &'a crate::dataset::Volume,
    correction: bool,
) -> Result<ObjectCaster<'a>, RenderError> {
    ObjectCaster::new(object, volume, correction)
        .map_err(|source| CastError::Bind { object: object.name().to_string(), source }.into())
}

/// Dataset `index` of `scene` from the store, timing the call (loading and waiting for room).
fn get(store: &VolumeStore, scene: &Scene, index: usize, nanos: &mut u64) -> Result<Pinned, RenderError> {
    let started = Instant::now();
    let volume = store.get(&scene.datasets()[index]);
    *nanos += started.elapsed().as_nanos() as u64;
    Ok(volume?)
}

/// Sample positions of every object over `pieces`, never cast because the ray is opaque.
fn skipped_samples(scene: &Scene, ray: &Ray, pieces: &[Piece], cover: &[u32]) -> u64 {
    let mut n = 0;
    for piece in pieces {
        for &o in &cover[piece.cover.0 as usize..piece.cover.1 as usize] {
            n += sample_positions(scene, ray, o as usize, piece.t0, piece.t1);
        }
    }
    n
}
