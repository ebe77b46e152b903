//! Resident voxel data: each dataset loaded when first needed, shared by every object and
//! thread that uses it, and counted.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::Instant;

use crate::dataset::Volume;
use crate::scene::Scene;
use crate::RenderError;

/// Loads datasets on first use and keeps them (no memory budget).
pub struct VolumeStore<'s> {
    scene: &'s Scene,
    slots: Vec<OnceLock<Result<Arc<Volume>, String>>>,
    loads: AtomicU64,
    bytes_loaded: AtomicU64,
    loading_nanos: AtomicU64,
}

impl<'s> VolumeStore<'s> {
    /// An empty store for `scene`'s datasets.
    pub fn new(scene: &'s Scene) -> VolumeStore<'s> {
        VolumeStore {
            scene,
            slots: scene.datasets.iter().map(|_| OnceLock::new()).collect(),
            loads: AtomicU64::new(0),
            bytes_loaded: AtomicU64::new(0),
            loading_nanos: AtomicU64::new(0),
        }
    }

    /// Dataset `index`'s voxels, loading them the first time.
    pub fn get(&self, index: usize) -> Result<Arc<Volume>, RenderError> {
        let info = &self.scene.datasets[index];
        let slot = self.slots[index].get_or_init(|| {
            let started = Instant::now();
            let loaded = info.load();
            self.loading_nanos.fetch_add(started.elapsed().as_nanos() as u64, Ordering::Relaxed);
            if let Ok(v) = &loaded {
                self.loads.fetch_add(1, Ordering::Relaxed);
                self.bytes_loaded.fetch_add(v.byte_len(), Ordering::Relaxed);
                tracing::debug!(dataset = %info.name, bytes = v.byte_len(), "loaded");
            }
            loaded.map_err(|e| e.to_string())
        });
        slot.clone().map_err(|message| RenderError::Dataset {
            name: info.name.clone(),
            source: crate::DatasetError::format(&self.scene.path, message),
        })
    }

    /// Whole-dataset loads so far.
    pub fn loads(&self) -> u64 {
        self.loads.load(Ordering::Relaxed)
    }

    /// Bytes brought into memory so far.
    pub fn bytes_loaded(&self) -> u64 {
        self.bytes_loaded.load(Ordering::Relaxed)
    }

    /// Seconds spent loading (summed over threads).
    pub fn loading_seconds(&self) -> f64 {
        self.loading_nanos.load(Ordering::Relaxed) as f64 * 1e-9
    }
}
