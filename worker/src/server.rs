//! A worker as a library function: scan the data root, serve `Worker.Cast` on a bound
//! listener, and stay registered with the coordinator until `shutdown` resolves.

use std::future::Future;
use std::hash::{BuildHasher, Hasher};
use std::path::PathBuf;
use std::sync::atomic::AtomicU64;
use std::sync::Arc;

use thiserror::Error;
use tokio::net::TcpListener;
use tokio_stream::wrappers::TcpListenerStream;
use trove_core::render::VolumeStore;
use trove_proto::v1::worker_server::WorkerServer;

use crate::cast::CastService;
use crate::files::{DataFiles, ScanError};
use crate::membership::{self, Announcement};

/// How a worker runs.
#[derive(Clone, Debug)]
pub struct WorkerConfig {
    /// The coordinator's URL, e.g. `http://127.0.0.1:7000`.
    pub coordinator: String,
    /// The address the coordinator reaches this worker at; `None`: the listener's own
    /// address (right on one machine; a cluster passes the pod's address).
    pub advertise: Option<String>,
    /// The folder whose files the worker holds; it never reads outside it.
    pub data_root: PathBuf,
    /// Most voxel bytes kept resident.
    pub memory_budget: Option<u64>,
    /// The id this worker registers under, stable across coordinator restarts; `None`: a
    /// fresh random one for this process ([`random_worker_id`]).
    pub worker_id: Option<String>,
}

/// A worker id unlikely to be anyone else's: `worker-` and 64 random bits (from the
/// standard library's per-process random hash keys, mixed with the process id and the
/// time).
pub fn random_worker_id() -> String {
    let mut hasher = std::collections::hash_map::RandomState::new().build_hasher();
    hasher.write_u32(std::process::id());
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
    hasher.write_u128(now.as_nanos());
    format!("worker-{:016x}", hasher.finish())
}

/// Why a worker cannot run.
#[derive(Debug, Error)]
pub enum WorkerError {
    /// The data root cannot be read.
    #[error(transparent)]
    Scan(#[from] ScanError),
    /// The listener or the coordinator's URL is unusable.
    #[error(transparent)]
    Transport(#[from] tonic::transport::Error),
    /// The listener has no local address.
    #[error("the listener has no address: {0}")]
    Listener(#[source] std::io::Error),
    /// Scanning was interrupted.
    #[error("scanning the data root failed: {0}")]
    Join(#[from] tokio::task::JoinError),
}

/// Serves until `shutdown` resolves.
pub async fn run(
    listener: TcpListener,
    shutdown: impl Future<Output = ()>,
    config: WorkerConfig,
) -> Result<(), WorkerError> {
    let address = match &config.advertise {
        Some(a) => a.clone(),
        None => listener.local_addr().map_err(WorkerError::Listener)?.to_string(),
    };
    let root = config.data_root.clone();
    let files = Arc::new(tokio::task::spawn_blocking(move || DataFiles::scan(&root)).await??);
    let (count, bytes) = files.totals();
    tracing::info!(root = %files.root().display(), files = count, bytes, "data root scanned");
    let store = VolumeStore::new(config.memory_budget);
    let busy = Arc::new(AtomicU64::new(0));
    let channel = membership::channel(&config.coordinator)?;
    let worker_id = config.worker_id.clone().unwrap_or_else(random_worker_id);
    tracing::info!(worker = %worker_id, %address, "worker starting");
    let me = Announcement {
        worker_id,
        address,
        files: files.clone(),
        memory_budget: config.memory_budget,
        busy: busy.clone(),
    };
    let service = CastService::new(files, store, busy);
    let serve = tonic::transport::Server::builder()
        .add_service(WorkerServer::new(service).max_decoding_message_size(trove_proto::MAX_MESSAGE_BYTES))
        .serve_with_incoming_shutdown(TcpListenerStream::new(listener), shutdown);
    tokio::select! {
        served = serve => served?,
        () = membership::stay_registered(channel, me) => {}
    }
    Ok(())
}
