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
//!
//! # Classifications kept with a dataset
//! Binding an object for many pieces classifies every macrocell of its dataset for it
//! (`sampling::skip`: one bit per cell and each cell's distance to the nearest non-empty
//! one). The store keeps those classifications with the resident dataset they were worked
//! out from, keyed by everything else they depend on (channel, interpolation, the opacity
//! map's zero set: [`ClassKey`]), so that a later bind over the same load — the next band
//! of an image, the next job on a farm worker, the next frame of a local sequence rendered
//! through one store (`RenderOptions::store`) — uses them instead of classifying again.
//! They are part of the dataset's residency: their bytes count as resident bytes from the
//! moment they are kept until the dataset is evicted or unloaded, which drops them too; a
//! reload starts with none. They are only kept in room the budget has free (never by
//! evicting a dataset), at most a quarter of their dataset's own bytes per dataset (the
//! least recently used dropped first), and when room is needed for a load, those of
//! datasets nobody reads go before any dataset does. A classification the store declines
//! is still worked out and used by the caster that asked, as without a store.

use std::collections::HashMap;
use std::ops::Deref;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Instant;

use super::error::StoreError;
use crate::dataset::{DatasetId, DatasetInfo, Volume};
use crate::sampling::{ClassKey, Classes, ClassificationCache};
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
    class_hits: AtomicU64,
    class_misses: AtomicU64,
}

struct State {
    /// Datasets resident or being loaded; absent ones have no entry.
    slots: HashMap<DatasetKey, Slot>,
    /// Bytes of resident datasets (their kept classifications included) plus loads in
    /// flight.
    resident: u64,
    peak: u64,
    /// Logical clock for least-recently-used order.
    clock: u64,
    /// Counts loads, so that a reload is never taken for the load before it.
    generation: u64,
}

enum Slot {
    /// A thread is loading it; its bytes are already counted as resident.
    Loading,
    Resident {
        volume: Arc<Volume>,
        /// The dataset's own bytes.
        bytes: u64,
        pins: u32,
        last_used: u64,
        /// Which load this is.
        generation: u64,
        /// Classifications worked out from this load.
        kept: Kept,
    },
}

/// Classifications kept with one resident dataset, and their bytes (counted in
/// `State::resident`).
#[derive(Default)]
struct Kept {
    classes: HashMap<ClassKey, (Arc<Classes>, u64)>,
    bytes: u64,
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
    /// Binds that found their object's macrocell classification kept with the dataset.
    pub classification_hits: u64,
    /// Binds through the store that did not (and classified, or bound lazily).
    pub classification_misses: u64,
}

impl StoreStats {
    /// The work done since `earlier`, a snapshot of the same store: counts and seconds
    /// less `earlier`'s, the peak as it stands (the most resident over the store's life).
    pub fn since(&self, earlier: &StoreStats) -> StoreStats {
        StoreStats {
            loads: self.loads - earlier.loads,
            bytes_loaded: self.bytes_loaded - earlier.bytes_loaded,
            peak_resident_bytes: self.peak_resident_bytes,
            loading_seconds: self.loading_seconds - earlier.loading_seconds,
            classification_hits: self.classification_hits - earlier.classification_hits,
            classification_misses: self.classification_misses - earlier.classification_misses,
        }
    }

    /// Adds another store's work to this one.
    pub fn merge(&mut self, other: &StoreStats) {
        self.loads += other.loads;
        self.bytes_loaded += other.bytes_loaded;
        self.peak_resident_bytes = self.peak_resident_bytes.max(other.peak_resident_bytes);
        self.loading_seconds += other.loading_seconds;
        self.classification_hits += other.classification_hits;
        self.classification_misses += other.classification_misses;
    }
}

/// A dataset's voxels, kept resident while this guard lives.
pub struct Pinned {
    inner: Arc<Inner>,
    key: DatasetKey,
    /// The load it pins (see `State::generation`).
    generation: u64,
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

impl Pinned {
    /// The pinned load's kept classifications, under the store's lock.
    /// With the dataset's own bytes. While pinned, the load is resident (never evicted), so
    /// the generation only guards against a mistake.
    fn kept<'s>(&self, state: &'s mut State) -> Option<(&'s mut Kept, u64)> {
        match state.slots.get_mut(&self.key) {
            Some(Slot::Resident { generation, kept, bytes, .. }) if *generation == self.generation => {
                Some((kept, *bytes))
            }
            _ => None,
        }
    }
}

/// Most bytes of classifications kept per dataset, as a fraction of its own bytes.
const KEPT_PER_DATASET_BYTES: u64 = 4;

impl ClassificationCache for Pinned {
    fn find(&self, key: &ClassKey) -> Option<Arc<Classes>> {
        let mut state = lock(&self.inner.state);
        state.clock += 1;
        let now = state.clock;
        let found = self.kept(&mut state).and_then(|(kept, _)| {
            let (classes, last_used) = kept.classes.get_mut(key)?;
            *last_used = now;
            Some(classes.clone())
        });
        drop(state);
        let counter = if found.is_some() { &self.inner.class_hits } else { &self.inner.class_misses };
        counter.fetch_add(1, Ordering::Relaxed);
        found
    }

    fn has_room(&self, bytes: u64) -> bool {
        let mut state = lock(&self.inner.state);
        let free = self.inner.budget.map_or(u64::MAX, |b| b.saturating_sub(state.resident));
        self.kept(&mut state)
            .is_some_and(|(kept, dataset)| bytes <= free && kept.bytes + bytes <= dataset / KEPT_PER_DATASET_BYTES)
    }

    fn keep(&self, key: ClassKey, classes: &Arc<Classes>) {
        let bytes = classes.bytes();
        let mut state = lock(&self.inner.state);
        state.clock += 1;
        let now = state.clock;
        let budget = self.inner.budget;
        let resident = state.resident;
        let Some((kept, dataset)) = self.kept(&mut state) else { return };
        let cap = dataset / KEPT_PER_DATASET_BYTES;
        if kept.classes.contains_key(&key) || bytes > cap {
            return;
        }
        // Make room within the dataset's share by dropping its least recently used.
        let mut freed = 0;
        while kept.bytes + bytes > cap {
            let Some(oldest) = kept.classes.iter().min_by_key(|(_, (_, used))| *used).map(|(k, _)| k.clone()) else {
                break;
            };
            if let Some((c, _)) = kept.classes.remove(&oldest) {
                kept.bytes -= c.bytes();
                freed += c.bytes();
            }
        }
        let fits = budget.is_none_or(|b| resident - freed + bytes <= b);
        if fits {
            kept.classes.insert(key, (classes.clone(), now));
            kept.bytes += bytes;
        }
        state.resident = state.resident - freed + if fits { bytes } else { 0 };
        state.peak = state.peak.max(state.resident);
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
                state: Mutex::new(State { slots: HashMap::new(), resident: 0, peak: 0, clock: 0, generation: 0 }),
                changed: Condvar::new(),
                loads: AtomicU64::new(0),
                bytes_loaded: AtomicU64::new(0),
                loading_nanos: AtomicU64::new(0),
                class_hits: AtomicU64::new(0),
                class_misses: AtomicU64::new(0),
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
                Some(Slot::Resident { volume, pins, last_used, generation, .. }) => {
                    *pins += 1;
                    *last_used = now;
                    let (volume, generation) = (volume.clone(), *generation);
                    return Ok(Pinned { inner: inner.clone(), key, generation, volume, loaded: false });
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
        let loaded =
            info.load_at(super::vector_width())
                .map(|v| if inner.budget.is_some() { Arc::new(v.owned_copy()) } else { v });
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
                state.generation += 1;
                let generation = state.generation;
                let slot = Slot::Resident {
                    volume: volume.clone(),
                    bytes: needed,
                    pins: 1,
                    last_used: now,
                    generation,
                    kept: Kept::default(),
                };
                state.slots.insert(key.clone(), slot);
                Ok(Pinned { inner: inner.clone(), key, generation, volume, loaded: true })
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
        if let Some(Slot::Resident { pins: 0, bytes, kept, .. }) = state.slots.get(&key) {
            let bytes = bytes + kept.bytes;
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
            classification_hits: self.inner.class_hits.load(Ordering::Relaxed),
            classification_misses: self.inner.class_misses.load(Ordering::Relaxed),
        }
    }

    /// Bytes resident now (including loads in flight and kept classifications).
    pub fn resident_bytes(&self) -> u64 {
        lock(&self.inner.state).resident
    }
}

/// Evicts unpinned datasets, least recently used first, until `needed` more bytes fit in
/// `budget`; the classifications kept with unpinned datasets go first, datasets only if
/// that is not enough. Returns false (having evicted nothing) when even evicting every
/// unpinned one would not make room: the caller must wait for pins to be released.
fn evict_until_fits(state: &mut State, needed: u64, budget: u64) -> bool {
    let free = |s: &State| budget.saturating_sub(s.resident);
    if free(state) >= needed {
        return true;
    }
    let evictable: u64 = state
        .slots
        .values()
        .map(|s| match s {
            Slot::Resident { pins: 0, bytes, kept, .. } => bytes + kept.bytes,
            _ => 0,
        })
        .sum();
    if free(state) + evictable < needed {
        return false;
    }
    // Classifications of datasets nobody reads go first, least recently used dataset first:
    // working one out again costs milliseconds, loading a dataset again much more.
    while free(state) < needed {
        let Some(victim) = state
            .slots
            .iter()
            .filter_map(|(k, s)| match s {
                Slot::Resident { pins: 0, last_used, kept, .. } if kept.bytes > 0 => Some((*last_used, k)),
                _ => None,
            })
            .min_by_key(|(last_used, _)| *last_used)
            .map(|(_, k)| k.clone())
        else {
            break;
        };
        let freed = match state.slots.get_mut(&victim) {
            Some(Slot::Resident { kept, .. }) => std::mem::take(kept).bytes,
            _ => 0,
        };
        state.resident -= freed;
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
        if let Some(Slot::Resident { bytes, kept, .. }) = state.slots.remove(&victim) {
            state.resident -= bytes + kept.bytes;
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
    fn statistics_since_a_snapshot_are_the_work_done_after_it() {
        let s = scene(2);
        let store = VolumeStore::new(None);
        drop(store.get(&s.datasets()[0]).unwrap());
        let before = store.stats();
        drop(store.get(&s.datasets()[0]).unwrap());
        drop(store.get(&s.datasets()[1]).unwrap());
        let since = store.stats().since(&before);
        assert_eq!((since.loads, since.bytes_loaded), (1, BYTES));
        assert_eq!(since.peak_resident_bytes, 2 * BYTES);
        assert!(since.loading_seconds <= store.stats().loading_seconds);
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

    /// One 32³ u8 dataset, a radial sphere (255 at the centre, 0 beyond the radius), seen
    /// by two objects with `opacity` (points of a ramp): one in front, one behind.
    fn sphere_scene(opacity: &str) -> Scene {
        let text = format!(
            "[image]\nwidth = 24\nheight = 20\nbackground = [0, 0, 0]\n\
             [camera]\neye = [0.6, 0.7, 3.0]\ntarget = [0.5, 0.5, 0.0]\nup = [0, 1, 0]\nfov_y = 40.0\n\
             [[datasets]]\nname = \"ball\"\ndims = [32, 32, 32]\n[datasets.channels.voxel]\n\
             generator = {{ kind = \"sphere\", radius = 0.45, profile = \"radial\", value = 255 }}\n\
             [[objects]]\nname = \"front\"\ndataset = \"ball\"\n\
             colour = {{ type = \"ramp\", points = [[0, 1, 0.5, 0], [255, 1, 1, 1]] }}\n\
             opacity = {{ type = \"ramp\", points = {opacity} }}\n\
             [[objects]]\nname = \"back\"\ndataset = \"ball\"\n\
             colour = {{ type = \"ramp\", points = [[0, 0, 0.5, 1], [255, 1, 1, 1]] }}\n\
             opacity = {{ type = \"ramp\", points = {opacity} }}\n\
             transform = {{ matrix = [[1, 0, 0, 0.4], [0, 1, 0, 0.1], [0, 0, 1, -1.2], [0, 0, 0, 1]] }}\n"
        );
        Scene::parse(&text, "kept.toml").unwrap()
    }

    const SOFT: &str = "[[0, 0], [60, 0], [255, 0.3]]";

    /// Renders `scene` as a farm worker casts it: one scheduler over the whole image, each
    /// dataset pinned in `store` and bound with [`BatchCaster::new`] per queue of batches
    /// (here per batch, the worst case for a worker).
    fn render_through(store: &VolumeStore, scene: &Scene) -> Vec<[f64; 3]> {
        use crate::render::intersection::intersect;
        use crate::render::schedule::Scheduler;
        use crate::render::{BatchCaster, PieceRgba};
        let h = scene.image().height;
        let mut s = Scheduler::new(scene, intersect(scene, 0..h), 64).unwrap();
        for d in s.datasets().to_vec() {
            while let Some(batch) = s.next_batch(d) {
                let volume = store.get(&scene.datasets()[d]).unwrap();
                let caster = BatchCaster::new(scene, d, &volume).unwrap();
                let mut out = vec![PieceRgba::default(); batch.tasks.len()];
                caster.cast(&batch.tasks, &mut out).unwrap();
                s.record(batch.id, &out).unwrap();
            }
            assert!(s.is_dataset_done(d));
        }
        s.composite_pixels(scene.image().background)
    }

    /// The image a fresh local render gives (its own store, every object classified anew).
    fn fresh(scene: &Scene) -> Vec<[f64; 3]> {
        crate::render::render(scene, &crate::render::RenderOptions::default()).unwrap().image.pixels().to_vec()
    }

    fn hits_and_misses(store: &VolumeStore) -> (u64, u64) {
        let s = store.stats();
        (s.classification_hits, s.classification_misses)
    }

    #[test]
    fn a_second_render_through_one_store_binds_with_the_kept_classification() {
        let scene = sphere_scene(SOFT);
        let store = VolumeStore::new(None);
        let first = render_through(&store, &scene);
        // The first bind classifies the two objects' cells (one key: the same map and
        // interpolation) and keeps that; every later bind, here one per batch, finds it.
        let (hits, misses) = hits_and_misses(&store);
        assert_eq!(misses, 1);
        assert!(hits >= 3, "{hits} hits");
        let dataset = scene.datasets()[0].resident_bytes();
        assert!(store.resident_bytes() > dataset, "the classification counts as resident");
        let second = render_through(&store, &scene);
        assert_eq!(hits_and_misses(&store).1, 1, "no bind of the second render classified again");
        assert_eq!(store.stats().loads, 1);
        assert_eq!(first, second);
        assert_eq!(first, fresh(&scene), "a kept classification renders what a fresh one does");
        assert!(first.iter().any(|p| p[0] > 0.1), "the sphere is visible");
    }

    #[test]
    fn a_changed_opacity_map_or_a_reload_classifies_again() {
        let store = VolumeStore::new(None);
        let soft = sphere_scene(SOFT);
        let before = render_through(&store, &soft);
        assert_eq!(hits_and_misses(&store).1, 1);
        // Zero over more values: another classification, and the image of the new map.
        let hard = sphere_scene("[[0, 0], [150, 0], [255, 0.6]]");
        let after = render_through(&store, &hard);
        assert_eq!(hits_and_misses(&store).1, 2, "the changed map missed");
        assert_eq!(store.stats().loads, 1, "the same dataset, still resident");
        assert_eq!(after, fresh(&hard));
        assert_ne!(after, before);
        // Other opacities over the same zero set: the classification still holds.
        let brighter = sphere_scene("[[0, 0], [60, 0], [255, 0.9]]");
        let (hits, misses) = hits_and_misses(&store);
        let brighter_image = render_through(&store, &brighter);
        assert_eq!(hits_and_misses(&store).1, misses, "the same zero set hit");
        assert!(hits_and_misses(&store).0 > hits);
        assert_eq!(brighter_image, fresh(&brighter));
        // Another load of the dataset starts with nothing kept.
        store.unload(&soft.datasets()[0]);
        assert_eq!(store.resident_bytes(), 0, "its classifications went with it");
        assert_eq!(render_through(&store, &soft), before);
        assert_eq!((store.stats().loads, hits_and_misses(&store).1), (2, misses + 1));
    }

    #[test]
    fn local_renders_through_a_kept_store_reuse_its_loads_and_classifications() {
        use crate::render::{render, RenderOptions};
        // The frames of a sequence: one store for every render, kept by the caller.
        let store = VolumeStore::new(None);
        let options = RenderOptions { store: Some(store.clone()), ..RenderOptions::default() };
        let soft = sphere_scene(SOFT);
        let first = render(&soft, &options).unwrap();
        assert_eq!((first.stats.dataset_loads, first.stats.classification_misses), (1, 1));
        let dataset = soft.datasets()[0].resident_bytes();
        assert!(store.resident_bytes() > dataset, "the dataset and its classification stay resident");
        // The same job again: nothing loaded, nothing classified, the same image.
        let again = render(&soft, &options).unwrap();
        assert_eq!((again.stats.dataset_loads, again.stats.classification_misses), (0, 0));
        assert!(again.stats.classification_hits > 0, "the repeated render found the kept classification");
        assert_eq!(again.image.pixels(), first.image.pixels());
        assert_eq!(first.image.pixels(), &fresh(&soft)[..]);
        // A changed opacity map (zero over more values): classified again, and its image is
        // a fresh render's of the changed scene.
        let hard = sphere_scene("[[0, 0], [150, 0], [255, 0.6]]");
        let changed = render(&hard, &options).unwrap();
        assert_eq!((changed.stats.dataset_loads, changed.stats.classification_misses), (0, 1));
        assert_eq!(changed.image.pixels(), &fresh(&hard)[..]);
        assert_ne!(changed.image.pixels(), first.image.pixels());
        // A store of the render's own (no `store`) is emptied as it goes.
        let own = render(&soft, &RenderOptions::default()).unwrap();
        assert_eq!((own.stats.dataset_loads, own.stats.classification_misses), (1, 1));
    }

    #[test]
    fn classifications_are_kept_only_in_room_the_budget_has_free() {
        let scene = sphere_scene(SOFT);
        let info = &scene.datasets()[0];
        let dataset = info.resident_bytes();
        // A budget of the dataset alone: nothing kept, every bind classifies, nothing over.
        let store = VolumeStore::new(Some(dataset));
        let image = render_through(&store, &scene);
        let (hits, misses) = hits_and_misses(&store);
        assert_eq!(hits, 0);
        assert!(misses >= 2);
        assert_eq!((store.resident_bytes(), store.stats().peak_resident_bytes), (dataset, dataset));
        assert_eq!(image, fresh(&scene));
        // Room for it: kept, counted, within the budget.
        let roomy = VolumeStore::new(Some(2 * dataset));
        assert_eq!(render_through(&roomy, &scene), image);
        let kept = roomy.resident_bytes() - dataset;
        assert!(kept > 0 && kept <= dataset / KEPT_PER_DATASET_BYTES);
        assert_eq!(roomy.stats().peak_resident_bytes, dataset + kept);
        assert_eq!(hits_and_misses(&roomy).1, 1);
    }

    #[test]
    fn a_load_drops_kept_classifications_before_any_dataset() {
        // Datasets "ball" and "other" with a budget of both and a little: the ball's kept
        // classification goes, not the ball, when the other dataset needs its room.
        let scene = sphere_scene(SOFT);
        let ball = scene.datasets()[0].resident_bytes();
        let others = super::tests::scene(1);
        let other = &others.datasets()[0];
        let store = VolumeStore::new(Some(ball + other.resident_bytes() + 8));
        render_through(&store, &scene);
        assert!(store.resident_bytes() > ball + 8, "kept");
        drop(store.get(other).unwrap());
        assert_eq!(store.resident_bytes(), ball + other.resident_bytes());
        render_through(&store, &scene);
        assert_eq!(store.stats().loads, 2, "the ball stayed resident");
        assert!(store.stats().peak_resident_bytes <= store.budget().unwrap());
    }

    #[test]
    fn many_threads_binding_through_the_store_never_exceed_the_budget() {
        let scene = sphere_scene(SOFT);
        let others = super::tests::scene(3);
        let ball = &scene.datasets()[0];
        let budget = ball.resident_bytes() + 2 * BYTES + 600;
        let store = VolumeStore::new(Some(budget));
        std::thread::scope(|scope| {
            for thread in 0..4usize {
                let (store, scene, others) = (&store, &scene, &others);
                scope.spawn(move || {
                    for i in 0..60usize {
                        if (i + thread) % 2 == 0 {
                            let v = store.get(ball).unwrap();
                            let caster = crate::render::BatchCaster::for_dataset_turn(scene, 0, &v).unwrap();
                            assert_eq!(caster.dataset(), 0);
                        } else {
                            drop(store.get(&others.datasets()[(i * 7 + thread) % 3]).unwrap());
                        }
                        assert!(store.resident_bytes() <= budget);
                    }
                });
            }
        });
        assert!(store.stats().peak_resident_bytes <= budget);
        assert!(store.stats().classification_hits > 0);
    }

    #[test]
    fn store_statistics_merge_by_summing_work_and_keeping_the_largest_peak() {
        let stats = |loads, bytes_loaded, peak_resident_bytes, loading_seconds, hits| StoreStats {
            loads,
            bytes_loaded,
            peak_resident_bytes,
            loading_seconds,
            classification_hits: hits,
            classification_misses: 2 * hits,
        };
        let mut a = stats(2, 10, 7, 0.5, 1);
        a.merge(&stats(1, 5, 9, 0.25, 3));
        assert_eq!(a, stats(3, 15, 9, 0.75, 4));
    }
}
