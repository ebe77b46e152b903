//! The jobs a coordinator holds: each one's status (watched by clients), its cancellation
//! signal and, once it succeeded, its result files.
//!
//! Finished jobs are kept, most recent first, up to [`KEEP_FINISHED`]; older ones are
//! forgotten (their results too), so a long-lived coordinator's memory stays bounded.
//! [`Admission`] runs at most a configured number of jobs at once; the others wait QUEUED
//! in submission order, each status saying its place.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{SystemTime, UNIX_EPOCH};

use tokio::sync::{watch, Notify};
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
    /// Its scene file's name, as submitted (for `trove jobs`).
    pub scene_name: String,
    /// When it was submitted.
    pub submitted: SystemTime,
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

    /// Its line in `ListJobs`.
    pub fn summary(&self) -> pb::JobSummary {
        let status = self.status.borrow();
        let since_epoch = self.submitted.duration_since(UNIX_EPOCH).unwrap_or_default();
        pb::JobSummary {
            job_id: self.id.clone(),
            scene_name: self.scene_name.clone(),
            state: status.state,
            pieces_done: status.pieces_done,
            pieces_total: status.pieces_total,
            queue_position: status.queue_position,
            submitted_unix_ms: since_epoch.as_millis() as u64,
        }
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
    /// A new queued job of the scene file named `scene_name`.
    pub fn create(&self, scene_name: &str) -> Arc<Job> {
        let id = format!("job-{}", self.next.fetch_add(1, Ordering::Relaxed) + 1);
        let status = pb::JobStatus { job_id: id.clone(), state: pb::JobState::Queued as i32, ..Default::default() };
        let job = Arc::new(Job {
            id: id.clone(),
            scene_name: scene_name.to_string(),
            submitted: SystemTime::now(),
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

    /// Every job held, oldest submission first.
    pub fn list(&self) -> Vec<pb::JobSummary> {
        let mut jobs: Vec<Arc<Job>> = lock(&self.state).jobs.values().cloned().collect();
        jobs.sort_by(|a, b| a.submitted.cmp(&b.submitted).then_with(|| a.id.cmp(&b.id)));
        jobs.iter().map(|j| j.summary()).collect()
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

/// Admission control: at most `max_running` jobs run at once; the others wait, QUEUED, in
/// the order they were submitted, their `queue_position` kept up to date (1 runs next).
pub struct Admission {
    state: Mutex<AdmissionState>,
    changed: Notify,
}

struct AdmissionState {
    max_running: usize,
    running: usize,
    waiting: VecDeque<Arc<Job>>,
}

impl AdmissionState {
    /// Writes every waiting job's place into its status.
    fn renumber(&self) {
        for (i, job) in self.waiting.iter().enumerate() {
            let position = i as u32 + 1;
            if job.status().queue_position != position {
                job.update(|s| s.queue_position = position);
            }
        }
    }
}

/// A running job's place among the `max_running`; dropping it lets the next job in.
pub struct Slot(Arc<Admission>);

impl Drop for Slot {
    fn drop(&mut self) {
        lock(&self.0.state).running -= 1;
        self.0.changed.notify_waiters();
    }
}

impl Admission {
    /// Room for `max_running` jobs at once (at least one).
    pub fn new(max_running: usize) -> Arc<Admission> {
        let state = AdmissionState { max_running: max_running.max(1), running: 0, waiting: VecDeque::new() };
        Arc::new(Admission { state: Mutex::new(state), changed: Notify::new() })
    }

    /// Puts `job` at the back of the queue; called as the job is submitted, so that the
    /// queue's order is the order of submission.
    pub fn enqueue(&self, job: Arc<Job>) {
        let mut state = lock(&self.state);
        state.waiting.push_back(job);
        state.renumber();
    }

    /// Jobs waiting now.
    pub fn waiting(&self) -> usize {
        lock(&self.state).waiting.len()
    }

    /// Waits until `job` (enqueued before) is at the front of the queue and a job's room is
    /// free, then takes it; `None` when the job is cancelled while it waits (it leaves the
    /// queue).
    pub async fn admit(self: &Arc<Self>, job: &Arc<Job>) -> Option<Slot> {
        let mut cancelled = job.cancelled();
        loop {
            let notified = self.changed.notified();
            tokio::pin!(notified);
            // Registered before the state is read, so a change between the two is not missed.
            notified.as_mut().enable();
            {
                let mut state = lock(&self.state);
                let first = state.waiting.front().is_some_and(|j| Arc::ptr_eq(j, job));
                if first && state.running < state.max_running {
                    state.waiting.pop_front();
                    state.running += 1;
                    job.update(|s| s.queue_position = 0);
                    state.renumber();
                    drop(state);
                    self.changed.notify_waiters();
                    return Some(Slot(self.clone()));
                }
            }
            tokio::select! {
                _ = &mut notified => {}
                _ = cancelled.wait_for(|c| *c) => {
                    let mut state = lock(&self.state);
                    state.waiting.retain(|j| !Arc::ptr_eq(j, job));
                    job.update(|s| s.queue_position = 0);
                    state.renumber();
                    drop(state);
                    self.changed.notify_waiters();
                    return None;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn jobs_wait_in_order_with_their_places_and_a_cancelled_one_leaves() {
        let (jobs, admission) = (Jobs::default(), Admission::new(1));
        let all: Vec<Arc<Job>> = (0..4).map(|i| jobs.create(&format!("s{i}.toml"))).collect();
        for job in &all {
            admission.enqueue(job.clone());
        }
        let places = || all.iter().map(|j| j.status().queue_position).collect::<Vec<_>>();
        assert_eq!(places(), [1, 2, 3, 4]);
        let first = admission.admit(&all[0]).await.expect("room for one");
        assert_eq!(places(), [0, 1, 2, 3]);
        // The third cannot pass the second, and the second waits for room.
        let third = tokio::spawn({
            let (admission, job) = (admission.clone(), all[2].clone());
            async move { admission.admit(&job).await.is_some() }
        });
        let fourth = tokio::spawn({
            let (admission, job) = (admission.clone(), all[3].clone());
            async move { admission.admit(&job).await.is_some() }
        });
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        assert!(all[3].cancel());
        assert!(!fourth.await.unwrap(), "a job cancelled while queued is not admitted");
        assert_eq!(places(), [0, 1, 2, 0]);
        assert!(!third.is_finished());
        drop(first);
        let second = admission.admit(&all[1]).await.expect("next in line");
        assert_eq!(places(), [0, 0, 1, 0]);
        drop(second);
        assert!(third.await.unwrap());
        assert_eq!(admission.waiting(), 0);
        let listed: Vec<(String, String)> = jobs.list().into_iter().map(|j| (j.job_id, j.scene_name)).collect();
        let expected: Vec<(String, String)> = all.iter().map(|j| (j.id.clone(), j.scene_name.clone())).collect();
        assert_eq!(listed, expected, "listed in submission order, with their scenes");
    }
}
