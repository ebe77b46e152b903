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

use tonic::transport::{Channel, Endpoint};
use trove_proto::v1 as pb;
use trove_proto::v1::membership_client::MembershipClient;

use crate::files::DataFiles;

/// Deadline of one membership call.
const CALL_DEADLINE: Duration = Duration::from_secs(5);
/// Longest wait between attempts to reach an unreachable coordinator.
const MAX_BACKOFF: Duration = Duration::from_secs(5);

/// The longest worker id a coordinator accepts.
pub const MAX_WORKER_ID_BYTES: usize = 128;

/// Checks a worker id as the coordinator will (1 to [`MAX_WORKER_ID_BYTES`] letters,
/// digits, `-`, `_`, `.`), so a bad `--worker-id` stops the worker at start instead of
/// being refused at every registration.
pub fn check_worker_id(id: &str) -> Result<(), String> {
    let usable = |b: u8| b.is_ascii_alphanumeric() || b"-_.".contains(&b);
    if id.is_empty() || id.len() > MAX_WORKER_ID_BYTES || !id.bytes().all(usable) {
        return Err(format!(
            "worker id `{id}` is not usable: expected 1 to {MAX_WORKER_ID_BYTES} letters, digits, '-', '_' or '.'"
        ));
    }
    Ok(())
}

/// What the worker tells the coordinator about itself.
pub struct Announcement {
    /// Its stable id: the same across coordinator restarts, so it gets its entry back.
    pub worker_id: String,
    /// Where the coordinator reaches this worker.
    pub address: String,
    /// The files it holds.
    pub files: Arc<DataFiles>,
    /// Its memory budget, if any.
    pub memory_budget: Option<u64>,
    /// Batches being cast right now.
    pub busy: Arc<AtomicU64>,
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
            worker_id: me.worker_id.clone(),
        };
        let registered = match client.register(request).await {
            Ok(r) => r.into_inner(),
            Err(status) if status.code() == tonic::Code::AlreadyExists => {
                // Another live worker holds this id: an operator's mistake, not a network
                // one. Said loudly, and retried slowly in case the other one goes away.
                tracing::error!(worker = %me.worker_id, message = status.message(), "registration refused; retrying");
                tokio::time::sleep(MAX_BACKOFF).await;
                continue;
            }
            Err(status) => {
                tracing::warn!(code = ?status.code(), message = status.message(), "cannot register; retrying");
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(MAX_BACKOFF);
                continue;
            }
        };
        backoff = Duration::from_millis(50);
        tracing::info!(worker = %registered.worker_id, "registered");
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
                    break;
                }
                Err(status) => tracing::warn!(code = ?status.code(), "heartbeat failed"),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn worker_ids_are_checked_as_the_coordinator_checks_them() {
        for good in ["trove-worker-0", "w.1_a", &"x".repeat(MAX_WORKER_ID_BYTES)] {
            assert!(check_worker_id(good).is_ok(), "{good}");
        }
        for bad in ["", "has space", "a/b", "ü", &"x".repeat(MAX_WORKER_ID_BYTES + 1)] {
            let e = check_worker_id(bad).unwrap_err();
            assert!(e.contains("letters, digits"), "{bad}: {e}");
        }
    }
}
