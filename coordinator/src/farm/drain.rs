//! A coordinator's drain, on SIGTERM: it stops admitting jobs (`SubmitJob` answers
//! `UNAVAILABLE`, reason `UNAVAILABLE`, retryable), lets the jobs it holds finish within a
//! grace, and lingers briefly so their clients can fetch their results; then it stops. A job
//! still running when the grace ends is not waited for: a coordinator with a state store
//! resumes it after its restart.

use std::collections::HashSet;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::sync::Notify;
use tokio::time::Instant;
use tonic::Status;
use trove_proto::convert;
use trove_proto::v1 as pb;

use super::jobs::Job;

/// How long a drained coordinator still serves the results of the jobs that finished during
/// its drain, for clients that were watching them (at most what is left of the grace).
pub const RESULT_LINGER: Duration = Duration::from_secs(5);

/// What a drain waits for.
#[derive(Default)]
pub struct Drain {
    draining: AtomicBool,
    state: Mutex<DrainState>,
    changed: Notify,
}

#[derive(Default)]
struct DrainState {
    /// Jobs submitted and not ended.
    open: HashSet<String>,
    /// Jobs that succeeded during the drain and whose result no client fetched yet.
    unfetched: HashSet<String>,
}

fn lock(m: &Mutex<DrainState>) -> MutexGuard<'_, DrainState> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A submitted job, as a drain sees it: dropping it notes that the job ended.
pub struct Tracked {
    drain: Arc<Drain>,
    job: Arc<Job>,
}

impl Drop for Tracked {
    fn drop(&mut self) {
        let succeeded = self.job.status().state() == pb::JobState::Succeeded;
        let mut state = lock(&self.drain.state);
        state.open.remove(&self.job.id);
        if succeeded && self.drain.is_draining() {
            state.unfetched.insert(self.job.id.clone());
        }
        drop(state);
        self.drain.changed.notify_waiters();
    }
}

impl Drain {
    /// Whether new jobs are refused.
    pub fn is_draining(&self) -> bool {
        self.draining.load(Ordering::Acquire)
    }

    /// The refusal of a job submitted while draining.
    pub fn refusal() -> Status {
        let message = "this coordinator is stopping and takes no new jobs; submit again once it is back".to_string();
        convert::failure_status(convert::failure(pb::Reason::Unavailable, true, message))
    }

    /// Counts `job` as open until the returned guard is dropped (when the job has ended).
    pub fn track(self: &Arc<Self>, job: Arc<Job>) -> Tracked {
        lock(&self.state).open.insert(job.id.clone());
        Tracked { drain: self.clone(), job }
    }

    /// A client has fetched job `id`'s whole result.
    pub fn fetched(&self, id: &str) {
        if lock(&self.state).unfetched.remove(id) {
            self.changed.notify_waiters();
        }
    }

    /// Refuses new jobs from now on.
    pub fn begin(&self) {
        self.draining.store(true, Ordering::Release);
    }

    /// Waits until every open job has ended, for at most `grace`, then until their results
    /// are fetched, for at most [`RESULT_LINGER`] more within the grace; returns the jobs
    /// still open.
    pub async fn wait(&self, grace: Duration) -> usize {
        let deadline = Instant::now() + grace;
        if !self.wait_until(deadline, |s| s.open.is_empty()).await {
            return lock(&self.state).open.len();
        }
        let linger = deadline.min(Instant::now() + RESULT_LINGER);
        if !self.wait_until(linger, |s| s.unfetched.is_empty()).await {
            tracing::info!(jobs = lock(&self.state).unfetched.len(), "results not fetched during the drain");
        }
        0
    }

    /// Waits until `done` holds or `deadline` passes; whether it holds.
    async fn wait_until(&self, deadline: Instant, done: impl Fn(&DrainState) -> bool) -> bool {
        loop {
            let notified = self.changed.notified();
            tokio::pin!(notified);
            // Registered before the state is read, so a change between the two is not missed.
            notified.as_mut().enable();
            if done(&lock(&self.state)) {
                return true;
            }
            if tokio::time::timeout_at(deadline, notified).await.is_err() {
                return done(&lock(&self.state));
            }
        }
    }
}
