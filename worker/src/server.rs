//! A worker as a library function: scan the data root, serve `Worker.Cast` on a bound
//! listener, and stay registered with every coordinator it is given until `shutdown`
//! resolves; then drain: deregister from each, stop taking streams, finish the batches
//! held, and return. Beside `Worker`, the listener serves gRPC health — SERVING while at
//! least one coordinator has accepted the worker's registration and not forgotten it,
//! NOT_SERVING otherwise and while the worker drains — and server reflection.
//!
//! Several coordinators share one worker's dataset store, `Cast` service (its stream and
//! batch caps hold over all of them) and busy count; only membership is per coordinator. A
//! coordinator that refuses the worker's token ends its own membership task, logged as an
//! error; the worker goes on serving the others, and stops with the refusal only when every
//! coordinator has refused it. One misconfigured coordinator out of many then costs its own
//! jobs only, instead of taking every worker from the others.

use std::future::Future;
use std::hash::{BuildHasher, Hasher};
use std::path::PathBuf;
use std::sync::atomic::AtomicU64;
use std::sync::Arc;
use std::time::Duration;

use thiserror::Error;
use tokio::net::TcpListener;
use tokio::sync::{oneshot, watch};
use tokio::task::JoinSet;
use tonic::service::interceptor::InterceptedService;
use tonic_health::server::HealthReporter;
use tonic_health::ServingStatus;
use tracing::Instrument;
use trove_core::render::VolumeStore;
use trove_proto::auth::{RequireToken, Token};
use trove_proto::connect::{self, ConnectError, Connector};
use trove_proto::tls::{CaCert, ServerTls};
use trove_proto::v1::worker_server::WorkerServer;

use crate::cast::{default_max_batches, CastService, DEFAULT_MAX_STREAMS};
use crate::files::{DataFiles, ScanError};
use crate::membership::{self, Announcement, Refused};
use crate::metrics::{Metered, WorkerMetrics};

/// Longest a stopping worker spends finishing the batches it holds; a Kubernetes pod has 30 s
/// between SIGTERM and SIGKILL unless told otherwise.
pub const DRAIN_GRACE: Duration = Duration::from_secs(25);

/// How a worker runs.
#[derive(Clone, Debug)]
pub struct WorkerConfig {
    /// The URLs of the coordinators it serves, e.g. `http://127.0.0.1:7000` (`https://` for
    /// TLS): at least one, each once.
    pub coordinators: Vec<String>,
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
    /// Tokens and TLS.
    pub security: WorkerSecurity,
    /// `Cast` streams served at once, at most; one more is refused as busy.
    pub max_streams: usize,
    /// Batches held at once (queued or being cast) over every coordinator and job; one more
    /// is refused as busy unless its job has less than its share.
    pub max_batches: usize,
    /// Where the worker counts what it casts (served by [`crate::metrics::serve`]).
    pub metrics: Arc<WorkerMetrics>,
}

impl WorkerConfig {
    /// A worker of the coordinator at `coordinator` over `data_root`, with no budget, no
    /// token, no TLS and the default stream and batch caps (add coordinators to
    /// `coordinators` to serve several).
    pub fn new(coordinator: impl Into<String>, data_root: impl Into<PathBuf>) -> WorkerConfig {
        WorkerConfig {
            coordinators: vec![coordinator.into()],
            advertise: None,
            data_root: data_root.into(),
            memory_budget: None,
            security: WorkerSecurity::default(),
            max_streams: DEFAULT_MAX_STREAMS,
            max_batches: default_max_batches(),
            worker_id: None,
            metrics: Arc::default(),
        }
    }
}

/// A worker's credentials; the default has none (plaintext, no tokens).
#[derive(Clone, Debug, Default)]
pub struct WorkerSecurity {
    /// The worker token: presented to the coordinator's `Membership` service, and required
    /// of every `Cast` stream (the coordinator presents the same token).
    pub token: Option<Token>,
    /// Serve `Worker` over TLS with this certificate and key.
    pub tls: Option<ServerTls>,
    /// The CA that signed the coordinator's certificate (an `https://` coordinator).
    pub coordinator_ca: Option<CaCert>,
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
    /// The listener or its TLS configuration is unusable.
    #[error(transparent)]
    Transport(#[from] tonic::transport::Error),
    /// The coordinator's URL is unusable.
    #[error(transparent)]
    Connect(#[from] ConnectError),
    /// The coordinator refused the worker's token (the only one it serves).
    #[error(transparent)]
    Refused(#[from] Refused),
    /// Every coordinator it serves refused the worker's token.
    #[error("all {count} coordinators refused this worker; the first: {first}")]
    AllRefused {
        /// How many coordinators it serves.
        count: usize,
        /// The first refusal.
        #[source]
        first: Refused,
    },
    /// No coordinator, or one listed twice.
    #[error("{0}")]
    Coordinators(String),
    /// The listener has no local address.
    #[error("the listener has no address: {0}")]
    Listener(#[source] std::io::Error),
    /// Scanning was interrupted.
    #[error("scanning the data root failed: {0}")]
    Join(#[from] tokio::task::JoinError),
}

/// Serves until `shutdown` resolves, then drains (at most [`DRAIN_GRACE`]).
pub async fn run(
    listener: TcpListener,
    shutdown: impl Future<Output = ()>,
    config: WorkerConfig,
) -> Result<(), WorkerError> {
    let address = match &config.advertise {
        Some(a) => a.clone(),
        None => listener.local_addr().map_err(WorkerError::Listener)?.to_string(),
    };
    check_coordinators(&config.coordinators)?;
    let security = config.security;
    let connector = Connector::new(security.coordinator_ca, security.token.clone());
    let channels = config
        .coordinators
        .iter()
        .map(|url| Ok((url.clone(), membership::channel(&connector, url)?)))
        .collect::<Result<Vec<_>, ConnectError>>()?;
    let mut builder = connect::server(security.tls.as_ref())?;
    let root = config.data_root.clone();
    let files = Arc::new(tokio::task::spawn_blocking(move || DataFiles::scan(&root)).await??);
    let (count, bytes) = files.totals();
    tracing::info!(root = %files.root().display(), files = count, bytes, "data root scanned");
    let store = VolumeStore::new(config.memory_budget);
    let busy = Arc::new(AtomicU64::new(0));
    let worker_id = config.worker_id.clone().unwrap_or_else(random_worker_id);
    tracing::info!(worker = %worker_id, %address, "worker starting");
    let (registered, registration) = watch::channel(0usize);
    let me = Announcement {
        worker_id,
        address,
        files: files.clone(),
        memory_budget: config.memory_budget,
        busy: busy.clone(),
        registered,
    };
    config.metrics.observe(&store);
    let service = CastService::new(files, store, busy, config.max_streams, config.max_batches);
    config.metrics.observe_scenes(service.scenes());
    let drain = service.drain();
    let worker = InterceptedService::new(
        WorkerServer::new(Metered::new(service, config.metrics.clone()))
            .max_decoding_message_size(trove_proto::MAX_MESSAGE_BYTES),
        RequireToken::new(security.token),
    );
    // Health and reflection answer without the token: probes and generic clients ask them.
    let (health, health_service) = tonic_health::server::health_reporter();
    report_health(&health, false).await;
    let (reflection_v1, reflection_v1alpha) = trove_proto::reflection::services();
    let (stop, stopped) = oneshot::channel::<()>();
    let serve = builder
        .add_service(health_service)
        .add_optional_service(reflection_v1)
        .add_optional_service(reflection_v1alpha)
        .add_service(worker)
        .serve_with_incoming_shutdown(trove_proto::connect::incoming(listener), async {
            let _ = stopped.await;
        });
    tokio::pin!(serve);
    // One membership task per coordinator; dropping the set (at shutdown) ends them all.
    let mut members = JoinSet::new();
    let mut ids = Vec::with_capacity(channels.len());
    for (url, channel) in &channels {
        let (id_tx, id) = watch::channel(None);
        ids.push(id);
        let span = tracing::info_span!("membership", coordinator = %url);
        members.spawn(membership::stay_registered(url.clone(), channel.clone(), me.clone(), id_tx).instrument(span));
    }
    drop(me);
    let count = channels.len();
    tokio::select! {
        served = &mut serve => return Ok(served?),
        mut refusals = every_refusal(&mut members) => {
            return Err(match count {
                1 => WorkerError::Refused(refusals.remove(0)),
                _ => WorkerError::AllRefused { count, first: refusals.remove(0) },
            });
        }
        () = follow_registration(registration, health.clone()) => {}
        () = shutdown => {}
    }
    // Draining: each coordinator takes this worker out first, so that it sends no new batch;
    // then new streams are refused, and each stream casts what it holds and ends.
    tracing::info!("stopping: deregistering, then finishing the batches held");
    members.abort_all();
    report_health(&health, false).await;
    let mut leaving = JoinSet::new();
    for ((url, channel), id) in channels.into_iter().zip(ids) {
        let id = id.borrow().clone();
        if let Some(id) = id {
            let span = tracing::info_span!("membership", coordinator = %url);
            leaving.spawn(membership::deregister(channel, id).instrument(span));
        }
    }
    while leaving.join_next().await.is_some() {}
    drain.begin();
    let _ = stop.send(());
    match tokio::time::timeout(DRAIN_GRACE, &mut serve).await {
        Ok(served) => served?,
        Err(_) => tracing::warn!(grace = ?DRAIN_GRACE, "streams still open after the drain's grace; stopping anyway"),
    }
    tracing::info!("stopped");
    Ok(())
}

/// At least one coordinator, none listed twice.
fn check_coordinators(urls: &[String]) -> Result<(), WorkerError> {
    if urls.is_empty() {
        return Err(WorkerError::Coordinators("a worker needs at least one coordinator (--coordinator URL)".into()));
    }
    for (i, url) in urls.iter().enumerate() {
        if urls[..i].contains(url) {
            return Err(WorkerError::Coordinators(format!("coordinator {url} is listed twice")));
        }
    }
    Ok(())
}

/// Waits until every membership task has ended (each coordinator refused the worker's
/// token), and returns their refusals, at least one.
async fn every_refusal(members: &mut JoinSet<Refused>) -> Vec<Refused> {
    let mut refusals = Vec::new();
    while let Some(ended) = members.join_next().await {
        match ended {
            Ok(refused) => refusals.push(refused),
            Err(e) => tracing::error!(error = %e, "a membership task ended abnormally"),
        }
    }
    if refusals.is_empty() {
        // Only panics ended them; the worker serves on, registered nowhere (NOT_SERVING).
        return std::future::pending().await;
    }
    refusals
}

/// The worker as a whole (service `""`, what a Kubernetes gRPC probe asks) and its `Worker`
/// service: SERVING when registered, NOT_SERVING otherwise.
async fn report_health(health: &HealthReporter, registered: bool) {
    let status = if registered { ServingStatus::Serving } else { ServingStatus::NotServing };
    health.set_service_status("", status).await;
    health.set_service_status(<WorkerServer<CastService> as tonic::server::NamedService>::NAME, status).await;
}

/// Keeps the health status in step with registration — SERVING while at least one
/// coordinator knows the worker — for as long as the worker runs.
async fn follow_registration(mut registration: watch::Receiver<usize>, health: HealthReporter) {
    loop {
        let registered = *registration.borrow_and_update() > 0;
        report_health(&health, registered).await;
        if registration.changed().await.is_err() {
            // Every membership task has ended, and with them the worker.
            return std::future::pending().await;
        }
    }
}
