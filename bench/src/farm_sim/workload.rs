//! The work of one job, as the farm's coordinator would meet it: the image in bands of rows
//! (as `coordinator/src/farm/driver/` cuts it), and in each band, per dataset, the waves
//! that the scheduler hands out one after the other, each with its tasks and samples.
//!
//! It is taken from `trove-core` itself: the scene is intersected with
//! [`trove_core::render::intersection::intersect`] at a reduced resolution (a few sampled
//! rows per band), and the real [`Scheduler`] is driven over each band with results of zero
//! opacity, so that nothing is culled and each batch it hands out is one whole wave; each
//! task's samples are what `Placement::walk` would evaluate. Counts are then scaled from
//! the sampled rows to the band's rows at the full resolution. Nothing here depends on
//! time, so a workload is the same on every run.

use anyhow::Result;
use trove_core::render::intersection::intersect;
use trove_core::render::{PieceRgba, Scheduler};
use trove_core::scene::Scene;

use super::scene::SceneSpec;

/// Pixels per band when the job does not say (`BAND_PIXELS` in
/// `coordinator/src/farm/driver/raster.rs`, private there): the band has
/// `BAND_PIXELS / width` rows.
pub(crate) const BAND_PIXELS: u32 = 1 << 16;

/// Bytes of one file's registration in an `open` message (`DatasetFile`: key, size, dims,
/// voxel type, protobuf framing).
const HEADER_BYTES: u64 = 40;

/// One wave of one dataset in one band: handed out only once the previous one is recorded.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Wave {
    /// Piece tasks.
    pub tasks: u64,
    /// Sample positions over those tasks (every one cast: nothing terminates early).
    pub samples: u64,
}

/// One dataset's waves in one band.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Lane {
    /// The dataset's index in the scene.
    pub dataset: usize,
    /// Its waves, in order.
    pub waves: Vec<Wave>,
}

/// One band of rows.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Band {
    /// Rays (pixels) of the band.
    pub rays: u64,
    /// Pieces over those rays.
    pub pieces: u64,
    /// Bytes the band's scheduler holds (`Scheduler::heap_bytes` right after planning,
    /// which the driver's admission counts).
    pub bytes: u64,
    /// Datasets with tasks, in dataset order (the order the driver's ready set visits).
    pub lanes: Vec<Lane>,
}

impl Band {
    /// Tasks of the band.
    pub(crate) fn tasks(&self) -> u64 {
        self.lanes.iter().flat_map(|l| &l.waves).map(|w| w.tasks).sum()
    }
}

/// A job's work, band by band.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Workload {
    /// Image width and height.
    pub width: u32,
    pub height: u32,
    /// Datasets in the scene (some may have no tasks).
    pub datasets: usize,
    /// Objects in the scene (each ray is tested against every one).
    pub objects: usize,
    /// Bytes of each dataset once loaded.
    pub dataset_bytes: u64,
    /// Voxels of each dataset (binding its objects visits them).
    pub dataset_voxels: u64,
    /// Bytes of a stream's `open` message: the scene's text and a header per file.
    pub scene_bytes: u64,
    /// The bands, top to bottom.
    pub bands: Vec<Band>,
}

impl Workload {
    /// Tasks over the whole image.
    pub(crate) fn tasks(&self) -> u64 {
        self.bands.iter().map(Band::tasks).sum()
    }

    /// Samples over the whole image.
    pub(crate) fn samples(&self) -> u64 {
        self.bands.iter().flat_map(|b| &b.lanes).flat_map(|l| &l.waves).map(|w| w.samples).sum()
    }

    /// Per dataset: (tasks, samples) over the whole image.
    pub(crate) fn per_dataset(&self) -> Vec<(u64, u64)> {
        let mut out = vec![(0, 0); self.datasets];
        for lane in self.bands.iter().flat_map(|b| &b.lanes) {
            for w in &lane.waves {
                out[lane.dataset].0 += w.tasks;
                out[lane.dataset].1 += w.samples;
            }
        }
        out
    }
}

/// Takes the workload of the scene `spec` describes at its full size, in bands of
/// `band_pixels` pixels (rounded to whole rows), intersecting `sampled_rows` rows per band,
/// with datasets of `dataset_bytes` each.
pub(crate) fn extract(spec: &SceneSpec, band_pixels: u32, sampled_rows: u32, dataset_bytes: u64) -> Result<Workload> {
    let (w, h) = (spec.width, spec.height);
    let band_rows = (band_pixels / w).clamp(1, h);
    let bands = h.div_ceil(band_rows);
    let low_h = bands * sampled_rows.max(1);
    let low_w = ((w as f64 * low_h as f64 / h as f64).round() as u32).max(1);
    let low = SceneSpec { width: low_w, height: low_h, ..spec.clone() }.build()?;
    let mut out = Workload {
        width: w,
        height: h,
        datasets: low.datasets().len(),
        objects: low.objects().len(),
        dataset_bytes,
        dataset_voxels: (spec.dims as u64).pow(3),
        scene_bytes: spec.toml().len() as u64 + HEADER_BYTES * spec.datasets as u64,
        bands: Vec::with_capacity(bands as usize),
    };
    for b in 0..bands {
        let rows = band_rows.min(h - b * band_rows);
        let sampled = b * sampled_rows.max(1)..(b + 1) * sampled_rows.max(1);
        let scale = (w as f64 * rows as f64) / (low_w as f64 * sampled.len() as f64);
        out.bands.push(band_work(&low, sampled, scale, w as u64 * rows as u64)?);
    }
    Ok(out)
}

/// One band: intersect the sampled rows and drive the scheduler wave by wave.
fn band_work(scene: &Scene, rows: std::ops::Range<u32>, scale: f64, rays: u64) -> Result<Band> {
    let inter = intersect(scene, rows);
    let pieces = inter.pieces() as f64 * scale;
    // One batch is one whole wave: the scheduler cuts batches out of a wave, never across.
    let mut scheduler = Scheduler::new(scene, inter, u32::MAX as usize)?;
    let bytes = (scheduler.heap_bytes() as f64 * scale).round() as u64;
    let (w, h) = (scene.image().width, scene.image().height);
    let mut lanes = Vec::new();
    for d in scheduler.datasets().to_vec() {
        let mut waves = Vec::new();
        while let Some(batch) = scheduler.next_batch(d) {
            let samples: u64 = batch
                .tasks
                .iter()
                .map(|t| {
                    let object = &scene.objects()[t.object as usize];
                    let ray = scene.camera().ray(t.ray % w, t.ray / w, w, h);
                    object.placement().walk(&ray, t.t0, t.t1, object.sampling_distance()).len()
                })
                .sum();
            let n = batch.tasks.len();
            scheduler.record(batch.id, &vec![PieceRgba::default(); n])?;
            let tasks = ((n as f64 * scale).round() as u64).max(1);
            waves.push(Wave { tasks, samples: ((samples as f64 * scale).round() as u64).max(tasks) });
        }
        lanes.push(Lane { dataset: d, waves });
    }
    anyhow::ensure!(scheduler.is_complete(), "the scheduler did not finish a band");
    lanes.sort_by_key(|l| l.dataset);
    Ok(Band { rays, pieces: pieces.round() as u64, bytes, lanes })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(width: u32, height: u32) -> SceneSpec {
        SceneSpec { datasets: 10, depth: 3.0, dims: 64, width, height, step_voxels: 1.0, seed: 11 }
    }

    #[test]
    fn a_workload_sampled_at_full_resolution_holds_every_task_of_the_image() {
        // 64×64 pixels make one band; sampling all 64 rows is the whole intersection.
        let work = extract(&spec(64, 64), BAND_PIXELS, 64, 1).unwrap();
        assert_eq!(work.bands.len(), 1);
        let scene = spec(64, 64).build().unwrap();
        let inter = intersect(&scene, 0..64);
        assert_eq!(work.tasks(), inter.tasks.len() as u64);
        assert_eq!(work.bands[0].pieces, inter.pieces() as u64);
        assert_eq!(work.bands[0].rays, 64 * 64);
        // Overlapping cubes split pieces: some dataset has more than one wave.
        assert!(work.bands[0].lanes.iter().any(|l| l.waves.len() > 1));
        // Every sample counted is a sample a real cast evaluates: a piece of a cube of 64
        // voxels per side holds between 1 and 64·√3 samples.
        let per_task = work.samples() as f64 / work.tasks() as f64;
        assert!((1.0..=64.0 * 3f64.sqrt()).contains(&per_task), "{per_task}");
    }

    #[test]
    fn the_samples_counted_are_the_samples_the_renderer_takes() {
        let spec = SceneSpec { dims: 16, ..spec(48, 48) };
        let work = extract(&spec, BAND_PIXELS, 48, 1).unwrap();
        let rendered = trove_core::render::render(&spec.build().unwrap(), &Default::default()).unwrap();
        // Cast, or skipped because the ray was opaque in front of the piece; a cast that
        // stops early inside its piece takes fewer (rare: the scene is faint).
        let positions = rendered.stats.samples + rendered.stats.samples_skipped;
        let ratio = work.samples() as f64 / positions as f64;
        assert!((1.0..1.02).contains(&ratio), "workload {} vs renderer {positions}", work.samples());
    }

    #[test]
    fn sampling_fewer_rows_scales_counts_to_the_full_image() {
        // 1024×1024 pixels in bands of 256 rows. Two sampled rows per band stand for 256.
        let coarse = extract(&spec(1024, 1024), 1 << 18, 2, 1).unwrap();
        let fine = extract(&spec(1024, 1024), 1 << 18, 16, 1).unwrap();
        assert_eq!(coarse.bands.len(), 4);
        assert!(coarse.bands.iter().all(|b| b.rays == 1024 * 256));
        let ratio = coarse.bands.iter().map(|b| b.bytes).sum::<u64>() as f64
            / fine.bands.iter().map(|b| b.bytes).sum::<u64>() as f64;
        assert!((0.85..1.15).contains(&ratio), "bytes scale: {ratio}");
        let ratio = coarse.tasks() as f64 / fine.tasks() as f64;
        assert!((0.85..1.15).contains(&ratio), "tasks scale: {ratio}");
        let ratio = coarse.samples() as f64 / fine.samples() as f64;
        assert!((0.85..1.15).contains(&ratio), "samples scale: {ratio}");
    }
}
