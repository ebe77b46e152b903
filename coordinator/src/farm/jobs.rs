//! The jobs a coordinator holds: each one's status (watched by clients), its cancellation
//! signal and, once it succeeded, its result files.
//!
//! With a state store (`--state-dir`), every job is written there when it is accepted, when
//! it starts and when it ends (its files with it); a finished job's files are then served
//! from the store, not kept in memory. Either way at most [`KEEP_FINISHED`] finished jobs
//! stay in memory, most recent first, and finished jobs older than the configured keep time
//! are swept from memory and store, so a long-lived coordinator's memory stays bounded.
//! Job ids are `job-<prefix>-<n>`: the prefix is the coordinator's start time (base 36
//! milliseconds, never repeated over one store), `n` counts on across restarts over a
//! store, so an old id never names a newer job.
//! [`Admission`] runs at most a configured number of jobs at once; the others wait QUEUED
//! in submission order, each status saying its place.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::sync::{mpsc, watch, Notify};
use trove_proto::v1 as pb;

use super::state::{now_unix_ms, JobRecord, StateError, StateStore};

/// Finished jobs kept in memory for `GetResult` and `WatchJob` (beyond them, only the state
/// store, when there is one, still answers).
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
    /// When it was submitted, in milliseconds since the Unix epoch.
    pub submitted_unix_ms: u64,
    /// When it ended, in milliseconds since the Unix epoch; 0 while it has not.
    finished_unix_ms: AtomicU64,
    /// Its scene file's name, as submitted (for `trove jobs`).
    pub scene_name: String,
    status: watch::Sender<pb::JobStatus>,
    cancel: watch::Sender<bool>,
    output: Mutex<Option<Arc<JobOutput>>>,
}

impl Job {
    fn new(
        id: String,
        scene_name: String,
        status: pb::JobStatus,
        submitted_unix_ms: u64,
        finished_unix_ms: u64,
    ) -> Arc<Job> {
        Arc::new(Job {
            id,
            scene_name,
            submitted_unix_ms,
            finished_unix_ms: AtomicU64::new(finished_unix_ms),
            status: watch::channel(status).0,
            cancel: watch::channel(false).0,
            output: Mutex::new(None),
        })
    }

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

    /// The result files, once the job succeeded, while they are in memory (see
    /// [`Jobs::output`], which also asks the store).
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
        pb::JobSummary {
            job_id: self.id.clone(),
            scene_name: self.scene_name.clone(),
            state: status.state,
            pieces_done: status.pieces_done,
            pieces_total: status.pieces_total,
            queue_position: status.queue_position,
            submitted_unix_ms: self.submitted_unix_ms,
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

/// The shortest time between two statuses that [`forward_statuses`] sends one watcher
/// while a job runs.
pub const WATCH_INTERVAL: Duration = Duration::from_millis(20);

/// Sends a job's statuses from `updates` to one watcher (`tx`, each status wrapped by
/// `wrap`) until the job ends or the watcher leaves: the status now, then each change.
/// Progress arrives in bursts (every batch moves it), and a watcher needs the latest state,
/// not every step, so changes within [`WATCH_INTERVAL`] of the last status sent are
/// coalesced into one. The job's end is never held back: a client waits for it, and on a
/// short job a coalescing sleep was a fifth of the time a user waited.
pub async fn forward_statuses<T>(
    mut updates: watch::Receiver<pb::JobStatus>,
    tx: mpsc::Sender<T>,
    wrap: impl Fn(pb::JobStatus) -> T,
) {
    loop {
        let status = updates.borrow_and_update().clone();
        let done = is_final(status.state());
        if tx.send(wrap(status)).await.is_err() || done {
            return;
        }
        let next = tokio::time::Instant::now() + WATCH_INTERVAL;
        if updates.changed().await.is_err() {
            return;
        }
        while !is_final(updates.borrow().state()) {
            tokio::select! {
                _ = tokio::time::sleep_until(next) => break,
                changed = updates.changed() => {
                    if changed.is_err() {
                        // The job is gone: what it said last is still sent.
                        break;
                    }
                }
            }
        }
    }
}

/// `n` in base 36 (digits, then lower-case letters): short, sortable within one length.
pub fn base36(mut n: u64) -> String {
    let mut digits = Vec::new();
    loop {
        digits.push(b"0123456789abcdefghijklmnopqrstuvwxyz"[(n % 36) as usize]);
        n /= 36;
        if n == 0 {
            break;
        }
    }
    digits.reverse();
    String::from_utf8(digits).unwrap_or_default()
}

/// Every job the coordinator holds.
pub struct Jobs {
    state: Mutex<JobsState>,
    /// This run's id prefix.
    prefix: String,
    /// The last job number handed out.
    next: AtomicU64,
    store: Option<Arc<StateStore>>,
}

impl Default for Jobs {
    /// Memory only, ids prefixed by the time now.
    fn default() -> Jobs {
        Jobs::new(now_unix_ms(), 0, None)
    }
}

#[derive(Default)]
struct JobsState {
    jobs: HashMap<String, Arc<Job>>,
    finished: VecDeque<String>,
}

impl Jobs {
    /// A job table whose ids start with `epoch_ms` (a time never used by an earlier run over
    /// `store`) and count on from `last_seq`, written to `store` when there is one.
    pub fn new(epoch_ms: u64, last_seq: u64, store: Option<Arc<StateStore>>) -> Jobs {
        Jobs { state: Mutex::default(), prefix: base36(epoch_ms), next: AtomicU64::new(last_seq), store }
    }

    /// The state store, when jobs are kept on disk.
    pub fn store(&self) -> Option<&Arc<StateStore>> {
        self.store.as_ref()
    }

    fn queued(&self, id: String, scene_name: &str, submitted_unix_ms: u64) -> Arc<Job> {
        let status = pb::JobStatus { job_id: id.clone(), state: pb::JobState::Queued as i32, ..Default::default() };
        let job = Job::new(id.clone(), scene_name.to_string(), status, submitted_unix_ms, 0);
        lock(&self.state).jobs.insert(id, job.clone());
        job
    }

    /// A new queued job of the scene file named `scene_name`, in memory only.
    pub fn create(&self, scene_name: &str) -> Arc<Job> {
        let n = self.next.fetch_add(1, Ordering::Relaxed) + 1;
        self.queued(format!("job-{}-{n}", self.prefix), scene_name, now_unix_ms())
    }

    /// The jobs held in memory (every job not yet ended, and the latest finished ones), in
    /// no particular order; never blocks.
    pub fn held(&self) -> Vec<pb::JobSummary> {
        lock(&self.state).jobs.values().map(|j| j.summary()).collect()
    }

    /// Every job held, oldest submission first.
    /// With a state store, finished jobs no longer in memory (older ones, or ones from
    /// before a restart) are listed from it too (blocking, then).
    pub fn list(&self) -> Vec<pb::JobSummary> {
        let mut listed = self.held();
        if let Some(store) = &self.store {
            match store.jobs() {
                Ok(records) => {
                    let held: std::collections::HashSet<String> = listed.iter().map(|j| j.job_id.clone()).collect();
                    for record in records.into_iter().filter(|r| !held.contains(&r.job_id)) {
                        let status = record.status.unwrap_or_default();
                        // Only finished jobs leave memory; others are ones this run did not resume.
                        if is_final(status.state()) {
                            listed.push(pb::JobSummary {
                                job_id: record.job_id,
                                scene_name: record.scene_name,
                                state: status.state,
                                pieces_done: status.pieces_done,
                                pieces_total: status.pieces_total,
                                queue_position: 0,
                                submitted_unix_ms: record.submitted_unix_ms,
                            });
                        }
                    }
                }
                Err(e) => tracing::error!(error = %e, "cannot list the jobs of the state store"),
            }
        }
        listed.sort_by(|a, b| a.submitted_unix_ms.cmp(&b.submitted_unix_ms).then_with(|| a.job_id.cmp(&b.job_id)));
        listed
    }

    /// A new queued job of a validated submission, written to the store (when there is one)
    /// before it exists here, so that an id a client was given always survives a restart.
    /// Blocking: it commits to disk.
    pub fn submit(&self, scene_toml: &str, scene_name: &str, options: &pb::JobOptions) -> Result<Arc<Job>, StateError> {
        let seq = self.next.fetch_add(1, Ordering::Relaxed) + 1;
        let id = format!("job-{}-{seq}", self.prefix);
        let submitted = now_unix_ms();
        if let Some(store) = &self.store {
            let status = pb::JobStatus { job_id: id.clone(), state: pb::JobState::Queued as i32, ..Default::default() };
            store.put_job(&JobRecord {
                job_id: id.clone(),
                seq,
                scene_toml: scene_toml.to_string(),
                scene_name: scene_name.to_string(),
                options: Some(*options),
                status: Some(status),
                submitted_unix_ms: submitted,
                finished_unix_ms: 0,
            })?;
        }
        Ok(self.queued(id, scene_name, submitted))
    }

    /// A stored job that had not ended when the coordinator stopped, queued again under its id
    /// (it runs again from the start).
    pub fn resume(&self, record: &JobRecord) -> Arc<Job> {
        self.queued(record.job_id.clone(), &record.scene_name, record.submitted_unix_ms)
    }

    /// The job `id`: from memory, else (a finished job no longer in memory) from the store.
    pub fn get(&self, id: &str) -> Option<Arc<Job>> {
        if let Some(job) = lock(&self.state).jobs.get(id).cloned() {
            return Some(job);
        }
        let record = match self.store.as_ref()?.job(id) {
            Ok(record) => record?,
            Err(e) => {
                tracing::error!(job = %id, error = %e, "cannot read a job from the state store");
                return None;
            }
        };
        let mut status = record.status.clone().unwrap_or_default();
        // Only finished jobs leave memory; a record still QUEUED or RUNNING that is not
        // in memory is one this run did not resume (it cannot be followed).
        is_final(status.state()).then(|| {
            status.job_id = record.job_id.clone();
            Job::new(record.job_id, record.scene_name, status, record.submitted_unix_ms, record.finished_unix_ms)
        })
    }

    /// The files of job `job` once it succeeded: from memory while they are there, else read
    /// from the store (blocking).
    pub fn output(&self, job: &Job) -> Result<Option<Arc<JobOutput>>, StateError> {
        if let Some(output) = job.output() {
            return Ok(Some(output));
        }
        match (&self.store, job.status().state()) {
            (Some(store), pb::JobState::Succeeded) => Ok(store.result(&job.id)?.map(Arc::new)),
            _ => Ok(None),
        }
    }

    /// Writes that `job` left the queue to run (blocking).
    pub fn started(&self, job: &Job) -> Result<(), StateError> {
        let Some(store) = &self.store else { return Ok(()) };
        let mut status = job.status();
        status.state = pb::JobState::Running as i32;
        status.queue_position = 0;
        store.set_status(&job.id, &status, 0).map(drop)
    }

    /// Notes that `id` ended: writes its status and files to the store (then serves its
    /// files from there), and forgets the oldest finished jobs beyond [`KEEP_FINISHED`]
    /// (blocking). If the store cannot be written, the files stay in memory.
    pub fn finished(&self, id: &str) {
        let Some(job) = lock(&self.state).jobs.get(id).cloned() else { return };
        let now = now_unix_ms();
        job.finished_unix_ms.store(now, Ordering::Relaxed);
        if let Some(store) = &self.store {
            let output = job.output();
            match store.finish(id, &job.status(), now, output.as_deref()) {
                Ok(_) => *lock(&job.output) = None,
                Err(e) => tracing::error!(job = %id, error = %e, "cannot write the job's end to the state store"),
            }
        }
        let mut state = lock(&self.state);
        state.finished.push_back(id.to_string());
        while state.finished.len() > KEEP_FINISHED {
            if let Some(old) = state.finished.pop_front() {
                state.jobs.remove(&old);
            }
        }
    }

    /// Removes the jobs that ended more than `keep` ago, with their files, from memory and
    /// store (blocking); returns how many the store removed (memory's count when there is
    /// no store).
    pub fn sweep(&self, keep: Duration) -> Result<usize, StateError> {
        let cutoff = now_unix_ms().saturating_sub(keep.as_millis() as u64);
        let expired = |job: &Job| {
            let finished = job.finished_unix_ms.load(Ordering::Relaxed);
            finished != 0 && finished < cutoff
        };
        let forgotten = {
            let mut state = lock(&self.state);
            let JobsState { jobs, finished } = &mut *state;
            let before = finished.len();
            finished.retain(|id| !jobs.get(id).is_some_and(|j| expired(j)));
            jobs.retain(|_, j| !expired(j));
            before - finished.len()
        };
        match &self.store {
            Some(store) => Ok(store.sweep(cutoff)?.len()),
            None => Ok(forgotten),
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

    /// Takes `job` out of the queue without running it (a resumed job whose scene no
    /// longer plans).
    pub fn leave(&self, job: &Arc<Job>) {
        let mut state = lock(&self.state);
        state.waiting.retain(|j| !Arc::ptr_eq(j, job));
        job.update(|s| s.queue_position = 0);
        state.renumber();
        drop(state);
        self.changed.notify_waiters();
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
                    // Out of the queue and running in one change: no watcher ever sees a
                    // QUEUED job without its place.
                    job.update(|s| {
                        s.queue_position = 0;
                        s.state = pb::JobState::Running as i32;
                    });
                    state.renumber();
                    drop(state);
                    self.changed.notify_waiters();
                    return Some(Slot(self.clone()));
                }
            }
            tokio::select! {
                _ = &mut notified => {}
                _ = cancelled.wait_for(|c| *c) => {
                    self.leave(job);
                    return None;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn succeed(jobs: &Jobs, job: &Job, tag: u8) {
        job.set_output(JobOutput { png: vec![tag; 64], pfm: None, stats_json: b"{}".to_vec() });
        job.update(|s| s.state = pb::JobState::Succeeded as i32);
        jobs.finished(&job.id);
    }

    #[test]
    fn finished_jobs_are_served_from_the_store_across_restarts_until_swept() {
        let dir = trove_tests::scratch("jobs-store");
        let options = pb::JobOptions::default();
        let (first_id, ids) = {
            let store = Arc::new(StateStore::open(&dir).unwrap());
            let jobs = Jobs::new(store.claim_epoch(now_unix_ms()).unwrap(), store.last_job_seq().unwrap(), Some(store));
            let first = jobs.submit("# first", "first.toml", &options).unwrap();
            succeed(&jobs, &first, 1);
            assert!(first.output().is_none(), "a stored job's files leave memory");
            assert_eq!(jobs.output(&first).unwrap().unwrap().png, vec![1; 64], "and are read from the store");
            let mut ids = vec![first.id.clone()];
            for i in 0..KEEP_FINISHED {
                let job = jobs.submit("# more", "more.toml", &options).unwrap();
                succeed(&jobs, &job, i as u8);
                ids.push(job.id.clone());
            }
            // Out of memory, still in the store.
            let again = jobs.get(&first.id).expect("a finished job beyond memory");
            assert!(!Arc::ptr_eq(&again, &first));
            assert_eq!(again.status().state(), pb::JobState::Succeeded);
            assert_eq!(jobs.output(&again).unwrap().unwrap().png, vec![1; 64]);
            (first.id.clone(), ids)
        };
        // A restarted coordinator over the same store.
        let store = Arc::new(StateStore::open(&dir).unwrap());
        let jobs = Jobs::new(store.claim_epoch(now_unix_ms()).unwrap(), store.last_job_seq().unwrap(), Some(store));
        assert_eq!(jobs.get(&first_id).expect("served after a restart").status().state(), pb::JobState::Succeeded);
        let next = jobs.submit("# next", "next.toml", &options).unwrap();
        assert!(!ids.contains(&next.id), "{} was handed out before the restart", next.id);
        let number = |id: &str| id.rsplit('-').next().unwrap().parse::<u64>().unwrap();
        assert_eq!(number(&next.id), KEEP_FINISHED as u64 + 2, "the counter went on");
        // The sweep removes only what has ended, from store and memory.
        std::thread::sleep(Duration::from_millis(5));
        assert_eq!(jobs.sweep(Duration::from_millis(1)).unwrap(), ids.len());
        assert!(jobs.get(&first_id).is_none());
        assert_eq!(jobs.get(&next.id).expect("a queued job is kept").status().state(), pb::JobState::Queued);
    }

    /// On a paused clock: bursts of progress reach a watcher as one status, no sooner than
    /// [`WATCH_INTERVAL`] after the last, but the job's end arrives the moment it is set,
    /// even while the watcher waits out that interval.
    #[tokio::test(start_paused = true)]
    async fn a_watcher_gets_progress_coalesced_and_the_end_at_once() {
        let job = Jobs::default().create("s.toml");
        let (tx, mut rx) = mpsc::channel(16);
        let watcher = tokio::spawn(forward_statuses(job.watch(), tx, |s| s));
        assert_eq!(rx.recv().await.unwrap().state(), pb::JobState::Queued);
        let first_sent = tokio::time::Instant::now();
        job.update(|s| {
            s.state = pb::JobState::Running as i32;
            s.pieces_done = 1;
        });
        job.update(|s| s.pieces_done = 2);
        let progress = rx.recv().await.unwrap();
        assert_eq!(progress.pieces_done, 2, "the burst arrives as its latest state");
        assert_eq!(tokio::time::Instant::now() - first_sent, WATCH_INTERVAL);
        job.update(|s| s.pieces_done = 3);
        // Let the watcher start waiting out its interval before the job ends.
        for _ in 0..8 {
            tokio::task::yield_now().await;
        }
        let ended = tokio::time::Instant::now();
        job.update(|s| s.state = pb::JobState::Succeeded as i32);
        let last = rx.recv().await.unwrap();
        assert_eq!((last.state(), last.pieces_done), (pb::JobState::Succeeded, 3));
        assert_eq!(tokio::time::Instant::now(), ended, "the end is not held back");
        assert!(rx.recv().await.is_none(), "nothing follows the end");
        watcher.await.unwrap();
    }

    #[test]
    fn without_a_store_the_sweep_forgets_jobs_past_their_time() {
        let jobs = Jobs::default();
        let (old, fresh) = (jobs.create("old.toml"), jobs.create("fresh.toml"));
        assert_ne!(old.id, fresh.id);
        succeed(&jobs, &old, 1);
        assert!(old.output().is_some(), "without a store the files stay in memory");
        std::thread::sleep(Duration::from_millis(5));
        assert_eq!(jobs.sweep(Duration::from_millis(1)).unwrap(), 1);
        assert!(jobs.get(&old.id).is_none());
        assert!(jobs.get(&fresh.id).is_some(), "a job that has not ended stays");
        assert_eq!(jobs.sweep(Duration::from_secs(3600)).unwrap(), 0);
    }

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
