//! What a job counts while it runs — samples, loads, batches, bytes on the wire, each
//! worker's share — and how much of it the job's status shows. The status is published on
//! the driver's tick and when a band completes, not on every answer: a watcher sees it a few
//! times a second, and the driver does not rebuild it per batch.

use std::collections::BTreeMap;
use std::time::Instant;

use trove_core::render::{RenderStats, StoreStats};
use trove_proto::v1 as pb;

use super::super::jobs::Job;
use super::super::stats::{CoordinatorSeconds, FarmStats, WorkerStats};

/// A job's counters.
#[derive(Default)]
pub(super) struct Tally {
    pub stats: RenderStats,
    pub store: StoreStats,
    pub batches: u64,
    pub wire_to: u64,
    pub wire_from: u64,
    workers: BTreeMap<String, WorkerStats>,
    pub cast_started: Option<Instant>,
    /// The coordinator's own time by stage.
    pub coordinator: CoordinatorSeconds,
}

impl Tally {
    /// An answered batch of `tasks` tasks from `worker`.
    pub fn answered(&mut self, worker: &str, tasks: u64, result: &pb::BatchResult) {
        self.batches += 1;
        self.stats.samples += result.samples;
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

    /// Shows `pieces_done` tasks done and each worker's share in the job's status.
    pub fn publish(&self, job: &Job, pieces_done: u64) {
        let workers: Vec<pb::WorkerCount> = self.workers.values().map(WorkerStats::to_proto).collect();
        job.update(|s| {
            s.pieces_done = pieces_done;
            s.workers = workers;
        });
    }

    /// The finished job's statistics.
    pub fn into_stats(self, render: RenderStats) -> FarmStats {
        let mut stats =
            FarmStats::new(render, self.batches, self.wire_to, self.wire_from, self.workers.into_values().collect());
        stats.coordinator_seconds = self.coordinator;
        stats
    }
}
