//! Algorithm 2 (paper §3.3): intersect every ray first, then cast dataset by dataset —
//! each loaded once, every piece of every object that uses it cast while it is resident,
//! then unloaded — and finally composite each ray's pieces front to back.
//!
//! # Early termination, recovered
//! The paper gives early termination up: a piece is cast before anyone knows whether the
//! ray is already opaque in front of it. Here the volume-rendering phase runs in
//! front-to-back *waves*, so that pieces behind rays already known to be opaque are never
//! cast (`samples_skipped` counts what that saved):
//!
//! * Datasets are visited once each, in an order that follows the rays front to back where
//!   the scene allows it ([`dataset_order`]): a greedy order of the graph "dataset A is met
//!   just before dataset B on n rays" (Eades–Lin–Smyth), exact when that graph has no cycle.
//! * While a dataset is resident, its tasks are cast in waves: wave k holds, for every ray,
//!   the tasks of the k-th piece of that ray that this dataset covers. Before each wave the
//!   scheduler composites, per ray, every result it already has in front of the piece.
//!   Results from other datasets may still be missing; leaving them out gives a *lower
//!   bound* on the opacity in front (opacity only grows), so: a task whose lower bound has
//!   reached the termination threshold is dropped — the ray would have stopped before it in
//!   Algorithm 1 too — and any other task is cast with that lower bound as its front
//!   opacity, so it can stop early inside the piece. When every piece in front is known
//!   (the usual case once datasets are ordered) the bound is exact and the cast matches
//!   Algorithm 1's, sample for sample.
//!
//! Waves only ever run over the dataset that is resident, and each dataset's turn comes
//! once, so early termination never adds a load: under a budget that holds the largest
//! dataset, every voxel is brought in at most once.
//!
//! Each wave is exactly what a farm ships: a batch of [`PieceTask`]s for one dataset, cast
//! by [`cast_batch`], answered with [`PieceRgba`]s in the same order.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use rayon::prelude::*;

use super::intersection::{intersect, Intersections};
use super::workunit::{cast_batch, PieceRgba, PieceTask};
use super::{Image, Progress, RenderStats, Rendered, VolumeStore};
use crate::composite::Rgba;
use crate::scene::Scene;
use crate::RenderError;

/// Tasks per parallel batch within a wave: large enough to amortise scheduling, small
/// enough to balance two threads over uneven pieces.
const BATCH_TASKS: usize = 256;

/// Where a task stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Status {
    /// Not reached yet.
    Pending,
    /// Cast; its result is in `results`.
    Done,
    /// Dropped: the ray was known to be opaque in front of it.
    Culled,
}

/// What the scheduler knows of the ray in front of a piece.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Front {
    /// A lower bound on the opacity in front (exact when every piece in front is known).
    Alpha(f64),
    /// The ray is known to be opaque (≥ termination) before this piece.
    Opaque,
}

/// The volume-rendering phase's bookkeeping: each task's status and result.
struct Waves<'i> {
    inter: &'i Intersections,
    termination: f64,
    status: Vec<Status>,
    results: Vec<PieceRgba>,
}

impl<'i> Waves<'i> {
    fn new(inter: &'i Intersections, termination: f64) -> Waves<'i> {
        let n = inter.tasks.len();
        Waves { inter, termination, status: vec![Status::Pending; n], results: vec![PieceRgba::default(); n] }
    }

    /// The ray's colour over one piece from what is known: every result when all are in
    /// (one object: its own; several: co-located, SPEC §4.4), else the co-located
    /// combination of those that are in (a lower bound on its opacity). `None` when a task
    /// of the piece was culled.
    fn piece_rgba(&self, p: usize) -> Option<Rgba> {
        let tasks = self.inter.tasks_of(p);
        if tasks.len() == 1 {
            return match self.status[tasks.start] {
                Status::Done => Some(self.results[tasks.start].into()),
                Status::Pending => Some(Rgba::CLEAR),
                Status::Culled => None,
            };
        }
        if tasks.clone().any(|t| self.status[t] == Status::Culled) {
            return None;
        }
        Some(Rgba::colocated(tasks.filter(|&t| self.status[t] == Status::Done).map(|t| self.results[t].into())))
    }

    /// What is known in front of task `t`'s piece: the pieces before it composited front
    /// to back as the composition phase (and Algorithm 1) will, missing results left out.
    fn front(&self, t: usize) -> Front {
        let mut acc = Rgba::CLEAR;
        for p in self.inter.pieces_of(self.inter.tasks[t].ray as usize) {
            if acc.alpha >= self.termination {
                return Front::Opaque;
            }
            if self.inter.piece_start[p + 1] > t {
                return Front::Alpha(acc.alpha);
            }
            match self.piece_rgba(p) {
                Some(c) => acc.over(c),
                None => return Front::Opaque,
            }
        }
        unreachable!("task {t} lies in one of its ray's pieces")
    }

    /// Decides every task of a wave: culls those behind opaque fronts (returning the count
    /// of their sample positions) and returns the others, with their fronts, as a batch.
    fn prepare(&mut self, scene: &Scene, wave: &[usize]) -> (Vec<usize>, Vec<PieceTask>, u64) {
        let (index, batch, culled) = self.decide(wave);
        let skipped = culled.par_iter().map(|&t| sample_positions(scene, &self.inter.tasks[t])).sum();
        (index, batch, skipped)
    }

    /// [`Waves::prepare`] without counting the culled tasks' samples: the wave's tasks to
    /// cast (indices and tasks with their fronts) and those culled.
    fn decide(&mut self, wave: &[usize]) -> (Vec<usize>, Vec<PieceTask>, Vec<usize>) {
        let fronts: Vec<Front> = wave.par_iter().map(|&t| self.front(t)).collect();
        let (mut index, mut batch, mut culled) = (Vec::new(), Vec::new(), Vec::new());
        for (&t, front) in wave.iter().zip(fronts) {
            match front {
                Front::Opaque => {
                    self.status[t] = Status::Culled;
                    culled.push(t);
                }
                Front::Alpha(a) => {
                    let mut task = self.inter.tasks[t];
                    task.set_front_alpha(a);
                    index.push(t);
                    batch.push(task);
                }
            }
        }
        (index, batch, culled)
    }

    /// Stores a cast wave's results.
    fn record(&mut self, index: &[usize], results: &[PieceRgba]) {
        for (&t, r) in index.iter().zip(results) {
            self.status[t] = Status::Done;
            self.results[t] = *r;
        }
    }

    /// Phase 3: one ray's pieces front to back (SPEC §4.4), stopping where it is opaque.
    fn composite(&self, r: usize) -> Rgba {
        let mut acc = Rgba::CLEAR;
        for p in self.inter.pieces_of(r) {
            if acc.alpha >= self.termination {
                break;
            }
            debug_assert!(self.inter.tasks_of(p).all(|t| self.status[t] != Status::Pending), "uncast task");
            match self.piece_rgba(p) {
                Some(c) => acc.over(c),
                // A culled piece lies behind a front already known to be opaque.
                None => break,
            }
        }
        acc
    }
}

/// The sample positions an object would take over a task's piece (SPEC §4.2), for
/// `samples_skipped`.
fn sample_positions(scene: &Scene, task: &PieceTask) -> u64 {
    let (w, h) = (scene.image().width, scene.image().height);
    let ray = scene.camera().ray(task.ray % w, task.ray / w, w, h);
    let object = &scene.objects()[task.object as usize];
    object.placement().walk(&ray, task.t0, task.t1, object.sampling_distance()).len()
}

/// The order in which datasets take their turn, and each dataset's waves.
#[derive(Debug, PartialEq)]
pub struct Plan {
    /// Datasets front to back (only those some task uses).
    pub datasets: Vec<usize>,
    /// Per dataset in `datasets` order, its waves: task indices, wave by wave.
    pub waves: Vec<Vec<Vec<usize>>>,
}

/// Orders datasets front to back as far as the scene allows, and splits each dataset's
/// tasks into waves by their rank along their ray.
pub fn plan(scene: &Scene, inter: &Intersections) -> Plan {
    let dataset_of = |t: usize| scene.objects()[inter.tasks[t].object as usize].dataset();
    let order = dataset_order(scene, inter);
    let mut position = vec![usize::MAX; scene.datasets().len()];
    for (i, &d) in order.iter().enumerate() {
        position[d] = i;
    }
    // rank[t]: how many earlier pieces of t's ray this dataset also covers.
    let rank: Vec<u32> = (0..inter.rays())
        .into_par_iter()
        .flat_map_iter(|r| {
            let mut seen: Vec<(usize, u32, usize)> = Vec::new(); // (dataset, pieces so far, last piece)
            let mut ranks = Vec::new();
            for p in inter.pieces_of(r) {
                for t in inter.tasks_of(p) {
                    let d = dataset_of(t);
                    let rank = match seen.iter_mut().find(|s| s.0 == d) {
                        Some(s) if s.2 == p => s.1 - 1,
                        Some(s) => {
                            s.1 += 1;
                            s.2 = p;
                            s.1 - 1
                        }
                        None => {
                            seen.push((d, 1, p));
                            0
                        }
                    };
                    ranks.push(rank);
                }
            }
            ranks
        })
        .collect();
    let mut waves: Vec<Vec<Vec<usize>>> = vec![Vec::new(); order.len()];
    for (t, &k) in rank.iter().enumerate() {
        let per_dataset = &mut waves[position[dataset_of(t)]];
        if per_dataset.len() <= k as usize {
            per_dataset.resize_with(k as usize + 1, Vec::new);
        }
        per_dataset[k as usize].push(t);
    }
    Plan { datasets: order, waves }
}

/// The datasets some task uses, front to back as far as the scene allows.
///
/// Each ray votes "A before B" for each pair of datasets it meets one right after the
/// other (first appearances along the ray), and [`greedy_order`] orders that graph: when it
/// has no cycle every ray meets datasets in their turn order. Ties go to the smaller mean
/// depth of the dataset's pieces.
pub fn dataset_order(scene: &Scene, inter: &Intersections) -> Vec<usize> {
    let n = scene.datasets().len();
    let dataset_of = |t: usize| scene.objects()[inter.tasks[t].object as usize].dataset();
    type Votes = (HashMap<(usize, usize), u64>, Vec<f64>, Vec<u64>);
    let (votes, depth_sum, count): Votes = (0..inter.rays())
        .into_par_iter()
        .fold(
            || (HashMap::new(), vec![0.0; n], vec![0; n]),
            |(mut votes, mut depth, mut count), r| {
                let mut seq: Vec<usize> = Vec::new();
                for p in inter.pieces_of(r) {
                    for t in inter.tasks_of(p) {
                        let d = dataset_of(t);
                        depth[d] += inter.tasks[t].t0;
                        count[d] += 1;
                        if !seq.contains(&d) {
                            seq.push(d);
                        }
                    }
                }
                for pair in seq.windows(2) {
                    *votes.entry((pair[0], pair[1])).or_insert(0) += 1;
                }
                (votes, depth, count)
            },
        )
        .reduce(
            || (HashMap::new(), vec![0.0; n], vec![0; n]),
            |(mut va, mut da, mut ca), (vb, db, cb)| {
                for (k, v) in vb {
                    *va.entry(k).or_insert(0) += v;
                }
                da.iter_mut().zip(db).for_each(|(a, b)| *a += b);
                ca.iter_mut().zip(cb).for_each(|(a, b)| *a += b);
                (va, da, ca)
            },
        );
    let used: Vec<usize> = (0..n).filter(|&d| count[d] > 0).collect();
    let mean_depth: Vec<f64> =
        (0..n).map(|d| if count[d] > 0 { depth_sum[d] / count[d] as f64 } else { 0.0 }).collect();
    greedy_order(&used, &votes, &mean_depth)
}

/// The Eades–Lin–Smyth greedy ordering of `nodes` under weighted edges `votes[(a, b)]`
/// ("a before b"): sinks go last, sources first, otherwise the node with the largest
/// out-minus-in weight goes next. Exact (a topological order) on an acyclic graph. Ties go
/// to the smaller `depth`, then the lower index.
pub fn greedy_order(nodes: &[usize], votes: &HashMap<(usize, usize), u64>, depth: &[f64]) -> Vec<usize> {
    let n = depth.len();
    let mut out_edges: Vec<Vec<(usize, u64)>> = vec![Vec::new(); n];
    let mut in_edges: Vec<Vec<(usize, u64)>> = vec![Vec::new(); n];
    for (&(a, b), &v) in votes {
        if a != b && v > 0 {
            out_edges[a].push((b, v));
            in_edges[b].push((a, v));
        }
    }
    let mut remaining = vec![false; n];
    nodes.iter().for_each(|&d| remaining[d] = true);
    let weight = |edges: &[(usize, u64)], remaining: &[bool]| -> u64 {
        edges.iter().filter(|(o, _)| remaining[*o]).map(|(_, v)| v).sum()
    };
    let nearer = |a: &usize, b: &usize| depth[*a].total_cmp(&depth[*b]).then(a.cmp(b));
    let (mut front, mut back) = (Vec::new(), Vec::new());
    for _ in 0..nodes.len() {
        let alive: Vec<usize> = nodes.iter().copied().filter(|&d| remaining[d]).collect();
        let sinks = alive.iter().filter(|&&d| weight(&out_edges[d], &remaining) == 0);
        // The farthest sink goes to the very back.
        let pick = if let Some(&sink) = sinks.max_by(|a, b| nearer(a, b)) {
            back.push(sink);
            sink
        } else {
            let sources = alive.iter().filter(|&&d| weight(&in_edges[d], &remaining) == 0);
            let best = match sources.min_by(|a, b| nearer(a, b)) {
                Some(&s) => s,
                None => {
                    let net =
                        |d: usize| weight(&out_edges[d], &remaining) as i128 - weight(&in_edges[d], &remaining) as i128;
                    *alive.iter().min_by(|a, b| net(**b).cmp(&net(**a)).then_with(|| nearer(a, b))).expect("non-empty")
                }
            };
            front.push(best);
            best
        };
        remaining[pick] = false;
    }
    front.extend(back.into_iter().rev());
    front
}

/// Renders with Algorithm 2.
pub(super) fn render(scene: &Scene, store: &VolumeStore, progress: Option<&Progress>) -> Result<Rendered, RenderError> {
    let (w, h) = (scene.image().width, scene.image().height);
    let mut stats = RenderStats::default();

    // Phase 1: intersection (object level only).
    let started = Instant::now();
    let inter = intersect(scene);
    stats.segments = inter.segments;
    stats.pieces = inter.pieces() as u64;
    stats.seconds.intersection = started.elapsed().as_secs_f64();

    // Phase 2: volume rendering, dataset by dataset, in front-to-back waves.
    let started = Instant::now();
    let plan = plan(scene, &inter);
    let mut waves = Waves::new(&inter, scene.render().termination);
    let mut loading = Duration::ZERO;
    let total_tasks = inter.tasks.len().max(1) as u64;
    let mut tasks_done = 0u64;
    for (&dataset, dataset_waves) in plan.datasets.iter().zip(&plan.waves) {
        let load_started = Instant::now();
        let volume = store.get(dataset)?;
        loading += load_started.elapsed();
        for wave in dataset_waves {
            let (index, batch, skipped) = waves.prepare(scene, wave);
            stats.samples_skipped += skipped;
            let mut results = vec![PieceRgba::default(); batch.len()];
            stats.samples += batch
                .par_chunks(BATCH_TASKS)
                .zip(results.par_chunks_mut(BATCH_TASKS))
                .map(|(tasks, out)| cast_batch(scene, &volume, tasks, out))
                .sum::<u64>();
            waves.record(&index, &results);
            tasks_done += wave.len() as u64;
            if let Some(p) = progress {
                p(h as u64 * tasks_done / total_tasks);
            }
        }
        drop(volume);
        store.unload(dataset);
    }
    stats.seconds.loading = loading.as_secs_f64();
    stats.seconds.volume_rendering = (started.elapsed() - loading).as_secs_f64();

    // Phase 3: composition, front to back per ray.
    let started = Instant::now();
    let background = scene.image().background;
    let pixels: Vec<[f64; 3]> =
        (0..inter.rays()).into_par_iter().map(|r| waves.composite(r).with_background(background)).collect();
    stats.seconds.composition = started.elapsed().as_secs_f64();
    if let Some(p) = progress {
        p(h as u64);
    }
    Ok(Rendered { image: Image::new(w, h, pixels), stats })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One ray of three pieces: [task 0], [tasks 1 and 2, shared], [task 3].
    fn one_ray() -> Intersections {
        let task = |object, t0, t1, shared| PieceTask::new(0, object, t0, t1, shared);
        Intersections {
            tasks: vec![
                task(0, 1.0, 2.0, false),
                task(1, 2.0, 3.0, true),
                task(2, 2.0, 3.0, true),
                task(3, 3.0, 4.0, false),
            ],
            piece_start: vec![0, 1, 3, 4],
            ray_start: vec![0, 3],
            segments: 4,
        }
    }

    fn done(waves: &mut Waves, t: usize, alpha: f32) {
        waves.record(&[t], &[PieceRgba { colour: [alpha; 3], alpha }]);
    }

    #[test]
    fn the_front_is_a_lower_bound_that_becomes_exact_once_every_piece_in_front_is_known() {
        let inter = one_ray();
        let mut w = Waves::new(&inter, 0.9);
        assert_eq!(w.front(0), Front::Alpha(0.0));
        assert_eq!(w.front(3), Front::Alpha(0.0), "nothing known in front");
        done(&mut w, 0, 0.5);
        assert_eq!(w.front(1), Front::Alpha(0.5));
        assert_eq!(w.front(2), Front::Alpha(0.5), "shared tasks have the same front");
        assert_eq!(w.front(3), Front::Alpha(0.5), "piece 1 unknown: left out");
        done(&mut w, 1, 0.5);
        assert_eq!(w.front(3), Front::Alpha(0.75), "half of piece 1 known: a lower bound");
        done(&mut w, 2, 0.5);
        // Piece 1 co-located: 1 − 0.5·0.5 = 0.75; over 0.5 in front: 0.875, exactly as the
        // composition phase will compute it.
        assert_eq!(w.front(3), Front::Alpha(0.875));
        done(&mut w, 3, 0.5);
        let composited = w.composite(0);
        assert_eq!(composited.alpha, 0.875 + 0.125 * 0.5);
        let mut per_ray = Rgba::CLEAR;
        per_ray.over(Rgba { colour: [0.5; 3], alpha: 0.5 });
        per_ray.over(Rgba::colocated([Rgba { colour: [0.5; 3], alpha: 0.5 }; 2]));
        per_ray.over(Rgba { colour: [0.5; 3], alpha: 0.5 });
        assert_eq!(composited, per_ray);
    }

    #[test]
    fn tasks_behind_an_opaque_front_are_culled_and_composition_stops_there() {
        let inter = one_ray();
        let mut w = Waves::new(&inter, 0.8);
        done(&mut w, 1, 0.7);
        done(&mut w, 2, 0.7);
        // Piece 1 alone makes 1 − 0.3² = 0.91 ≥ 0.8, whatever piece 0 holds.
        assert_eq!(w.front(3), Front::Opaque);
        let (index, batch, _) = w.decide(&[0, 3]);
        assert_eq!(index, vec![0]);
        assert_eq!(batch[0].front_alpha(), 0.0);
        assert_eq!(w.status[3], Status::Culled);
        done(&mut w, 0, 0.0);
        let piece_1 = 1.0 - (1.0 - 0.7_f32 as f64).powi(2);
        assert_eq!(w.composite(0).alpha, piece_1, "piece 2 never composited");
        // A culled task in front makes everything behind it opaque too.
        let mut w = Waves::new(&inter, 0.8);
        w.status[0] = Status::Culled;
        assert_eq!(w.front(1), Front::Opaque);
        assert_eq!(w.front(3), Front::Opaque);
    }

    #[test]
    fn the_front_alpha_travels_rounded_down_and_shared_pieces_go_whole() {
        let inter = one_ray();
        let mut w = Waves::new(&inter, 0.999);
        done(&mut w, 0, 0.3);
        let (index, batch, _) = w.decide(&[1, 2, 3]);
        assert_eq!(index, vec![1, 2, 3]);
        assert!(batch[0].is_whole() && batch[1].is_whole());
        let a = batch[2].front_alpha();
        assert!(a <= 0.3_f32 as f64 && 0.3_f32 as f64 - a < 2e-5, "{a}");
    }

    #[test]
    fn greedy_order_is_topological_on_an_acyclic_graph() {
        // A → B on one ray, B → C on a hundred: a net-score order would put B first.
        let votes = HashMap::from([((0, 1), 1), ((1, 2), 100)]);
        assert_eq!(greedy_order(&[0, 1, 2], &votes, &[5.0, 1.0, 3.0]), vec![0, 1, 2]);
        // Unconnected datasets: nearest first.
        assert_eq!(greedy_order(&[0, 1, 2], &HashMap::new(), &[5.0, 1.0, 3.0]), vec![1, 2, 0]);
        // Nodes not listed are left out.
        assert_eq!(greedy_order(&[2, 0], &votes, &[0.0; 3]), vec![0, 2]);
    }

    #[test]
    fn greedy_order_breaks_a_cycle_at_its_lightest_edge() {
        // 0 → 1 (10), 1 → 2 (10), 2 → 0 (1): dropping 2 → 0 gives 0, 1, 2.
        let votes = HashMap::from([((0, 1), 10), ((1, 2), 10), ((2, 0), 1)]);
        assert_eq!(greedy_order(&[0, 1, 2], &votes, &[0.0; 3]), vec![0, 1, 2]);
        let order = greedy_order(&[2, 1, 0], &votes, &[3.0, 2.0, 1.0]);
        assert_eq!(order.len(), 3);
        assert_eq!(order, vec![0, 1, 2]);
    }

    fn scene(objects: &[(&str, f64)]) -> Scene {
        let mut text = String::from(
            "[image]\nwidth = 4\nheight = 4\nbackground = [0, 0, 0]\n\
             [camera]\neye = [0.5, 0.5, 5.0]\ntarget = [0.5, 0.5, 0.0]\nup = [0, 1, 0]\nfov_y = 5.0\n",
        );
        for d in ["near", "far"] {
            text += &format!(
                "[[datasets]]\nname = \"{d}\"\ndims = [2, 2, 2]\n[datasets.channels.voxel]\n\
                 generator = {{ kind = \"constant\", value = 1.0 }}\n"
            );
        }
        for (i, (d, z)) in objects.iter().enumerate() {
            text += &format!(
                "[[objects]]\nname = \"o{i}\"\ndataset = \"{d}\"\n\
                 colour = {{ type = \"constant\", red = [1], green = [1], blue = [1] }}\n\
                 opacity = {{ type = \"constant\", coefficients = [0.5] }}\n\
                 transform = {{ matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0.5, {z}], [0, 0, 0, 1]] }}\n"
            );
        }
        Scene::parse(&text, "plan.toml").unwrap()
    }

    #[test]
    fn datasets_go_front_to_back_and_waves_follow_each_ray() {
        // Along every ray: far-dataset object at z ∈ [1, 1.5], near at [0, 0.5] behind it,
        // and near again at [-1, -0.5]: the dataset declared first is met second.
        let s = scene(&[("near", 0.0), ("far", 1.0), ("near", -1.0)]);
        let inter = intersect(&s);
        assert_eq!(inter.rays(), 16);
        let p = plan(&s, &inter);
        assert_eq!(p.datasets, vec![1, 0], "the dataset met first goes first");
        // Dataset 1 has one piece per ray: one wave. Dataset 0 has two: two waves, the
        // nearer piece of every ray in the first.
        assert_eq!(p.waves[0].len(), 1);
        assert_eq!(p.waves[1].len(), 2);
        for (k, wave) in p.waves[1].iter().enumerate() {
            assert_eq!(wave.len(), 16);
            for &t in wave {
                let task = inter.tasks[t];
                assert_eq!(task.object, [0, 2][k], "wave {k}");
                assert_eq!(inter.piece_of(t), inter.ray_start[task.ray as usize] + k + 1);
            }
        }
    }
}
