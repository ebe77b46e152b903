//! The farm's coordinator: it takes jobs from clients, validates each scene against the
//! headers its workers registered (it never reads a voxel), runs the intersection phase,
//! hands batches of piece tasks to the workers that hold each dataset, gathers their results
//! and composites the image with the same `trove-core` scheduler as local mode.
//!
//! * [`registry`]: the workers, their files and heartbeats.
//! * [`jobs`]: the job table, statuses, cancellation and results.
//! * [`state`]: jobs and results on disk (`--state-dir`), so a restart loses none.
//! * [`driver`]: one job from submission to image, band by band.
//! * [`api`]: the gRPC services (`Coordinator` for clients, `Membership` for workers).
//! * [`drain`]: what a stopping coordinator waits for.
//! * [`metrics`]: the Prometheus metrics, served by [`metrics::serve`] on a port of their own.
//! * [`run`]: the server as a library function over a bound listener and a shutdown signal,
//!   so tests start a whole farm in one process on `127.0.0.1:0`.
//!
//! Each service may require its own bearer token ([`FarmSecurity`]): the client token guards
//! `Coordinator`, the worker token `Membership` (and the coordinator presents it on its
//! `Cast` streams to workers). TLS, when configured, covers every connection.

pub mod api;
pub mod drain;
pub mod driver;
pub mod jobs;
pub mod metrics;
pub mod registry;
pub mod state;
pub mod stats;

use std::future::Future;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use thiserror::Error;
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tonic::service::interceptor::InterceptedService;
use trove_proto::auth::{RequireToken, Token};
use trove_proto::connect::Connector;
use trove_proto::tls::{CaCert, ServerTls};
use trove_proto::v1::coordinator_server::CoordinatorServer;
use trove_proto::v1::membership_server::MembershipServer;

pub use driver::DriverConfig;
#[cfg(debug_assertions)]
pub use driver::Fault;

/// Jobs a coordinator runs at once when not told: enough to keep a small farm's workers
/// busy across jobs, few enough that their bands and images (each bounded by
/// [`DriverConfig`]) stay within a modest machine.
pub const DEFAULT_MAX_JOBS: usize = 4;

/// How long a stopping coordinator lets its jobs finish when not told.
pub const DEFAULT_DRAIN_GRACE: Duration = Duration::from_secs(30);

/// How long connections still open after the drain (a client watching a job left running)
/// are given to close before the server stops without them.
const CLOSE_GRACE: Duration = Duration::from_secs(1);

/// How a coordinator runs.
#[derive(Clone, Debug)]
pub struct FarmConfig {
    /// How often workers send heartbeats; one that misses five counts as lost.
    pub heartbeat: Duration,
    /// How jobs treat workers.
    pub driver: DriverConfig,
    /// Jobs running at once, at most; later ones wait QUEUED, in order.
    pub max_jobs: usize,
    /// Where jobs and results are kept ([`state`]); `None`: in memory only, lost with the
    /// process.
    pub state_dir: Option<PathBuf>,
    /// How long a finished job and its files are kept before a sweep removes them.
    pub keep_results: Duration,
    /// Tokens and TLS.
    pub security: FarmSecurity,
    /// How long, once `shutdown` resolves, running jobs are given to finish.
    pub drain_grace: Duration,
}

/// How long finished jobs are kept when not told: a day.
pub const DEFAULT_KEEP_RESULTS: Duration = Duration::from_secs(86_400);

impl Default for FarmConfig {
    fn default() -> Self {
        FarmConfig {
            heartbeat: Duration::from_secs(1),
            driver: DriverConfig::default(),
            max_jobs: DEFAULT_MAX_JOBS,
            state_dir: None,
            keep_results: DEFAULT_KEEP_RESULTS,
            security: FarmSecurity::default(),
            drain_grace: DEFAULT_DRAIN_GRACE,
        }
    }
}

/// Why a coordinator stopped or could not start.
#[derive(Debug, Error)]
pub enum FarmError {
    /// The server failed.
    #[error(transparent)]
    Transport(#[from] tonic::transport::Error),
    /// The state store cannot be opened or read.
    #[error(transparent)]
    State(#[from] state::StateError),
    /// Opening the state store was interrupted.
    #[error("opening the state store failed: {0}")]
    Join(#[from] tokio::task::JoinError),
}

/// How often finished jobs past [`FarmConfig::keep_results`] are looked for: often enough
/// that none outlives its time by more than a tenth, at most once a minute.
fn sweep_every(keep: Duration) -> Duration {
    (keep / 10).clamp(Duration::from_millis(100), Duration::from_secs(60))
}

/// A coordinator's credentials; the default has none (plaintext, no tokens).
#[derive(Clone, Debug, Default)]
pub struct FarmSecurity {
    /// Serve over TLS with this certificate and key.
    pub tls: Option<ServerTls>,
    /// Reach workers over TLS, verifying their certificates against this CA.
    pub worker_ca: Option<CaCert>,
    /// Required of every `Coordinator` call (clients).
    pub client_token: Option<Token>,
    /// Required of every `Membership` call, and presented on `Cast` streams (workers).
    pub worker_token: Option<Token>,
}

/// Serves the job API and worker membership on `listener` until `shutdown` resolves, then
/// drains: new jobs are refused while those held finish, for at most
/// [`FarmConfig::drain_grace`] ([`drain`]). With a state folder, the jobs it holds that had
/// not ended are run again first, in submission order, and its finished jobs are still
/// served; jobs still running when the drain ends resume at the next start. gRPC health
/// (`grpc.health.v1`: SERVING while it takes jobs, NOT_SERVING once it drains) and server
/// reflection are served beside them, without a token; its metrics are
/// `config.driver.metrics`, for [`metrics::serve`] on another listener.
pub async fn run(
    listener: TcpListener,
    shutdown: impl Future<Output = ()>,
    config: FarmConfig,
) -> Result<(), FarmError> {
    let now = state::now_unix_ms();
    let opened = match config.state_dir.clone() {
        Some(dir) => Some(
            tokio::task::spawn_blocking(move || {
                let store = state::StateStore::open(&dir)?;
                let epoch = store.claim_epoch(now)?;
                let seq = store.last_job_seq()?;
                Ok::<_, state::StateError>((Arc::new(store), epoch, seq))
            })
            .await??,
        ),
        None => None,
    };
    let (store, epoch, seq) = match opened {
        Some((store, epoch, seq)) => (Some(store), epoch, seq),
        None => (None, now, 0),
    };
    let security = config.security;
    let connector = Connector::new(security.worker_ca, security.worker_token.clone());
    let farm = Arc::new(api::Farm {
        registry: Arc::new(registry::Registry::with(config.heartbeat, epoch, connector)),
        jobs: Arc::new(jobs::Jobs::new(epoch, seq, store.clone())),
        driver: config.driver,
        admission: jobs::Admission::new(config.max_jobs),
        drain: Arc::new(drain::Drain::default()),
    });
    if let Some(store) = &store {
        let resumer = farm.clone();
        let resumed = tokio::task::spawn_blocking(move || api::resume(&resumer)).await??;
        tracing::info!(path = %store.path().display(), resumed, "state store opened");
    }
    let sweeper = {
        let (jobs, keep) = (farm.jobs.clone(), config.keep_results);
        tokio::spawn(async move {
            let mut every = tokio::time::interval(sweep_every(keep));
            every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                every.tick().await;
                let jobs = jobs.clone();
                match tokio::task::spawn_blocking(move || jobs.sweep(keep)).await {
                    Ok(Ok(0)) => {}
                    Ok(Ok(removed)) => tracing::info!(removed, "finished jobs past their keep time removed"),
                    Ok(Err(e)) => tracing::error!(error = %e, "sweeping finished jobs failed"),
                    Err(e) => tracing::error!(error = %e, "sweeping finished jobs failed"),
                }
            }
        })
    };
    farm.driver.metrics.observe(&farm.jobs, &farm.registry);
    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<CoordinatorServer<api::CoordinatorService>>().await;
    health.set_serving::<MembershipServer<api::MembershipService>>().await;
    let (reflection_v1, reflection_v1alpha) = trove_proto::reflection::services();
    let limit = trove_proto::MAX_MESSAGE_BYTES;
    let coordinator = InterceptedService::new(
        CoordinatorServer::new(api::CoordinatorService(farm.clone()))
            .max_decoding_message_size(limit)
            .max_encoding_message_size(limit),
        RequireToken::new(security.client_token),
    );
    let membership = InterceptedService::new(
        MembershipServer::new(api::MembershipService(farm.clone())).max_decoding_message_size(limit),
        RequireToken::new(security.worker_token),
    );
    let (stop, stopped) = oneshot::channel::<()>();
    // Health and reflection answer without a token: probes and generic clients ask them.
    let serve = trove_proto::connect::server(security.tls.as_ref())?
        .add_service(health_service)
        .add_optional_service(reflection_v1)
        .add_optional_service(reflection_v1alpha)
        .add_service(coordinator)
        .add_service(membership)
        .serve_with_incoming_shutdown(trove_proto::connect::incoming(listener), async {
            let _ = stopped.await;
        });
    tokio::pin!(serve);
    tokio::select! {
        served = &mut serve => {
            sweeper.abort();
            return Ok(served?);
        }
        () = shutdown => {}
    }
    farm.drain.begin();
    // Taking no new jobs: a load balancer's probe sends them elsewhere.
    health.set_service_status("", tonic_health::ServingStatus::NotServing).await;
    health.set_not_serving::<CoordinatorServer<api::CoordinatorService>>().await;
    tracing::info!(grace = ?config.drain_grace, "draining: new jobs are refused; the jobs held may finish");
    tokio::select! {
        served = &mut serve => {
            sweeper.abort();
            return Ok(served?);
        }
        left = farm.drain.wait(config.drain_grace) => match left {
            0 => tracing::info!("drained: every job ended"),
            n => tracing::warn!(jobs = n, "the drain's grace ended with jobs still running; stopping without them"),
        },
    }
    let _ = stop.send(());
    // Connections still open (a watcher of a job left running) are not waited for long.
    let closed = tokio::time::timeout(CLOSE_GRACE, serve).await.unwrap_or(Ok(()));
    sweeper.abort();
    Ok(closed?)
}
