//! What a job counts while it runs — samples, loads, batches, bytes on the wire, each
//! worker's share — and how much of it the job's status shows. The status is published on
//! the driver's tick and when a band completes, not on every answer: a watcher sees it a few
//! times a second, and the driver does not rebuild it per batch.
//!
//! The tally also feeds the coordinator's Prometheus metrics: each accepted batch as it is
//! answered, and what the driver adds up in its fields (bytes on the wire, its event loop's
//! busy time) as deltas whenever the status is published and once more when the job ends,
//! so the driver itself never touches a metric.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use trove_core::render::{RenderStats, StoreStats};
use trove_proto::v1 as pb;

use super::super::jobs::Job;
use super::super::metrics::FarmMetrics;
use super::super::stats::{CoordinatorSeconds, FarmStats, WorkerStats};

/// A job's counters.
pub(super) struct Tally {
    pub stats: RenderStats,
    /// Samples shaded per object (scene index), as the workers report them.
    pub shaded: Vec<u64>,
    pub store: StoreStats,
    pub batches: u64,
    /// Batches refused as busy and sent again.
    pub refused: u64,
    pub wire_to: u64,
    pub wire_from: u64,
    /// Cast streams opened, and how many of their opens carried the scene.
    pub streams_opened: u64,
    pub scenes_sent: u64,
    workers: BTreeMap<String, WorkerStats>,
    pub cast_started: Option<Instant>,
    /// The coordinator's own time by stage.
    pub coordinator: CoordinatorSeconds,
    metrics: Arc<FarmMetrics>,
    /// What of `wire_to`, `wire_from` and `coordinator.event_loop` the metrics have.
    reported: (u64, u64, f64),
}

impl Tally {
    /// Nothing counted yet; the job's counts go to `metrics` too.
    pub fn new(metrics: Arc<FarmMetrics>) -> Tally {
        Tally {
            stats: RenderStats::default(),
            shaded: Vec::new(),
            store: StoreStats::default(),
            batches: 0,
            refused: 0,
            wire_to: 0,
            wire_from: 0,
            streams_opened: 0,
            scenes_sent: 0,
            workers: BTreeMap::new(),
            cast_started: None,
            coordinator: CoordinatorSeconds::default(),
            metrics,
            reported: (0, 0, 0.0),
        }
    }

    /// An answered batch of `tasks` tasks from `worker`, `latency` after it was sent.
    pub fn answered(&mut self, worker: &str, tasks: u64, latency: Duration, result: &pb::BatchResult) {
        self.metrics.answered(tasks, latency.as_secs_f64());
        self.batches += 1;
        self.stats.samples += result.samples;
        for (&object, &n) in &result.shading_evaluations {
            // A scene has at most 4096 objects; an index beyond that is a bad answer's.
            let object = object as usize;
            if object < trove_core::scene::MAX_OBJECTS {
                if self.shaded.len() <= object {
                    self.shaded.resize(object + 1, 0);
                }
                self.shaded[object] += n;
            }
        }
        if result.bytes_loaded > 0 {
            self.store.loads += 1;
            self.store.bytes_loaded += result.bytes_loaded;
        }
        self.store.loading_seconds += result.loading_nanos as f64 * 1e-9;
        let w = self.workers.entry(worker.to_string()).or_insert_with(|| WorkerStats::new(worker));
        w.batches += 1;
        w.tasks += tasks;
        w.samples += result.samples;
    }

    /// Hands the metrics what was added up since they were last told.
    fn report(&mut self) {
        let (to, from, busy) = self.reported;
        self.metrics.wire(self.wire_to - to, self.wire_from - from);
        self.metrics.busy(self.coordinator.event_loop - busy);
        self.reported = (self.wire_to, self.wire_from, self.coordinator.event_loop);
    }

    /// Shows `pieces_done` tasks done and each worker's share in the job's status.
    pub fn publish(&mut self, job: &Job, pieces_done: u64) {
        self.report();
        let workers: Vec<pb::WorkerCount> = self.workers.values().map(WorkerStats::to_proto).collect();
        job.update(|s| {
            s.pieces_done = pieces_done;
            s.workers = workers;
        });
    }

    /// The finished job's statistics.
    pub fn into_stats(mut self, render: RenderStats) -> FarmStats {
        let workers = std::mem::take(&mut self.workers).into_values().collect();
        let mut stats = FarmStats::new(render, self.batches, self.wire_to, self.wire_from, workers);
        stats.coordinator_seconds = self.coordinator.clone();
        stats.batches_refused_busy = self.refused;
        stats.streams_opened = self.streams_opened;
        stats.scenes_sent = self.scenes_sent;
        stats
    }
}

impl Drop for Tally {
    /// However the job ends, the metrics get its last counts.
    fn drop(&mut self) {
        self.report();
    }
}
