//! The workers the coordinator knows: their addresses, the files they hold, when they last
//! sent a heartbeat, and how much work each has in flight.
//!
//! A worker is *alive* while its last heartbeat is recent ([`Registry::lost_after`]); jobs
//! dispatch only to alive workers. The files of alive workers form the catalog against which
//! submitted scenes are validated: the coordinator never opens a dataset file itself.
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

use trove_core::dataset::{Catalog, DatasetError, FileInfo, FileKind};
use trove_proto::connect::{AuthChannel, ConnectError, Connector};
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
    next_id: AtomicU64,
    /// Changes whenever a worker registers or leaves, so a job's dispatcher knows when to
    /// look its datasets' holders up again instead of on every batch.
    generation: AtomicU64,
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

impl Registry {
    /// An empty registry whose workers send a heartbeat every `heartbeat`, reached over
    /// plaintext without a token.
    pub fn new(heartbeat: Duration) -> Registry {
        Registry::with_connector(heartbeat, Connector::default())
    }

    /// As [`Registry::new`], reaching workers through `connector` (TLS, the worker token).
    pub fn with_connector(heartbeat: Duration, connector: Connector) -> Registry {
        Registry {
            state: Mutex::new(State::default()),
            heartbeat,
            next_id: AtomicU64::new(1),
            generation: AtomicU64::new(0),
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

    /// Adds a worker (replacing any earlier registration from the same address, which then
    /// stops being known) and returns its id.
    pub fn register(&self, request: pb::RegisterRequest) -> Result<String, ConnectError> {
        let endpoint =
            self.connector.endpoint(&self.connector.url_for(&request.address))?.connect_timeout(CONNECT_DEADLINE);
        let id = format!("w{}", self.next_id.fetch_add(1, Ordering::Relaxed));
        let entry = WorkerEntry {
            id: id.clone(),
            address: request.address.clone(),
            files: request.files.into_iter().map(|f| (f.key.clone(), f)).collect(),
            threads: request.threads.max(1),
            channel: self.connector.authorize(endpoint.connect_lazy()),
            in_flight: Arc::new(AtomicU64::new(0)),
            done: Arc::new(AtomicU64::new(0)),
            last_heartbeat: Instant::now(),
            leaving: false,
        };
        let mut state = lock(&self.state);
        let lost_after = self.lost_after();
        state
            .workers
            .retain(|_, w| w.address != request.address && !(w.leaving && w.last_heartbeat.elapsed() > lost_after));
        tracing::info!(worker = %id, address = %entry.address, files = entry.files.len(), "worker registered");
        state.workers.insert(id.clone(), entry);
        self.generation.fetch_add(1, Ordering::Release);
        Ok(id)
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
