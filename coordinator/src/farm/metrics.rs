//! The coordinator's Prometheus metrics (`trove coordinator --metrics-listen ADDR`, page
//! `/metrics`), with the Prometheus project's own client, `prometheus-client`.
//!
//! Counters are written as work happens: every job's driver records into its
//! coordinator's one [`FarmMetrics`] through its tally (`driver/tally.rs`). Gauges of state
//! — jobs by state, workers registered and alive — are read from the job table and the
//! registry when scraped, so they cannot drift from what `trove jobs` and `trove workers`
//! show (a worker turns dead by missing heartbeats, with no event to count).
//!
//! | name | kind | what |
//! | --- | --- | --- |
//! | `trove_jobs{state}` | gauge | jobs held, by state (`queued`, `running`, `succeeded`, `failed`, `cancelled`) |
//! | `trove_pieces_cast_total` | counter | piece tasks cast by workers and accepted |
//! | `trove_batches_total` | counter | batches answered and accepted |
//! | `trove_batch_latency_seconds` | histogram | from a batch's dispatch to its accepted answer |
//! | `trove_wire_bytes_total{direction}` | counter | payload bytes `to_workers` and `from_workers` |
//! | `trove_workers_registered`, `trove_workers_alive` | gauge | workers known, and of them those heartbeating |
//! | `trove_dispatch_busy_seconds_total` | counter | seconds the job drivers' event loops spent working, not waiting |

use std::future::Future;
use std::sync::{Arc, Mutex, Weak};

use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::{Registry as MetricsRegistry, Unit};
use tokio::net::TcpListener;
use trove_proto::v1 as pb;

use super::jobs::Jobs;
use super::registry::Registry;

/// A metric's labels: `(name, value)` pairs.
type Labels = Vec<(&'static str, &'static str)>;

/// The job states `trove_jobs` reports, each always present (zero when no job is in it).
const STATES: [(pb::JobState, &str); 5] = [
    (pb::JobState::Queued, "queued"),
    (pb::JobState::Running, "running"),
    (pb::JobState::Succeeded, "succeeded"),
    (pb::JobState::Failed, "failed"),
    (pb::JobState::Cancelled, "cancelled"),
];

/// One coordinator's metrics: shared by its every job, served by [`serve`].
pub struct FarmMetrics {
    registry: MetricsRegistry,
    jobs: Family<Labels, Gauge>,
    pieces_cast: Counter,
    batches: Counter,
    batch_latency: Histogram,
    wire_bytes: Family<Labels, Counter>,
    workers_registered: Gauge,
    workers_alive: Gauge,
    busy_seconds: Counter<f64>,
    /// Where the gauges are read from when scraped; weak, so metrics kept by a caller do
    /// not keep a stopped coordinator's jobs alive.
    sources: Mutex<Option<(Weak<Jobs>, Weak<Registry>)>>,
}

impl std::fmt::Debug for FarmMetrics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FarmMetrics").field("pieces_cast", &self.pieces_cast.get()).finish_non_exhaustive()
    }
}

impl Default for FarmMetrics {
    fn default() -> Self {
        FarmMetrics::new()
    }
}

impl FarmMetrics {
    /// Every metric at zero.
    pub fn new() -> FarmMetrics {
        let mut registry = MetricsRegistry::with_prefix("trove");
        let jobs = Family::<Labels, Gauge>::default();
        registry.register("jobs", "Jobs the coordinator holds, by state", jobs.clone());
        let pieces_cast = Counter::default();
        registry.register("pieces_cast", "Piece tasks cast by workers and accepted", pieces_cast.clone());
        let batches = Counter::default();
        registry.register("batches", "Batches answered by workers and accepted", batches.clone());
        // 1 ms to about 65 s: a batch is a few milliseconds of casting on a warm worker, and
        // seconds when its dataset must be loaded first.
        let batch_latency = Histogram::new(exponential_buckets(0.001, 2.0, 17));
        registry.register_with_unit(
            "batch_latency",
            "From a batch's dispatch to its accepted answer",
            Unit::Seconds,
            batch_latency.clone(),
        );
        let wire_bytes = Family::<Labels, Counter>::default();
        registry.register_with_unit(
            "wire",
            "Payload bytes on the wire to and from the workers",
            Unit::Bytes,
            wire_bytes.clone(),
        );
        let workers_registered = Gauge::default();
        registry.register("workers_registered", "Workers the coordinator knows", workers_registered.clone());
        let workers_alive = Gauge::default();
        registry.register("workers_alive", "Known workers whose heartbeats are on time", workers_alive.clone());
        let busy_seconds = Counter::<f64>::default();
        registry.register_with_unit(
            "dispatch_busy",
            "Time the job drivers' event loops spent working (dispatch, encoding, recording), not waiting",
            Unit::Seconds,
            busy_seconds.clone(),
        );
        FarmMetrics {
            registry,
            jobs,
            pieces_cast,
            batches,
            batch_latency,
            wire_bytes,
            workers_registered,
            workers_alive,
            busy_seconds,
            sources: Mutex::new(None),
        }
    }

    /// Reads the gauges from `jobs` and `registry` on every scrape (a coordinator calls
    /// this as it starts).
    pub fn observe(&self, jobs: &Arc<Jobs>, registry: &Arc<Registry>) {
        *self.sources.lock().unwrap_or_else(|e| e.into_inner()) =
            Some((Arc::downgrade(jobs), Arc::downgrade(registry)));
    }

    /// An accepted answer to a batch of `tasks` tasks, `latency_s` seconds after it was sent.
    pub fn answered(&self, tasks: u64, latency_s: f64) {
        self.batches.inc();
        self.pieces_cast.inc_by(tasks);
        self.batch_latency.observe(latency_s);
    }

    /// Payload bytes sent to and received from workers.
    pub fn wire(&self, to_workers: u64, from_workers: u64) {
        self.wire_bytes.get_or_create(&vec![("direction", "to_workers")]).inc_by(to_workers);
        self.wire_bytes.get_or_create(&vec![("direction", "from_workers")]).inc_by(from_workers);
    }

    /// Seconds a job's driver spent working.
    pub fn busy(&self, seconds: f64) {
        if seconds > 0.0 {
            self.busy_seconds.inc_by(seconds);
        }
    }

    /// Piece tasks cast and accepted so far, over every job.
    pub fn pieces_cast(&self) -> u64 {
        self.pieces_cast.get()
    }

    /// The page Prometheus scrapes (OpenMetrics text), with the gauges read now.
    pub fn render(&self) -> String {
        let sources = self.sources.lock().unwrap_or_else(|e| e.into_inner()).clone();
        if let Some((jobs, registry)) = sources {
            if let Some(jobs) = jobs.upgrade() {
                let list = jobs.held();
                for (state, name) in STATES {
                    let n = list.iter().filter(|j| j.state() == state).count();
                    self.jobs.get_or_create(&vec![("state", name)]).set(n as i64);
                }
            }
            if let Some(registry) = registry.upgrade() {
                let workers = registry.list();
                self.workers_registered.set(workers.len() as i64);
                self.workers_alive.set(workers.iter().filter(|w| w.alive).count() as i64);
            }
        }
        // Both families show every label from the first scrape on, zeros included.
        for (_, name) in STATES {
            let _ = self.jobs.get_or_create(&vec![("state", name)]);
        }
        self.wire(0, 0);
        let mut page = String::new();
        // Writing to a String cannot fail.
        let _ = encode(&mut page, &self.registry);
        page
    }
}

/// Serves `metrics` as `GET /metrics` on `listener` until `shutdown` resolves.
pub async fn serve(
    listener: TcpListener,
    shutdown: impl Future<Output = ()>,
    metrics: Arc<FarmMetrics>,
) -> std::io::Result<()> {
    trove_proto::serve_metrics(listener, shutdown, Arc::new(move || metrics.render())).await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counters_accumulate_and_every_label_shows_from_the_start() {
        let metrics = FarmMetrics::new();
        let page = metrics.render();
        assert!(page.contains("trove_jobs{state=\"queued\"} 0"), "{page}");
        assert!(page.contains("trove_wire_bytes_total{direction=\"to_workers\"} 0"), "{page}");
        metrics.answered(40, 0.003);
        metrics.answered(2, 0.5);
        metrics.wire(100, 7);
        metrics.busy(0.25);
        let page = metrics.render();
        assert!(page.contains("trove_pieces_cast_total 42\n"), "{page}");
        assert!(page.contains("trove_batches_total 2\n"), "{page}");
        assert!(page.contains("trove_batch_latency_seconds_count 2\n"), "{page}");
        assert!(page.contains("trove_wire_bytes_total{direction=\"to_workers\"} 100\n"), "{page}");
        assert!(page.contains("trove_wire_bytes_total{direction=\"from_workers\"} 7\n"), "{page}");
        assert!(page.contains("trove_dispatch_busy_seconds_total 0.25\n"), "{page}");
        assert!(page.ends_with("# EOF\n"), "{page}");
    }
}
