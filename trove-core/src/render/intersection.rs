//! Phase 1 of Algorithm 2 (paper §3.3, lines 1–9): every ray against every object, the
//! segments split into pieces, and one [`PieceTask`] per object per piece. Only object-level
//! data is read — placements and dataset dims — never a voxel.
//!
//! The result is flat, so that it can be sliced into batches and shipped: `tasks` holds the
//! work units ray by ray, pieces front to back, a shared piece's objects in scene order;
//! `piece_start` and `ray_start` delimit pieces and rays (as u32: a band holds at most
//! [`super::limits::MAX_TASKS_PER_RENDER`] tasks, and pieces are never more than tasks, so
//! half the bytes of `usize` that every later stage reads). A task's index in `tasks` is also
//! its result's index, so the composition phase finds every ray's ordered piece slots
//! without any ids travelling with the work.
//!
//! A region is a band of whole image rows, so that a farm can work through a large image a
//! band at a time and hold only that band's pieces; tasks carry the pixel index in the
//! whole image either way.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use rayon::prelude::*;

use super::kept;
use super::limits::LimitError;
use super::workunit::PieceTask;
use crate::geometry::{
    count_pieces, split_into_pieces, BoxOrigin, Crossing, Crossings, Piece, PieceScratch, PixelRays, PixelRect, Ray,
    RowDirections, Segment,
};
use crate::scene::Scene;
use crate::width::VectorWidth;
use glam::DVec3;

/// Rows per parallel work item.
const BAND_ROWS: usize = 4;

/// Bytes of an entry of [`Intersections::piece_start`] and [`Intersections::ray_start`],
/// for the memory counts that size bands (`limits.rs`, `Scheduler::heap_bytes`).
pub(crate) const INDEX_BYTES: u64 = std::mem::size_of::<u32>() as u64;

/// Every ray's pieces and the work units they make, for a band of image rows.
#[derive(Clone, Debug, Default)]
pub struct Intersections {
    /// Pixel index of the region's first ray (its first row times the image width).
    pub first_ray: u32,
    /// One task per (piece, covering object), ray by ray, front to back.
    pub tasks: Vec<PieceTask>,
    /// Piece `p`'s tasks are `tasks[piece_start[p]..piece_start[p + 1]]`.
    pub piece_start: Vec<u32>,
    /// Ray `r`'s pieces are `ray_start[r]..ray_start[r + 1]` (rays row-major).
    pub ray_start: Vec<u32>,
    /// Ray–object segments of non-zero length.
    pub segments: u64,
}

impl Intersections {
    /// Number of rays (pixels) in the region.
    pub fn rays(&self) -> usize {
        self.ray_start.len() - 1
    }

    /// The region's ray index of pixel `ray` (a task's `ray`).
    pub fn local_ray(&self, ray: u32) -> usize {
        (ray - self.first_ray) as usize
    }

    /// Number of pieces over all rays.
    pub fn pieces(&self) -> usize {
        self.piece_start.len() - 1
    }

    /// The pieces of ray `r`, as indices into `piece_start`.
    pub fn pieces_of(&self, r: usize) -> std::ops::Range<usize> {
        self.ray_start[r] as usize..self.ray_start[r + 1] as usize
    }

    /// The tasks of piece `p`, as indices into `tasks`.
    pub fn tasks_of(&self, p: usize) -> std::ops::Range<usize> {
        self.piece_start[p] as usize..self.piece_start[p + 1] as usize
    }

    /// The tasks of rays `rays` (local indices), as indices into `tasks`: rays own
    /// consecutive runs of tasks.
    pub fn tasks_of_rays(&self, rays: std::ops::Range<usize>) -> std::ops::Range<usize> {
        let first_task = |r: usize| self.piece_start[self.ray_start[r] as usize] as usize;
        first_task(rays.start)..first_task(rays.end)
    }

    /// Bytes of its three lists.
    pub fn heap_bytes(&self) -> u64 {
        let index = (self.piece_start.len() + self.ray_start.len()) as u64 * INDEX_BYTES;
        (self.tasks.len() * std::mem::size_of::<PieceTask>()) as u64 + index
    }

    /// The piece that task `t` belongs to (binary search within its ray).
    pub fn piece_of(&self, t: usize) -> usize {
        let pieces = self.pieces_of(self.local_ray(self.tasks[t].ray));
        pieces.start + self.piece_start[pieces.clone()].partition_point(|&s| s as usize <= t) - 1
    }
}

/// One band of rows, intersected on one thread.
struct Band {
    tasks: Vec<PieceTask>,
    tasks_per_piece: Vec<u32>,
    pieces_per_ray: Vec<u32>,
    segments: u64,
}

impl Band {
    /// An empty band of `rays` rays, its lists kept from earlier bands where there are some
    /// ([`kept`]; a ray makes about one piece and task, so that is their room to start with).
    fn new(rays: usize) -> Band {
        let (tasks, tasks_per_piece, pieces_per_ray) = (kept::growing(rays), kept::growing(rays), kept::growing(rays));
        Band { tasks, tasks_per_piece, pieces_per_ray, segments: 0 }
    }

    /// Keeps its lists for later bands, once copied out.
    fn keep(self) {
        kept::keep(self.tasks);
        kept::keep(self.tasks_per_piece);
        kept::keep(self.pieces_per_ray);
    }
}

/// Hands the lists of intersections that are no longer needed (their region is
/// composited) to later intersections and schedulers (`kept.rs`), which then write them
/// without the kernel's page faults of fresh memory.
pub fn recycle(region: Intersections) {
    kept::keep(region.tasks);
    kept::keep(region.piece_start);
    kept::keep(region.ray_start);
}

/// Per object of a scene, the pixels whose rays can meet it (the projected bounding
/// rectangle of its box's corners, [`crate::geometry::Camera::pixels_reaching`]): a ray
/// outside is not tested against the object. An object's box lies in the convex hull of its
/// corners (trilinear points are convex combinations of them), so this never drops a hit.
/// It also keeps the image's pixel rays' shared parts ([`PixelRays`]).
/// And how wide the slab tests of a row's rays may run ([`VectorWidth`]).
pub(crate) struct Reach(Vec<PixelRect>, Vec<Option<BoxOrigin>>, PixelRays, VectorWidth);

impl Reach {
    pub(crate) fn new(scene: &Scene) -> Reach {
        let (w, h) = (scene.image().width, scene.image().height);
        let camera = scene.camera();
        let rays = camera.pixel_rays(w.max(1), h.max(1));
        Reach(
            scene.objects().iter().map(|o| camera.pixels_reaching(&o.placement().corners(), w, h)).collect(),
            // Every ray starts at the eye: its part of each slab test is worked out once.
            scene.objects().iter().map(|o| o.placement().box_origin(rays.eye())).collect(),
            rays,
            super::vector_width(),
        )
    }
}

impl Reach {
    /// The objects some pixel of image row `row` can meet, in scene order: what the rays of
    /// that row are tested against ([`RayScratch::segments`]), so that a ray is not even
    /// rectangle-tested against objects far from its row.
    fn on_row(&self, row: u32, out: &mut Vec<u32>) {
        out.clear();
        out.extend(self.0.iter().enumerate().filter(|(_, r)| r.has_row(row)).map(|(i, _)| i as u32));
    }
}

/// The segments of every object that the ray of pixel `(col, row)` crosses over a non-zero
/// length, in scene order (SPEC §4.2): the one place where rays meet objects, for both
/// algorithms.
pub(crate) fn segments_of(
    scene: &Scene,
    reach: &Reach,
    (col, row): (u32, u32),
    ray: &Ray,
    segments: &mut Vec<Segment>,
) {
    segments.clear();
    for (i, ((object, rect), origin)) in scene.objects().iter().zip(&reach.0).zip(&reach.1).enumerate() {
        if !rect.contains(col, row) {
            continue;
        }
        if let Some((t_near, t_far)) = object.placement().segment_from(origin.as_ref(), ray) {
            if t_far > t_near {
                segments.push(Segment { object: i as u32, t_near, t_far });
            }
        }
    }
}

/// What one ray's intersection needs, kept from ray to ray so that none allocates.
#[derive(Default)]
struct RayScratch {
    segments: Vec<Segment>,
    split: PieceScratch,
    pieces: Vec<Piece>,
    cover: Vec<u32>,
    /// The candidate objects of row `row_objects_of` ([`Reach::on_row`]), and the row's
    /// part of its rays' directions ([`PixelRays::row`]).
    row_objects: Vec<u32>,
    row_part: DVec3,
    row_objects_of: Option<u32>,
    /// The (row, first column) of the chunk of columns whose rays are held below.
    chunk_of: Option<(u32, u32)>,
    /// The chunk's ray directions, from its first column.
    dirs: RowDirections,
    /// Per candidate object of the row (as `row_objects`), its crossings of the chunk's rays
    /// that its columns reach, from the column in `first_col`.
    crossings: Vec<Crossings>,
    first_col: Vec<u32>,
}

/// Columns of a row whose rays are tested against an object together
/// ([`BoxOrigin::cross_many`]): long enough to fill vector registers many times over, short
/// enough that a row's candidates' results stay in cache on a scene of many objects.
const CHUNK_COLS: u32 = 64;

impl RayScratch {
    /// The segments of the ray of pixel `(col, row)`, tested against its row's candidates:
    /// affine boxes from the crossings of the ray's chunk of columns, worked out together
    /// the first time one of its rays is asked for.
    fn segments(&mut self, scene: &Scene, reach: &Reach, (col, row): (u32, u32)) {
        if self.row_objects_of != Some(row) {
            reach.on_row(row, &mut self.row_objects);
            self.row_part = reach.2.row(row);
            self.row_objects_of = Some(row);
        }
        self.segments.clear();
        if self.row_objects.is_empty() {
            return;
        }
        let chunk_start = col - col % CHUNK_COLS;
        if self.chunk_of != Some((row, chunk_start)) {
            self.cross_chunk(reach, row, chunk_start, scene.image().width);
        }
        let i_ray = (col - chunk_start) as usize;
        let objects = scene.objects();
        for (k, &i) in self.row_objects.iter().enumerate() {
            let i = i as usize;
            if !reach.0[i].has_col(col) {
                continue;
            }
            let segment = match &reach.1[i] {
                Some(origin) => match self.crossings[k].get((col - self.first_col[k]) as usize) {
                    Crossing::Segment(t_near, t_far) => Some((t_near, t_far)),
                    Crossing::Miss => None,
                    Crossing::Graze => origin.segment(&self.dirs.ray(reach.2.eye(), i_ray)),
                },
                None => objects[i].placement().segment(&self.dirs.ray(reach.2.eye(), i_ray)),
            };
            if let Some((t_near, t_far)) = segment {
                if t_far > t_near {
                    self.segments.push(Segment { object: i as u32, t_near, t_far });
                }
            }
        }
    }

    /// The directions of the rays of columns `chunk_start..` (a chunk) of `row`, and each
    /// affine candidate's crossings of those its columns reach.
    fn cross_chunk(&mut self, reach: &Reach, row: u32, chunk_start: u32, width: u32) {
        let chunk = chunk_start..(chunk_start + CHUNK_COLS).min(width);
        self.dirs.fill(&reach.2, self.row_part, chunk.start as usize..chunk.end as usize);
        let n = self.row_objects.len();
        if self.crossings.len() < n {
            self.crossings.resize_with(n, Crossings::default);
        }
        self.first_col.resize(n, 0);
        for (k, &i) in self.row_objects.iter().enumerate() {
            let i = i as usize;
            let Some(origin) = &reach.1[i] else { continue };
            let cols = reach.0[i].cols();
            // Columns outside the chunk (an object whose span ends before it or starts after
            // it) make an empty range: the object is not asked about any of its rays.
            let first = cols.start.clamp(chunk.start, chunk.end);
            let end = cols.end.clamp(first, chunk.end);
            self.first_col[k] = first;
            let rays = (first - chunk.start) as usize..(end - chunk.start) as usize;
            origin.cross_many(&self.dirs, rays, reach.3, &mut self.crossings[k]);
        }
        self.chunk_of = Some((row, chunk_start));
    }

    /// Splits the ray of pixel `(col, row)` into pieces (`self.pieces`, their objects in
    /// `self.cover`); returns its number of segments.
    fn pieces(&mut self, scene: &Scene, reach: &Reach, pixel: (u32, u32)) -> usize {
        self.segments(scene, reach, pixel);
        split_into_pieces(&self.segments, &mut self.split, &mut self.pieces, &mut self.cover);
        self.segments.len()
    }

    /// The pieces and tasks of the ray of pixel `(col, row)`, counted without storing them.
    fn count(&mut self, scene: &Scene, reach: &Reach, pixel: (u32, u32)) -> (u64, u64) {
        self.segments(scene, reach, pixel);
        count_pieces(&self.segments, &mut self.split)
    }
}

/// Counts the pieces and tasks of whole image rows without storing any, for the limits
/// checked before a render ([`super::limits::Work`]).
pub(crate) struct RowCounter<'s> {
    scene: &'s Scene,
    reach: Reach,
}

impl<'s> RowCounter<'s> {
    pub(crate) fn new(scene: &'s Scene) -> RowCounter<'s> {
        RowCounter { scene, reach: Reach::new(scene) }
    }

    /// (pieces, tasks) of image row `row`; counting stops once the tasks pass `max`.
    pub(crate) fn row(&self, row: u32, max: u64) -> (u64, u64) {
        let mut scratch = RayScratch::default();
        let (mut pieces, mut tasks) = (0, 0);
        for col in 0..self.scene.image().width {
            let (p, t) = scratch.count(self.scene, &self.reach, (col, row));
            pieces += p;
            tasks += t;
            if tasks > max {
                break;
            }
        }
        (pieces, tasks)
    }
}

/// Intersects every ray of image rows `rows` of `scene` with every object (the scene
/// guarantees at most [`crate::scene::MAX_OBJECTS`] objects, so an object index fits the
/// task's 16 bits). It holds every task of the rows, which must be at most
/// [`super::limits::MAX_TASKS_PER_RENDER`] (what [`super::limits::Work`] checks before any
/// render): a driver that must stay within a memory bound calls [`intersect_within`].
pub fn intersect(scene: &Scene, rows: std::ops::Range<u32>) -> Intersections {
    intersect_within(scene, rows, u64::MAX, u64::MAX).expect("rows within a render's tasks, as counted")
}

/// As [`intersect`], refusing rows that make more than `max_tasks` tasks (what
/// `band_memory` bytes hold, [`super::limits::max_band_tasks`], which the error quotes) as
/// soon as the count passes it: no ray's tasks are stored once the total a thread knows of
/// would exceed the limit (threads add their counts to the shared total a row at a time, so
/// each may store up to a row's tasks more than the others' rows leave room for), so a band
/// denser than its sizing expected allocates at most a row per thread past it.
pub fn intersect_within(
    scene: &Scene,
    rows: std::ops::Range<u32>,
    max_tasks: u64,
    band_memory: u64,
) -> Result<Intersections, LimitError> {
    let (w, h) = (scene.image().width, scene.image().height);
    let rows = rows.start.min(h)..rows.end.min(h);
    // The lists index tasks and pieces in u32: no band holds more than a render may.
    let max_tasks = max_tasks.min(super::limits::MAX_TASKS_PER_RENDER);
    let reach = Reach::new(scene);
    let (total, over) = (AtomicU64::new(0), AtomicBool::new(false));
    let bands: Vec<Band> = (rows.start as usize..rows.end as usize)
        .into_par_iter()
        .step_by(BAND_ROWS)
        .map(|first_row| {
            let mut band = Band::new(BAND_ROWS * w as usize);
            let mut scratch = RayScratch::default();
            // The shared total is added to once a row, not once a ray: `known` is what it
            // held after this thread's last addition (it only grows), `row_tasks` this row's
            // tasks since. A thread stops as soon as those two pass the limit, adding its
            // row's tasks first, so the total then passes it too; and a band within the
            // limit adds up to its exact count.
            let mut known = 0u64;
            for row in first_row..(first_row + BAND_ROWS).min(rows.end as usize) {
                let mut row_tasks = 0u64;
                for col in 0..w {
                    if over.load(Ordering::Relaxed) {
                        return band;
                    }
                    let ray_index = row as u32 * w + col;
                    band.segments += scratch.pieces(scene, &reach, (col, row as u32)) as u64;
                    row_tasks += scratch.cover.len() as u64;
                    if known.saturating_add(row_tasks) > max_tasks {
                        total.fetch_add(row_tasks, Ordering::Relaxed);
                        over.store(true, Ordering::Relaxed);
                        return band;
                    }
                    band.pieces_per_ray.push(scratch.pieces.len() as u32);
                    for p in &scratch.pieces {
                        let objects = &scratch.cover[p.cover.0 as usize..p.cover.1 as usize];
                        let shared = objects.len() > 1;
                        for &o in objects {
                            band.tasks.push(PieceTask::new(ray_index, o as u16, p.t0, p.t1, shared));
                        }
                        band.tasks_per_piece.push(objects.len() as u32);
                    }
                }
                known = total.fetch_add(row_tasks, Ordering::Relaxed).saturating_add(row_tasks);
                if known > max_tasks {
                    over.store(true, Ordering::Relaxed);
                    return band;
                }
            }
            band
        })
        .collect();
    let counted = total.into_inner();
    if counted > max_tasks {
        return Err(LimitError::TasksPerBand { rows, counted, max: max_tasks, band_memory });
    }

    Ok(merge(bands, rows.start * w))
}

/// The bands' lists laid end to end as one region's, each band copied into its place on
/// rayon's threads: on a new process this is memory written for the first time, whose page
/// faults (about 2 µs each in a VM) made the serial copy a tenth of the CT head's frame
/// before casting.
fn merge(bands: Vec<Band>, first_ray: u32) -> Intersections {
    let tasks: usize = bands.iter().map(|b| b.tasks.len()).sum();
    let pieces: usize = bands.iter().map(|b| b.tasks_per_piece.len()).sum();
    let rays: usize = bands.iter().map(|b| b.pieces_per_ray.len()).sum();
    let mut out = Intersections {
        first_ray,
        tasks: kept::with_room(tasks),
        piece_start: kept::for_overwrite(pieces + 1),
        ray_start: kept::for_overwrite(rays + 1),
        segments: bands.iter().map(|b| b.segments).sum(),
    };
    out.piece_start[0] = 0;
    out.ray_start[0] = 0;
    {
        let mut task_slots = &mut out.tasks.spare_capacity_mut()[..tasks];
        let (mut piece_slots, mut ray_slots) = (&mut out.piece_start[1..], &mut out.ray_start[1..]);
        // Each band's share of the lists, and where its tasks and pieces start in them.
        let mut parts = Vec::with_capacity(bands.len());
        let (mut first_task, mut first_piece) = (0, 0);
        for band in &bands {
            let t;
            (t, task_slots) = std::mem::take(&mut task_slots).split_at_mut(band.tasks.len());
            let p;
            (p, piece_slots) = std::mem::take(&mut piece_slots).split_at_mut(band.tasks_per_piece.len());
            let r;
            (r, ray_slots) = std::mem::take(&mut ray_slots).split_at_mut(band.pieces_per_ray.len());
            parts.push((band, (first_task, first_piece), t, p, r));
            first_task += band.tasks.len();
            first_piece += band.tasks_per_piece.len();
        }
        parts.into_par_iter().for_each(|(band, (first_task, first_piece), t, p, r)| {
            for (slot, task) in t.iter_mut().zip(&band.tasks) {
                slot.write(*task);
            }
            // Tasks and pieces are below 2^29 (`intersect_within`'s cap), so u32 holds them.
            let mut last = first_task as u32;
            for (slot, &n) in p.iter_mut().zip(&band.tasks_per_piece) {
                last += n;
                *slot = last;
            }
            let mut last = first_piece as u32;
            for (slot, &n) in r.iter_mut().zip(&band.pieces_per_ray) {
                last += n;
                *slot = last;
            }
        });
    }
    // SAFETY: the parts above cover the first `tasks` slots exactly (each band's chunk is as
    // long as its list, the chunks taken in turn from those slots), and each was written.
    unsafe { out.tasks.set_len(tasks) };
    bands.into_iter().for_each(Band::keep);
    out
}

/// The sample positions `object` takes over [t0, t1] of `ray` (SPEC §4.2): what a cast would
/// evaluate, for counting the samples that early termination saved.
pub(crate) fn sample_positions(scene: &Scene, ray: &Ray, object: usize, t0: f64, t1: f64) -> u64 {
    let object = &scene.objects()[object];
    object.placement().walk(ray, t0, t1, object.sampling_distance()).len()
}

/// The sample positions of a task, its ray recomputed from the camera: what culling it
/// saved, for statistics.
pub(crate) fn task_sample_positions(scene: &Scene, task: &PieceTask) -> u64 {
    let (w, h) = (scene.image().width, scene.image().height);
    let ray = scene.camera().ray(task.ray % w, task.ray / w, w, h);
    sample_positions(scene, &ray, task.object as usize, task.t0, task.t1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::PixelRect;

    #[test]
    fn rays_outside_an_objects_pixels_would_have_missed_it() {
        // Rotated, stretched, distorted (eight corners), partly behind the eye, and out of
        // view: culling must drop only misses.
        let objects = [
            "transform = { matrix = [[0.5736, 0.8192, 0, -1.2964], [0, 0, -0.883, 0.9915], [0.8192, -0.5736, 0, -0.3228], [0, 0, 0, 1]] }",
            "transform = { matrix = [[1.53, 0, 0, -0.765], [0, 0, -0.7947, -0.1527], [0, -0.9, 0, 1.05], [0, 0, 0, 1]] }",
            "transform = { corners = [[0.85, -0.15, 1.2], [1.45, -0.15, 1.2], [0.85, -0.15, 0], [1.45, -0.15, 0], [0.95, -0.95, 1.05], [1.85, -0.95, 1.05], [0.95, -0.95, 0.15], [1.85, -0.95, 0.15]] }",
            "transform = { matrix = [[1, 0, 0, -0.5], [0, 1, 0, -0.5], [0, 0, 6, 1.0], [0, 0, 0, 1]] }",
            "transform = { matrix = [[1, 0, 0, 30], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]] }",
        ];
        let mut text = String::from(
            "[image]\nwidth = 161\nheight = 47\nbackground = [0, 0, 0]\n[camera]\neye = [0.2, 0.3, 4.0]\ntarget = [0, 0, 0]\nup = [0, 1, 0]\n\
             fov_y = 40.0\n[[datasets]]\nname = \"v\"\ndims = [3, 4, 5]\n[datasets.channels.voxel]\n\
             generator = { kind = \"ramp\", axis = \"x\", from = 0.0, to = 1.0 }\n",
        );
        for (i, transform) in objects.iter().enumerate() {
            text += &format!(
                "[[objects]]\nname = \"o{i}\"\ndataset = \"v\"\n{transform}\n\
                 colour = {{ type = \"ramp\", points = [[0, 1, 0, 0], [1, 0, 0, 1]] }}\n\
                 opacity = {{ type = \"ramp\", points = [[0, 0.1], [1, 0.9]] }}\n"
            );
        }
        let scene = Scene::parse(&text, "reach.toml").unwrap();
        let (w, h) = (scene.image().width, scene.image().height);
        let reach = Reach::new(&scene);
        let everywhere = Reach(
            vec![PixelRect::whole(w, h); objects.len()],
            vec![None; objects.len()],
            scene.camera().pixel_rays(w, h),
            VectorWidth::Baseline,
        );
        let (mut culled, mut hits) = (0, 0);
        let (mut a, mut b) = (Vec::new(), Vec::new());
        let mut scratch = RayScratch::default();
        for row in 0..h {
            for col in 0..w {
                let ray = scene.camera().ray(col, row, w, h);
                segments_of(&scene, &reach, (col, row), &ray, &mut a);
                segments_of(&scene, &everywhere, (col, row), &ray, &mut b);
                assert_eq!(a, b, "pixel ({col}, {row})");
                // What intersecting tests: only its row's candidates, the same segments.
                scratch.segments(&scene, &reach, (col, row));
                assert_eq!(scratch.segments, b, "pixel ({col}, {row}), row candidates");
                hits += a.len();
                culled += reach.0.iter().filter(|r| !r.contains(col, row)).count();
            }
        }
        // Counting stores no task and counts what intersecting makes.
        let tasks = intersect(&scene, 3..40).tasks.len() as u64;
        let counter = RowCounter::new(&scene);
        assert_eq!((3..40).map(|row| counter.row(row, u64::MAX).1).sum::<u64>(), tasks);
        // A limit below the count refuses the rows; one at it does not.
        assert!(intersect_within(&scene, 3..40, tasks, 0).is_ok());
        let err = intersect_within(&scene, 3..40, tasks - 1, 0).unwrap_err();
        assert!(matches!(err, LimitError::TasksPerBand { counted, .. } if counted >= tasks), "{err}");
        // The test means something: objects are hit, and many rays are never tested.
        assert!(hits > 500 && culled > (w * h) as usize, "{hits} hits, {culled} culled");
        // Out of view: no pixel; partly behind the eye: every pixel.
        assert_eq!(reach.0[4].pixels(), 0);
        assert_eq!(reach.0[3], PixelRect::whole(w, h));
    }

    /// The region's lists, merged from bands of rows cast on different threads, delimit each
    /// ray's pieces and each piece's tasks in order: every task of ray r's pieces names
    /// pixel `first_ray + r`, and the starts rise to exactly the lists' ends.
    #[test]
    fn the_merged_lists_delimit_each_ray_s_pieces_and_tasks() {
        let scene = super::super::limits::tests::nested_boxes(3, 37, "0.1");
        for rows in [0..37, 5..23, 36..37] {
            let inter = intersect(&scene, rows.clone());
            assert_eq!(inter.first_ray, rows.start * 37);
            assert_eq!(inter.rays(), rows.len() * 37);
            assert_eq!(*inter.ray_start.last().unwrap() as usize, inter.pieces());
            assert_eq!(*inter.piece_start.last().unwrap() as usize, inter.tasks.len());
            assert!(inter.ray_start.windows(2).all(|w| w[0] <= w[1]));
            assert!(inter.piece_start.windows(2).all(|w| w[0] < w[1]), "a piece has at least one task");
            for r in 0..inter.rays() {
                for p in inter.pieces_of(r) {
                    for t in inter.tasks_of(p) {
                        assert_eq!(inter.local_ray(inter.tasks[t].ray), r, "rows {rows:?}, ray {r}, task {t}");
                    }
                }
            }
            if rows.len() > 4 {
                assert!(inter.pieces() > inter.rays(), "rays cross several pieces: {}", inter.pieces());
            }
        }
    }

    /// Intersections written into kept buffers are those written into fresh ones: whatever
    /// a recycled region or band held (more, fewer, other rows), none of it shows.
    #[test]
    fn kept_buffers_change_nothing() {
        let text = |size: u32| {
            format!(
                "[image]\nwidth = {size}\nheight = {size}\nbackground = [0, 0, 0]\n[camera]\neye = [0.2, 0.3, 4.0]\n\
                 target = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 40.0\n[[datasets]]\nname = \"v\"\ndims = [3, 4, 5]\n\
                 [datasets.channels.voxel]\ngenerator = {{ kind = \"constant\", value = 1.0 }}\n\
                 [[objects]]\nname = \"a\"\ndataset = \"v\"\ncolour = {{ type = \"constant\", red = [1], green = [1], blue = [1] }}\n\
                 opacity = {{ type = \"constant\", coefficients = [0.5] }}\n\
                 [[objects]]\nname = \"b\"\ndataset = \"v\"\ncolour = {{ type = \"constant\", red = [1], green = [1], blue = [1] }}\n\
                 opacity = {{ type = \"constant\", coefficients = [0.5] }}\n\
                 transform = {{ matrix = [[1, 0, 0, -0.3], [0, 1, 0, -0.2], [0, 0, 1, -0.4], [0, 0, 0, 1]] }}\n"
            )
        };
        let small = Scene::parse(&text(19), "small.toml").unwrap();
        let large = Scene::parse(&text(61), "large.toml").unwrap();
        let fresh: Vec<Intersections> =
            [(&small, 2..15), (&large, 0..61), (&large, 30..31), (&small, 0..19)].map(|(s, r)| intersect(s, r)).into();
        let key =
            |i: &Intersections| (i.first_ray, i.tasks.clone(), i.piece_start.clone(), i.ray_start.clone(), i.segments);
        for round in 0..3 {
            // Regions of other sizes handed back, some with more room than they use.
            for (k, region) in fresh.iter().enumerate() {
                let mut kept = region.clone();
                kept.tasks.reserve(k * 1000);
                recycle(kept);
            }
            for (i, (s, rows)) in
                [(&small, 2..15), (&large, 0..61), (&large, 30..31), (&small, 0..19)].into_iter().enumerate()
            {
                let again = intersect(s, rows);
                assert_eq!(key(&again), key(&fresh[i]), "round {round}, region {i}");
                // A kept list much larger than the region needs was cut down: what its holder
                // counts is about what it needs.
                let n = again.tasks.len();
                assert!(again.tasks.capacity() <= n + n / 8, "round {round}, region {i}: {}", again.tasks.capacity());
            }
        }
        assert!(fresh[1].tasks.len() > fresh[0].tasks.len() && fresh[1].pieces() > 100, "{}", fresh[1].pieces());
    }
}
