//! What a render did, in the shape of the paper's Table 1 (SPEC §5 `--stats`).

use serde::Serialize;

use super::{Algorithm, VolumeStore};
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
    /// flight included); never above `memory_budget`.
    pub peak_resident_bytes: u64,
    /// Per-phase timings.
    pub seconds: Seconds,
}

impl RenderStats {
    /// Fills the scene-level fields and the totals once rendering is over.
    pub(crate) fn finish(&mut self, scene: &Scene, algorithm: Algorithm, store: &VolumeStore, total: f64) {
        self.algorithm = algorithm.name().to_string();
        self.width = scene.image().width;
        self.height = scene.image().height;
        self.objects = scene.objects().len();
        self.datasets = scene.datasets().len();
        self.dataset_loads = store.loads();
        self.bytes_loaded = store.bytes_loaded();
        self.memory_budget = store.budget();
        self.peak_resident_bytes = store.peak_resident_bytes();
        let s = &mut self.seconds;
        s.total = total;
        s.other = (total - s.intersection - s.volume_rendering - s.composition - s.loading).max(0.0);
    }
}
