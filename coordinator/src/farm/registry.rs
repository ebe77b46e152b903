//! The workers the coordinator knows: their addresses, the files they hold, when they last
//! sent a heartbeat, and how much work each has in flight.
//!
//! A worker is *alive* while its last heartbeat is recent ([`Registry::lost_after`]); jobs
//! dispatch only to alive workers. The files of alive workers form the catalog against which
//! submitted scenes are validated: the coordinator never opens a dataset file itself.
//!
//! Workers are keyed by the id each one chooses (`trove-worker --worker-id`, else random per
//! process), so one that registers again after a coordinator restart is the same entry, and
//! a heartbeat can only ever name the worker that sent it. An id that a live worker at
//! another address holds is refused (two workers claim one id); a worker too old to send an
//! id is given one made of the coordinator's start time and a counter, unique across
//! restarts.
//!
//! A worker that deregisters (it is stopping) *leaves*: it is no longer a holder, in the
//! catalog or listed, so no new batch goes to it, but it stays alive for the jobs that have
//! batches on it until its heartbeats stop, so that the answers it still sends are taken.
//! Channels to workers are made by the registry's [`Connector`]: `https://` and the CA
//! when the coordinator verifies its workers' certificates, and the worker token on every
//! `Cast` stream.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use thiserror::Error;
use trove_core::dataset::{Catalog, DatasetError, FileInfo, FileKind};
use trove_proto::connect::{AuthChannel, ConnectError, Connector};
use trove_proto::convert;
use trove_proto::v1 as pb;

use super::jobs::base36;
use super::state::now_unix_ms;

/// One registered worker.
pub struct WorkerEntry {
    /// The worker's own id (or one assigned at registration).
    pub id: String,
    /// Where its `Worker` service listens.
    pub address: String,
    /// Files by key.
    pub files: HashMap<String, pb::DatasetFile>,
    /// Its rayon threads (how much it can cast at once).
    pub threads: u32,
    /// A lazily connecting channel to it.
    pub channel: AuthChannel,
    /// Batches handed to it and not answered yet, over all jobs.
    pub in_flight: Arc<AtomicU64>,
    /// Batches it has answered, over all jobs.
    pub done: Arc<AtomicU64>,
    last_heartbeat: Instant,
    /// It deregistered: no new batch goes to it.
    leaving: bool,
}

/// The coordinator's view of its workers.
pub struct Registry {
    state: Mutex<State>,
    heartbeat: Duration,
    /// This run's prefix of assigned ids.
    prefix: String,
    next_id: AtomicU64,
    /// Changes whenever a worker registers or leaves, so a job's dispatcher knows when to
    /// look its datasets' holders up again instead of on every batch.
    generation: AtomicU64,
    /// Counts the times a worker's batches in flight went down, over all jobs. Room that one
    /// job's answer freed may be taken by another job waiting for it: each driver watches
    /// this, so a worker shared by several jobs is never left idle while one of them has a
    /// batch ready (a `watch`, not a `Notify`: a driver busy at the moment of the change
    /// still sees it when it next waits).
    room: tokio::sync::watch::Sender<u64>,
    /// How channels to workers are made.
    connector: Connector,
}

#[derive(Default)]
struct State {
    workers: BTreeMap<String, WorkerEntry>,
}

fn lock(m: &Mutex<State>) -> MutexGuard<'_, State> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Heartbeats a worker may miss before it counts as lost.
const MISSED_HEARTBEATS: u32 = 5;

/// Deadline for connecting to a worker.
const CONNECT_DEADLINE: Duration = Duration::from_secs(5);

pub use trove_proto::MAX_WORKER_ID_BYTES;

/// Why a registration is refused.
#[derive(Debug, Error)]
pub enum RegisterError {
    /// The worker's address is not a usable URL authority.
    #[error("the worker's address `{address}` is not usable: {source}")]
    Address {
        /// The address it sent.
        address: String,
        /// Why.
        #[source]
        source: ConnectError,
    },
    /// The id is too long or holds characters other than letters, digits, `-`, `_`, `.`.
    #[error("worker id `{id}` is not usable: expected 1 to {MAX_WORKER_ID_BYTES} letters, digits, '-', '_' or '.'")]
    BadId {
        /// The id it sent.
        id: String,
    },
    /// A live worker at another address holds the id.
    #[error("worker id `{id}` is held by a live worker at {held_by}, not {address}: two workers claim one id (give each its own --worker-id)")]
    IdTaken {
        /// The id.
        id: String,
        /// The address of the worker that holds it.
        held_by: String,
        /// The address of the one refused.
        address: String,
    },
}

impl Registry {
    /// An empty registry whose workers send a heartbeat every `heartbeat`, reached over
    /// plaintext without a token; the ids it assigns start with the time now.
    pub fn new(heartbeat: Duration) -> Registry {
        Registry::with(heartbeat, now_unix_ms(), Connector::default())
    }

    /// As [`Registry::new`], the ids it assigns starting with `epoch_ms` (a time no earlier
    /// run of this coordinator used: the state store's claimed epoch), reaching workers
    /// through `connector` (TLS, the worker token).
    pub fn with(heartbeat: Duration, epoch_ms: u64, connector: Connector) -> Registry {
        Registry {
            state: Mutex::new(State::default()),
            heartbeat,
            prefix: base36(epoch_ms),
            next_id: AtomicU64::new(1),
            generation: AtomicU64::new(0),
            room: tokio::sync::watch::channel(0).0,
            connector,
        }
    }

    /// Whether worker `w` may be handed new batches: alive and not leaving.
    fn serving(&self, w: &WorkerEntry) -> bool {
        !w.leaving && w.last_heartbeat.elapsed() <= self.lost_after()
    }

    /// How often workers are asked to send heartbeats.
    pub fn heartbeat(&self) -> Duration {
        self.heartbeat
    }

    /// How long a silent worker still counts as alive.
    pub fn lost_after(&self) -> Duration {
        self.heartbeat * MISSED_HEARTBEATS
    }

    /// Adds a worker under the id it sent (or a new one when it sent none) and returns the
    /// id. The same id registering again replaces its entry, keeping its load counters (and
    /// its channel, at the same address); another worker's entry at the same address is
    /// dropped (it stops being known), and so are workers that left and went silent; an id
    /// a live worker at another address holds is refused.
    pub fn register(&self, request: pb::RegisterRequest) -> Result<String, RegisterError> {
        let endpoint = self
            .connector
            .endpoint(&self.connector.url_for(&request.address))
            .map_err(|source| RegisterError::Address { address: request.address.clone(), source })?
            .connect_timeout(CONNECT_DEADLINE);
        let id = match request.worker_id.as_str() {
            "" => format!("w-{}-{}", self.prefix, self.next_id.fetch_add(1, Ordering::Relaxed)),
            id if trove_proto::is_usable_worker_id(id) => id.to_string(),
            id => return Err(RegisterError::BadId { id: id.to_string() }),
        };
        let mut state = lock(&self.state);
        let lost_after = self.lost_after();
        let earlier = match state.workers.remove(&id) {
            Some(held)
                if held.address != request.address && !held.leaving && held.last_heartbeat.elapsed() <= lost_after =>
            {
                let (held_by, address) = (held.address.clone(), request.address.clone());
                state.workers.insert(id.clone(), held);
                return Err(RegisterError::IdTaken { id, held_by, address });
            }
            held => held,
        };
        state
            .workers
            .retain(|_, w| w.address != request.address && !(w.leaving && w.last_heartbeat.elapsed() > lost_after));
        let (channel, in_flight, done) = match earlier {
            Some(w) if w.address == request.address => (w.channel, w.in_flight, w.done),
            Some(w) => (self.connector.authorize(endpoint.connect_lazy()), w.in_flight, w.done),
            None => (self.connector.authorize(endpoint.connect_lazy()), Arc::default(), Arc::default()),
        };
        let entry = WorkerEntry {
            id: id.clone(),
            address: request.address,
            files: request.files.into_iter().map(|f| (f.key.clone(), f)).collect(),
            threads: request.threads.max(1),
            channel,
            in_flight,
            done,
            last_heartbeat: Instant::now(),
            leaving: false,
        };
        tracing::info!(worker = %id, address = %entry.address, files = entry.files.len(), "worker registered");
        state.workers.insert(id.clone(), entry);
        self.generation.fetch_add(1, Ordering::Release);
        drop(state);
        // A new worker is room: jobs waiting for a holder with room look again at once.
        self.room_freed();
        Ok(id)
    }

    /// Tells every job that a worker has room again (its batches in flight went down).
    pub fn room_freed(&self) {
        self.room.send_modify(|n| *n = n.wrapping_add(1));
    }

    /// A receiver that changes whenever some worker has room again ([`Registry::room_freed`]).
    pub fn watch_room(&self) -> tokio::sync::watch::Receiver<u64> {
        self.room.subscribe()
    }

    /// Takes worker `id` out of dispatch: it is stopping. Its streams stay usable while it
    /// finishes the batches it holds; returns false when the id is unknown.
    pub fn deregister(&self, id: &str) -> bool {
        let mut state = lock(&self.state);
        let Some(w) = state.workers.get_mut(id) else { return false };
        w.leaving = true;
        tracing::info!(worker = %id, address = %w.address, "worker deregistered");
        self.generation.fetch_add(1, Ordering::Release);
        true
    }

    /// A number that changes whenever the set of registered workers does.
    pub fn generation(&self) -> u64 {
        self.generation.load(Ordering::Acquire)
    }

    /// Records a heartbeat; false when the worker is unknown (it must register again).
    pub fn heartbeat_from(&self, id: &str) -> bool {
        match lock(&self.state).workers.get_mut(id) {
            Some(w) => {
                w.last_heartbeat = Instant::now();
                true
            }
            None => false,
        }
    }

    /// Whether worker `id` is registered and has sent a heartbeat recently.
    pub fn is_alive(&self, id: &str) -> bool {
        lock(&self.state).workers.get(id).is_some_and(|w| w.last_heartbeat.elapsed() <= self.lost_after())
    }

    /// What a dispatcher needs of an alive worker that takes batches: its channel and
    /// counters.
    pub fn handle(&self, id: &str) -> Option<WorkerHandle> {
        let state = lock(&self.state);
        let w = state.workers.get(id).filter(|w| self.serving(w))?;
        Some(WorkerHandle {
            id: w.id.clone(),
            channel: w.channel.clone(),
            threads: w.threads,
            in_flight: w.in_flight.clone(),
            done: w.done.clone(),
        })
    }

    /// The alive workers that take batches and hold every key in `keys` (every such worker
    /// when `keys` is empty: a generated dataset can be cast anywhere).
    pub fn holders(&self, keys: &[String]) -> Vec<String> {
        let state = lock(&self.state);
        state
            .workers
            .values()
            .filter(|w| self.serving(w))
            .filter(|w| keys.iter().all(|k| w.files.contains_key(k)))
            .map(|w| w.id.clone())
            .collect()
    }

    /// A snapshot of the files alive workers hold, to validate a scene against.
    pub fn catalog(&self) -> RegistryCatalog {
        let state = lock(&self.state);
        let mut files: HashMap<String, Held> = HashMap::new();
        for w in state.workers.values().filter(|w| self.serving(w)) {
            for (key, f) in &w.files {
                files
                    .entry(key.clone())
                    .and_modify(|held| {
                        if let Held::One(known) = held {
                            if known != f {
                                *held = Held::Disagree;
                            }
                        }
                    })
                    .or_insert_with(|| Held::One(f.clone()));
            }
        }
        RegistryCatalog { files }
    }

    /// Every registered worker that has not left, for `ListWorkers`.
    pub fn list(&self) -> Vec<pb::WorkerInfo> {
        let state = lock(&self.state);
        state
            .workers
            .values()
            .filter(|w| !w.leaving)
            .map(|w| pb::WorkerInfo {
                worker_id: w.id.clone(),
                address: w.address.clone(),
                files: w.files.len() as u32,
                file_bytes: w.files.values().map(|f| f.bytes).sum(),
                alive: w.last_heartbeat.elapsed() <= self.lost_after(),
                batches_in_flight: w.in_flight.load(Ordering::Relaxed),
                batches_done: w.done.load(Ordering::Relaxed),
                millis_since_heartbeat: w.last_heartbeat.elapsed().as_millis() as u64,
            })
            .collect()
    }
}

/// What a job's dispatcher holds of one worker.
#[derive(Clone)]
pub struct WorkerHandle {
    /// The worker's id.
    pub id: String,
    /// A channel to it.
    pub channel: AuthChannel,
    /// Its threads.
    pub threads: u32,
    /// Its batches in flight over all jobs.
    pub in_flight: Arc<AtomicU64>,
    /// Its batches answered over all jobs.
    pub done: Arc<AtomicU64>,
}

enum Held {
    One(pb::DatasetFile),
    /// Two workers registered different files under the same key.
    Disagree,
}

/// The files alive workers held when a job was submitted, as a catalog: scenes are
/// validated against their headers, and every source is remote.
pub struct RegistryCatalog {
    files: HashMap<String, Held>,
}

impl RegistryCatalog {
    /// The registration of `key`, for the workers' `CastOpen`.
    pub fn file(&self, key: &str) -> Option<&pb::DatasetFile> {
        match self.files.get(key) {
            Some(Held::One(f)) => Some(f),
            _ => None,
        }
    }
}

impl Catalog for RegistryCatalog {
    fn describe(&self, key: &str, kind: FileKind) -> Result<FileInfo, DatasetError> {
        match self.files.get(key) {
            Some(Held::One(f)) => convert::describe_remote(f, kind),
            Some(Held::Disagree) => Err(convert::workers_disagree(key)),
            None => Err(DatasetError::not_held(key)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const BEAT: Duration = Duration::from_millis(100);

    fn request(id: &str, address: &str, keys: &[&str]) -> pb::RegisterRequest {
        pb::RegisterRequest {
            address: address.to_string(),
            files: keys
                .iter()
                .map(|k| pb::DatasetFile { key: k.to_string(), bytes: 8, ..Default::default() })
                .collect(),
            threads: 2,
            memory_budget: 0,
            worker_id: id.to_string(),
        }
    }

    fn ids(registry: &Registry) -> Vec<(String, String)> {
        registry.list().into_iter().map(|w| (w.worker_id, w.address)).collect()
    }

    #[tokio::test]
    async fn the_same_id_registering_again_gets_its_entry_back() {
        let registry = Registry::new(BEAT);
        assert_eq!(registry.register(request("wk-a", "127.0.0.1:9001", &["a.raw"])).unwrap(), "wk-a");
        assert_eq!(registry.register(request("wk-b", "127.0.0.1:9002", &[])).unwrap(), "wk-b");
        let counters = registry.handle("wk-a").unwrap().in_flight;
        counters.fetch_add(3, Ordering::Relaxed);
        // The worker registers again (it was told `known = false`), now with another file.
        assert_eq!(registry.register(request("wk-a", "127.0.0.1:9001", &["b.raw"])).unwrap(), "wk-a");
        assert_eq!(
            ids(&registry),
            [("wk-a".to_string(), "127.0.0.1:9001".to_string()), ("wk-b".to_string(), "127.0.0.1:9002".to_string())]
        );
        assert_eq!(registry.handle("wk-a").unwrap().in_flight.load(Ordering::Relaxed), 3, "its load is kept");
        assert_eq!(registry.holders(&["b.raw".to_string()]), ["wk-a"]);
        assert!(registry.holders(&["a.raw".to_string()]).is_empty(), "its files are the new ones");
        assert!(registry.heartbeat_from("wk-a") && registry.heartbeat_from("wk-b"));

        // A coordinator restarted over the same workers: each id comes back as itself.
        let restarted = Registry::new(BEAT);
        assert!(!restarted.heartbeat_from("wk-a"), "unknown until it registers again");
        assert_eq!(restarted.register(request("wk-b", "127.0.0.1:9002", &[])).unwrap(), "wk-b");
        assert_eq!(restarted.register(request("wk-a", "127.0.0.1:9001", &[])).unwrap(), "wk-a");
        assert!(restarted.heartbeat_from("wk-a") && restarted.heartbeat_from("wk-b"));
    }

    #[tokio::test]
    async fn an_id_a_live_worker_holds_is_refused_from_another_address() {
        let registry = Registry::new(BEAT);
        registry.register(request("wk-a", "127.0.0.1:9001", &["a.raw"])).unwrap();
        let refused = registry.register(request("wk-a", "127.0.0.1:9009", &[])).unwrap_err();
        assert!(matches!(&refused, RegisterError::IdTaken { held_by, .. } if held_by == "127.0.0.1:9001"));
        let message = refused.to_string();
        assert!(message.contains("wk-a") && message.contains("127.0.0.1:9009") && message.contains("two workers"));
        assert_eq!(ids(&registry), [("wk-a".to_string(), "127.0.0.1:9001".to_string())], "the live one is kept");
        assert_eq!(registry.holders(&["a.raw".to_string()]), ["wk-a"]);

        // A different worker at the same address replaces the old entry, as a restarted
        // worker on the same port does.
        registry.register(request("wk-new", "127.0.0.1:9001", &[])).unwrap();
        assert_eq!(ids(&registry), [("wk-new".to_string(), "127.0.0.1:9001".to_string())]);
        assert!(!registry.heartbeat_from("wk-a"));

        // Once the holder is lost, the id may move (a worker rescheduled elsewhere).
        let quick = Registry::new(Duration::from_millis(1));
        quick.register(request("wk-a", "127.0.0.1:9001", &[])).unwrap();
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(quick.register(request("wk-a", "127.0.0.1:9002", &[])).unwrap(), "wk-a");
        assert_eq!(ids(&quick), [("wk-a".to_string(), "127.0.0.1:9002".to_string())]);

        for bad in ["has space", "semi;colon", &"x".repeat(MAX_WORKER_ID_BYTES + 1)] {
            let e = registry.register(request(bad, "127.0.0.1:9003", &[])).unwrap_err();
            assert!(matches!(e, RegisterError::BadId { .. }), "{bad}: {e}");
        }
    }

    #[tokio::test]
    async fn assigned_ids_are_never_reused_by_a_restarted_coordinator() {
        // The old bug: ids `w1, w2, …` per process. Worker X got `w1` from the first run and
        // kept heartbeating as `w1` after the restart, while the new run gave `w1` to Y: X
        // was answered `known` forever and never registered again.
        let first = Registry::with(BEAT, 1_700_000_000_000, Connector::default());
        let x = first.register(request("", "127.0.0.1:9001", &["a.raw"])).unwrap();
        let restarted = Registry::with(BEAT, 1_700_000_000_001, Connector::default());
        let y = restarted.register(request("", "127.0.0.1:9002", &[])).unwrap();
        assert_ne!(x, y);
        assert!(!restarted.heartbeat_from(&x), "X is told to register again");
        let x_again = restarted.register(request("", "127.0.0.1:9001", &["a.raw"])).unwrap();
        assert!(x_again != x && x_again != y && x_again.starts_with("w-"), "{x_again}");
        assert!(restarted.heartbeat_from(&x_again) && restarted.heartbeat_from(&y));
        assert_eq!(restarted.list().len(), 2);
    }
}
