//! Measures the workers' inputs on this processor with the code a worker runs
//! (`worker/src/cast.rs`): each dataset pinned in a `VolumeStore`, bound with
//! `BatchCaster::new` through the store (the first bind classifies the cells and keeps them;
//! later binds reuse them), and each batch cast in chunks of 256 tasks by
//! `BatchCaster::cast`, the sampler's packet loop. The datasets are u16 raw files of CT-like
//! heads, as the farm's Table-1 scene holds, placed as the simulated scenes place their
//! cubes. Each timing is the fastest of a few runs on one thread (the machine is shared, and
//! a slower run only measures the neighbours).
//!
//! The coordinator's costs are not measured here: they come from the real coordinator,
//! `trove-bench coordinator --record` (`super::recorded`).

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use trove_core::render::intersection::intersect;
use trove_core::render::{BatchCaster, PieceRgba, Scheduler, VolumeStore};
use trove_core::scene::Scene;

use super::recorded::{self, WorkerRecord};
use super::scene::SceneSpec;

/// Runs of each timing; the fastest counts.
const RUNS: usize = 3;
/// Tasks per batch, as the driver's default.
const BATCH_TASKS: usize = 4096;
/// Tasks per rayon work item of a worker's batch (`CHUNK_TASKS` in `worker/src/cast.rs`).
const CHUNK_TASKS: usize = 256;

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

/// Least squares for `y ≈ Σ cᵢ·xᵢ` with two unknowns, neither negative: a cost is never
/// below zero, but timings of small work on a busy machine can make the unconstrained fit
/// say so. Where it does, the constrained optimum lies on the boundary: of the two fits
/// with one cost 0 and the other fitted alone (itself at least 0), the one with the smaller
/// residual.
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
    let free = [(p * c - b * q) / det, (a * q - b * p) / det];
    if free.iter().all(|&v| v.is_finite() && v >= 0.0) {
        return free;
    }
    // The better of the two boundary fits (each unknown alone, the other 0).
    let alone = |p: f64, a: f64| if a > 0.0 { (p / a).max(0.0) } else { 0.0 };
    let residual =
        |fit: [f64; 2]| -> f64 { rows.iter().map(|([x0, x1], y)| (y - fit[0] * x0 - fit[1] * x1).powi(2)).sum() };
    let (first, second) = ([alone(p, a), 0.0], [0.0, alone(q, c)]);
    if residual(first) <= residual(second) {
        first
    } else {
        second
    }
}

/// How big the measurement is: [`Size::FULL`], or small for tests.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Size {
    /// Image side of the timed scenes.
    pub side: u32,
    /// Voxels per axis of the datasets cast (128³ u16 is 4 MiB: larger than a core's
    /// caches, as the farm's datasets are).
    pub dims: u32,
}

impl Size {
    pub(crate) const FULL: Size = Size { side: 128, dims: 128 };
}

/// Measures the worker's costs on this processor.
pub(crate) fn measure(size: Size) -> Result<WorkerRecord> {
    let dir = std::env::temp_dir().join(format!("trove-farm-sim-{}", std::process::id()));
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let result = measure_in(size, &dir);
    let _ = std::fs::remove_dir_all(&dir);
    result
}

fn measure_in(size: Size, dir: &Path) -> Result<WorkerRecord> {
    let datasets = 8;
    for d in 0..datasets {
        crate::table1::write_dataset(&dir.join(format!("d{d}.raw")), d as u32, size.dims, crate::table1::Storage::Raw)?;
    }
    // The same pieces cast at a sample every 2 voxels, every voxel and 2 per voxel: what
    // changes with the step is the samples; what does not is the tasks.
    let mut rows = Vec::new();
    let mut binds = (f64::INFINITY, f64::INFINITY, f64::INFINITY);
    for step in [2.0, 1.0, 0.5] {
        let spec = SceneSpec {
            datasets,
            depth: 3.0,
            dims: size.dims,
            width: size.side,
            height: size.side,
            step_voxels: step,
            seed: 1,
        };
        let path = dir.join("scene.toml");
        let scene = Scene::parse(&spec.toml_raw(), &path).context("the worker-timing scene")?;
        let timed = time_casting(&scene)?;
        rows.push(([timed.tasks as f64, timed.samples as f64], timed.seconds));
        binds = (binds.0.min(timed.load), binds.1.min(timed.bind), binds.2.min(timed.rebind));
    }
    let [per_task, per_sample] = fit2(&rows);
    let text =
        SceneSpec { datasets: 256, depth: 4.0, dims: 256, width: 1024, height: 1024, step_voxels: 1.0, seed: 1 }.toml();
    let parse = fastest(|| Scene::parse(&text, "parse.toml").map(|s| s.objects().len())) / 256.0;
    Ok(WorkerRecord {
        processor: recorded::processor(),
        simd: recorded::simd_path().to_string(),
        commit: recorded::commit(),
        cast_per_sample: per_sample,
        cast_per_task: per_task,
        load_per_byte: binds.0,
        bind_per_voxel: binds.1,
        rebind_per_voxel: binds.2,
        parse_per_object: parse,
    })
}

/// What casting one scene took.
struct Timed {
    tasks: u64,
    samples: u64,
    /// Seconds casting.
    seconds: f64,
    /// Per byte loaded, per voxel bound the first time, per voxel bound again.
    load: f64,
    bind: f64,
    rebind: f64,
}

/// Casts every task of `scene` as a worker does (one thread): per dataset, pinned in a
/// store, bound through it, batches of [`BATCH_TASKS`] in chunks of [`CHUNK_TASKS`].
fn time_casting(scene: &Scene) -> Result<Timed> {
    let infos = scene.datasets();
    let bytes: u64 = infos.iter().map(|d| d.resident_bytes()).sum();
    let voxels: u64 = infos.iter().map(|d| d.dims().voxel_count()).sum();
    let (mut load, mut bind, mut rebind) = (f64::INFINITY, f64::INFINITY, f64::INFINITY);
    let mut kept = None;
    for _ in 0..RUNS {
        let store = VolumeStore::new(None);
        let started = Instant::now();
        let pinned = infos.iter().map(|d| store.get(d)).collect::<Result<Vec<_>, _>>()?;
        let loaded = Instant::now();
        let first = (0..infos.len()).map(|d| BatchCaster::new(scene, d, &pinned[d])).collect::<Result<Vec<_>, _>>()?;
        let bound = Instant::now();
        drop(first);
        let again = Instant::now();
        let casters =
            (0..infos.len()).map(|d| BatchCaster::new(scene, d, &pinned[d])).collect::<Result<Vec<_>, _>>()?;
        let rebound = Instant::now();
        load = load.min((loaded - started).as_secs_f64() / bytes as f64);
        bind = bind.min((bound - loaded).as_secs_f64() / voxels as f64);
        rebind = rebind.min((rebound - again).as_secs_f64() / voxels as f64);
        drop(casters);
        kept = Some((store, pinned));
    }
    let (_store, pinned) = kept.expect("at least one run");
    let casters = (0..infos.len()).map(|d| BatchCaster::new(scene, d, &pinned[d])).collect::<Result<Vec<_>, _>>()?;
    let mut best = (0, 0, f64::INFINITY);
    for _ in 0..RUNS {
        let mut scheduler = Scheduler::new(scene, intersect(scene, 0..scene.image().height), BATCH_TASKS)?;
        let (mut tasks, mut samples, mut seconds) = (0, 0, 0.0);
        for d in scheduler.datasets().to_vec() {
            while let Some(batch) = scheduler.next_batch(d) {
                let mut out = vec![PieceRgba::default(); batch.tasks.len()];
                let started = Instant::now();
                for (t, o) in batch.tasks.chunks(CHUNK_TASKS).zip(out.chunks_mut(CHUNK_TASKS)) {
                    samples += casters[d].cast(t, o)?;
                }
                seconds += started.elapsed().as_secs_f64();
                tasks += batch.tasks.len() as u64;
                scheduler.record(batch.id, &out)?;
            }
        }
        if seconds < best.2 {
            best = (tasks, samples, seconds);
        }
    }
    Ok(Timed { tasks: best.0, samples: best.1, seconds: best.2, load, bind, rebind })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_small_measurement_gives_every_cost_a_plausible_value() {
        // Small, but large enough that the samples' time stands above a busy machine's noise:
        // at 24² pixels and 12³ voxels, one run in thirty beside three busy loops (as in a
        // parallel test run) fitted a negative cost a sample.
        let w = measure(Size { side: 64, dims: 16 }).unwrap();
        let per_core_ns = [w.cast_per_sample, w.load_per_byte, w.parse_per_object, w.bind_per_voxel].map(|c| c * 1e9);
        assert!(per_core_ns.iter().all(|c| c.is_finite() && *c > 0.0 && *c < 1e7), "{per_core_ns:?}");
        assert!(w.rebind_per_voxel.is_finite() && w.rebind_per_voxel >= 0.0);
        assert!(w.cast_per_task.is_finite() && w.cast_per_task >= 0.0);
    }

    #[test]
    fn least_squares_recovers_two_costs() {
        let rows: Vec<([f64; 2], f64)> =
            [[1.0, 10.0], [2.0, 3.0], [5.0, 40.0]].iter().map(|&[a, b]| ([a, b], 3.0 * a + 0.5 * b)).collect();
        let [x, y] = fit2(&rows);
        assert!((x - 3.0).abs() < 1e-12 && (y - 0.5).abs() < 1e-12, "{x} {y}");
    }

    #[test]
    fn least_squares_never_gives_a_negative_cost() {
        // y = 2·x0 − 0.1·x1 exactly: the free fit's second cost is negative; the constrained
        // one is x1's cost 0 and x0's fitted alone, as one would fit by hand.
        let rows: Vec<([f64; 2], f64)> =
            [[1.0, 1.0], [1.0, 2.0], [1.0, 4.0]].iter().map(|&[a, b]| ([a, b], 2.0 * a - 0.1 * b)).collect();
        let [x, y] = fit2(&rows);
        let alone =
            rows.iter().map(|(x, y)| x[0] * y).sum::<f64>() / rows.iter().map(|(x, _)| x[0] * x[0]).sum::<f64>();
        assert_eq!(y, 0.0);
        assert!((x - alone).abs() < 1e-12, "{x} against {alone}");
        // Counts that move together (no unique fit) with times that fall as they grow: still
        // no negative cost.
        let falling = [([1.0, 1.0], 3.0), ([2.0, 2.0], 2.0), ([3.0, 3.0], 1.0)];
        assert!(fit2(&falling).iter().all(|&c| c >= 0.0), "{:?}", fit2(&falling));
    }
}
