use super::*;
use crate::render::intersection::intersect;

/// A 4×4 scene: datasets "near" and "far" (index 0 and 1), one object per entry of
/// `objects` (dataset name, z of its slab), each a constant half-opaque white.
fn scene(objects: &[(&str, f64)]) -> Scene {
    scene_with(objects, 0.999)
}

fn scene_with(objects: &[(&str, f64)], termination: f64) -> Scene {
    Scene::parse(&scene_text(objects, termination), "plan.toml").unwrap()
}

fn scene_text(objects: &[(&str, f64)], termination: f64) -> String {
    let mut text = format!(
        "[image]\nwidth = 4\nheight = 4\nbackground = [0, 0, 0]\n\
         [camera]\neye = [0.5, 0.5, 5.0]\ntarget = [0.5, 0.5, 0.0]\nup = [0, 1, 0]\nfov_y = 5.0\n\
         [render]\ntermination = {termination}\n",
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
    text
}

/// One ray of three pieces: [task 0, object 0], [tasks 1 and 2, objects 1 and 2, shared],
/// [task 3, object 3]. Objects 0, 1, 3 use dataset "near" (0); object 2 uses "far" (1).
fn one_ray(termination: f64) -> (Scene, Intersections) {
    let scene = scene_with(&[("near", 0.0), ("near", 0.0), ("far", 0.0), ("near", 0.0)], termination);
    let task = |object, t0, t1, shared| PieceTask::new(0, object, t0, t1, shared);
    let inter = Intersections {
        first_ray: 0,
        tasks: vec![
            task(0, 1.0, 2.0, false),
            task(1, 2.0, 3.0, true),
            task(2, 2.0, 3.0, true),
            task(3, 3.0, 4.0, false),
        ],
        piece_start: vec![0, 1, 3, 4],
        ray_start: vec![0, 3],
        segments: 4,
    };
    (scene, inter)
}

fn rgba(alpha: f32) -> PieceRgba {
    PieceRgba { colour: [alpha; 3], alpha }
}

/// Hands out every ready batch of `d` and returns them.
fn drain(s: &mut Scheduler, d: usize) -> Vec<Batch> {
    std::iter::from_fn(|| s.next_batch(d)).collect()
}

#[test]
fn a_wave_waits_for_the_previous_wave_of_its_dataset_but_not_for_other_datasets() {
    let (scene, inter) = one_ray(0.999);
    let mut s = Scheduler::new(&scene, inter, 16).unwrap();
    // "near" has three waves (pieces 0, 1, 2 of the ray), "far" one.
    let near = drain(&mut s, 0);
    assert_eq!(near.len(), 1);
    assert_eq!(near[0].tasks.len(), 1, "wave 0 of near: task 0 only");
    assert!(s.next_batch(0).is_none(), "wave 1 waits for wave 0");
    let far = drain(&mut s, 1);
    assert_eq!((far.len(), far[0].tasks[0].object), (1, 2), "far is independent of near");
    s.record(near[0].id, &[rgba(0.5)]).unwrap();
    let wave1 = drain(&mut s, 0);
    assert_eq!(wave1[0].tasks[0].object, 1);
    assert!(wave1[0].tasks[0].is_whole(), "a shared piece is cast whole");
    s.record(wave1[0].id, &[rgba(0.5)]).unwrap();
    s.record(far[0].id, &[rgba(0.5)]).unwrap();
    let wave2 = drain(&mut s, 0);
    s.record(wave2[0].id, &[rgba(0.5)]).unwrap();
    assert!(s.is_complete() && s.is_dataset_done(0) && s.is_dataset_done(1));
    // Composition: 0.5, then the co-located pair 1 − 0.5² = 0.75, then 0.5.
    let mut expected = Rgba::CLEAR;
    expected.over(Rgba { colour: [0.5; 3], alpha: 0.5 });
    expected.over(Rgba::colocated([Rgba { colour: [0.5; 3], alpha: 0.5 }; 2]));
    expected.over(Rgba { colour: [0.5; 3], alpha: 0.5 });
    assert_eq!(s.composite_ray(0), expected);
}

#[test]
fn in_piece_fronts_count_only_the_same_datasets_pieces_so_timing_cannot_change_them() {
    // Two orders of arrival: "far" answered before or after near's last wave is handed out.
    let fronts = |far_first: bool| {
        let (scene, inter) = one_ray(0.999);
        let mut s = Scheduler::new(&scene, inter, 16).unwrap();
        let far = drain(&mut s, 1);
        if far_first {
            s.record(far[0].id, &[rgba(0.9)]).unwrap();
        }
        let w0 = drain(&mut s, 0);
        s.record(w0[0].id, &[rgba(0.5)]).unwrap();
        let w1 = drain(&mut s, 0);
        s.record(w1[0].id, &[rgba(0.5)]).unwrap();
        let w2 = drain(&mut s, 0);
        w2[0].tasks[0].front_alpha()
    };
    let (a, b) = (fronts(true), fronts(false));
    assert_eq!(a, b, "the front of task 3 must not depend on when far's result came in");
    // Only piece 0 (wholly near) counts: piece 1 is shared with far.
    assert!((a - 0.5).abs() < 2e-5, "{a}");
}

#[test]
fn tasks_behind_a_known_opaque_front_are_culled_whichever_dataset_made_it_opaque() {
    let (scene, inter) = one_ray(0.8);
    let mut s = Scheduler::new(&scene, inter, 16).unwrap();
    let w0 = drain(&mut s, 0);
    let far = drain(&mut s, 1);
    s.record(w0[0].id, &[rgba(0.0)]).unwrap();
    let w1 = drain(&mut s, 0);
    s.record(w1[0].id, &[rgba(0.7)]).unwrap();
    s.record(far[0].id, &[rgba(0.7)]).unwrap();
    // Piece 1 alone makes 1 − 0.3² = 0.91 ≥ 0.8: task 3 is culled, no batch is handed out.
    assert!(s.next_batch(0).is_none());
    assert!(s.is_complete());
    assert_eq!(s.progress(), Progress { total: 4, cast: 3, culled: 1 });
    assert_eq!(s.culled().count(), 1);
    let piece_1 = 1.0 - (1.0 - 0.7_f32 as f64).powi(2);
    assert_eq!(s.composite_ray(0).alpha, piece_1, "piece 2 never composited");
}

#[test]
fn a_bound_that_only_just_reaches_termination_does_not_cull() {
    // Culling needs termination + CULL_MARGIN, so rounding in the bound cannot cull a task
    // that composition would reach.
    let (scene, inter) = one_ray(0.5);
    let mut s = Scheduler::new(&scene, inter, 16).unwrap();
    let w0 = drain(&mut s, 0);
    s.record(w0[0].id, &[rgba(0.5)]).unwrap();
    let w1 = drain(&mut s, 0);
    assert_eq!(w1.len(), 1, "0.5 = termination is not above it by the margin");
}

#[test]
fn abandoned_batches_are_handed_out_again_under_a_new_id_and_late_answers_are_refused() {
    let (scene, inter) = one_ray(0.999);
    let mut s = Scheduler::new(&scene, inter, 16).unwrap();
    let first = drain(&mut s, 0);
    s.abandon(first[0].id).unwrap();
    let again = drain(&mut s, 0);
    assert_eq!(again.len(), 1);
    assert_ne!(again[0].id, first[0].id);
    assert_eq!(again[0].tasks, first[0].tasks);
    assert_eq!((first[0].attempt, again[0].attempt), (0, 1), "each re-dispatch counts");
    s.abandon(again[0].id).unwrap();
    let third = drain(&mut s, 0);
    assert_eq!(third[0].attempt, 2);
    s.abandon(third[0].id).unwrap();
    let again = drain(&mut s, 0);
    assert_eq!(s.record(first[0].id, &[rgba(0.5)]), Err(ScheduleError::UnknownBatch { id: first[0].id }));
    s.record(again[0].id, &[rgba(0.5)]).unwrap();
    assert_eq!(s.record(again[0].id, &[rgba(0.5)]), Err(ScheduleError::UnknownBatch { id: again[0].id }));
}

#[test]
fn results_of_the_wrong_count_or_impossible_values_are_refused() {
    let (scene, inter) = one_ray(0.999);
    let mut s = Scheduler::new(&scene, inter, 16).unwrap();
    let b = drain(&mut s, 0).remove(0);
    assert_eq!(s.record(b.id, &[]), Err(ScheduleError::ResultCount { id: b.id, expected: 1, got: 0 }));
    for bad in [
        PieceRgba { colour: [0.0; 3], alpha: f32::NAN },
        PieceRgba { colour: [0.0; 3], alpha: 1.5 },
        PieceRgba { colour: [0.9, 0.0, 0.0], alpha: 0.1 },
        PieceRgba { colour: [-0.1, 0.0, 0.0], alpha: 0.1 },
    ] {
        assert_eq!(s.record(b.id, &[bad]), Err(ScheduleError::BadResult { id: b.id, index: 0 }));
    }
    s.record(b.id, &[rgba(0.25)]).unwrap();
}

#[test]
fn a_lit_object_s_colour_may_exceed_its_opacity_by_its_gain_and_no_more() {
    // Object 0 lit by one light of intensity 2: c' ≤ 0.2 + (0.7 + 0.2)·2 = 2 per channel.
    let objects = [("near", 0.0), ("near", 0.0), ("far", 0.0), ("near", 0.0)];
    let text = scene_text(&objects, 0.999)
        .replacen(
            "[[datasets]]",
            "[[lights]]\ntype = \"directional\"\ndirection = [0, 0, -1]\nintensity = 2\n[[datasets]]",
            1,
        )
        .replacen("name = \"o0\"\n", "name = \"o0\"\nshading = { ambient = 0.2 }\n", 1);
    let lit = Scene::parse(&text, "lit.toml").unwrap();
    assert!((lit.objects()[0].colour_gain() - 2.0).abs() < 1e-12);
    assert_eq!(lit.objects()[1].colour_gain(), 1.0);
    let (_, inter) = one_ray(0.999);
    let mut s = Scheduler::new(&lit, inter, 16).unwrap();
    let b = drain(&mut s, 0).remove(0);
    assert_eq!(b.tasks[0].object, 0);
    let over = |c: f32| PieceRgba { colour: [c, 0.0, 0.0], alpha: 0.1 };
    assert_eq!(s.record(b.id, &[over(0.25)]), Err(ScheduleError::BadResult { id: b.id, index: 0 }));
    s.record(b.id, &[over(0.15)]).unwrap();
    // Object 1, unlit, is held to its opacity.
    let b = drain(&mut s, 0).remove(0);
    assert_eq!(b.tasks[0].object, 1);
    assert_eq!(s.record(b.id, &[over(0.15)]), Err(ScheduleError::BadResult { id: b.id, index: 0 }));
    s.record(b.id, &[over(0.1)]).unwrap();
}

#[test]
fn batches_hold_at_most_the_batch_size() {
    let s = scene(&[("near", 0.0)]);
    let inter = intersect(&s, 0..4);
    assert_eq!(inter.tasks.len(), 16);
    let mut sched = Scheduler::new(&s, inter, 5).unwrap();
    let sizes: Vec<usize> = drain(&mut sched, 0).iter().map(|b| b.tasks.len()).collect();
    assert_eq!(sizes, vec![5, 5, 5, 1]);
}

#[test]
fn a_wave_s_last_tasks_can_be_cut_smaller_and_are_counted_down() {
    let s = scene(&[("near", 0.0)]);
    let mut sched = Scheduler::new(&s, intersect(&s, 0..4), 5).unwrap();
    assert_eq!(sched.wave_left(0), 16);
    // A smaller cap cuts the batch; a larger one than the batch size does not widen it.
    let a = sched.next_batch_of(0, 3).unwrap();
    let b = sched.next_batch_of(0, 100).unwrap();
    assert_eq!((a.tasks.len(), b.tasks.len(), sched.wave_left(0)), (3, 5, 8));
    let rest: Vec<usize> = std::iter::from_fn(|| sched.next_batch_of(0, 2)).map(|b| b.tasks.len()).collect();
    assert_eq!((rest, sched.wave_left(0)), (vec![2, 2, 2, 2], 0));
    // The same tasks as whole batches hand out, in the same order.
    let mut whole = Scheduler::new(&s, intersect(&s, 0..4), 5).unwrap();
    let all: Vec<PieceTask> = drain(&mut whole, 0).into_iter().flat_map(|b| b.tasks).collect();
    let mut cut = Scheduler::new(&s, intersect(&s, 0..4), 5).unwrap();
    let mut pieces = Vec::new();
    for max in [1, 4, 2, 7, 3, 9] {
        pieces.extend(cut.next_batch_of(0, max).map(|b| b.tasks).unwrap_or_default());
    }
    assert_eq!(pieces, all);
    assert_eq!(cut.wave_left(7), 0, "a dataset the scene does not have");
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
    assert_eq!(greedy_order(&[2, 1, 0], &votes, &[3.0, 2.0, 1.0]), vec![0, 1, 2]);
}

#[test]
fn datasets_go_front_to_back_and_waves_follow_each_ray() {
    // Along every ray: far-dataset object at z ∈ [1, 1.5], near at [0, 0.5] behind it,
    // and near again at [-1, -0.5]: the dataset declared first is met second.
    let s = scene(&[("near", 0.0), ("far", 1.0), ("near", -1.0)]);
    let inter = intersect(&s, 0..4);
    assert_eq!(inter.rays(), 16);
    let dataset_of: Vec<u32> = s.objects().iter().map(|o| o.dataset() as u32).collect();
    let Plan { order, queue, waves } = plan(&inter, &dataset_of, 2);
    assert_eq!(order, vec![1, 0], "the dataset met first goes first");
    // Dataset 1 has one piece per ray: one wave. Dataset 0 has two: two waves, the
    // nearer piece of every ray in the first.
    assert_eq!(waves[1], vec![0, 16]);
    assert_eq!(waves[0], vec![16, 32, 48]);
    for k in 0..2 {
        let wave = &queue[waves[0][k] as usize..waves[0][k + 1] as usize];
        assert_eq!(wave.len(), 16);
        for q in wave {
            let t = q.task();
            let task = inter.tasks[t as usize];
            assert_eq!(task.object, [0, 2][k], "wave {k}");
            assert_eq!(inter.piece_of(t as usize), inter.ray_start[task.ray as usize] as usize + k + 1);
        }
    }
}

/// The plan by its definition, one ray at a time: each dataset's wave k lists, in task
/// order, the tasks of the k-th piece of each ray that the dataset covers; every ray votes
/// once for each pair of datasets it meets one right after the other; depths are summed
/// per chunk of 8192 rays, then chunk by chunk (the order [`plan`] sums them in).
fn plan_by_definition(inter: &Intersections, dataset_of: &[u32], datasets: usize) -> (Vec<usize>, Vec<Vec<Vec<u32>>>) {
    let mut waves: Vec<Vec<Vec<u32>>> = vec![Vec::new(); datasets];
    let mut votes: HashMap<(usize, usize), u64> = HashMap::new();
    let (mut count, mut depth) = (vec![0u64; datasets], vec![0.0f64; datasets]);
    for chunk in (0..inter.rays()).step_by(8192) {
        let mut chunk_depth = vec![0.0f64; datasets];
        for r in chunk..(chunk + 8192).min(inter.rays()) {
            let mut met: Vec<usize> = Vec::new();
            let mut pieces_of_dataset = vec![0usize; datasets];
            for p in inter.pieces_of(r) {
                let mut seen_here = Vec::new();
                for t in inter.tasks_of(p) {
                    let d = dataset_of[inter.tasks[t].object as usize] as usize;
                    count[d] += 1;
                    chunk_depth[d] += inter.tasks[t].t0;
                    if !seen_here.contains(&d) {
                        seen_here.push(d);
                        pieces_of_dataset[d] += 1;
                    }
                    let rank = pieces_of_dataset[d] - 1;
                    if waves[d].len() <= rank {
                        waves[d].resize(rank + 1, Vec::new());
                    }
                    waves[d][rank].push(t as u32);
                    if !met.contains(&d) {
                        met.push(d);
                    }
                }
            }
            for pair in met.windows(2) {
                *votes.entry((pair[0], pair[1])).or_insert(0) += 1;
            }
        }
        for d in 0..datasets {
            depth[d] += chunk_depth[d];
        }
    }
    let used: Vec<usize> = (0..datasets).filter(|&d| count[d] > 0).collect();
    let mean: Vec<f64> = (0..datasets).map(|d| if count[d] > 0 { depth[d] / count[d] as f64 } else { 0.0 }).collect();
    (greedy_order(&used, &votes, &mean), waves)
}

/// A scene of random boxes of random datasets, some overlapping along the rays, rendered to
/// opacity `termination`, and its intersections.
fn random_scene(seed: u64, width: u32, height: u32, termination: f64) -> (Scene, Intersections) {
    let mut next = crate::testing::numbers(seed | 1);
    let datasets = 1 + next(5);
    let mut text = format!(
        "[image]\nwidth = {width}\nheight = {height}\nbackground = [0, 0, 0]\n\
         [camera]\neye = [0.3, 0.2, 6.0]\ntarget = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 30.0\n\
         [render]\ntermination = {termination}\n"
    );
    for d in 0..datasets {
        text += &format!(
            "[[datasets]]\nname = \"d{d}\"\ndims = [2, 2, 2]\n[datasets.channels.voxel]\n\
             generator = {{ kind = \"constant\", value = 1.0 }}\n"
        );
    }
    for i in 0..1 + next(9) {
        let at = |next: &mut dyn FnMut(u64) -> u64| next(20) as f64 * 0.1 - 1.0;
        let (x, y, z) = (at(&mut next), at(&mut next), at(&mut next) * 2.0);
        let size = 0.3 + next(10) as f64 * 0.1;
        text += &format!(
            "[[objects]]\nname = \"o{i}\"\ndataset = \"d{}\"\n\
             colour = {{ type = \"constant\", red = [1], green = [1], blue = [1] }}\n\
             opacity = {{ type = \"constant\", coefficients = [0.5] }}\n\
             transform = {{ matrix = [[{size}, 0, 0, {x}], [0, {size}, 0, {y}], [0, 0, {size}, {z}], [0, 0, 0, 1]] }}\n",
            next(datasets)
        );
    }
    let scene = Scene::parse(&text, "random.toml").unwrap();
    let inter = intersect(&scene, 0..height);
    (scene, inter)
}

#[test]
fn the_plan_lists_the_waves_and_the_order_of_its_definition() {
    let mut shared_pieces = 0;
    for seed in 0..60 {
        // Wide enough for several survey chunks in some scenes.
        let (w, h) = if seed % 10 == 0 { (200, 90) } else { (23, 17) };
        let (scene, inter) = random_scene(seed, w, h, 0.999);
        let dataset_of: Vec<u32> = scene.objects().iter().map(|o| o.dataset() as u32).collect();
        let datasets = scene.datasets().len();
        let (order, waves) = plan_by_definition(&inter, &dataset_of, datasets);
        let got = plan(&inter, &dataset_of, datasets);
        assert_eq!(got.order, order, "seed {seed}");
        let mut expected_queue = Vec::new();
        for &d in &order {
            let starts: Vec<u32> = got.waves[d].clone();
            assert_eq!(starts.len(), waves[d].len() + 1, "seed {seed}, dataset {d}");
            for (k, wave) in waves[d].iter().enumerate() {
                assert_eq!(starts[k] as usize, expected_queue.len(), "seed {seed}, dataset {d}, wave {k}");
                expected_queue.extend_from_slice(wave);
            }
        }
        let tasks: Vec<u32> = got.queue.iter().map(|q| q.task()).collect();
        assert_eq!(tasks, expected_queue, "seed {seed}");
        // A task leads when its piece is its ray's first: nothing lies in front of it.
        for q in &got.queue {
            let t = q.task() as usize;
            let first = inter.pieces_of(inter.local_ray(inter.tasks[t].ray)).start;
            assert_eq!(q.leads(), inter.piece_of(t) == first, "seed {seed}, task {t}");
        }
        shared_pieces += inter.tasks.len() - inter.pieces();
    }
    assert!(shared_pieces > 100, "the scenes overlap: {shared_pieces}");
}

#[test]
fn a_band_of_rows_carries_whole_image_pixel_indices() {
    let s = scene(&[("near", 0.0)]);
    let band = intersect(&s, 1..3);
    assert_eq!((band.first_ray, band.rays()), (4, 8));
    assert!(band.tasks.iter().all(|t| (4..12).contains(&t.ray)));
    assert_eq!(band.local_ray(band.tasks[0].ray), 0);
    let whole = intersect(&s, 0..4);
    assert_eq!(&whole.tasks[4..12], &band.tasks[..]);
}

/// Every front a batch carries is the definition's — the composite, with colours, of the
/// same-dataset pieces in front (`front_to_back` over `piece_rgba`), clear in a first wave
/// or for a shared piece — and every culled task has, by the end, a full-colour bound on the
/// opacity in front of at least the cull threshold: the opacity-only `decide` agrees with
/// the compositing it stands for.
#[test]
fn fronts_and_culls_are_those_of_full_compositing() {
    let mut culled_any = 0;
    let mut fronted = 0;
    for seed in 0..40 {
        let (scene, inter) = random_scene(seed, 23, 17, [0.6, 0.95, 0.999][seed as usize % 3]);
        let index: HashMap<(u32, u16, u64), usize> =
            inter.tasks.iter().enumerate().map(|(i, t)| ((t.ray, t.object, t.t0.to_bits()), i)).collect();
        let mut s = Scheduler::new(&scene, inter, 7).unwrap();
        let mut step = 0u64;
        while !s.is_complete() {
            let order = s.datasets().to_vec();
            let mut batches = Vec::new();
            for &d in &order {
                while let Some(b) = s.next_batch(d) {
                    batches.push(b);
                }
            }
            // Handing out may cull every task left.
            assert!(!batches.is_empty() || s.is_complete(), "seed {seed}: stuck at {:?}", s.progress());
            for b in batches {
                let first_wave = s.lanes[b.dataset].wave == 0;
                let mut results = Vec::new();
                for task in &b.tasks {
                    let t = index[&(task.ray, task.object, task.t0.to_bits())];
                    let own = s.inter.piece_of(t);
                    let r = s.inter.local_ray(task.ray);
                    let d = s.dataset_of_object[task.object as usize];
                    let front = if task.is_whole() || first_wave {
                        0.0
                    } else {
                        let in_front = s.inter.pieces_of(r).start..own;
                        s.front_to_back(Rgba::CLEAR, in_front, s.termination, |p| {
                            Some(if s.piece_is_of(p, d) { s.piece_rgba(p)? } else { Rgba::CLEAR })
                        })
                        .0
                        .alpha
                    };
                    let mut expected = s.inter.tasks[t];
                    expected.set_front_alpha(front);
                    assert_eq!(task.front, expected.front, "seed {seed}, task {t}");
                    fronted += usize::from(front > 0.0);
                    step += 1;
                    results.push(rgba([0.1, 0.45, 0.8, 0.3][(step % 4) as usize]));
                }
                s.record(b.id, &results).unwrap();
            }
        }
        let cull_at = s.termination + CULL_MARGIN;
        for (t, _) in s.status.iter().enumerate().filter(|(_, st)| **st == Status::Culled) {
            let r = s.inter.local_ray(s.inter.tasks[t].ray);
            let in_front = s.inter.pieces_of(r).start..s.inter.piece_of(t);
            let (bound, stopped) = s.front_to_back(Rgba::CLEAR, in_front, cull_at, |p| s.piece_rgba(p));
            assert!(stopped || bound.alpha >= cull_at, "seed {seed}: task {t} culled with {} in front", bound.alpha);
            culled_any += 1;
        }
    }
    assert!(culled_any > 50 && fronted > 50, "the scenes cull ({culled_any}) and set fronts ({fronted})");
}

/// Batches written straight into their wire form are the batches `next_batch` hands out,
/// encoded: the same ids, attempts and bytes, through culls, fronts and a retried batch.
#[test]
fn encoded_batches_are_the_batches_encoded() {
    use crate::render::wire::{encode_tasks, TaskWriter};
    let mut batches = 0;
    for seed in 0..20 {
        let (scene, inter) = random_scene(seed, 23, 17, [0.6, 0.95, 0.999][seed as usize % 3]);
        let mut listed = Scheduler::new(&scene, inter.clone(), 7).unwrap();
        let mut encoded = Scheduler::new(&scene, inter, 7).unwrap();
        let mut writer = TaskWriter::with_capacity(0);
        let mut step = 0u64;
        while !listed.is_complete() {
            let order = listed.datasets().to_vec();
            let mut handed = Vec::new();
            for &d in &order {
                loop {
                    let (a, b) = match (listed.next_batch(d), encoded.next_batch_encoded(d, &mut writer)) {
                        (Some(a), Some(b)) => (a, b),
                        (None, None) => break,
                        _ => panic!("seed {seed}: one scheduler handed out a batch and the other did not"),
                    };
                    assert_eq!((a.id, a.dataset, a.attempt, a.tasks.len()), (b.id, b.dataset, b.attempt, b.tasks));
                    let (bytes, start) = std::mem::replace(&mut writer, TaskWriter::with_capacity(0)).finish();
                    assert_eq!(&bytes[start..], &encode_tasks(&a.tasks)[..], "seed {seed}, batch {}", a.id);
                    handed.push(a);
                    batches += 1;
                }
            }
            for (i, b) in handed.into_iter().enumerate() {
                if i == 1 && b.attempt == 0 && step.is_multiple_of(3) {
                    listed.abandon(b.id).unwrap();
                    encoded.abandon(b.id).unwrap();
                    continue;
                }
                let results: Vec<PieceRgba> =
                    (0..b.tasks.len()).map(|k| rgba([0.1, 0.45, 0.8, 0.3][((step + k as u64) % 4) as usize])).collect();
                step += 1;
                listed.record(b.id, &results).unwrap();
                encoded.record(b.id, &results).unwrap();
            }
        }
        assert!(encoded.is_complete() && encoded.progress() == listed.progress(), "seed {seed}");
    }
    assert!(batches > 200, "{batches} batches");
}

/// Lists written before they are read ([`kept::for_overwrite`]: the plan's keys and queue,
/// the results) may hold a former band's values: with kept lists full of them (opaque
/// results, which a read would take for a ray opaque in front, and keys and queue entries
/// out of range) the same batches and the same pixels, bit for bit. (Other tests may take
/// those lists first; most runs give them to this one.)
#[test]
fn stale_kept_lists_change_no_batch_and_no_pixel() {
    /// Each batch's dataset and tasks, and the pixels' bits.
    type Run = (Vec<(usize, Vec<PieceTask>)>, Vec<[u64; 3]>);
    fn run(scene: &Scene, inter: Intersections) -> Run {
        let mut s = Scheduler::new(scene, inter, 5).unwrap();
        let mut batches = Vec::new();
        while !s.is_complete() {
            // Every ready batch out, then the answers back to front: tasks are decided with
            // other datasets' pieces in front still pending.
            let mut out = Vec::new();
            for d in s.datasets().to_vec() {
                out.extend(std::iter::from_fn(|| s.next_batch(d)));
            }
            for b in out.into_iter().rev() {
                let results: Vec<PieceRgba> =
                    (0..b.tasks.len()).map(|k| rgba([0.2, 0.7, 0.95][(batches.len() + k) % 3])).collect();
                s.record(b.id, &results).unwrap();
                batches.push((b.dataset, b.tasks));
            }
        }
        let pixels = s.composite_pixels([0.1, 0.2, 0.3]).iter().map(|p| p.map(f64::to_bits)).collect();
        (batches, pixels)
    }
    for seed in 0..6 {
        let (scene, inter) = random_scene(seed, 19, 13, 0.95);
        let clean = run(&scene, inter.clone());
        let n = inter.tasks.len();
        for len in [n, n / 2, 2 * n] {
            kept::keep(vec![[1.0f32; 4]; len]);
            kept::keep(vec![u32::MAX; len]);
            kept::keep(vec![Queued(u32::MAX); len]);
        }
        assert_eq!(run(&scene, inter), clean, "seed {seed}");
    }
}

/// The scheduler's own list types come back from the kept lists holding exactly `n` copies
/// of the value asked for, whatever they held and however long they were (other tests may
/// take them first: each case holds either way).
#[test]
fn kept_lists_come_back_refilled_whole() {
    use crate::render::kept::{filled, keep};
    for (len, n) in [(100, 60), (60, 60), (10, 200)] {
        keep(vec![7u32; len]);
        assert_eq!(filled(n, 0u32), vec![0; n]);
        keep(vec![Status::Done; len]);
        assert!(filled(n, Status::Pending).iter().all(|&s| s == Status::Pending));
        keep(vec![[1.0f32; 4]; len]);
        assert_eq!(filled(n, [0.0f32; 4]), vec![[0.0; 4]; n]);
        keep(vec![KnownFront { pieces: 3, alpha: 0.5 }.pack(); len]);
        let known = filled(n, KnownFront::default().pack());
        assert!(known.len() == n && known.iter().all(|&k| KnownFront::unpack(k) == KnownFront::default()));
    }
}

/// A known front comes back from its packed form bit for bit, and the clear front packs to
/// zero, which a new list of them is allocated as.
#[test]
fn known_fronts_pack_bit_for_bit_and_the_clear_front_is_zero() {
    assert_eq!(KnownFront::default().pack(), 0);
    for front in [
        KnownFront { pieces: 0, alpha: 0.0 },
        KnownFront { pieces: 1, alpha: 0.25 },
        KnownFront { pieces: u32::MAX, alpha: 1.0 - f64::EPSILON },
        KnownFront { pieces: 7, alpha: f64::MIN_POSITIVE / 2.0 },
    ] {
        let back = KnownFront::unpack(front.pack());
        assert_eq!((back.pieces, back.alpha.to_bits()), (front.pieces, front.alpha.to_bits()));
    }
}
