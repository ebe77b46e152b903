//! Measures the simulation's inputs on this machine by running the code the farm runs:
//! `trove-core`'s intersection, scheduler, caster, compositor, loaders and PNG encoder on
//! scenes of the simulated family, each timed on one thread (the minimum of a few runs, since
//! the machine is shared and a slower run only measures the neighbours). What the farm's
//! binaries add around `trove-core` — the registry, the job status, the `open` message —
//! is timed on replicas of their data structures (`registry.rs`, `driver.rs`,
//! `jobs.rs` on the `farm` branch), built from the same std types.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::io::Write as _;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Instant;

use anyhow::{Context, Result};
use trove_core::render::intersection::{intersect, Intersections};
use trove_core::render::wire::{decode_results, encode_results, encode_tasks};
use trove_core::render::{BatchCaster, PieceRgba, Scheduler};
use trove_core::scene::Scene;

use super::inputs::Inputs;
use super::scene::SceneSpec;

/// Runs of each timing; the fastest counts.
const RUNS: usize = 5;
/// Tasks per batch, as the driver's default.
const BATCH_TASKS: usize = 4096;

/// Seconds of the fastest of [`RUNS`] runs of `f`, on one thread.
fn fastest<T: Send>(mut f: impl FnMut() -> T + Send) -> f64 {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().expect("a one-thread pool");
    (0..RUNS)
        .map(|_| {
            let started = Instant::now();
            std::hint::black_box(pool.install(&mut f));
            started.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

/// Least squares for `y ≈ Σ cᵢ·xᵢ` with two unknowns.
fn fit2(rows: &[([f64; 2], f64)]) -> [f64; 2] {
    let (mut a, mut b, mut c, mut p, mut q) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for ([x0, x1], y) in rows {
        a += x0 * x0;
        b += x0 * x1;
        c += x1 * x1;
        p += x0 * y;
        q += x1 * y;
    }
    let det = a * c - b * b;
    [(p * c - b * q) / det, (a * q - b * p) / det]
}

/// How big the measurement is: `quick` for tests.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Size {
    /// Image side of the timed scenes.
    pub side: u32,
    /// Voxels per axis of the datasets cast.
    pub dims: u32,
}

impl Size {
    pub(crate) const FULL: Size = Size { side: 128, dims: 64 };
}

/// Measures every input that can be measured here; the network and the fixed per-event
/// costs are kept from `base`.
pub(crate) fn measure(size: Size, base: &Inputs) -> Result<Inputs> {
    let mut i = base.clone();
    measure_worker(size, &mut i)?;
    measure_coordinator(size, &mut i)?;
    measure_replicas(&mut i);
    Ok(i)
}

fn spec(size: Size, datasets: usize, depth: f64, step_voxels: f64) -> SceneSpec {
    SceneSpec { datasets, depth, dims: size.dims, width: size.side, height: size.side, step_voxels, seed: 1 }
}

/// Casting, binding, loading and parsing: what a worker does.
fn measure_worker(size: Size, i: &mut Inputs) -> Result<()> {
    // The same pieces cast at a sample every 4 voxels, every voxel and 4 per voxel: what
    // changes with the step is the samples; what does not is the tasks.
    let mut rows = Vec::new();
    for step in [4.0, 1.0, 0.25] {
        let (tasks, samples, seconds, bind) = time_casting(&spec(size, 8, 3.0, step).build()?)?;
        rows.push(([tasks as f64, samples as f64], seconds));
        i.bind_per_voxel = bind;
    }
    let [per_task, per_sample] = fit2(&rows);
    i.cast_per_task = per_task.max(0.0);
    i.cast_per_sample = per_sample;
    i.load_per_byte = time_gzip_load(size.dims * 3 / 2)?;
    let text = spec(size, 256, 4.0, 1.0).toml();
    i.parse_per_object = fastest(|| Scene::parse(&text, "parse.toml").map(|s| s.objects().len())) / 256.0;
    Ok(())
}

/// Casts every task of `scene` (one thread, batches of [`BATCH_TASKS`]); returns tasks,
/// samples, the seconds of the casts, and binding's seconds per voxel.
fn time_casting(scene: &Scene) -> Result<(u64, u64, f64, f64)> {
    let volumes = scene.datasets().iter().map(|d| d.load()).collect::<Result<Vec<_>, _>>()?;
    let voxels: u64 = scene.datasets().iter().map(|d| d.dims().voxel_count()).sum();
    let bind = fastest(|| {
        volumes.iter().enumerate().map(|(d, v)| BatchCaster::new(scene, d, v).is_ok()).filter(|ok| *ok).count()
    }) / voxels as f64;
    let casters =
        volumes.iter().enumerate().map(|(d, v)| BatchCaster::new(scene, d, v)).collect::<Result<Vec<_>, _>>()?;
    let mut best = (0, 0, f64::INFINITY);
    for _ in 0..RUNS {
        let mut scheduler = Scheduler::new(scene, intersect(scene, 0..scene.image().height), BATCH_TASKS)?;
        let (mut tasks, mut samples, mut seconds) = (0, 0, 0.0);
        for d in scheduler.datasets().to_vec() {
            while let Some(batch) = scheduler.next_batch(d) {
                let mut out = vec![PieceRgba::default(); batch.tasks.len()];
                let started = Instant::now();
                samples += casters[d].cast(&batch.tasks, &mut out)?;
                seconds += started.elapsed().as_secs_f64();
                tasks += batch.tasks.len() as u64;
                scheduler.record(batch.id, &out)?;
            }
        }
        if seconds < best.2 {
            best = (tasks, samples, seconds);
        }
    }
    Ok((best.0, best.1, best.2, bind))
}

/// Seconds per byte to load a CT-like `n`³ u16 volume from a gzip NRRD file.
fn time_gzip_load(n: u32) -> Result<f64> {
    let dir = std::env::temp_dir().join(format!("trove-farm-sim-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let result = (|| {
        let mut voxels = Vec::with_capacity(2 * (n as usize).pow(3));
        for k in 0..n {
            for j in 0..n {
                for i in 0..n {
                    voxels.extend_from_slice(&ct_like([i, j, k], n).to_le_bytes());
                }
            }
        }
        let header =
            format!("NRRD0004\ntype: uint16\ndimension: 3\nsizes: {n} {n} {n}\nendian: little\nencoding: gzip\n\n");
        let mut gz = flate2::write::GzEncoder::new(header.into_bytes(), flate2::Compression::default());
        gz.write_all(&voxels)?;
        std::fs::write(dir.join("ct.nrrd"), gz.finish()?)?;
        let text = format!(
            "{}[[datasets]]\nname = \"ct\"\nfile = \"ct.nrrd\"\n",
            trove_tests::Header::new(8, [0.0, 0.0, 4.0], [0.0; 3], 30.0)
        );
        let scene = Scene::parse(&text, dir.join("scene.toml")).context("the load-timing scene")?;
        let info = &scene.datasets()[0];
        Ok(fastest(|| info.load().map(|v| v.byte_len())) / info.resident_bytes() as f64)
    })();
    let _ = std::fs::remove_dir_all(&dir);
    result
}

/// A CT-like value: an ellipsoid of soft tissue with a textured interior and a shell of
/// bone, 12-bit, with a little noise in the low bits as a scanner leaves.
fn ct_like([i, j, k]: [u32; 3], n: u32) -> u16 {
    let p = [i, j, k].map(|c| (c as f64 + 0.5) / n as f64 - 0.5);
    let r = (p[0] / 0.4).hypot(p[1] / 0.46).hypot(p[2] / 0.42);
    let tau = std::f64::consts::TAU;
    let texture = (tau * 6.0 * p[0]).sin() * (tau * 6.0 * p[1]).sin() * (tau * 6.0 * p[2]).sin();
    let noise = ((i.wrapping_mul(73_856_093) ^ j.wrapping_mul(19_349_663) ^ k.wrapping_mul(83_492_791)) % 16) as f64;
    let value = match r {
        r if r < 0.70 => 1500.0 + 400.0 * texture,
        r if r < 0.85 => 3000.0,
        r if r < 0.95 => 1000.0,
        _ => 0.0,
    };
    (value + noise) as u16
}

/// One timed scene of the coordinator's measurements.
struct CoordinatorRun {
    rays: f64,
    objects: f64,
    tasks: f64,
    pieces: f64,
    intersect: f64,
    plan: f64,
    dispatch: f64,
    record: f64,
    composite: f64,
}

/// Intersection, planning, dispatch, recording and composition, on scenes of 16 and 256
/// datasets at two depths, so that costs per ray·object, per task and per piece separate.
fn measure_coordinator(size: Size, i: &mut Inputs) -> Result<()> {
    let mut runs = Vec::new();
    for (datasets, depth) in [(16, 2.0), (16, 6.0), (256, 2.0), (256, 6.0)] {
        runs.push(time_coordinator(&spec(size, datasets, depth, 1.0).build()?)?);
    }
    let per = |f: &dyn Fn(&CoordinatorRun) -> f64| {
        runs.iter().map(f).sum::<f64>() / runs.iter().map(|r| r.tasks).sum::<f64>()
    };
    [i.intersect_per_ray_object, i.intersect_per_task] =
        fit2(&runs.iter().map(|r| ([r.rays * r.objects, r.tasks], r.intersect)).collect::<Vec<_>>());
    i.intersect_per_ray_object = i.intersect_per_ray_object.max(0.0);
    i.intersect_per_task = i.intersect_per_task.max(0.0);
    i.plan_per_task = per(&|r| r.plan);
    i.dispatch_per_task = per(&|r| r.dispatch);
    i.record_per_task = per(&|r| r.record);
    [i.composite_per_ray, i.composite_per_piece] =
        fit2(&runs.iter().map(|r| ([r.rays, r.pieces], r.composite)).collect::<Vec<_>>());
    i.composite_per_ray = i.composite_per_ray.max(0.0);
    i.composite_per_piece = i.composite_per_piece.max(0.0);
    i.png_per_pixel = time_png(1024)?;
    Ok(())
}

fn time_coordinator(scene: &Scene) -> Result<CoordinatorRun> {
    let rows = 0..scene.image().height;
    let inter = intersect(scene, rows.clone());
    let (rays, tasks, pieces) = (inter.rays() as f64, inter.tasks.len() as f64, inter.pieces() as f64);
    let intersect_s = fastest(|| intersect(scene, rows.clone()).tasks.len());
    let plan = fastest(|| Scheduler::new(scene, inter.clone(), BATCH_TASKS).map(|s| s.datasets().len()));
    let (mut dispatch, mut record, mut composite) = (f64::INFINITY, f64::INFINITY, f64::INFINITY);
    for _ in 0..RUNS {
        let (d, r, c) = time_schedule(scene, inter.clone())?;
        dispatch = dispatch.min(d);
        record = record.min(r);
        composite = composite.min(c);
    }
    let objects = scene.objects().len() as f64;
    Ok(CoordinatorRun { rays, objects, tasks, pieces, intersect: intersect_s, plan, dispatch, record, composite })
}

/// Drives the scheduler as the coordinator's loop does, with every result of zero opacity
/// (nothing culled): seconds handing out and encoding batches, decoding and recording their
/// results, and compositing every ray (one thread).
fn time_schedule(scene: &Scene, inter: Intersections) -> Result<(f64, f64, f64)> {
    let mut scheduler = Scheduler::new(scene, inter, BATCH_TASKS)?;
    let (mut dispatch, mut record) = (0.0, 0.0);
    let order = scheduler.datasets().to_vec();
    // Round robin over the datasets, a wave at a time, as batches come back from many workers.
    let mut open: Vec<usize> = order.clone();
    while !open.is_empty() {
        open.retain(|&d| {
            let started = Instant::now();
            let Some(batch) = scheduler.next_batch(d) else { return false };
            std::hint::black_box(encode_tasks(&batch.tasks));
            dispatch += started.elapsed().as_secs_f64();
            let answer = encode_results(&vec![PieceRgba::default(); batch.tasks.len()]);
            let started = Instant::now();
            let results = decode_results(&answer).expect("whole results");
            let ok = scheduler.record(batch.id, &results).is_ok();
            record += started.elapsed().as_secs_f64();
            ok
        });
    }
    anyhow::ensure!(scheduler.is_complete(), "the timed schedule did not finish");
    let rays = scheduler.intersections().rays();
    let composite = fastest(|| (0..rays).map(|r| scheduler.composite_ray(r).alpha).sum::<f64>());
    Ok((dispatch, record, composite))
}

/// Seconds per pixel to encode a `side`² PNG of a smooth image with a little noise.
fn time_png(side: u32) -> Result<f64> {
    let rgb: Vec<u8> = (0..side * side * 3)
        .map(|k| {
            let (p, c) = (k / 3, k % 3);
            let (x, y) = (p % side, p / side);
            ((x * (c + 1) + y) / 8 % 256) as u8 ^ ((p.wrapping_mul(2_654_435_761) >> 29) as u8)
        })
        .collect();
    let seconds = fastest(|| trove_core::render::encode_png(side, side, &rgb).map(|png| png.len()));
    trove_core::render::encode_png(side, side, &rgb)?;
    Ok(seconds / (side as f64 * side as f64))
}

/// What the registry holds of a worker (`WorkerEntry` in `registry.rs`); the tonic channel,
/// whose clone is a sender and a semaphore, stands as two `Arc`s.
struct Entry {
    id: String,
    address: String,
    files: HashMap<String, FileStub>,
    threads: u32,
    channel: (Arc<()>, Arc<()>),
    in_flight: Arc<AtomicU64>,
    done: Arc<AtomicU64>,
    last_heartbeat: Instant,
}

/// A `DatasetFile` registration: key, size and a volume header.
#[derive(Clone)]
struct FileStub {
    key: String,
    bytes: u64,
    dims: [u32; 3],
    voxel_type: i32,
}

/// What a dispatcher holds of a worker (`WorkerHandle`).
struct Handle {
    id: String,
    _channel: (Arc<()>, Arc<()>),
    threads: u32,
    in_flight: Arc<AtomicU64>,
    _done: Arc<AtomicU64>,
}

struct Registry {
    state: Mutex<BTreeMap<String, Entry>>,
    lost_after: std::time::Duration,
}

impl Registry {
    /// `workers` workers; dataset `d` is file `data/d{d}.nrrd`, held round robin `replicas`
    /// times.
    fn new(workers: usize, datasets: usize, replicas: usize) -> Registry {
        let mut state = BTreeMap::new();
        for w in 0..workers {
            let files = (0..datasets)
                .filter(|d| (0..replicas).any(|j| (d + j * (workers / replicas)) % workers == w))
                .map(|d| {
                    let key = format!("data/d{d}.nrrd");
                    (key.clone(), FileStub { key, bytes: 1 << 25, dims: [256; 3], voxel_type: 3 })
                })
                .collect();
            let id = format!("w{}", w + 1);
            let channel = (Arc::new(()), Arc::new(()));
            let (in_flight, done) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
            let address = format!("10.0.{}.{}:7001", w / 256, w % 256);
            let entry = Entry {
                id: id.clone(),
                address,
                files,
                threads: 8,
                channel,
                in_flight,
                done,
                last_heartbeat: Instant::now(),
            };
            state.insert(id, entry);
        }
        Registry { state: Mutex::new(state), lost_after: std::time::Duration::from_secs(5) }
    }

    /// `Registry::holders`, as written.
    fn holders(&self, keys: &[String]) -> Vec<String> {
        let state = self.state.lock().expect("unpoisoned");
        state
            .values()
            .filter(|w| w.last_heartbeat.elapsed() <= self.lost_after)
            .filter(|w| keys.iter().all(|k| w.files.contains_key(k)))
            .map(|w| w.id.clone())
            .collect()
    }

    /// `Registry::handle`, as written.
    fn handle(&self, id: &str) -> Option<Handle> {
        let state = self.state.lock().expect("unpoisoned");
        let w = state.get(id).filter(|w| w.last_heartbeat.elapsed() <= self.lost_after)?;
        Some(Handle {
            id: w.id.clone(),
            _channel: w.channel.clone(),
            threads: w.threads,
            in_flight: w.in_flight.clone(),
            _done: w.done.clone(),
        })
    }
}

/// The driver's `pick_worker`, as written.
fn pick_worker(registry: &Registry, keys: &[String], d: usize, unusable: &HashSet<(String, usize)>) -> Option<Handle> {
    let holders: Vec<Handle> = registry
        .holders(keys)
        .into_iter()
        .filter(|w| !unusable.contains(&(w.clone(), d)))
        .filter_map(|w| registry.handle(&w))
        .collect();
    holders
        .into_iter()
        .filter(|w| w.in_flight.load(Ordering::Relaxed) < (2 * w.threads as u64).max(4))
        .min_by_key(|w| (w.in_flight.load(Ordering::Relaxed), w.id.clone()))
}

/// Seconds of one `pick_worker` over `datasets` datasets of a registry of `workers` with
/// `replicas` holders each.
fn time_pick(workers: usize, replicas: usize) -> f64 {
    let datasets = 256;
    let registry = Registry::new(workers, datasets, replicas);
    let keys: Vec<Vec<String>> = (0..datasets).map(|d| vec![format!("data/d{d}.nrrd")]).collect();
    let unusable = HashSet::new();
    // Each timed run picks for every dataset 16 times: long enough that a preemption shows as
    // a slow run, which the minimum drops.
    let rounds = 16;
    let seconds = fastest(|| {
        (0..rounds)
            .map(|_| keys.iter().enumerate().filter_map(|(d, k)| pick_worker(&registry, k, d, &unusable)).count())
            .sum::<usize>()
    });
    // Every field a real registry carries is there to be cloned or scanned.
    let state = registry.state.lock().expect("unpoisoned");
    let held = state
        .values()
        .map(|e| {
            e.files.values().map(|f| f.bytes + f.dims[0] as u64 + f.voxel_type as u64 + f.key.len() as u64).sum::<u64>()
                + e.address.len() as u64
        })
        .sum::<u64>();
    std::hint::black_box(held);
    seconds / (rounds * datasets) as f64
}

/// The job's status as `update_progress` rebuilds it after every answer: one count per
/// worker, cloned into the status, which watchers are told of.
fn time_progress(workers: usize) -> f64 {
    #[derive(Clone)]
    struct Count {
        id: String,
        batches: u64,
        tasks: u64,
        samples: u64,
    }
    let stats: BTreeMap<String, Count> = (0..workers)
        .map(|w| (format!("w{w}"), Count { id: format!("w{w}"), batches: 1, tasks: 2, samples: 3 }))
        .collect();
    let status = (Mutex::new(Vec::<Count>::new()), Condvar::new());
    let updates = 1000;
    let seconds = fastest(|| {
        for _ in 0..updates {
            let counts: Vec<Count> = stats.values().cloned().collect();
            *status.0.lock().expect("unpoisoned") = counts;
            status.1.notify_all();
        }
        status
            .0
            .lock()
            .expect("unpoisoned")
            .iter()
            .map(|c| c.id.len() as u64 + c.batches + c.tasks + c.samples)
            .sum::<u64>()
    });
    seconds / (updates * workers) as f64
}

/// The `open` message's copy of the scene text and headers, per byte.
fn time_open(datasets: usize) -> f64 {
    let text = spec(Size::FULL, datasets, 4.0, 1.0).toml();
    let headers: Vec<FileStub> = (0..datasets)
        .map(|d| FileStub { key: format!("data/d{d}.nrrd"), bytes: 1 << 25, dims: [256; 3], voxel_type: 3 })
        .collect();
    let bytes = text.len() + 40 * datasets;
    let seconds = fastest(|| (text.clone(), headers.clone()));
    seconds / bytes as f64
}

/// The replicas' costs.
fn measure_replicas(i: &mut Inputs) {
    let rows: Vec<([f64; 2], f64)> = [(16, 1), (16, 16), (256, 1), (256, 16)]
        .iter()
        .map(|&(w, r)| ([w as f64, r as f64], time_pick(w, r)))
        .collect();
    let [per_worker, per_holder] = fit2(&rows);
    i.holders_per_worker = per_worker.max(0.0);
    i.pick_per_holder = per_holder.max(0.0);
    i.progress_per_worker = time_progress(256);
    i.open_per_byte = time_open(256);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_small_measurement_gives_every_cost_a_plausible_value() {
        let base = Inputs::recorded();
        let i = measure(Size { side: 24, dims: 12 }, &base).unwrap();
        let per_core_ns = [
            i.cast_per_sample,
            i.load_per_byte,
            i.parse_per_object,
            i.intersect_per_ray_object,
            i.plan_per_task,
            i.composite_per_piece,
            i.png_per_pixel,
            i.dispatch_per_task,
            i.record_per_task,
            i.holders_per_worker,
            i.progress_per_worker,
            i.open_per_byte,
        ]
        .map(|c| c * 1e9);
        assert!(per_core_ns.iter().all(|c| c.is_finite() && *c > 0.0 && *c < 1e7), "{per_core_ns:?}");
        // What is not measured is kept.
        assert_eq!((i.latency, i.per_event, i.link_bytes_per_s), (base.latency, base.per_event, base.link_bytes_per_s));
    }

    #[test]
    fn least_squares_recovers_two_costs() {
        let rows: Vec<([f64; 2], f64)> =
            [[1.0, 10.0], [2.0, 3.0], [5.0, 40.0]].iter().map(|&[a, b]| ([a, b], 3.0 * a + 0.5 * b)).collect();
        let [x, y] = fit2(&rows);
        assert!((x - 3.0).abs() < 1e-12 && (y - 0.5).abs() < 1e-12, "{x} {y}");
    }
}
