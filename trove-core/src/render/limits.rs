//! Bounds on the work and memory of one render, checked before any is done: the scene's
//! own limits (`scene::limits`: image side, objects, samples) bound what a scene *says*;
//! these bound what its geometry *makes* — the piece tasks of the intersection phase,
//! counted ray by ray without storing one, so that neither a huge sampling distance (which
//! makes the sample estimate near zero) nor nested boxes (n nested objects make about n²
//! tasks per ray) can make a render allocate without bound. Local mode and the farm's
//! coordinator both check them, and the farm's intersection refuses a band that exceeds
//! its share as it goes ([`super::intersection::intersect_within`]).

use std::ops::Range;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use rayon::prelude::*;
use thiserror::Error;

use super::intersection::{intersect_within, Intersections, RowCounter, INDEX_BYTES};
use crate::scene::Scene;

/// Most piece tasks (one per object per piece of a ray) in one render. 2²⁹ ≈ 5.4·10⁸ admits
/// the paper's Fig. 1 at 16384² (about 1.2 tasks per pixel) with room to spare; a scene of
/// 300 nested boxes makes about 90 000 per ray and reaches it within 6 000 rays. Pieces are
/// never more than tasks (each has at least one), so this bounds them too.
pub const MAX_TASKS_PER_RENDER: u64 = 1 << 29;

/// Most ray–object pairs the intersection phase may consider: pixels × objects. Each costs
/// a test of the pixel against the object's projected rectangle at least, whatever the
/// sampling distance; 2³⁶ admits 4096 objects at 4096² or 256 at 16384² (about a minute of
/// one core at most), and refuses 4096 objects at 16384² (16 times that).
pub const MAX_RAY_OBJECT_TESTS: u64 = 1 << 36;

/// Bytes one piece task of a band takes at its peak, for sizing the per-band cap: the task
/// as intersected and again in the band's flat list (24 + 24), then its status, result,
/// wave entry and share of the piece index in the scheduler (1 + 16 + 4 + `INDEX_BYTES`,
/// 4). (Planning holds a 4-byte key a task for a moment too, once the intersection's second
/// copy is gone, so the peak stays the intersection's.)
pub const BYTES_PER_BAND_TASK: u64 = 24 + 24 + 1 + 16 + 4 + INDEX_BYTES;

/// Bytes one ray of a band takes at its peak, whatever its tasks: its entry in the
/// intersection's ray index (`INDEX_BYTES`, 4) and the piece count it is built from (4),
/// and its known front in the scheduler (a piece count and an opacity, packed in 16).
pub const BYTES_PER_BAND_RAY: u64 = INDEX_BYTES + 4 + 16;

/// Tasks a band may always hold, however small the band memory: one row of any everyday
/// scene (about 80 MiB of bookkeeping), so that a tiny band memory means one-row bands
/// rather than refusals.
pub const MIN_BAND_TASKS: u64 = 1 << 20;

/// Bytes a kept band ([`Work::count_keeping`]) takes per task at most: the task, and its
/// piece's and its ray's index entries.
pub const KEPT_BYTES_PER_TASK: u64 = 24 + 4 + 4;

/// Most pixels of an image written as a PFM: 4096² (192 MiB of floats, and as much again
/// for the file's bytes). A PNG may take the scene's largest side, 16384² (768 MiB of RGB
/// bytes); the same image as floats would take four times that.
pub const MAX_PFM_PIXELS: u64 = 1 << 24;

/// The most tasks one band may hold within `band_memory` bytes of band bookkeeping:
/// `band_memory / BYTES_PER_BAND_TASK`, never fewer than [`MIN_BAND_TASKS`] nor more than
/// [`MAX_TASKS_PER_RENDER`].
pub fn max_band_tasks(band_memory: u64) -> u64 {
    (band_memory / BYTES_PER_BAND_TASK).clamp(MIN_BAND_TASKS, MAX_TASKS_PER_RENDER)
}

/// A render refused because it would exceed one of this module's limits; each message names
/// the limit and the count that exceeded it.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
pub enum LimitError {
    /// More ray–object pairs than [`MAX_RAY_OBJECT_TESTS`].
    #[error(
        "a {width}×{height} image of {objects} objects makes {tests} ray–object tests; the limit on ray–object \
         tests per render is {max}: use fewer objects or a smaller image"
    )]
    RayObjectTests {
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
        /// Objects in the scene.
        objects: usize,
        /// Pixels × objects.
        tests: u64,
        /// The limit.
        max: u64,
    },
    /// More piece tasks than [`MAX_TASKS_PER_RENDER`]; counting stopped once it was clear.
    #[error(
        "the scene makes at least {counted} piece tasks (one per object per piece of a ray; n nested or \
         overlapping objects make about n² per ray, whatever their sampling distance); the limit on piece tasks \
         per render is {max}: use fewer overlapping objects or a smaller image"
    )]
    TasksPerRender {
        /// Tasks counted before counting stopped (more than `max`).
        counted: u64,
        /// The limit.
        max: u64,
    },
    /// A band of rows makes more piece tasks than its band memory holds.
    #[error(
        "image rows {}..{} make at least {counted} piece tasks; the limit on piece tasks per band is {max} \
         (band memory {band_memory} bytes at {BYTES_PER_BAND_TASK} bytes per task): raise the band memory or use \
         fewer overlapping objects", rows.start, rows.end
    )]
    TasksPerBand {
        /// The band's rows.
        rows: Range<u32>,
        /// Tasks counted before counting stopped (more than `max`).
        counted: u64,
        /// The limit: [`max_band_tasks`] of the band memory.
        max: u64,
        /// The band memory it was derived from.
        band_memory: u64,
    },
    /// A PFM larger than its limit.
    #[error(
        "a {width}×{height} PFM is {pixels} pixels; the limit on PFM pixels is {max}: write a PNG (up to the \
         scene's largest image) or render a smaller image"
    )]
    PfmPixels {
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
        /// width × height.
        pixels: u64,
        /// The limit.
        max: u64,
    },
}

/// Refuses a PFM of more than `max_pixels` pixels (locally [`MAX_PFM_PIXELS`]; a farm's
/// coordinator has its own setting).
pub fn check_pfm(width: u32, height: u32, max_pixels: u64) -> Result<(), LimitError> {
    let pixels = width as u64 * height as u64;
    if pixels > max_pixels {
        return Err(LimitError::PfmPixels { width, height, pixels, max: max_pixels });
    }
    Ok(())
}

/// Refuses a scene of more ray–object pairs than [`MAX_RAY_OBJECT_TESTS`], before any is
/// tested.
fn check_ray_object_tests(scene: &Scene) -> Result<(), LimitError> {
    let (width, height) = (scene.image().width, scene.image().height);
    let objects = scene.objects().len();
    let tests = width as u64 * height as u64 * objects as u64;
    if tests > MAX_RAY_OBJECT_TESTS {
        return Err(LimitError::RayObjectTests { width, height, objects, tests, max: MAX_RAY_OBJECT_TESTS });
    }
    Ok(())
}

/// A scene's intersection work, counted row by row without storing a task.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Work {
    /// Piece tasks over the image.
    pub tasks: u64,
    /// Pieces over the image.
    pub pieces: u64,
    /// The image's width: each row's rays.
    width: u32,
    tasks_per_row: Vec<u64>,
}

impl Work {
    /// Counts every ray's pieces and tasks (in parallel, about the cost of an intersection
    /// without its allocation), refusing a scene over [`MAX_RAY_OBJECT_TESTS`] before
    /// counting and one over [`MAX_TASKS_PER_RENDER`] as soon as the count passes it, so
    /// that counting a hostile scene stays short too.
    pub fn count(scene: &Scene) -> Result<Work, LimitError> {
        let (width, height) = (scene.image().width, scene.image().height);
        check_ray_object_tests(scene)?;
        let max = MAX_TASKS_PER_RENDER;
        let (total, over) = (AtomicU64::new(0), AtomicBool::new(false));
        let counter = RowCounter::new(scene);
        let rows: Vec<(u64, u64)> = (0..height)
            .into_par_iter()
            .map(|row| {
                if over.load(Ordering::Relaxed) {
                    return (0, 0);
                }
                let counted = counter.row(row, max);
                if total.fetch_add(counted.1, Ordering::Relaxed) + counted.1 > max {
                    over.store(true, Ordering::Relaxed);
                }
                counted
            })
            .collect();
        let tasks = total.into_inner();
        if tasks > max {
            return Err(LimitError::TasksPerRender { counted: tasks, max });
        }
        let pieces = rows.iter().map(|r| r.0).sum();
        Ok(Work { tasks, pieces, width, tasks_per_row: rows.into_iter().map(|r| r.1).collect() })
    }

    /// [`Work::count`] by intersecting the image in bands of `band_rows` rows, keeping each
    /// band's [`Intersections`] while all of them fit `keep` bytes, so that a driver whose
    /// bands are those rows never intersects the image twice: counting is most of an
    /// intersection's cost (slab tests and splits; only storing the tasks is not), and on
    /// the farm's coordinator it was half of all intersection work. Where the image's
    /// tasks do not fit (`keep` is a small share of the memory bound), or a band is refused,
    /// it counts as [`Work::count`] does and keeps nothing; the count, and every refusal,
    /// is the same either way.
    pub fn count_keeping(scene: &Scene, band_rows: u32, keep: u64) -> Result<(Work, Vec<Intersections>), LimitError> {
        let (width, height) = (scene.image().width, scene.image().height);
        check_ray_object_tests(scene)?;
        let band_rows = band_rows.clamp(1, height.max(1));
        let mut kept: Vec<Intersections> = Vec::new();
        let mut held = 0u64;
        for start in (0..height).step_by(band_rows as usize) {
            let rows = start..(start + band_rows).min(height);
            // What the rest of `keep` holds, at the bytes a kept task takes at most (its
            // piece and its ray each own a slot only once, so this over-counts).
            // Its rays' index is held whatever its tasks.
            held += (rows.len() as u64 * width as u64 + 2) * INDEX_BYTES;
            let room = keep.saturating_sub(held) / KEPT_BYTES_PER_TASK;
            match intersect_within(scene, rows.clone(), room, keep).ok().filter(|_| held <= keep) {
                Some(inter) => {
                    held += inter.heap_bytes() - (inter.ray_start.len() as u64 * INDEX_BYTES);
                    kept.push(inter);
                }
                None => return Work::count(scene).map(|work| (work, Vec::new())),
            }
        }
        let mut tasks_per_row = Vec::with_capacity(height as usize);
        let mut pieces = 0u64;
        for inter in &kept {
            let w = width as usize;
            for r in 0..inter.rays() / w.max(1) {
                tasks_per_row.push(inter.tasks_of_rays(r * w..(r + 1) * w).len() as u64);
            }
            pieces += inter.pieces() as u64;
        }
        let tasks = tasks_per_row.iter().sum();
        Ok((Work { tasks, pieces, width, tasks_per_row }, kept))
    }

    /// Tasks of image rows `rows`.
    pub fn tasks_in(&self, rows: Range<u32>) -> u64 {
        let end = (rows.end as usize).min(self.tasks_per_row.len());
        self.tasks_per_row[(rows.start as usize).min(end)..end].iter().sum()
    }

    /// Refuses the first band of `band_rows` rows (bands from row 0, the last one shorter)
    /// whose tasks exceed [`max_band_tasks`] of `band_memory`.
    pub fn check_bands(&self, band_rows: u32, band_memory: u64) -> Result<(), LimitError> {
        let max = max_band_tasks(band_memory);
        let height = self.tasks_per_row.len() as u32;
        let band_rows = band_rows.clamp(1, height.max(1));
        for start in (0..height).step_by(band_rows as usize) {
            let rows = start..(start + band_rows).min(height);
            let counted = self.tasks_in(rows.clone());
            if counted > max {
                return Err(LimitError::TasksPerBand { rows, counted, max, band_memory });
            }
        }
        Ok(())
    }

    /// The rows per band that keep every band of the image within `band_memory` bytes of
    /// tasks and rays ([`BYTES_PER_BAND_TASK`], [`BYTES_PER_BAND_RAY`]) by this exact count: the whole image when it fits, else the tallest halving of
    /// it that does, and at least the rows its densest row guarantees (one row at the
    /// least). Refused only when one row is over [`max_band_tasks`]. Both drivers size
    /// their bands with it, so no band is estimated from samples.
    pub fn rows_within(&self, band_memory: u64) -> Result<u32, LimitError> {
        self.check_bands(1, band_memory)?;
        let height = (self.tasks_per_row.len() as u32).max(1);
        // Sizing aims at the memory itself; the floor of `max_band_tasks` only keeps a
        // small band memory from refusing scenes.
        // A band's bytes are its tasks' and its rays' (a sparse view of one small object has
        // few tasks but as many rays as pixels).
        let row_rays = self.width as u64 * BYTES_PER_BAND_RAY;
        let bytes = |rows: std::ops::Range<u32>| {
            self.tasks_in(rows.clone()) * BYTES_PER_BAND_TASK + (rows.end - rows.start) as u64 * row_rays
        };
        let fits =
            |r: u32| (0..height).step_by(r as usize).all(|start| bytes(start..(start + r).min(height)) <= band_memory);
        let densest = self.tasks_per_row.iter().copied().max().unwrap_or(0) * BYTES_PER_BAND_TASK + row_rays;
        let guaranteed = (band_memory / densest.max(1)).clamp(1, height as u64) as u32;
        let halving = std::iter::successors(Some(height), |&r| (r > 1).then_some(r.div_ceil(2)))
            .take_while(|&r| r > guaranteed)
            .find(|&r| fits(r));
        Ok(halving.unwrap_or(guaranteed))
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// `n` nested cubes over one 2³ dataset, the outermost filling the view, at `step`.
    pub(in crate::render) fn nested_boxes(n: usize, size: u32, step: &str) -> Scene {
        Scene::parse(&nested_text(n, size, step), "nested.toml").unwrap_or_else(|e| panic!("{e}"))
    }

    /// The text of [`nested_boxes`].
    fn nested_text(n: usize, size: u32, step: &str) -> String {
        let mut text = format!(
            "[image]\nwidth = {size}\nheight = {size}\nbackground = [0, 0, 0]\n\
             [camera]\neye = [0, 0, 4]\ntarget = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 30.0\n\
             [[datasets]]\nname = \"d\"\ndims = [2, 2, 2]\n[datasets.channels.voxel]\n\
             generator = {{ kind = \"constant\", value = 0.5 }}\n"
        );
        for i in 0..n {
            let half = 1.0 - i as f64 / (n as f64 + 1.0);
            let (s, t) = (2.0 * half, -half);
            text += &format!(
                "[[objects]]\nname = \"o{i}\"\ndataset = \"d\"\nsampling_distance = {step}\n\
                 transform = {{ matrix = [[{s}, 0, 0, {t}], [0, {s}, 0, {t}], [0, 0, {s}, {t}], [0, 0, 0, 1]] }}\n\
                 colour = {{ type = \"ramp\", points = [[0, 1, 1, 1], [1, 1, 1, 1]] }}\n\
                 opacity = {{ type = \"ramp\", points = [[0, 0.01], [1, 0.01]] }}\n"
            );
        }
        text
    }

    #[test]
    fn counting_agrees_with_intersecting() {
        let scene = nested_boxes(5, 24, "0.1");
        let work = Work::count(&scene).unwrap();
        let inter = super::super::intersection::intersect(&scene, 0..24);
        assert_eq!((work.tasks, work.pieces), (inter.tasks.len() as u64, inter.pieces() as u64));
        assert_eq!(work.tasks_in(0..24), work.tasks);
        assert!(work.tasks > 24 * 24 * 5, "nested boxes share pieces: {}", work.tasks);
    }

    #[test]
    fn counting_while_keeping_the_bands_counts_the_same_and_keeps_what_intersecting_makes() {
        let scene = nested_boxes(5, 24, "0.1");
        let work = Work::count(&scene).unwrap();
        let (kept_work, kept) = Work::count_keeping(&scene, 7, u64::MAX).unwrap();
        assert_eq!(kept_work, work);
        assert_eq!(kept.len(), 4, "bands of 7 rows of 24");
        for (band, inter) in kept.iter().enumerate() {
            let rows = band as u32 * 7..(band as u32 * 7 + 7).min(24);
            let fresh = super::super::intersection::intersect(&scene, rows);
            assert_eq!(
                (&inter.tasks, &inter.piece_start, &inter.ray_start),
                (&fresh.tasks, &fresh.piece_start, &fresh.ray_start)
            );
        }
        // Too little room to keep: the same count, nothing kept.
        let (small, none) = Work::count_keeping(&scene, 7, 1000).unwrap();
        assert_eq!((small, none.len()), (work, 0));
        // A hostile scene is refused as counting refuses it.
        let err = Work::count_keeping(&nested_boxes(300, 512, "1e9"), 32, 1 << 26).unwrap_err();
        assert!(matches!(err, LimitError::TasksPerRender { .. }), "{err}");
    }

    #[test]
    fn a_sparse_view_is_banded_by_its_rays_too() {
        // One small cube in a wide view: a few tasks, many rays.
        let text = nested_text(1, 512, "0.5").replace(
            "[[2, 0, 0, -1], [0, 2, 0, -1], [0, 0, 2, -1]",
            "[[0.1, 0, 0, -0.05], [0, 0.1, 0, -0.05], [0, 0, 0.1, -0.05]",
        );
        let scene = Scene::parse(&text, "sparse.toml").unwrap();
        let work = Work::count(&scene).unwrap();
        assert!(work.tasks > 0 && work.tasks < 512 * 64, "{} tasks", work.tasks);
        let all = 512 * 512 * BYTES_PER_BAND_RAY + work.tasks * BYTES_PER_BAND_TASK;
        // Half the bytes of one band of the whole image: two bands at least.
        let rows = work.rows_within(all / 2).unwrap();
        assert!(rows <= 256, "{rows} rows");
        assert_eq!(work.rows_within(all).unwrap(), 512);
        // Keeping the bands holds their ray index too: none kept within a small bound.
        let (_, kept) = Work::count_keeping(&scene, 16, 512 * 8 * 8).unwrap();
        assert!(kept.is_empty(), "{} bands kept", kept.len());
    }

    #[test]
    fn three_hundred_nested_boxes_at_a_huge_step_are_refused_quickly() {
        let scene = nested_boxes(300, 512, "1e9");
        let started = std::time::Instant::now();
        let err = Work::count(&scene).unwrap_err();
        assert!(started.elapsed().as_secs() < 30, "counting took {:?}", started.elapsed());
        let LimitError::TasksPerRender { counted, max } = err else { panic!("{err}") };
        assert!(counted > max && max == MAX_TASKS_PER_RENDER);
        assert!(err.to_string().contains("limit on piece tasks per render is 536870912"), "{err}");
    }

    #[test]
    fn a_band_denser_than_its_memory_is_refused_naming_its_rows() {
        let scene = nested_boxes(40, 64, "0.1");
        let work = Work::count(&scene).unwrap();
        // The middle rows are the densest: one band of the whole image is over 2²⁰ tasks.
        assert!(work.tasks > MIN_BAND_TASKS, "{}", work.tasks);
        let err = work.check_bands(64, 1).unwrap_err();
        assert!(
            matches!(&err, LimitError::TasksPerBand { rows, max, .. } if *rows == (0..64) && *max == MIN_BAND_TASKS),
            "{err}"
        );
        assert!(err.to_string().contains("limit on piece tasks per band"), "{err}");
        // One-row bands fit, and so does a band memory that holds the whole image.
        work.check_bands(1, 1).unwrap();
        work.check_bands(64, work.tasks * BYTES_PER_BAND_TASK).unwrap();
        // Local mode narrows its bands until each fits rather than refusing.
        let rows = work.rows_within(1 << 20).unwrap();
        work.check_bands(rows, 1 << 20).unwrap();
    }

    #[test]
    fn ray_object_tests_and_pfm_pixels_are_capped() {
        assert!(check_pfm(4096, 4096, MAX_PFM_PIXELS).is_ok());
        let err = check_pfm(16384, 16384, MAX_PFM_PIXELS).unwrap_err();
        assert!(err.to_string().contains("limit on PFM pixels is 16777216"), "{err}");
        assert_eq!(max_band_tasks(0), MIN_BAND_TASKS);
        assert_eq!(max_band_tasks(u64::MAX), MAX_TASKS_PER_RENDER);
    }
}
