//! Resident voxel data: datasets loaded on demand, shared by every object and thread that
//! uses them, counted, and — under a memory budget — evicted least-recently-used.
//!
//! # Policy
//! The unit of residency is the **whole dataset** (no bricks): `dataset_loads` counts
//! whole-dataset loads and `bytes_loaded` their resident sizes. A budget must therefore hold
//! the largest dataset a render uses; a smaller one is refused up front by
//! [`VolumeStore::check_budget`] with [`RenderError::BudgetTooSmall`], never rendered
//! wrongly.
//!
//! # Resident bytes are exact
//! A dataset counts as resident from the moment its load is *reserved* (before the bytes
//! arrive) until it is evicted. [`VolumeStore::get`] hands out a [`Pinned`] guard, not an
//! `Arc`, so the store always knows who still reads a dataset: a pinned dataset is never
//! evicted, and a load that would exceed the budget waits until pins are released. Hence
//! `peak_resident_bytes ≤ budget` holds by construction (it is measured from this same
//! accounting). A thread must not ask for a second dataset while it holds a pin, or two
//! threads could each wait for the other's; both renderers hold at most one pin at a time.
//!
//! # What "loaded" means
//! Raw native files are memory-mapped (zero copy). With no budget a mapping counts as loaded
//! when it is made (the OS pages it in on first touch, as the paper's virtual memory did).
//! Under a budget the store copies mapped bytes into memory it owns, so a load really reads
//! the file and an eviction really frees it: `bytes_loaded` and the resident count are then
//! honest. A generated dataset counts as loaded when it is generated.

use std::ops::Deref;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Instant;

use crate::dataset::Volume;
use crate::scene::Scene;
use crate::RenderError;

/// Loads datasets on first use and keeps at most `budget` bytes of them resident.
pub struct VolumeStore<'s> {
    scene: &'s Scene,
    budget: Option<u64>,
    state: Mutex<State>,
    /// Signalled whenever a pin is released, a load finishes or a dataset is evicted.
    changed: Condvar,
    loads: AtomicU64,
    bytes_loaded: AtomicU64,
    loading_nanos: AtomicU64,
}

struct State {
    slots: Vec<Slot>,
    /// Bytes of resident datasets plus loads in flight.
    resident: u64,
    peak: u64,
    /// Logical clock for least-recently-used order.
    clock: u64,
}

enum Slot {
    Absent,
    /// A thread is loading it; its bytes are already counted as resident.
    Loading,
    Resident {
        volume: Arc<Volume>,
        bytes: u64,
        pins: u32,
        last_used: u64,
    },
    Failed(String),
}

/// A dataset's voxels, kept resident while this guard lives.
pub struct Pinned<'a> {
    state: &'a Mutex<State>,
    changed: &'a Condvar,
    index: usize,
    volume: Arc<Volume>,
}

impl Deref for Pinned<'_> {
    type Target = Volume;
    fn deref(&self) -> &Volume {
        &self.volume
    }
}

impl Drop for Pinned<'_> {
    fn drop(&mut self) {
        let mut state = lock(self.state);
        if let Slot::Resident { pins, .. } = &mut state.slots[self.index] {
            *pins -= 1;
        }
        drop(state);
        self.changed.notify_all();
    }
}

/// Poisoning only means another thread panicked mid-render; the accounting it protects is
/// updated in single statements, so it is still consistent.
fn lock(m: &Mutex<State>) -> MutexGuard<'_, State> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl<'s> VolumeStore<'s> {
    /// An empty store for `scene`'s datasets with no memory budget.
    pub fn new(scene: &'s Scene) -> VolumeStore<'s> {
        VolumeStore::with_budget(scene, None)
    }

    /// An empty store that keeps at most `budget` bytes resident (`None`: unlimited).
    pub fn with_budget(scene: &'s Scene, budget: Option<u64>) -> VolumeStore<'s> {
        VolumeStore {
            scene,
            budget,
            state: Mutex::new(State {
                slots: scene.datasets.iter().map(|_| Slot::Absent).collect(),
                resident: 0,
                peak: 0,
                clock: 0,
            }),
            changed: Condvar::new(),
            loads: AtomicU64::new(0),
            bytes_loaded: AtomicU64::new(0),
            loading_nanos: AtomicU64::new(0),
        }
    }

    /// The budget, if any.
    pub fn budget(&self) -> Option<u64> {
        self.budget
    }

    /// Refuses a budget that cannot hold one of the datasets some object uses: with
    /// whole-dataset residency such a render could never finish.
    pub fn check_budget(&self) -> Result<(), RenderError> {
        let Some(budget) = self.budget else { return Ok(()) };
        for d in self.scene.used_datasets() {
            let info = &self.scene.datasets[d];
            let needed = info.resident_bytes();
            if needed > budget {
                return Err(RenderError::BudgetTooSmall { name: info.name.clone(), needed, budget });
            }
        }
        Ok(())
    }

    /// Dataset `index`'s voxels, loading them (and evicting others) when needed. Blocks
    /// while the budget is held by datasets other threads still read, or while another
    /// thread loads this dataset. The load runs on the calling thread, often a rayon worker,
    /// so loaders must never use rayon themselves: a worker idle in a nested join may steal a
    /// job that waits here for the load on its own stack (see `Generator::generate`).
    pub fn get(&self, index: usize) -> Result<Pinned<'_>, RenderError> {
        let info = &self.scene.datasets[index];
        let needed = info.resident_bytes();
        let mut state = lock(&self.state);
        loop {
            state.clock += 1;
            let now = state.clock;
            match &mut state.slots[index] {
                Slot::Resident { volume, pins, last_used, .. } => {
                    *pins += 1;
                    *last_used = now;
                    let volume = volume.clone();
                    return Ok(Pinned { state: &self.state, changed: &self.changed, index, volume });
                }
                Slot::Failed(message) => return Err(self.failure(index, message.clone())),
                Slot::Loading => {
                    state = self.changed.wait(state).unwrap_or_else(|e| e.into_inner());
                    continue;
                }
                Slot::Absent => {}
            }
            if let Some(budget) = self.budget {
                if needed > budget {
                    return Err(RenderError::BudgetTooSmall { name: info.name.clone(), needed, budget });
                }
                if !evict_until_fits(&mut state, needed, budget) {
                    state = self.changed.wait(state).unwrap_or_else(|e| e.into_inner());
                    continue;
                }
            }
            state.slots[index] = Slot::Loading;
            state.resident += needed;
            state.peak = state.peak.max(state.resident);
            break;
        }
        drop(state);

        let started = Instant::now();
        let loaded = info.load().map(|v| if self.budget.is_some() { Arc::new(v.owned_copy()) } else { v });
        self.loading_nanos.fetch_add(started.elapsed().as_nanos() as u64, Ordering::Relaxed);

        let mut state = lock(&self.state);
        let result = match loaded {
            Ok(volume) => {
                // The reservation used the dataset's declared size; a load always yields
                // exactly that (channels are checked against dims), so no correction is due.
                debug_assert_eq!(volume.byte_len(), needed, "dataset `{}` resident size", info.name);
                self.loads.fetch_add(1, Ordering::Relaxed);
                self.bytes_loaded.fetch_add(needed, Ordering::Relaxed);
                tracing::debug!(dataset = %info.name, bytes = needed, "loaded");
                let now = state.clock;
                state.slots[index] = Slot::Resident { volume: volume.clone(), bytes: needed, pins: 1, last_used: now };
                Ok(Pinned { state: &self.state, changed: &self.changed, index, volume })
            }
            Err(e) => {
                state.resident -= needed;
                let message = e.to_string();
                state.slots[index] = Slot::Failed(message.clone());
                Err(self.failure(index, message))
            }
        };
        drop(state);
        self.changed.notify_all();
        result
    }

    /// Drops dataset `index` now if nobody reads it (Algorithm 2's `UnloadVolume`).
    pub fn unload(&self, index: usize) {
        let mut state = lock(&self.state);
        if let Slot::Resident { pins: 0, bytes, .. } = state.slots[index] {
            state.slots[index] = Slot::Absent;
            state.resident -= bytes;
            drop(state);
            self.changed.notify_all();
        }
    }

    fn failure(&self, index: usize, message: String) -> RenderError {
        RenderError::Dataset {
            name: self.scene.datasets[index].name.clone(),
            source: crate::DatasetError::format(&self.scene.path, message),
        }
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

    /// Bytes resident now (including loads in flight).
    pub fn resident_bytes(&self) -> u64 {
        lock(&self.state).resident
    }

    /// The most bytes ever resident at once (including loads in flight).
    pub fn peak_resident_bytes(&self) -> u64 {
        lock(&self.state).peak
    }
}

/// Evicts unpinned datasets, least recently used first, until `needed` more bytes fit in
/// `budget`. Returns false (having evicted nothing) when even evicting every unpinned one
/// would not make room: the caller must wait for pins to be released.
fn evict_until_fits(state: &mut State, needed: u64, budget: u64) -> bool {
    let free = |s: &State| budget.saturating_sub(s.resident);
    if free(state) >= needed {
        return true;
    }
    let evictable: u64 = state
        .slots
        .iter()
        .map(|s| match s {
            Slot::Resident { pins: 0, bytes, .. } => *bytes,
            _ => 0,
        })
        .sum();
    if free(state) + evictable < needed {
        return false;
    }
    while free(state) < needed {
        let victim = state
            .slots
            .iter()
            .enumerate()
            .filter_map(|(i, s)| match s {
                Slot::Resident { pins: 0, last_used, .. } => Some((*last_used, i)),
                _ => None,
            })
            .min()
            .map(|(_, i)| i)
            .expect("enough evictable bytes were counted");
        if let Slot::Resident { bytes, .. } = std::mem::replace(&mut state.slots[victim], Slot::Absent) {
            state.resident -= bytes;
            tracing::debug!(dataset = victim, bytes, "evicted");
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::AtomicBool;
    use std::time::Duration;

    use super::*;

    /// `count` generated datasets of 10³ f32 = 4000 bytes each, plus the macrocell ranges of
    /// their voxel channel: 3³ cells and 1 coarse block of 8 bytes.
    fn scene(count: usize) -> Scene {
        let mut text = String::from(
            "[image]\nwidth = 2\nheight = 2\nbackground = [0, 0, 0]\n\
             [camera]\neye = [0.5, 0.5, 5.0]\ntarget = [0.5, 0.5, 0.0]\nup = [0, 1, 0]\nfov_y = 5.0\n",
        );
        for d in 0..count {
            text += &format!(
                "[[datasets]]\nname = \"d{d}\"\ndims = [10, 10, 10]\n[datasets.channels.voxel]\n\
                 generator = {{ kind = \"constant\", value = {d} }}\n\
                 [[objects]]\nname = \"o{d}\"\ndataset = \"d{d}\"\n\
                 colour = {{ type = \"constant\", red = [1], green = [1], blue = [1] }}\n\
                 opacity = {{ type = \"constant\", coefficients = [0.5] }}\n"
            );
        }
        Scene::parse(&text, "store.toml").unwrap()
    }

    const BYTES: u64 = 4000 + (27 + 1) * 8;

    #[test]
    fn least_recently_used_goes_first() {
        let s = scene(3);
        let store = VolumeStore::with_budget(&s, Some(2 * BYTES));
        for d in [0, 1, 0, 2] {
            assert_eq!(store.get(d).unwrap().channel(crate::dataset::ChannelName::Voxel).unwrap().value(0), d as f32);
        }
        // Loading 2 evicted 1 (used before the second use of 0), so 0 is still here.
        assert_eq!(store.loads(), 3);
        drop(store.get(0).unwrap());
        assert_eq!(store.loads(), 3);
        drop(store.get(1).unwrap());
        assert_eq!(store.loads(), 4);
        assert_eq!(store.bytes_loaded(), 4 * BYTES);
        assert_eq!(store.peak_resident_bytes(), 2 * BYTES);
        assert_eq!(store.resident_bytes(), 2 * BYTES);
    }

    #[test]
    fn with_no_budget_nothing_is_evicted_but_unload_frees() {
        let s = scene(3);
        let store = VolumeStore::new(&s);
        for d in [0, 1, 2, 0, 1, 2] {
            drop(store.get(d).unwrap());
        }
        assert_eq!((store.loads(), store.peak_resident_bytes()), (3, 3 * BYTES));
        let pinned = store.get(1).unwrap();
        store.unload(1);
        assert_eq!(store.resident_bytes(), 3 * BYTES, "a pinned dataset stays");
        drop(pinned);
        store.unload(1);
        store.unload(2);
        assert_eq!(store.resident_bytes(), BYTES);
    }

    #[test]
    fn a_pinned_dataset_is_not_evicted_and_a_load_waits_for_room() {
        let s = scene(2);
        let store = VolumeStore::with_budget(&s, Some(BYTES));
        let pinned = store.get(0).unwrap();
        let finished = AtomicBool::new(false);
        std::thread::scope(|scope| {
            let waiter = scope.spawn(|| {
                let v = store.get(1).map(|v| v.dims());
                finished.store(true, Ordering::SeqCst);
                v
            });
            std::thread::sleep(Duration::from_millis(100));
            assert!(!finished.load(Ordering::SeqCst), "loaded dataset 1 while dataset 0 was pinned");
            assert_eq!(store.loads(), 1);
            assert_eq!(pinned.dims().voxel_count(), 1000);
            drop(pinned);
            assert!(waiter.join().unwrap().is_ok());
        });
        assert_eq!(store.loads(), 2);
        assert_eq!(store.peak_resident_bytes(), BYTES);
    }

    #[test]
    fn many_threads_never_exceed_the_budget() {
        let s = scene(5);
        let budget = 2 * BYTES + BYTES / 2;
        let store = VolumeStore::with_budget(&s, Some(budget));
        std::thread::scope(|scope| {
            for thread in 0..4usize {
                let store = &store;
                scope.spawn(move || {
                    for i in 0..200usize {
                        let v = store.get((i * 7 + thread * 3) % 5).unwrap();
                        assert!(store.resident_bytes() <= budget);
                        drop(v);
                    }
                });
            }
        });
        assert!(store.peak_resident_bytes() <= budget);
        assert!(store.loads() > 5);
        assert_eq!(store.bytes_loaded(), store.loads() * BYTES);
    }

    #[test]
    fn a_budget_below_a_dataset_is_refused_naming_it() {
        let s = scene(2);
        let store = VolumeStore::with_budget(&s, Some(BYTES - 1));
        for e in [store.check_budget().unwrap_err(), store.get(1).err().unwrap()] {
            assert!(matches!(&e, RenderError::BudgetTooSmall { needed: BYTES, .. }), "{e}");
        }
        assert!(store.get(1).err().unwrap().to_string().contains("`d1`"));
        assert_eq!(store.loads(), 0);
        assert!(VolumeStore::with_budget(&s, Some(BYTES)).check_budget().is_ok());
    }

    #[test]
    fn a_failed_load_gives_its_bytes_back_and_is_reported_each_time() {
        let dir = std::env::temp_dir().join(format!("trove-store-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("v.raw"), [0u8; 8]).unwrap();
        let text = "[image]\nwidth = 2\nheight = 2\nbackground = [0, 0, 0]\n\
                    [camera]\neye = [0.5, 0.5, 5.0]\ntarget = [0.5, 0.5, 0.0]\nup = [0, 1, 0]\nfov_y = 5.0\n\
                    [[datasets]]\nname = \"gone\"\ndims = [2, 2, 2]\n[datasets.channels.voxel]\nraw = \"v.raw\"\ntype = \"u8\"\n\
                    [[objects]]\nname = \"o\"\ndataset = \"gone\"\n\
                    colour = { type = \"constant\", red = [1], green = [1], blue = [1] }\n\
                    opacity = { type = \"constant\", coefficients = [0.5] }\n";
        let s = Scene::parse(text, dir.join("scene.toml")).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        let store = VolumeStore::with_budget(&s, Some(100));
        for _ in 0..2 {
            let e = store.get(0).err().expect("the file is gone");
            assert!(matches!(e, RenderError::Dataset { ref name, .. } if name == "gone"), "{e}");
        }
        assert_eq!((store.resident_bytes(), store.loads()), (0, 0));
    }
}
