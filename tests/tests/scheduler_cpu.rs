//! The coordinator's per-piece work without the coordinator: counting and intersecting a
//! Table-1-like scene (a floor and 14 heads of 15 datasets) at 1024² in the farm's bands of
//! 64 rows, planning each band (`Scheduler::new`), handing out and recording every batch
//! (`next_batch`, `record`) with made-up results, and compositing the band
//! (`Raster::composite_rows`) — each stage timed on one thread by its CPU time, in
//! nanoseconds per piece. Ignored by default (it is a measurement, not a check); run it in release:
//!
//! ```sh
//! cargo test --release -p trove-tests --test scheduler_cpu -- --ignored --nocapture
//! ```
//!
//! It also prints checksums of every batch handed out (tasks and fronts, in order) and of
//! the image, so that two builds can be shown to hand out the same batches and make the same
//! bytes, not only to take different times. `TROVE_REPEAT` sets the repeats (default 5).

use trove_core::render::limits::Work;
use trove_core::render::{PieceRgba, Raster, Scheduler};
use trove_core::scene::Scene;

/// The Table-1 geometry of `trove-bench`'s scene (`bench/src/table1.rs`), with generated
/// datasets: scheduling reads no voxel, only boxes and the camera.
fn table1(size: u32) -> Scene {
    let mut text = format!(
        "[image]\nwidth = {size}\nheight = {size}\nbackground = [0.05, 0.05, 0.08]\n\
         [camera]\neye = [0.0, 1.6, 6.5]\ntarget = [0.0, -0.3, -0.6]\nup = [0, 1, 0]\nfov_y = 42.0\n"
    );
    for v in 0..15 {
        text += &format!(
            "[[datasets]]\nname = \"head{v:02}\"\ndims = [81, 81, 81]\n[datasets.channels.voxel]\n\
             generator = {{ kind = \"constant\", value = 1.0 }}\n"
        );
    }
    let object = |name: &str, dataset: u32, matrix: [[f64; 4]; 3]| {
        format!(
            "[[objects]]\nname = \"{name}\"\ndataset = \"head{dataset:02}\"\n\
             colour = {{ type = \"constant\", red = [1], green = [1], blue = [1] }}\n\
             opacity = {{ type = \"constant\", coefficients = [0.5] }}\n\
             transform = {{ matrix = [{:?}, {:?}, {:?}, [0, 0, 0, 1]] }}\n",
            matrix[0], matrix[1], matrix[2]
        )
    };
    text += &object("floor", 14, [[7.5, 0.0, 0.0, -3.75], [0.0, 0.08, 0.0, -1.28], [0.0, 0.0, 6.5, -4.5]]);
    let rows: [(f64, f64, &[f64]); 3] = [
        (1.0, -1.2, &[-2.4, -1.2, 0.0, 1.2, 2.4]),
        (-0.4, -0.75, &[-1.8, -0.6, 0.6, 1.8]),
        (-1.9, -0.3, &[-2.4, -1.2, 0.0, 1.2, 2.4]),
    ];
    let mut i = 0u32;
    for (z, y, xs) in rows {
        for &x in xs {
            let (s, angle) = (1.15f64, 15.0 * (i as f64 - 7.0));
            let (sin, cos) = angle.to_radians().sin_cos();
            let m = [
                [s * cos, 0.0, s * sin, x - s / 2.0 * (cos + sin)],
                [0.0, s, 0.0, y],
                [-s * sin, 0.0, s * cos, z - s / 2.0 * (cos - sin)],
            ];
            text += &object(&format!("head{i}"), i, m);
            i += 1;
        }
    }
    Scene::parse(&text, "table1.toml").unwrap()
}

/// This thread's CPU time so far (`/proc/thread-self/schedstat`), so that time the machine's
/// other work takes the processor from it is not counted.
struct Instant(u64);

impl Instant {
    fn now() -> Instant {
        let text = std::fs::read_to_string("/proc/thread-self/schedstat").expect("schedstat (Linux)");
        Instant(text.split_whitespace().next().and_then(|v| v.parse().ok()).expect("a run time in ns"))
    }

    fn elapsed(&self) -> std::time::Duration {
        std::time::Duration::from_nanos(Instant::now().0 - self.0)
    }
}

/// FNV-1a, for the checksums.
struct Fnv(u64);

impl Fnv {
    fn eat(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 ^ b as u64).wrapping_mul(0x100000001b3);
        }
    }
}

/// A made-up cast of a task: an opacity from its ray, object and front (so that a different
/// front changes the image), and a premultiplied grey.
fn result_of(ray: u32, object: u16, front: u16) -> PieceRgba {
    let mut h = (ray as u64) << 32 | (object as u64) << 16 | front as u64;
    h = (h ^ (h >> 31)).wrapping_mul(0x9e3779b97f4a7c15);
    h ^= h >> 29;
    let alpha = (h % 1000) as f32 / 1000.0 * 0.95;
    PieceRgba { colour: [alpha * 0.5, alpha * 0.25, alpha], alpha }
}

#[derive(Default, Clone, Copy)]
struct Times {
    count: f64,
    plan: f64,
    batches: f64,
    record: f64,
    composite: f64,
}

fn once(scene: &Scene, batches_sum: &mut Fnv, image_sum: &mut Fnv) -> (Times, u64) {
    const BAND_ROWS: u32 = 64;
    let (w, h) = (scene.image().width, scene.image().height);
    let mut t = Times::default();
    let start = Instant::now();
    let (work, kept) = Work::count_keeping(scene, BAND_ROWS, u64::MAX).unwrap();
    t.count = start.elapsed().as_secs_f64();
    let mut raster = Raster::new(w, h, false);
    let mut results = Vec::new();
    for (b, inter) in kept.into_iter().enumerate() {
        let start = Instant::now();
        let mut s = Scheduler::new(scene, inter, 4096).unwrap();
        t.plan += start.elapsed().as_secs_f64();
        while !s.is_complete() {
            let order = s.datasets().to_vec();
            let mut out = Vec::new();
            let start = Instant::now();
            for &d in &order {
                while let Some(batch) = s.next_batch(d) {
                    out.push(batch);
                }
            }
            t.batches += start.elapsed().as_secs_f64();
            for batch in &out {
                results.clear();
                for task in &batch.tasks {
                    batches_sum.eat(&task.ray.to_le_bytes());
                    batches_sum.eat(&task.object.to_le_bytes());
                    batches_sum.eat(&task.front.to_le_bytes());
                    batches_sum.eat(&task.t0.to_bits().to_le_bytes());
                    results.push(result_of(task.ray, task.object, task.front));
                }
                let start = Instant::now();
                s.record(batch.id, &results).unwrap();
                t.record += start.elapsed().as_secs_f64();
            }
        }
        let start = Instant::now();
        raster.composite_rows(b as u32 * BAND_ROWS, &s, scene.image().background);
        t.composite += start.elapsed().as_secs_f64();
    }
    image_sum.eat(raster.rgb8());
    (t, work.pieces)
}

#[test]
#[ignore = "a measurement: run in release with --ignored --nocapture"]
fn coordinator_cpu_per_piece() {
    let scene = table1(1024);
    let repeat: usize = std::env::var("TROVE_REPEAT").ok().and_then(|v| v.parse().ok()).unwrap_or(5);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let mut runs = Vec::new();
    let mut pieces = 0;
    let (mut batches_sum, mut image_sum) = (Fnv(0xcbf29ce484222325), Fnv(0xcbf29ce484222325));
    for _ in 0..repeat {
        let (mut b, mut i) = (Fnv(0xcbf29ce484222325), Fnv(0xcbf29ce484222325));
        let (t, p) = pool.install(|| once(&scene, &mut b, &mut i));
        (batches_sum, image_sum, pieces) = (b, i, p);
        runs.push(t);
    }
    let ns = |f: fn(&Times) -> f64| {
        let mut v: Vec<f64> = runs.iter().map(|t| f(t) * 1e9 / pieces as f64).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let (c, p, b, r, x) = (ns(|t| t.count), ns(|t| t.plan), ns(|t| t.batches), ns(|t| t.record), ns(|t| t.composite));
    println!(
        "pieces {pieces}; ns/piece (median of {repeat}, one thread): count+intersect {c:.1}, plan {p:.1}, \
         next_batch {b:.1}, record {r:.1}, composite {x:.1}, sum {:.1}; batches {:016x}, image {:016x}",
        c + p + b + r + x,
        batches_sum.0,
        image_sum.0
    );
}
