//! What a render did, in the shape of the paper's Table 1 (SPEC §5 `--stats`).

use serde::Serialize;

use super::{Algorithm, StoreStats};
use crate::sampling::{self, SimdPath};
use crate::scene::Scene;

/// Wall-clock seconds per phase. The grouped algorithm runs its phases one after another,
/// so each is measured directly. Where phases interleave on several threads (the per-ray
/// algorithm), the parallel section's wall time is split in proportion to the thread time
/// each phase took; `other` is what remains of `total`.
#[derive(Clone, Copy, Debug, Default, Serialize, PartialEq)]
pub struct Seconds {
    /// Ray–box intersections and piece splitting.
    pub intersection: f64,
    /// Sampling, interpolation, mapping, per-piece compositing.
    pub volume_rendering: f64,
    /// Combining pieces into pixels (0 when interleaved with casting, as in Algorithm 1).
    pub composition: f64,
    /// Bringing voxel data into memory, including waiting for room under a budget.
    pub loading: f64,
    /// The shadow pass (SPEC §6, `render::shadow`): the other objects' shares of each lit
    /// object's shadows, loading included; 0 without shadows.
    pub shadows: f64,
    /// Everything else: setup, image assembly.
    pub other: f64,
    /// The whole render.
    pub total: f64,
}

/// Counts and timings of one render.
#[derive(Clone, Debug, Default, Serialize, PartialEq)]
pub struct RenderStats {
    /// `per-ray` or `grouped`.
    pub algorithm: String,
    /// The SIMD path the sampler's vector loops took in this process (`scalar`, `avx2`,
    /// `avx512` or `neon`: [`SimdPath::configured`], which `TROVE_SIMD` forces). On a farm
    /// it is the coordinator's; each worker takes its own processor's.
    pub simd: String,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Objects in the scene.
    pub objects: usize,
    /// Datasets in the scene.
    pub datasets: usize,
    /// Ray–object segments of non-zero length.
    pub segments: u64,
    /// Pieces (segments split where objects overlap).
    pub pieces: u64,
    /// Samples interpolated and mapped.
    pub samples: u64,
    /// Sample positions in (piece, object) pairs never cast because the ray was already
    /// known to be opaque in front of them (early termination). Samples a cast left out
    /// after reaching termination inside its own piece are not counted.
    pub samples_skipped: u64,
    /// Whole-dataset loads (the store does not brick), reloads after eviction included.
    pub dataset_loads: u64,
    /// Bytes loaded, over all loads.
    pub bytes_loaded: u64,
    /// The memory budget, in bytes (`null`: none).
    pub memory_budget: Option<u64>,
    /// The most voxel bytes resident at once, from the store's own accounting (loads in
    /// flight and the macrocell classifications kept with datasets included); never above
    /// `memory_budget`.
    pub peak_resident_bytes: u64,
    /// Objects bound with the macrocell classification an earlier bind kept with their
    /// resident dataset (a later band of the image), instead of classifying again. A farm's
    /// workers keep their own and do not report them: 0 there.
    pub classification_hits: u64,
    /// Objects bound through the store that found none kept.
    pub classification_misses: u64,
    /// Per object, in scene order: the effects its casts ran (SPEC §6) and how often.
    pub effects: Vec<ObjectEffects>,
    /// Per-phase timings.
    pub seconds: Seconds,
}

/// The effects one object's casts ran (`--stats`' `effects`).
#[derive(Clone, Debug, Default, Serialize, PartialEq)]
pub struct ObjectEffects {
    /// The object's name.
    pub object: String,
    /// The effects, by name: `shading` where the object was lit, and `shadows` where a
    /// light that lights it casts them. Empty for an unlit one.
    pub ran: Vec<&'static str>,
    /// Samples shaded (a gradient and Blinn–Phong each): samples of the object that
    /// contributed opacity. `null` where the render could not count them: a farm's workers
    /// do not report them yet.
    pub shading_evaluations: Option<u64>,
    /// Shadow lookups: the shaded samples times the lights that cast shadows onto the
    /// object, each a lattice lookup and a shadow ray through the object itself (SPEC §6's
    /// S) where the light is in front of the surface (N·L > 0; behind it S is not needed).
    /// `null` where not counted.
    pub shadow_lookups: Option<u64>,
    /// Lights casting shadows onto it (what `shadow_lookups` multiplies).
    #[serde(skip)]
    shadow_lights: u64,
}

impl ObjectEffects {
    /// Every object of `scene` with the effects its casts run, and `shading_evaluations`
    /// as given (`Some(0)` for a count to be added to, `None` for one not kept).
    pub fn listed(scene: &Scene, shading_evaluations: Option<u64>) -> Vec<ObjectEffects> {
        scene
            .objects()
            .iter()
            .map(|o| ObjectEffects {
                object: o.name().to_string(),
                ran: match (sampling::shades(o), o.needs_shadow_maps()) {
                    (true, true) => vec!["shading", "shadows"],
                    (true, false) => vec!["shading"],
                    _ => Vec::new(),
                },
                shading_evaluations,
                shadow_lookups: shading_evaluations.map(|_| 0),
                shadow_lights: match o.lighting() {
                    Some((_, lights)) if sampling::shades(o) => lights.iter().filter(|l| l.shadows()).count() as u64,
                    _ => 0,
                },
            })
            .collect()
    }

    /// Adds `shaded[i]` samples shaded to object i's counts.
    pub fn add(effects: &mut [ObjectEffects], shaded: &[u64]) {
        for (e, &n) in effects.iter_mut().zip(shaded) {
            if let Some(count) = &mut e.shading_evaluations {
                *count += n;
            }
            if let Some(count) = &mut e.shadow_lookups {
                *count += n * e.shadow_lights;
            }
        }
    }
}

impl RenderStats {
    /// Fills the scene-level fields and the totals once rendering is over: `store` is what
    /// the voxel store (or, in a farm, every worker's store together) did.
    pub fn finish(&mut self, scene: &Scene, algorithm: Algorithm, store: &StoreStats, budget: Option<u64>, total: f64) {
        self.algorithm = algorithm.name().to_string();
        // A path refused would have refused every bind before the render got here.
        self.simd = SimdPath::configured().map(|p| p.name().to_string()).unwrap_or_default();
        self.width = scene.image().width;
        self.height = scene.image().height;
        self.objects = scene.objects().len();
        self.datasets = scene.datasets().len();
        self.dataset_loads = store.loads;
        self.bytes_loaded = store.bytes_loaded;
        self.memory_budget = budget;
        self.peak_resident_bytes = store.peak_resident_bytes;
        self.classification_hits = store.classification_hits;
        self.classification_misses = store.classification_misses;
        if self.effects.len() != scene.objects().len() {
            // Nobody counted (a farm's workers do not report shading counts yet).
            self.effects = ObjectEffects::listed(scene, None);
        }
        let s = &mut self.seconds;
        s.total = total;
        s.other = (total - s.intersection - s.volume_rendering - s.composition - s.loading - s.shadows).max(0.0);
    }

    /// Adds the counts and phase times of another part of the same render (a tile, or a
    /// worker's share): counts add up, peaks take the larger.
    pub fn merge(&mut self, other: &RenderStats) {
        self.segments += other.segments;
        self.pieces += other.pieces;
        self.samples += other.samples;
        self.samples_skipped += other.samples_skipped;
        self.dataset_loads += other.dataset_loads;
        self.bytes_loaded += other.bytes_loaded;
        self.peak_resident_bytes = self.peak_resident_bytes.max(other.peak_resident_bytes);
        self.classification_hits += other.classification_hits;
        self.classification_misses += other.classification_misses;
        if self.effects.is_empty() {
            self.effects.clone_from(&other.effects);
        } else if self.effects.len() == other.effects.len() {
            for (e, o) in self.effects.iter_mut().zip(&other.effects) {
                e.shading_evaluations = e.shading_evaluations.zip(o.shading_evaluations).map(|(a, b)| a + b);
                e.shadow_lookups = e.shadow_lookups.zip(o.shadow_lookups).map(|(a, b)| a + b);
            }
        }
        let (s, o) = (&mut self.seconds, &other.seconds);
        s.intersection += o.intersection;
        s.volume_rendering += o.volume_rendering;
        s.composition += o.composition;
        s.loading += o.loading;
        s.shadows += o.shadows;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn merging_adds_counts_and_keeps_the_larger_peak() {
        let part = |n: u64| RenderStats {
            segments: n,
            pieces: 2 * n,
            samples: 3 * n,
            samples_skipped: 4 * n,
            dataset_loads: 5 * n,
            bytes_loaded: 6 * n,
            peak_resident_bytes: 7 * n,
            classification_hits: 8 * n,
            classification_misses: 9 * n,
            seconds: Seconds { intersection: n as f64, volume_rendering: 1.0, ..Seconds::default() },
            ..RenderStats::default()
        };
        let mut a = part(1);
        a.merge(&part(10));
        let expected = RenderStats {
            seconds: Seconds { intersection: 11.0, volume_rendering: 2.0, ..Seconds::default() },
            peak_resident_bytes: 70,
            ..part(11)
        };
        assert_eq!(a, expected);
    }

    #[test]
    fn finishing_names_the_simd_path_the_sampler_took() {
        let text = r#"
[image]
width = 2
height = 2
background = [0.0, 0.0, 0.0]
[camera]
eye = [0.5, 0.5, 3.0]
target = [0.5, 0.5, 0.5]
up = [0.0, 1.0, 0.0]
fov_y = 30.0
[[datasets]]
name = "cube"
dims = [2, 2, 2]
[datasets.channels.voxel]
generator = { kind = "constant", value = 9, type = "u8" }
[[objects]]
name = "cube"
dataset = "cube"
colour = { type = "lut", bounds = [5.0], colours = [[0, 0, 0], [1, 1, 1]] }
opacity = { type = "lut", bounds = [5.0], values = [0.0, 0.5] }
"#;
        let scene = Scene::parse(text, "stats.toml").unwrap();
        let mut stats = RenderStats::default();
        stats.finish(&scene, Algorithm::Grouped, &StoreStats::default(), None, 1.0);
        assert_eq!(stats.simd, SimdPath::configured().unwrap().name());
        assert!(!stats.simd.is_empty());
    }
}
