//! The statistics a farm job writes: SPEC §5's keys (the same as local mode's) plus what the
//! farm adds — batches, bytes on the wire each way, and each worker's share.

use serde::Serialize;
use trove_core::render::RenderStats;
use trove_proto::v1 as pb;

/// One worker's share of a job.
#[derive(Clone, Debug, Serialize, PartialEq, Eq)]
pub struct WorkerStats {
    /// The worker's id.
    pub worker_id: String,
    /// Batches it answered.
    pub batches: u64,
    /// Piece tasks in them.
    pub tasks: u64,
    /// Samples it cast.
    pub samples: u64,
}

impl WorkerStats {
    /// A worker that has done nothing yet.
    pub fn new(id: &str) -> WorkerStats {
        WorkerStats { worker_id: id.to_string(), batches: 0, tasks: 0, samples: 0 }
    }

    /// For `JobStatus`.
    pub fn to_proto(&self) -> pb::WorkerCount {
        pb::WorkerCount {
            worker_id: self.worker_id.clone(),
            batches: self.batches,
            tasks: self.tasks,
            samples: self.samples,
        }
    }
}

/// A farm job's statistics (`--stats` JSON).
#[derive(Clone, Debug, Serialize)]
pub struct FarmStats {
    /// SPEC §5's keys, as local mode writes them.
    #[serde(flatten)]
    pub render: RenderStats,
    /// `"farm"` (local mode writes no `mode`).
    pub mode: &'static str,
    /// Batches answered.
    pub batches: u64,
    /// Batches a worker refused as busy (it serves other coordinators or jobs too, and this
    /// job had its share), each sent again without spending an attempt.
    pub batches_refused_busy: u64,
    /// Payload bytes of every message to the workers (the scene on the first stream to each
    /// worker, a digest on the others, then tasks).
    pub wire_bytes_to_workers: u64,
    /// Payload bytes of every answer from the workers.
    pub wire_bytes_from_workers: u64,
    /// Cast streams opened (one per dataset and worker casting it, more where one was lost).
    pub streams_opened: u64,
    /// Of those, the ones whose open carried the scene: the first to each worker, and any
    /// opened before that one was accepted or after the worker had let the scene go.
    pub scenes_sent: u64,
    /// Each worker's share.
    pub workers: Vec<WorkerStats>,
    /// Where the coordinator's own time went, by stage.
    pub coordinator_seconds: CoordinatorSeconds,
}

/// The coordinator's time by stage (seconds, summed over the job). Every per-task step runs
/// on the thread of the band it belongs to (`farm/driver/band.rs`) and is timed by wall clock
/// there (intersection and composition run rayon threads within, so their CPU can exceed
/// their wall time; the others are close to CPU time unless the thread waits for a core);
/// `event_loop` holds the job's own task: per-batch dispatch, taking answers, the tick. What
/// gRPC, HTTP/2 and protobuf cost outside these is not here.
#[derive(Clone, Debug, Default, Serialize, PartialEq)]
pub struct CoordinatorSeconds {
    /// `intersect`: rays to piece tasks (the band's thread, rayon within).
    pub intersection: f64,
    /// `Scheduler::new`: waves and fronts (the band's thread).
    pub planning: f64,
    /// `Scheduler::next_batch`: fronts and culls (the band's thread).
    pub dispatch: f64,
    /// `encode_tasks` (the band's thread).
    pub encoding: f64,
    /// `decode_results` (the band's thread).
    pub decoding: f64,
    /// `Scheduler::record` (the band's thread).
    pub recording: f64,
    /// Every step of the job's task: per-batch dispatch, handling events, the tick.
    pub event_loop: f64,
    /// Compositing bands (the band's thread, rayon within).
    pub composition: f64,
    /// Encoding the PNG (and PFM) at the end (blocking thread).
    pub image_encoding: f64,
}

impl FarmStats {
    /// Wraps a finished render's statistics with the farm's.
    pub fn new(render: RenderStats, batches: u64, to: u64, from: u64, workers: Vec<WorkerStats>) -> FarmStats {
        FarmStats {
            render,
            mode: "farm",
            batches,
            batches_refused_busy: 0,
            wire_bytes_to_workers: to,
            wire_bytes_from_workers: from,
            streams_opened: 0,
            scenes_sent: 0,
            workers,
            coordinator_seconds: CoordinatorSeconds::default(),
        }
    }

    /// Pretty JSON with a final newline, as local mode writes its statistics.
    pub fn to_json(&self) -> Vec<u8> {
        let mut json = serde_json::to_vec_pretty(self).unwrap_or_default();
        json.push(b'\n');
        json
    }
}
