//! The worker's Prometheus metrics (`trove-worker --metrics-listen ADDR`, page `/metrics`),
//! with the Prometheus project's own client, `prometheus-client`.
//!
//! [`Metered`] wraps the `Worker` service and counts what flows out of its `Cast` streams —
//! each answered batch, its pieces (the count leading its results' wire form) and its
//! casting time — and the streams open, so the casting code itself never touches a metric.
//! Resident voxel bytes are read from the worker's `VolumeStore` when scraped.
//!
//! | name | kind | what |
//! | --- | --- | --- |
//! | `trove_worker_batches_total` | counter | batches cast and answered |
//! | `trove_worker_pieces_cast_total` | counter | piece tasks in them |
//! | `trove_worker_casting_seconds_total` | counter | wall time casting them (rayon threads within) |
//! | `trove_worker_resident_bytes` | gauge | voxel bytes resident in the store (kept classifications included) |
//! | `trove_worker_streams_open` | gauge | `Cast` streams open now |
//! | `trove_worker_batches_refused_total` | counter | batches refused as busy (`--max-batches`; several coordinators) |
//! | `trove_worker_scenes_parsed_total` | counter | job scenes parsed (once per distinct scene kept, not per stream) |
//! | `trove_worker_scenes_reused_total` | counter | streams whose scene was already parsed |

use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, Mutex};

use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::{Registry, Unit};
use tokio::net::TcpListener;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};
use trove_core::render::VolumeStore;
use trove_proto::v1 as pb;
use trove_proto::v1::worker_server::Worker;

use crate::scenes::JobScenes;

/// One worker's metrics, served by [`serve`].
pub struct WorkerMetrics {
    registry: Registry,
    batches: Counter,
    pieces: Counter,
    casting_seconds: Counter<f64>,
    resident_bytes: Gauge,
    streams_open: Gauge,
    refused: Counter,
    scenes_parsed: Counter,
    scenes_reused: Counter,
    store: Mutex<Option<VolumeStore>>,
    scenes: Mutex<Option<Arc<JobScenes>>>,
}

impl std::fmt::Debug for WorkerMetrics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WorkerMetrics").field("batches", &self.batches.get()).finish_non_exhaustive()
    }
}

impl Default for WorkerMetrics {
    fn default() -> Self {
        WorkerMetrics::new()
    }
}

impl WorkerMetrics {
    /// Every metric at zero.
    pub fn new() -> WorkerMetrics {
        let mut registry = Registry::with_prefix("trove_worker");
        let batches = Counter::default();
        registry.register("batches", "Batches cast and answered", batches.clone());
        let pieces = Counter::default();
        registry.register("pieces_cast", "Piece tasks in the batches answered", pieces.clone());
        let casting_seconds = Counter::<f64>::default();
        registry.register_with_unit(
            "casting",
            "Wall time spent casting the batches answered",
            Unit::Seconds,
            casting_seconds.clone(),
        );
        let resident_bytes = Gauge::default();
        registry.register_with_unit(
            "resident",
            "Voxel bytes resident in the worker's store, kept classifications included",
            Unit::Bytes,
            resident_bytes.clone(),
        );
        let streams_open = Gauge::default();
        registry.register("streams_open", "Cast streams open now", streams_open.clone());
        let refused = Counter::default();
        registry.register(
            "batches_refused",
            "Batches refused as busy: the worker held --max-batches and the job had its share",
            refused.clone(),
        );
        let scenes_parsed = Counter::default();
        registry.register(
            "scenes_parsed",
            "Job scenes parsed: once per distinct scene while it is kept, not once per stream",
            scenes_parsed.clone(),
        );
        let scenes_reused = Counter::default();
        registry.register("scenes_reused", "Cast streams whose scene was already parsed", scenes_reused.clone());
        WorkerMetrics {
            registry,
            batches,
            pieces,
            casting_seconds,
            resident_bytes,
            streams_open,
            refused,
            scenes_parsed,
            scenes_reused,
            store: Mutex::new(None),
            scenes: Mutex::new(None),
        }
    }

    /// Reads the scenes parsed and reused from `scenes` on every scrape (a worker calls this
    /// as it starts).
    pub fn observe_scenes(&self, scenes: Arc<JobScenes>) {
        *self.scenes.lock().unwrap_or_else(|e| e.into_inner()) = Some(scenes);
    }

    /// Brings the scene counters up to what the observed [`JobScenes`] counted.
    fn read_scenes(&self) {
        if let Some(scenes) = self.scenes.lock().unwrap_or_else(|e| e.into_inner()).as_ref() {
            // Counters only go up: add what was counted since the last read.
            self.scenes_parsed.inc_by(scenes.parsed().saturating_sub(self.scenes_parsed.get()));
            self.scenes_reused.inc_by(scenes.reused().saturating_sub(self.scenes_reused.get()));
        }
    }

    /// Job scenes parsed so far.
    pub fn scenes_parsed(&self) -> u64 {
        self.read_scenes();
        self.scenes_parsed.get()
    }

    /// Cast streams that found their scene parsed so far.
    pub fn scenes_reused(&self) -> u64 {
        self.read_scenes();
        self.scenes_reused.get()
    }

    /// Reads resident bytes from `store` on every scrape (a worker calls this as it starts).
    pub fn observe(&self, store: &VolumeStore) {
        *self.store.lock().unwrap_or_else(|e| e.into_inner()) = Some(store.clone());
    }

    /// Counts one answer leaving a stream.
    fn answered(&self, response: &pb::CastResponse) {
        if let Some(pb::cast_response::Kind::Result(result)) = &response.kind {
            self.batches.inc();
            // The results' wire form (`render::wire::encode_results`) starts with their
            // count as a varint: one result per task.
            let mut bytes = &result.results[..];
            if let Ok(pieces) = prost::encoding::decode_varint(&mut bytes) {
                self.pieces.inc_by(pieces);
            }
            self.casting_seconds.inc_by(result.casting_nanos as f64 * 1e-9);
        } else if let Some(pb::cast_response::Kind::Failure(f)) = &response.kind {
            if f.reason() == pb::Reason::Busy {
                self.refused.inc();
            }
        }
    }

    /// Batches refused as busy so far.
    pub fn refused(&self) -> u64 {
        self.refused.get()
    }

    /// Batches answered so far.
    pub fn batches(&self) -> u64 {
        self.batches.get()
    }

    /// The page Prometheus scrapes (OpenMetrics text), with the gauges read now.
    pub fn render(&self) -> String {
        if let Some(store) = self.store.lock().unwrap_or_else(|e| e.into_inner()).as_ref() {
            self.resident_bytes.set(store.resident_bytes().min(i64::MAX as u64) as i64);
        }
        self.read_scenes();
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
    metrics: Arc<WorkerMetrics>,
) -> std::io::Result<()> {
    trove_proto::serve_metrics(listener, shutdown, Arc::new(move || metrics.render())).await
}

/// A `Worker` service whose streams are counted in [`WorkerMetrics`].
pub struct Metered<S> {
    inner: S,
    metrics: Arc<WorkerMetrics>,
}

impl<S> Metered<S> {
    /// `inner`, counted in `metrics`.
    pub fn new(inner: S, metrics: Arc<WorkerMetrics>) -> Metered<S> {
        Metered { inner, metrics }
    }
}

/// Holds one open stream in the gauge; dropped with the stream.
struct OpenStream(Arc<WorkerMetrics>);

impl Drop for OpenStream {
    fn drop(&mut self) {
        self.0.streams_open.dec();
    }
}

type Answers = Pin<Box<dyn Stream<Item = Result<pb::CastResponse, Status>> + Send>>;

#[tonic::async_trait]
impl<S: Worker> Worker for Metered<S> {
    type CastStream = Answers;

    async fn shadow(&self, request: Request<pb::ShadowRequest>) -> Result<Response<pb::ShadowReply>, Status> {
        self.inner.shadow(request).await
    }

    async fn cast(&self, request: Request<Streaming<pb::CastRequest>>) -> Result<Response<Self::CastStream>, Status> {
        let response = self.inner.cast(request).await?;
        self.metrics.streams_open.inc();
        let open = OpenStream(self.metrics.clone());
        let answers = response.into_inner().map(move |answer| {
            if let Ok(a) = &answer {
                open.0.answered(a);
            }
            answer
        });
        Ok(Response::new(Box::pin(answers) as Answers))
    }
}
