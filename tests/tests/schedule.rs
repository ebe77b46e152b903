//! The scheduler alone, without a network: whatever order results arrive in, however many
//! datasets are in flight, however the image is cut into bands and batches, and whichever
//! batches are given up and handed out again, it composites the very image the local
//! renderer makes — bit for bit, since the farm is held to byte-identical PNGs.

use proptest::prelude::*;
use trove_core::render::intersection::intersect;
use trove_core::render::{render, Batch, BatchCaster, Image, PieceRgba, RenderOptions, Scheduler, VolumeStore};
use trove_core::scene::Scene;

/// Three datasets, six objects: translucent and opaque, overlapping along the rays (shared
/// pieces), one dataset met both in front of and behind another, so waves, culling and
/// co-located media all happen.
fn scene() -> Scene {
    let mut text = String::from(
        "[image]\nwidth = 20\nheight = 14\nbackground = [0.1, 0.2, 0.3]\n\
         [camera]\neye = [0.2, 0.5, 4.0]\ntarget = [0.0, 0.0, 0.0]\nup = [0, 1, 0]\nfov_y = 45.0\n\
         [render]\ntermination = 0.95\n",
    );
    for (i, radius) in [0.45, 0.3, 0.5].iter().enumerate() {
        text += &format!(
            "[[datasets]]\nname = \"d{i}\"\ndims = [9, 8, 7]\n[datasets.channels.voxel]\n\
             generator = {{ kind = \"sphere\", radius = {radius}, profile = \"radial\", value = 1.0, type = \"f32\" }}\n"
        );
    }
    // (dataset, box min, box size, opacity at the rim and at the centre)
    let objects = [
        (0, [-0.9, -0.6, 0.6], 1.0, 0.0, 0.35),
        (1, [-0.5, -0.4, 0.9], 0.9, 0.3, 1.0),
        (2, [-0.2, -0.7, -0.4], 1.3, 0.0, 0.25),
        (0, [0.1, -0.2, -1.2], 1.0, 0.4, 0.95),
        (1, [-1.2, -0.3, -0.8], 1.4, 0.0, 0.2),
        (2, [0.3, 0.1, 0.3], 0.7, 0.1, 0.6),
    ];
    for (i, (d, min, size, rim, centre)) in objects.iter().enumerate() {
        text += &format!(
            "[[objects]]\nname = \"o{i}\"\ndataset = \"d{d}\"\n\
             colour = {{ type = \"ramp\", points = [[0.0, 0.9, 0.2, 0.1], [1.0, 0.1, 0.6, 1.0]] }}\n\
             opacity = {{ type = \"ramp\", points = [[0.0, {rim}], [1.0, {centre}]] }}\n\
             transform = {{ matrix = [[{size}, 0, 0, {}], [0, {size}, 0, {}], [0, 0, {size}, {}], [0, 0, 0, 1]] }}\n",
            min[0], min[1], min[2]
        );
    }
    Scene::parse(&text, "schedule.toml").unwrap()
}

/// A small deterministic generator for the arrival orders (proptest picks the seed).
struct Rng(u64);

impl Rng {
    fn below(&mut self, n: usize) -> usize {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((self.0 >> 33) % n as u64) as usize
    }
}

/// Renders `scene` through schedulers driven in a random order: bands of random height,
/// batches of random size, a random dataset asked for work or a random batch in flight
/// answered at each step, and now and then a batch given up and handed out again.
fn shuffled(scene: &Scene, seed: u64) -> Image {
    let mut rng = Rng(seed);
    let store = VolumeStore::new(None);
    let volumes: Vec<_> = scene.datasets().iter().map(|d| store.get(d).unwrap()).collect();
    let casters: Vec<_> = (0..volumes.len()).map(|d| BatchCaster::new(scene, d, &volumes[d]).unwrap()).collect();
    let (w, h) = (scene.image().width, scene.image().height);
    let mut pixels = Vec::new();
    let mut row = 0;
    while row < h {
        let rows = row..(row + 1 + rng.below(6) as u32).min(h);
        let mut s = Scheduler::new(scene, intersect(scene, rows.clone()), 1 + rng.below(40)).unwrap();
        let datasets = s.datasets().to_vec();
        let mut in_flight: Vec<Batch> = Vec::new();
        while !s.is_complete() {
            if in_flight.is_empty() || rng.below(3) == 0 {
                let d = datasets[rng.below(datasets.len())];
                // Now and then a wave's tasks cut smaller, as the local driver cuts a wave's
                // last ones.
                in_flight.extend(if rng.below(4) == 0 {
                    s.next_batch_of(d, 1 + rng.below(8))
                } else {
                    s.next_batch(d)
                });
                continue;
            }
            let batch = in_flight.swap_remove(rng.below(in_flight.len()));
            if rng.below(10) == 0 {
                s.abandon(batch.id).unwrap();
                continue;
            }
            let mut out = vec![PieceRgba::default(); batch.tasks.len()];
            casters[batch.dataset].cast(&batch.tasks, &mut out).unwrap();
            s.record(batch.id, &out).unwrap();
        }
        assert!(in_flight.is_empty(), "complete with batches still out");
        let background = scene.image().background;
        pixels.extend((0..s.intersections().rays()).map(|r| s.composite_ray(r).with_background(background)));
        row = rows.end;
    }
    Image::new(w, h, pixels)
}

fn local(scene: &Scene) -> Image {
    render(scene, &RenderOptions::default()).unwrap().image
}

#[test]
fn the_scene_exercises_culling_shared_pieces_and_several_waves() {
    let s = scene();
    let rendered = render(&s, &RenderOptions::default()).unwrap();
    assert!(rendered.stats.samples_skipped > 0, "no task was culled: the test would prove little");
    let inter = intersect(&s, 0..s.image().height);
    let shared = inter.tasks.iter().filter(|t| t.is_whole()).count();
    assert!(shared > 0, "no shared piece");
    let sched = Scheduler::new(&s, inter, 64).unwrap();
    assert_eq!(sched.datasets().len(), 3);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn any_arrival_order_composites_the_local_image_bit_for_bit(seed in any::<u64>()) {
        let s = scene();
        let expected = local(&s);
        let got = shuffled(&s, seed);
        prop_assert!(got == expected, "differs by {}", got.max_abs_difference(&expected));
    }
}
