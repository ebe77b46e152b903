//! Registering with each coordinator and staying alive in its eyes.
//!
//! A worker may serve several coordinators (`--coordinator` repeated): it runs one
//! [`stay_registered`] task per coordinator, each with its own registration, heartbeats,
//! re-registration after that coordinator restarts and [`deregister`] at shutdown, and
//! counts in one [`Registered`] how many know it now (its health is SERVING while at least
//! one does).
//!
//! Heartbeats come from this task alone, on the async runtime, while casting runs on its
//! own threads: a worker busy with a long batch still answers on time (Ballista's lesson:
//! heartbeats that waited behind work made healthy executors look dead). Every call has a
//! deadline; a coordinator that restarted answers `known = false` and the worker registers
//! again; one that is unreachable is retried with capped backoff until shutdown. One that
//! refuses the worker's token is not retried: no number of attempts would change its answer,
//! so that coordinator's task ends and says why ([`Refused`]); the worker stops only once
//! every coordinator it serves has refused it (server.rs). A worker that stops deregisters
//! ([`deregister`]), so that no new batch is sent to it.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::watch;
use trove_proto::connect::{AuthChannel, ConnectError, Connector};
use trove_proto::v1 as pb;
use trove_proto::v1::membership_client::MembershipClient;

use crate::files::DataFiles;

/// Deadline of one membership call.
const CALL_DEADLINE: Duration = Duration::from_secs(5);
/// Longest wait between attempts to reach an unreachable coordinator.
const MAX_BACKOFF: Duration = Duration::from_secs(5);

pub use trove_proto::MAX_WORKER_ID_BYTES;

/// Checks a worker id as the coordinator will (1 to [`MAX_WORKER_ID_BYTES`] letters,
/// digits, `-`, `_`, `.`), so a bad `--worker-id` stops the worker at start instead of
/// being refused at every registration.
pub fn check_worker_id(id: &str) -> Result<(), String> {
    if !trove_proto::is_usable_worker_id(id) {
        return Err(format!(
            "worker id `{id}` is not usable: expected 1 to {MAX_WORKER_ID_BYTES} letters, digits, '-', '_' or '.'"
        ));
    }
    Ok(())
}

/// How many coordinators know this worker now (registered, not yet forgotten): what the
/// worker's gRPC health reports as SERVING while at least one does.
pub type Registered = watch::Sender<usize>;

/// One coordinator's part of [`Registered`]: counted while it knows the worker, and given
/// back when its task ends.
struct Known<'a> {
    count: &'a Registered,
    known: bool,
}

impl Known<'_> {
    fn set(&mut self, known: bool) {
        if known != self.known {
            self.known = known;
            self.count.send_modify(|n| if known { *n += 1 } else { *n = n.saturating_sub(1) });
        }
    }
}

impl Drop for Known<'_> {
    fn drop(&mut self) {
        self.set(false);
    }
}

/// What the worker tells every coordinator about itself.
#[derive(Clone)]
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
    /// How many coordinators know this worker, shared by every coordinator's task.
    pub registered: Registered,
}

/// A coordinator refused this worker's credentials.
#[derive(Debug, thiserror::Error)]
#[error(
    "the coordinator at {coordinator} refused this worker ({code:?}): {message}; the worker presents the \
     token in its --token-file, which must hold the coordinator's --worker-token-file token"
)]
pub struct Refused {
    /// The coordinator's URL.
    pub coordinator: String,
    /// `UNAUTHENTICATED` or `PERMISSION_DENIED`.
    pub code: tonic::Code,
    /// The coordinator's reason.
    pub message: String,
}

/// The refusal in `status` from the coordinator at `url`, when it is one that retrying
/// cannot fix.
fn refusal(url: &str, status: &tonic::Status) -> Option<Refused> {
    matches!(status.code(), tonic::Code::Unauthenticated | tonic::Code::PermissionDenied).then(|| Refused {
        coordinator: url.to_string(),
        code: status.code(),
        message: status.message().to_string(),
    })
}

/// A lazily connecting channel to the coordinator at `url` (it reconnects by itself), every
/// call with a deadline and the connector's token.
pub fn channel(connector: &Connector, url: &str) -> Result<AuthChannel, ConnectError> {
    let endpoint = connector.endpoint(url)?.connect_timeout(CALL_DEADLINE).timeout(CALL_DEADLINE);
    Ok(connector.authorize(endpoint.connect_lazy()))
}

/// Registers with the coordinator at `url` (reached over `channel`), then heartbeats, until
/// it refuses the worker's credentials (the caller drops this future at shutdown). `id` is
/// set to the id the coordinator gave on every registration, for [`deregister`]; while the
/// coordinator knows the worker it is counted in `me.registered`.
pub async fn stay_registered(
    url: String,
    channel: AuthChannel,
    me: Announcement,
    id: watch::Sender<Option<String>>,
) -> Refused {
    let mut known = Known { count: &me.registered, known: false };
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
                if let Some(refused) = refusal(&url, &status) {
                    tracing::error!(coordinator = %url, code = ?status.code(), message = status.message(), "the coordinator refused this worker's token");
                    return refused;
                }
                tracing::warn!(code = ?status.code(), message = status.message(), "cannot register; retrying");
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(MAX_BACKOFF);
                continue;
            }
        };
        backoff = Duration::from_millis(50);
        tracing::info!(worker = %registered.worker_id, coordinator = %url, "registered");
        id.send_replace(Some(registered.worker_id.clone()));
        known.set(true);
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
                    known.set(false);
                    break;
                }
                Err(status) => {
                    if let Some(refused) = refusal(&url, &status) {
                        tracing::error!(coordinator = %url, code = ?status.code(), message = status.message(), "the coordinator refused this worker's token");
                        return refused;
                    }
                    tracing::warn!(code = ?status.code(), "heartbeat failed");
                }
            }
        }
    }
}

/// Tells the coordinator that worker `id` leaves. Failing is only logged: a coordinator that
/// cannot be reached will notice the missed heartbeats instead.
pub async fn deregister(channel: AuthChannel, id: String) {
    let mut client = MembershipClient::new(channel);
    match client.deregister(pb::DeregisterRequest { worker_id: id.clone() }).await {
        Ok(_) => tracing::info!(worker = %id, "deregistered"),
        Err(status) => {
            tracing::warn!(worker = %id, code = ?status.code(), message = status.message(), "cannot deregister")
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
