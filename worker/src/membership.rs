//! Registering with the coordinator and staying alive in its eyes.
//!
//! Heartbeats come from this task alone, on the async runtime, while casting runs on its
//! own threads: a worker busy with a long batch still answers on time (Ballista's lesson:
//! heartbeats that waited behind work made healthy executors look dead). Every call has a
//! deadline; a coordinator that restarted answers `known = false` and the worker registers
//! again; one that is unreachable is retried with capped backoff until shutdown.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::watch;
use tonic::transport::{Channel, Endpoint};
use trove_proto::v1 as pb;
use trove_proto::v1::membership_client::MembershipClient;

use crate::files::DataFiles;

/// Deadline of one membership call.
const CALL_DEADLINE: Duration = Duration::from_secs(5);
/// Longest wait between attempts to reach an unreachable coordinator.
const MAX_BACKOFF: Duration = Duration::from_secs(5);

/// What the worker tells the coordinator about itself.
pub struct Announcement {
    /// Where the coordinator reaches this worker.
    pub address: String,
    /// The files it holds.
    pub files: Arc<DataFiles>,
    /// Its memory budget, if any.
    pub memory_budget: Option<u64>,
    /// Batches being cast right now.
    pub busy: Arc<AtomicU64>,
    /// True while the coordinator knows this worker (registered, not yet forgotten): what
    /// the worker's gRPC health reports as SERVING.
    pub registered: watch::Sender<bool>,
}

/// A lazily connecting channel to the coordinator at `url` (it reconnects by itself).
pub fn channel(url: &str) -> Result<Channel, tonic::transport::Error> {
    Ok(Endpoint::from_shared(url.to_string())?
        .connect_timeout(CALL_DEADLINE)
        .timeout(CALL_DEADLINE)
        .tcp_nodelay(true)
        .connect_lazy())
}

/// Registers, then heartbeats, forever (the caller drops this future at shutdown).
pub async fn stay_registered(channel: Channel, me: Announcement) {
    let mut client = MembershipClient::new(channel);
    let mut backoff = Duration::from_millis(50);
    loop {
        let request = pb::RegisterRequest {
            address: me.address.clone(),
            files: me.files.registration(),
            threads: rayon::current_num_threads() as u32,
            memory_budget: me.memory_budget.unwrap_or(0),
        };
        let registered = match client.register(request).await {
            Ok(r) => r.into_inner(),
            Err(status) => {
                tracing::warn!(code = ?status.code(), message = status.message(), "cannot register; retrying");
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(MAX_BACKOFF);
                continue;
            }
        };
        backoff = Duration::from_millis(50);
        tracing::info!(worker = %registered.worker_id, "registered");
        me.registered.send_replace(true);
        let every = Duration::from_millis(registered.heartbeat_millis.max(10) as u64);
        loop {
            tokio::time::sleep(every).await;
            let beat = pb::HeartbeatRequest {
                worker_id: registered.worker_id.clone(),
                batches_in_flight: me.busy.load(Ordering::Relaxed),
            };
            match client.heartbeat(beat).await {
                Ok(r) if r.get_ref().known => {}
                Ok(_) => {
                    tracing::warn!("the coordinator does not know this worker any more; registering again");
                    me.registered.send_replace(false);
                    break;
                }
                Err(status) => tracing::warn!(code = ?status.code(), "heartbeat failed"),
            }
        }
    }
}
