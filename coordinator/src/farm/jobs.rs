//! The jobs a coordinator holds: each one's status (watched by clients), its cancellation
//! signal and, once it succeeded, its result files.
//!
//! Finished jobs are kept, most recent first, up to [`KEEP_FINISHED`]; older ones are
//! forgotten (their results too), so a long-lived coordinator's memory stays bounded.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use tokio::sync::watch;
use trove_proto::v1 as pb;

/// Finished jobs kept for `GetResult` and `WatchJob`.
pub const KEEP_FINISHED: usize = 32;

/// A finished job's files.
#[derive(Debug)]
pub struct JobOutput {
    /// The 8-bit image.
    pub png: Vec<u8>,
    /// The unquantised image, when the job asked for it.
    pub pfm: Option<Vec<u8>>,
    /// Statistics (SPEC §5 plus the farm's).
    pub stats_json: Vec<u8>,
}

/// One job.
pub struct Job {
    /// Its id.
    pub id: String,
    status: watch::Sender<pb::JobStatus>,
    cancel: watch::Sender<bool>,
    output: Mutex<Option<Arc<JobOutput>>>,
}

impl Job {
    /// The status now.
    pub fn status(&self) -> pb::JobStatus {
        self.status.borrow().clone()
    }

    /// Changes the status and tells every watcher.
    pub fn update(&self, f: impl FnOnce(&mut pb::JobStatus)) {
        self.status.send_modify(f);
    }

    /// A receiver of every status change.
    pub fn watch(&self) -> watch::Receiver<pb::JobStatus> {
        self.status.subscribe()
    }

    /// Asks the job to stop; returns false when it had already ended.
    pub fn cancel(&self) -> bool {
        if is_final(self.status().state()) {
            return false;
        }
        self.cancel.send_replace(true);
        true
    }

    /// A receiver that turns true when the job is cancelled.
    pub fn cancelled(&self) -> watch::Receiver<bool> {
        self.cancel.subscribe()
    }

    /// The result files, once the job succeeded.
    pub fn output(&self) -> Option<Arc<JobOutput>> {
        lock(&self.output).clone()
    }

    /// Stores the result files.
    pub fn set_output(&self, output: JobOutput) {
        *lock(&self.output) = Some(Arc::new(output));
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Whether a job in `state` has ended.
pub fn is_final(state: pb::JobState) -> bool {
    matches!(state, pb::JobState::Succeeded | pb::JobState::Failed | pb::JobState::Cancelled)
}

/// Every job the coordinator holds.
#[derive(Default)]
pub struct Jobs {
    state: Mutex<JobsState>,
    next: AtomicU64,
}

#[derive(Default)]
struct JobsState {
    jobs: HashMap<String, Arc<Job>>,
    finished: VecDeque<String>,
}

impl Jobs {
    /// A new queued job.
    pub fn create(&self) -> Arc<Job> {
        let id = format!("job-{}", self.next.fetch_add(1, Ordering::Relaxed) + 1);
        let status = pb::JobStatus { job_id: id.clone(), state: pb::JobState::Queued as i32, ..Default::default() };
        let job = Arc::new(Job {
            id: id.clone(),
            status: watch::channel(status).0,
            cancel: watch::channel(false).0,
            output: Mutex::new(None),
        });
        lock(&self.state).jobs.insert(id, job.clone());
        job
    }

    /// The job `id`, if held.
    pub fn get(&self, id: &str) -> Option<Arc<Job>> {
        lock(&self.state).jobs.get(id).cloned()
    }

    /// Notes that `id` ended, forgetting the oldest finished jobs beyond [`KEEP_FINISHED`].
    pub fn finished(&self, id: &str) {
        let mut state = lock(&self.state);
        state.finished.push_back(id.to_string());
        while state.finished.len() > KEEP_FINISHED {
            if let Some(old) = state.finished.pop_front() {
                state.jobs.remove(&old);
            }
        }
    }
}
