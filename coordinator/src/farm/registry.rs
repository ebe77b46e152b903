//! The workers the coordinator knows: their addresses, the files they hold, when they last
//! sent a heartbeat, and how much work each has in flight.
//!
//! A worker is *alive* while its last heartbeat is recent ([`Registry::lost_after`]); jobs
//! dispatch only to alive workers. The files of alive workers form the catalog against which
//! submitted scenes are validated: the coordinator never opens a dataset file itself.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tonic::transport::{Channel, Endpoint};
use trove_core::dataset::{Catalog, DatasetError, FileInfo, FileKind};
use trove_proto::convert;
use trove_proto::v1 as pb;

/// One registered worker.
pub struct WorkerEntry {
    /// Assigned at registration.
    pub id: String,
    /// Where its `Worker` service listens.
    pub address: String,
    /// Files by key.
    pub files: HashMap<String, pb::DatasetFile>,
    /// Its rayon threads (how much it can cast at once).
    pub threads: u32,
    /// A lazily connecting channel to it.
    pub channel: Channel,
    /// Batches handed to it and not answered yet, over all jobs.
    pub in_flight: Arc<AtomicU64>,
    /// Batches it has answered, over all jobs.
    pub done: Arc<AtomicU64>,
    last_heartbeat: Instant,
}

/// The coordinator's view of its workers.
pub struct Registry {
    state: Mutex<State>,
    heartbeat: Duration,
    next_id: AtomicU64,
    /// Changes whenever a worker registers, so a job's dispatcher knows when to look its
    /// datasets' holders up again instead of on every batch.
    generation: AtomicU64,
    /// Counts the times a worker's batches in flight went down, over all jobs. Room that one
    /// job's answer freed may be taken by another job waiting for it: each driver watches
    /// this, so a worker shared by several jobs is never left idle while one of them has a
    /// batch ready (a `watch`, not a `Notify`: a driver busy at the moment of the change
    /// still sees it when it next waits).
    room: tokio::sync::watch::Sender<u64>,
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

impl Registry {
    /// An empty registry whose workers send a heartbeat every `heartbeat`.
    pub fn new(heartbeat: Duration) -> Registry {
        Registry {
            state: Mutex::new(State::default()),
            heartbeat,
            next_id: AtomicU64::new(1),
            generation: AtomicU64::new(0),
            room: tokio::sync::watch::channel(0).0,
        }
    }

    /// How often workers are asked to send heartbeats.
    pub fn heartbeat(&self) -> Duration {
        self.heartbeat
    }

    /// How long a silent worker still counts as alive.
    pub fn lost_after(&self) -> Duration {
        self.heartbeat * MISSED_HEARTBEATS
    }

    /// Adds a worker (replacing any earlier registration from the same address, which then
    /// stops being known) and returns its id.
    pub fn register(&self, request: pb::RegisterRequest) -> Result<String, tonic::transport::Error> {
        let endpoint = Endpoint::from_shared(format!("http://{}", request.address))?
            .connect_timeout(CONNECT_DEADLINE)
            .tcp_nodelay(true);
        let id = format!("w{}", self.next_id.fetch_add(1, Ordering::Relaxed));
        let entry = WorkerEntry {
            id: id.clone(),
            address: request.address.clone(),
            files: request.files.into_iter().map(|f| (f.key.clone(), f)).collect(),
            threads: request.threads.max(1),
            channel: endpoint.connect_lazy(),
            in_flight: Arc::new(AtomicU64::new(0)),
            done: Arc::new(AtomicU64::new(0)),
            last_heartbeat: Instant::now(),
        };
        let mut state = lock(&self.state);
        state.workers.retain(|_, w| w.address != request.address);
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

    /// What a dispatcher needs of an alive worker: its channel and counters.
    pub fn handle(&self, id: &str) -> Option<WorkerHandle> {
        let state = lock(&self.state);
        let w = state.workers.get(id).filter(|w| w.last_heartbeat.elapsed() <= self.lost_after())?;
        Some(WorkerHandle {
            id: w.id.clone(),
            channel: w.channel.clone(),
            threads: w.threads,
            in_flight: w.in_flight.clone(),
            done: w.done.clone(),
        })
    }

    /// The alive workers that hold every key in `keys` (every alive worker when `keys` is
    /// empty: a generated dataset can be cast anywhere).
    pub fn holders(&self, keys: &[String]) -> Vec<String> {
        let state = lock(&self.state);
        state
            .workers
            .values()
            .filter(|w| w.last_heartbeat.elapsed() <= self.lost_after())
            .filter(|w| keys.iter().all(|k| w.files.contains_key(k)))
            .map(|w| w.id.clone())
            .collect()
    }

    /// A snapshot of the files alive workers hold, to validate a scene against.
    pub fn catalog(&self) -> RegistryCatalog {
        let state = lock(&self.state);
        let mut files: HashMap<String, Held> = HashMap::new();
        for w in state.workers.values().filter(|w| w.last_heartbeat.elapsed() <= self.lost_after()) {
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

    /// Every registered worker, for `ListWorkers`.
    pub fn list(&self) -> Vec<pb::WorkerInfo> {
        let state = lock(&self.state);
        state
            .workers
            .values()
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
    pub channel: Channel,
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
