//! Resident voxel data: datasets loaded on demand, shared by every object and thread that
//! uses them, counted, and — under a memory budget — evicted least-recently-used.
//!
//! # Policy
//! The unit of residency is the **whole dataset** (no bricks): `dataset_loads` counts
//! whole-dataset loads and `bytes_loaded` their resident sizes. A budget must therefore hold
//! the largest dataset a render uses; a smaller one is refused up front by
//! [`VolumeStore::check_budget`] with [`StoreError::BudgetTooSmall`], never rendered
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

use std::collections::HashMap;
use std::ops::Deref;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Instant;

use super::error::StoreError;
use crate::dataset::{DatasetId, DatasetInfo, Volume};
use crate::scene::Scene;

/// What identifies a dataset's voxels across scenes and jobs ([`DatasetInfo::id`]): two
/// scenes that name the same files share one resident copy in a long-lived worker.
type DatasetKey = DatasetId;

/// Loads datasets on first use and keeps at most `budget` bytes of them resident. Cheap to
/// clone: clones share one store, so a long-lived worker and every job it serves see the
/// same resident datasets and the same budget.
#[derive(Clone)]
pub struct VolumeStore {
    inner: Arc<Inner>,
}

struct Inner {
    budget: Option<u64>,
    state: Mutex<State>,
    /// Signalled whenever a pin is released, a load finishes or a dataset is evicted.
    changed: Condvar,
    loads: AtomicU64,
    bytes_loaded: AtomicU64,
    loading_nanos: AtomicU64,
}

struct State {
    /// Datasets resident or being loaded; absent ones have no entry.
    slots: HashMap<DatasetKey, Slot>,
    /// Bytes of resident datasets plus loads in flight.
    resident: u64,
    peak: u64,
    /// Logical clock for least-recently-used order.
    clock: u64,
}

enum Slot {
    /// A thread is loading it; its bytes are already counted as resident.
    Loading,
    Resident {
        volume: Arc<Volume>,
        bytes: u64,
        pins: u32,
        last_used: u64,
    },
}

/// What a store did, for statistics: a snapshot that merges with others (the farm sums its
/// workers' loads and keeps the largest peak).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StoreStats {
    /// Whole-dataset loads, reloads after eviction included.
    pub loads: u64,
    /// Bytes brought into memory over all loads.
    pub bytes_loaded: u64,
    /// The most bytes resident at once (loads in flight included).
    pub peak_resident_bytes: u64,
    /// Seconds spent loading, summed over threads.
    pub loading_seconds: f64,
}

impl StoreStats {
    /// Adds another store's work to this one.
    pub fn merge(&mut self, other: &StoreStats) {
        self.loads += other.loads;
        self.bytes_loaded += other.bytes_loaded;
        self.peak_resident_bytes = self.peak_resident_bytes.max(other.peak_resident_bytes);
        self.loading_seconds += other.loading_seconds;
    }
}

/// A dataset's voxels, kept resident while this guard lives.
pub struct Pinned {
    inner: Arc<Inner>,
    key: DatasetKey,
    volume: Arc<Volume>,
    loaded: bool,
}

impl Pinned {
    /// Whether this request loaded the dataset (rather than finding it resident): what a
    /// farm worker reports as its loads.
    pub fn was_loaded(&self) -> bool {
        self.loaded
    }
}

impl Deref for Pinned {
    type Target = Volume;
    fn deref(&self) -> &Volume {
        &self.volume
    }
}

impl Drop for Pinned {
    fn drop(&mut self) {
        let mut state = lock(&self.inner.state);
        if let Some(Slot::Resident { pins, .. }) = state.slots.get_mut(&self.key) {
            *pins -= 1;
        }
        drop(state);
        self.inner.changed.notify_all();
    }
}

/// Poisoning only means another thread panicked mid-render; the accounting it protects is
/// updated in single statements, so it is still consistent.
fn lock(m: &Mutex<State>) -> MutexGuard<'_, State> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl VolumeStore {
    /// An empty store that keeps at most `budget` bytes resident (`None`: unlimited).
    pub fn new(budget: Option<u64>) -> VolumeStore {
        VolumeStore {
            inner: Arc::new(Inner {
                budget,
                state: Mutex::new(State { slots: HashMap::new(), resident: 0, peak: 0, clock: 0 }),
                changed: Condvar::new(),
                loads: AtomicU64::new(0),
                bytes_loaded: AtomicU64::new(0),
                loading_nanos: AtomicU64::new(0),
            }),
        }
    }

    /// The budget, if any.
    pub fn budget(&self) -> Option<u64> {
        self.inner.budget
    }

    /// Refuses a budget that cannot hold one of the datasets some object of `scene` uses:
    /// with whole-dataset residency such a render could never finish.
    pub fn check_budget(&self, scene: &Scene) -> Result<(), StoreError> {
        let Some(budget) = self.inner.budget else { return Ok(()) };
        for d in scene.used_datasets() {
            let info = &scene.datasets()[d];
            let needed = info.resident_bytes();
            if needed > budget {
                return Err(StoreError::BudgetTooSmall { name: info.name().to_string(), needed, budget });
            }
        }
        Ok(())
    }

    /// The dataset's voxels, loading them (and evicting others) when needed. Blocks while
    /// the budget is held by datasets other threads still read, or while another thread
    /// loads this dataset. The load runs on the calling thread, often a rayon worker, so
    /// loaders must never use rayon themselves: a worker idle in a nested join may steal a
    /// job that waits here for the load on its own stack (see `Generator::generate`). A
    /// failed load is not remembered: the next request tries again, so a transient failure
    /// does not poison a long-lived worker.
    pub fn get(&self, info: &DatasetInfo) -> Result<Pinned, StoreError> {
        let inner = &self.inner;
        let key = info.id().clone();
        let needed = info.resident_bytes();
        let mut state = lock(&inner.state);
        loop {
            state.clock += 1;
            let now = state.clock;
            match state.slots.get_mut(&key) {
                Some(Slot::Resident { volume, pins, last_used, .. }) => {
                    *pins += 1;
                    *last_used = now;
                    let volume = volume.clone();
                    return Ok(Pinned { inner: inner.clone(), key, volume, loaded: false });
                }
                Some(Slot::Loading) => {
                    state = inner.changed.wait(state).unwrap_or_else(|e| e.into_inner());
                    continue;
                }
                None => {}
            }
            if let Some(budget) = inner.budget {
                if needed > budget {
                    return Err(StoreError::BudgetTooSmall { name: info.name().to_string(), needed, budget });
                }
                if !evict_until_fits(&mut state, needed, budget) {
                    state = inner.changed.wait(state).unwrap_or_else(|e| e.into_inner());
                    continue;
                }
            }
            state.slots.insert(key.clone(), Slot::Loading);
            state.resident += needed;
            state.peak = state.peak.max(state.resident);
            break;
        }
        drop(state);

        let started = Instant::now();
        let loaded = info.load().map(|v| if inner.budget.is_some() { Arc::new(v.owned_copy()) } else { v });
        inner.loading_nanos.fetch_add(started.elapsed().as_nanos() as u64, Ordering::Relaxed);

        let mut state = lock(&inner.state);
        let result = match loaded {
            Ok(volume) => {
                // The reservation used the dataset's declared size; a load always yields
                // exactly that (channels are checked against dims), so no correction is due.
                debug_assert_eq!(volume.byte_len(), needed, "dataset `{}` resident size", info.name());
                inner.loads.fetch_add(1, Ordering::Relaxed);
                inner.bytes_loaded.fetch_add(needed, Ordering::Relaxed);
                tracing::debug!(dataset = %info.name(), bytes = needed, "loaded");
                let now = state.clock;
                let slot = Slot::Resident { volume: volume.clone(), bytes: needed, pins: 1, last_used: now };
                state.slots.insert(key.clone(), slot);
                Ok(Pinned { inner: inner.clone(), key, volume, loaded: true })
            }
            Err(e) => {
                state.resident -= needed;
                state.slots.remove(&key);
                Err(StoreError::Load { name: info.name().to_string(), source: Arc::new(e) })
            }
        };
        drop(state);
        inner.changed.notify_all();
        result
    }

    /// Drops the dataset now if nobody reads it (Algorithm 2's `UnloadVolume`).
    pub fn unload(&self, info: &DatasetInfo) {
        let key = info.id().clone();
        let mut state = lock(&self.inner.state);
        if let Some(Slot::Resident { pins: 0, bytes, .. }) = state.slots.get(&key) {
            let bytes = *bytes;
            state.slots.remove(&key);
            state.resident -= bytes;
            drop(state);
            self.inner.changed.notify_all();
        }
    }

    /// What the store has done so far.
    pub fn stats(&self) -> StoreStats {
        StoreStats {
            loads: self.inner.loads.load(Ordering::Relaxed),
            bytes_loaded: self.inner.bytes_loaded.load(Ordering::Relaxed),
            peak_resident_bytes: lock(&self.inner.state).peak,
            loading_seconds: self.inner.loading_nanos.load(Ordering::Relaxed) as f64 * 1e-9,
        }
    }

    /// Bytes resident now (including loads in flight).
    pub fn resident_bytes(&self) -> u64 {
        lock(&self.inner.state).resident
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
        .values()
        .map(|s| match s {
            Slot::Resident { pins: 0, bytes, .. } => *bytes,
            _ => 0,
        })
        .sum();
    if free(state) + evictable < needed {
        return false;
    }
    while free(state) < needed {
        let Some(victim) = state
            .slots
            .iter()
            .filter_map(|(k, s)| match s {
                Slot::Resident { pins: 0, last_used, .. } => Some((*last_used, k)),
                _ => None,
            })
            .min_by_key(|(last_used, _)| *last_used)
            .map(|(_, k)| k.clone())
        else {
            // Counted above; unreachable while the lock is held.
            return false;
        };
        if let Some(Slot::Resident { bytes, .. }) = state.slots.remove(&victim) {
            state.resident -= bytes;
            tracing::debug!(bytes, "evicted");
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
        let store = VolumeStore::new(Some(2 * BYTES));
        for d in [0, 1, 0, 2] {
            assert_eq!(
                store.get(&s.datasets()[d]).unwrap().channel(crate::dataset::ChannelName::Voxel).unwrap().value(0),
                d as f32
            );
        }
        // Loading 2 evicted 1 (used before the second use of 0), so 0 is still here.
        assert_eq!(store.stats().loads, 3);
        drop(store.get(&s.datasets()[0]).unwrap());
        assert_eq!(store.stats().loads, 3);
        drop(store.get(&s.datasets()[1]).unwrap());
        assert_eq!(store.stats().loads, 4);
        assert_eq!(store.stats().bytes_loaded, 4 * BYTES);
        assert_eq!(store.stats().peak_resident_bytes, 2 * BYTES);
        assert_eq!(store.resident_bytes(), 2 * BYTES);
    }

    #[test]
    fn with_no_budget_nothing_is_evicted_but_unload_frees() {
        let s = scene(3);
        let store = VolumeStore::new(None);
        for d in [0, 1, 2, 0, 1, 2] {
            drop(store.get(&s.datasets()[d]).unwrap());
        }
        assert_eq!((store.stats().loads, store.stats().peak_resident_bytes), (3, 3 * BYTES));
        let pinned = store.get(&s.datasets()[1]).unwrap();
        store.unload(&s.datasets()[1]);
        assert_eq!(store.resident_bytes(), 3 * BYTES, "a pinned dataset stays");
        drop(pinned);
        store.unload(&s.datasets()[1]);
        store.unload(&s.datasets()[2]);
        assert_eq!(store.resident_bytes(), BYTES);
    }

    #[test]
    fn a_pinned_dataset_is_not_evicted_and_a_load_waits_for_room() {
        let s = scene(2);
        let store = VolumeStore::new(Some(BYTES));
        let pinned = store.get(&s.datasets()[0]).unwrap();
        let finished = AtomicBool::new(false);
        std::thread::scope(|scope| {
            let waiter = scope.spawn(|| {
                let v = store.get(&s.datasets()[1]).map(|v| v.dims());
                finished.store(true, Ordering::SeqCst);
                v
            });
            std::thread::sleep(Duration::from_millis(100));
            assert!(!finished.load(Ordering::SeqCst), "loaded dataset 1 while dataset 0 was pinned");
            assert_eq!(store.stats().loads, 1);
            assert_eq!(pinned.dims().voxel_count(), 1000);
            drop(pinned);
            assert!(waiter.join().unwrap().is_ok());
        });
        assert_eq!(store.stats().loads, 2);
        assert_eq!(store.stats().peak_resident_bytes, BYTES);
    }

    #[test]
    fn many_threads_never_exceed_the_budget() {
        let s = scene(5);
        let budget = 2 * BYTES + BYTES / 2;
        let store = VolumeStore::new(Some(budget));
        std::thread::scope(|scope| {
            for thread in 0..4usize {
                let (store, s) = (&store, &s);
                scope.spawn(move || {
                    for i in 0..200usize {
                        let v = store.get(&s.datasets()[(i * 7 + thread * 3) % 5]).unwrap();
                        assert!(store.resident_bytes() <= budget);
                        drop(v);
                    }
                });
            }
        });
        assert!(store.stats().peak_resident_bytes <= budget);
        assert!(store.stats().loads > 5);
        assert_eq!(store.stats().bytes_loaded, store.stats().loads * BYTES);
    }

    #[test]
    fn a_budget_below_a_dataset_is_refused_naming_it() {
        let s = scene(2);
        let store = VolumeStore::new(Some(BYTES - 1));
        for e in [store.check_budget(&s).unwrap_err(), store.get(&s.datasets()[1]).err().unwrap()] {
            assert!(matches!(&e, StoreError::BudgetTooSmall { needed: BYTES, .. }), "{e}");
        }
        assert!(store.get(&s.datasets()[1]).err().unwrap().to_string().contains("`d1`"));
        assert_eq!(store.stats().loads, 0);
        assert!(VolumeStore::new(Some(BYTES)).check_budget(&s).is_ok());
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
        let store = VolumeStore::new(Some(100));
        for _ in 0..2 {
            let e = store.get(&s.datasets()[0]).err().expect("the file is gone");
            assert!(matches!(e, StoreError::Load { ref name, .. } if name == "gone"), "{e}");
        }
        assert_eq!((store.resident_bytes(), store.stats().loads), (0, 0));
    }

    #[test]
    fn scenes_that_name_the_same_data_share_one_resident_copy() {
        // A long-lived worker serves many jobs: the second scene's dataset is the first's.
        let (a, b) = (scene(2), scene(3));
        let store = VolumeStore::new(None);
        let first = store.get(&a.datasets()[1]).unwrap();
        let again = store.get(&b.datasets()[1]).unwrap();
        assert!(std::ptr::eq(&*first, &*again));
        assert_eq!(store.stats().loads, 1);
        drop(store.get(&b.datasets()[2]).unwrap());
        assert_eq!(store.stats().loads, 2);
    }

    #[test]
    fn store_statistics_merge_by_summing_work_and_keeping_the_largest_peak() {
        let mut a = StoreStats { loads: 2, bytes_loaded: 10, peak_resident_bytes: 7, loading_seconds: 0.5 };
        a.merge(&StoreStats { loads: 1, bytes_loaded: 5, peak_resident_bytes: 9, loading_seconds: 0.25 });
        assert_eq!(a, StoreStats { loads: 3, bytes_loaded: 15, peak_resident_bytes: 9, loading_seconds: 0.75 });
    }
}
