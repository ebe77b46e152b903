//! A worker as a library function: scan the data root, serve `Worker.Cast` on a bound
//! listener, and stay registered with the coordinator until `shutdown` resolves. Beside
//! `Worker`, the listener serves gRPC health — NOT_SERVING until the coordinator has
//! accepted the worker's registration, and again whenever it forgets the worker — and
//! server reflection.

use std::future::Future;
use std::path::PathBuf;
use std::sync::atomic::AtomicU64;
use std::sync::Arc;

use thiserror::Error;
use tokio::net::TcpListener;
use tokio::sync::watch;
use tokio_stream::wrappers::TcpListenerStream;
use tonic_health::server::HealthReporter;
use tonic_health::ServingStatus;
use trove_core::render::VolumeStore;
use trove_proto::v1::worker_server::WorkerServer;

use crate::cast::CastService;
use crate::files::{DataFiles, ScanError};
use crate::membership::{self, Announcement};
use crate::metrics::{Metered, WorkerMetrics};

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
    /// Where the worker counts what it casts (served by [`crate::metrics::serve`]).
    pub metrics: Arc<WorkerMetrics>,
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
    let (registered, registration) = watch::channel(false);
    let me = Announcement {
        address,
        files: files.clone(),
        memory_budget: config.memory_budget,
        busy: busy.clone(),
        registered,
    };
    config.metrics.observe(&store);
    let service = Metered::new(CastService::new(files, store, busy), config.metrics.clone());
    let (health, health_service) = tonic_health::server::health_reporter();
    report_health(&health, false).await;
    let (reflection_v1, reflection_v1alpha) = trove_proto::reflection::services();
    let serve = tonic::transport::Server::builder()
        .add_service(health_service)
        .add_optional_service(reflection_v1)
        .add_optional_service(reflection_v1alpha)
        .add_service(WorkerServer::new(service).max_decoding_message_size(trove_proto::MAX_MESSAGE_BYTES))
        .serve_with_incoming_shutdown(TcpListenerStream::new(listener), shutdown);
    tokio::select! {
        served = serve => served?,
        () = membership::stay_registered(channel, me) => {}
        () = follow_registration(registration, health) => {}
    }
    Ok(())
}

/// The worker as a whole (service `""`, what a Kubernetes gRPC probe asks) and its `Worker`
/// service: SERVING when registered, NOT_SERVING otherwise.
async fn report_health(health: &HealthReporter, registered: bool) {
    let status = if registered { ServingStatus::Serving } else { ServingStatus::NotServing };
    health.set_service_status("", status).await;
    health.set_service_status(<WorkerServer<CastService> as tonic::server::NamedService>::NAME, status).await;
}

/// Keeps the health status in step with registration, for as long as the worker runs.
async fn follow_registration(mut registration: watch::Receiver<bool>, health: HealthReporter) {
    loop {
        let registered = *registration.borrow_and_update();
        report_health(&health, registered).await;
        if registration.changed().await.is_err() {
            // The membership task has ended, and with it the worker.
            return std::future::pending().await;
        }
    }
}
