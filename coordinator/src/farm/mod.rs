//! The farm's coordinator: it takes jobs from clients, validates each scene against the
//! headers its workers registered (it never reads a voxel), runs the intersection phase,
//! hands batches of piece tasks to the workers that hold each dataset, gathers their results
//! and composites the image with the same `trove-core` scheduler as local mode.
//!
//! * [`registry`]: the workers, their files and heartbeats.
//! * [`jobs`]: the job table, statuses, cancellation and results.
//! * [`driver`]: one job from submission to image, band by band.
//! * [`api`]: the gRPC services (`Coordinator` for clients, `Membership` for workers).
//! * [`metrics`]: the Prometheus metrics, served by [`metrics::serve`] on a port of their own.
//! * [`run`]: the server as a library function over a bound listener and a shutdown signal,
//!   so tests start a whole farm in one process on `127.0.0.1:0`.

pub mod api;
pub mod driver;
pub mod jobs;
pub mod metrics;
pub mod registry;
pub mod stats;

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use tokio::net::TcpListener;
use tokio_stream::wrappers::TcpListenerStream;
use trove_proto::v1::coordinator_server::CoordinatorServer;
use trove_proto::v1::membership_server::MembershipServer;

pub use driver::DriverConfig;
#[cfg(debug_assertions)]
pub use driver::Fault;

/// Jobs a coordinator runs at once when not told: enough to keep a small farm's workers
/// busy across jobs, few enough that their bands and images (each bounded by
/// [`DriverConfig`]) stay within a modest machine.
pub const DEFAULT_MAX_JOBS: usize = 4;

/// How a coordinator runs.
#[derive(Clone, Debug)]
pub struct FarmConfig {
    /// How often workers send heartbeats; one that misses five counts as lost.
    pub heartbeat: Duration,
    /// How jobs treat workers.
    pub driver: DriverConfig,
    /// Jobs running at once, at most; later ones wait QUEUED, in order.
    pub max_jobs: usize,
}

impl Default for FarmConfig {
    fn default() -> Self {
        FarmConfig { heartbeat: Duration::from_secs(1), driver: DriverConfig::default(), max_jobs: DEFAULT_MAX_JOBS }
    }
}

/// Serves the job API and worker membership on `listener` until `shutdown` resolves, with
/// gRPC health (`grpc.health.v1`, SERVING while it runs) and server reflection beside them.
/// Its metrics are `config.driver.metrics`, for [`metrics::serve`] on another listener.
pub async fn run(
    listener: TcpListener,
    shutdown: impl Future<Output = ()>,
    config: FarmConfig,
) -> Result<(), tonic::transport::Error> {
    let farm = Arc::new(api::Farm {
        registry: Arc::new(registry::Registry::new(config.heartbeat)),
        jobs: Arc::new(jobs::Jobs::default()),
        driver: config.driver,
        admission: jobs::Admission::new(config.max_jobs),
    });
    farm.driver.metrics.observe(&farm.jobs, &farm.registry);
    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<CoordinatorServer<api::CoordinatorService>>().await;
    health.set_serving::<MembershipServer<api::MembershipService>>().await;
    let (reflection_v1, reflection_v1alpha) = trove_proto::reflection::services();
    let limit = trove_proto::MAX_MESSAGE_BYTES;
    tonic::transport::Server::builder()
        .add_service(health_service)
        .add_optional_service(reflection_v1)
        .add_optional_service(reflection_v1alpha)
        .add_service(
            CoordinatorServer::new(api::CoordinatorService(farm.clone()))
                .max_decoding_message_size(limit)
                .max_encoding_message_size(limit),
        )
        .add_service(MembershipServer::new(api::MembershipService(farm)).max_decoding_message_size(limit))
        .serve_with_incoming_shutdown(TcpListenerStream::new(listener), shutdown)
        .await
}
