//! The `Worker.Cast` stream: one per job and dataset. It opens with the job's scene and the
//! headers of every file it names, validated here as on the coordinator (the worker opens
//! the files it holds itself, through its sandbox) and parsed once for all the job's
//! streams (`scenes.rs`), or with the scene's digest alone where this worker was sent it
//! on another stream of the job; then batches of piece tasks
//! arrive and each is answered with its results, cast by `trove-core`'s `BatchCaster` on
//! rayon threads.
//!
//! Each stream has a thread of its own that owns the job's scene and pins the dataset while
//! it has batches queued, releasing the pin when its queue runs dry: under a memory budget
//! other streams can then load their datasets, so streams never wait on each other forever.
//! When the coordinator closes the stream (the job is done or cancelled), queued batches are
//! dropped and the batch being cast stops at its next chunk.
//!
//! A worker serves at most `max_streams` streams at once (each is a thread); one more is
//! refused with `RESOURCE_EXHAUSTED`, which the coordinator treats as "busy, ask again
//! later". When the worker drains ([`CastService::drain`], on SIGTERM), new streams are
//! refused with `UNAVAILABLE`, each stream stops taking batches, casts those it already
//! holds, and then ends, so that the coordinator sends whatever was left to another holder.
//!
//! A worker also holds at most `max_batches` batches at once (queued or being cast), over
//! every stream, job and coordinator ([`BatchSlots`]): each coordinator counts only the
//! batches it sent, so several coordinators sharing the worker could otherwise queue
//! several times what it casts while a replica elsewhere stands idle. A batch beyond it is
//! answered at once with a `BUSY` failure unless its job holds less than its fair share
//! (`trove_core::render::dispatch::admits`), so no job is starved by others keeping the
//! worker full; the coordinator sends a refused batch again, costing it no attempt.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use rayon::prelude::*;
use tokio::sync::{mpsc, watch, OwnedSemaphorePermit, Semaphore};
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status, Streaming};
use trove_core::dataset::{Catalog, DatasetError, FileInfo, FileKind};
use trove_core::render::dispatch;
use trove_core::render::shadow::{dataset_factors, ShadowPlan};
use trove_core::render::wire::{decode_tasks, encode_results};
use trove_core::render::{BatchCaster, PieceRgba, RenderError, VolumeStore};
use trove_core::scene::Scene;
use trove_proto::convert::{self, JOB_HEADER};
use trove_proto::v1 as pb;

use crate::files::DataFiles;
use crate::scenes::{JobScenes, SceneRefusal};

/// Tasks per rayon work item within a batch, and the granularity of cancellation.
const CHUNK_TASKS: usize = 256;

/// Streams a worker serves at once when not told.
pub const DEFAULT_MAX_STREAMS: usize = 64;

/// Batches a worker holds at most when not told: what one coordinator sends it at most
/// (`trove_core::render::dispatch::capacity` of its rayon threads), so that a worker of one
/// coordinator never refuses a batch.
pub fn default_max_batches() -> usize {
    dispatch::capacity(rayon::current_num_threads() as u32) as usize
}

/// The batches a worker holds (queued or being cast), over every stream, and per job.
pub struct BatchSlots {
    max: u64,
    held: Mutex<Held>,
}

#[derive(Default)]
struct Held {
    total: u64,
    /// Per job id (`CastOpen.job_id`): batches held; jobs holding none are removed.
    jobs: HashMap<Arc<str>, u64>,
}

/// One batch held; dropping it (the batch answered, failed or dropped) frees its place.
pub struct Slot {
    slots: Arc<BatchSlots>,
    job: Arc<str>,
}

impl BatchSlots {
    /// Places for `max` batches (at least one).
    pub fn new(max: usize) -> Arc<BatchSlots> {
        Arc::new(BatchSlots { max: max.max(1) as u64, held: Mutex::default() })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Held> {
        self.held.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A place for one more batch of `job`, or `None`: busy (see [`dispatch::admits`]).
    pub fn take(self: &Arc<Self>, job: &Arc<str>) -> Option<Slot> {
        let mut held = self.lock();
        let mine = held.jobs.get(job).copied().unwrap_or(0);
        let others = held.jobs.len() as u64 - u64::from(mine > 0);
        if !dispatch::admits(self.max, held.total, mine, others) {
            return None;
        }
        held.total += 1;
        *held.jobs.entry(job.clone()).or_default() += 1;
        Some(Slot { slots: self.clone(), job: job.clone() })
    }

    /// Batches held now, over every job.
    pub fn held(&self) -> u64 {
        self.lock().total
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        let mut held = self.slots.lock();
        held.total = held.total.saturating_sub(1);
        if let Some(n) = held.jobs.get_mut(&self.job) {
            *n -= 1;
            if *n == 0 {
                held.jobs.remove(&self.job);
            }
        }
    }
}

/// The `Worker` service.
pub struct CastService {
    files: Arc<DataFiles>,
    store: VolumeStore,
    busy: Arc<AtomicU64>,
    /// One permit per stream served at once.
    streams: Arc<Semaphore>,
    max_streams: usize,
    slots: Arc<BatchSlots>,
    draining: watch::Sender<bool>,
    scenes: Arc<JobScenes>,
}

/// Starts a worker's drain ([`CastService::drain`]); it outlives the service, which the
/// server owns.
#[derive(Clone)]
pub struct Drain(watch::Sender<bool>);

impl Drain {
    /// From now on new streams are refused, and each stream casts the batches it holds and
    /// ends.
    pub fn begin(&self) {
        self.0.send_replace(true);
    }
}

impl CastService {
    /// Serves casts of the datasets in `files`, keeping voxels in `store`, at most
    /// `max_streams` streams at once (at least one) holding at most `max_batches` batches
    /// (at least one; beyond, a job over its share is refused as busy); `busy` counts the
    /// batches being cast (reported with heartbeats).
    pub fn new(
        files: Arc<DataFiles>,
        store: VolumeStore,
        busy: Arc<AtomicU64>,
        max_streams: usize,
        max_batches: usize,
    ) -> CastService {
        let max_streams = max_streams.max(1);
        CastService {
            files,
            store,
            busy,
            streams: Arc::new(Semaphore::new(max_streams)),
            max_streams,
            slots: BatchSlots::new(max_batches),
            draining: watch::channel(false).0,
            scenes: Arc::default(),
        }
    }

    /// The scenes its streams parsed, shared by them (read by the worker's metrics).
    pub fn scenes(&self) -> Arc<JobScenes> {
        self.scenes.clone()
    }

    /// What starts this service's drain.
    pub fn drain(&self) -> Drain {
        Drain(self.draining.clone())
    }

    /// A permit for one more stream, or the refusal.
    fn admit(&self) -> Result<OwnedSemaphorePermit, Status> {
        if *self.draining.borrow() {
            let f = convert::failure(
                pb::Reason::Unavailable,
                true,
                "this worker is stopping and takes no new streams".into(),
            );
            return Err(convert::failure_status(f));
        }
        self.streams.clone().try_acquire_owned().map_err(|_| {
            let message = format!(
                "this worker serves at most {} cast streams at once (--max-streams) and all are in use; try again later",
                self.max_streams
            );
            convert::failure_status(convert::failure(pb::Reason::LimitExceeded, true, message))
        })
    }
}

/// A scene's files as this worker sees them: its own, opened through the sandbox, and the
/// others as the coordinator described them (their voxels are elsewhere).
struct JobCatalog<'a> {
    files: &'a DataFiles,
    others: HashMap<String, &'a pb::DatasetFile>,
}

impl Catalog for JobCatalog<'_> {
    fn describe(&self, key: &str, kind: FileKind) -> Result<FileInfo, DatasetError> {
        if self.files.holds(key) {
            return self.files.catalog().describe(key, kind);
        }
        match self.others.get(key) {
            Some(file) => convert::describe_remote(file, kind),
            None => Err(DatasetError::not_held(key)),
        }
    }
}

/// The job's scene as a worker holding `files` sees it: its own files through the
/// sandbox, the others as the coordinator described them in `open`; a refusal is a `Status`
/// carrying the typed failure. What every server of the `Worker` service parses with.
pub fn parse_job_scene(files: &DataFiles, open: &pb::CastOpen) -> Result<Scene, Status> {
    let others = open.headers.iter().map(|f| (f.key.clone(), f)).collect();
    let catalog = JobCatalog { files, others };
    let scene = Scene::parse_with(&open.scene_toml, std::path::Path::new(&open.scene_name), &catalog)
        .map_err(|e| convert::failure_status(convert::scene_failure(&e)))?;
    if !open.shadow_maps_computed {
        return Ok(scene);
    }
    convert::attach_shadow_maps(&scene, &open.shadow_maps).map_err(|e| {
        convert::failure_status(convert::failure(pb::Reason::BadBatch, false, format!("the stream's shadow maps: {e}")))
    })
}

/// Validates the job's scene (parsed once for all its streams: `scenes`) and checks that
/// this worker can cast `open.dataset`; a refusal is a `Status` carrying the typed failure.
fn open_job(files: &DataFiles, scenes: &JobScenes, open: &pb::CastOpen) -> Result<(Arc<Scene>, usize), Status> {
    let scene = scenes.get_or_parse(open, || parse_job_scene(files, open)).map_err(|refusal| match refusal {
        SceneRefusal::Parse(status) => status,
        SceneRefusal::Unknown => convert::failure_status(convert::failure(
            pb::Reason::SceneUnknown,
            true,
            "this worker does not hold the scene this stream names by digest; open it again with the scene".into(),
        )),
        SceneRefusal::Mismatch => convert::failure_status(convert::failure(
            pb::Reason::BadBatch,
            false,
            "the stream's scene digest is not its scene's: coordinator and worker name scenes differently".into(),
        )),
    })?;
    let d = open.dataset as usize;
    let Some(info) = scene.datasets().get(d) else {
        return Err(convert::failure_status(convert::failure(
            pb::Reason::BadBatch,
            false,
            format!("dataset {d} does not exist: the scene has {}", scene.datasets().len()),
        )));
    };
    if !info.is_local() {
        let mut f = convert::failure(
            pb::Reason::DatasetNotHeld,
            true,
            format!("this worker does not hold every file of dataset `{}`", info.name()),
        );
        f.dataset = info.name().to_string();
        return Err(convert::failure_status(f));
    }
    Ok((scene, d))
}

/// The shadow pass's share of the objects of `open.dataset` (SPEC §6, `render::shadow`):
/// their factors on every lattice of the scene's plan, cast from this worker's copy; with
/// `refine`, on the fine points of the first pass's maps, which `open` carries.
fn shadow_factors(
    files: &DataFiles,
    scenes: &JobScenes,
    store: &VolumeStore,
    open: &pb::CastOpen,
    refine: bool,
) -> Result<pb::ShadowReply, Status> {
    let (scene, d) = open_job(files, scenes, open)?;
    let mut plan = ShadowPlan::of(&scene);
    if refine {
        if !open.shadow_maps_computed {
            let message = "a refining shadow request must carry the first pass's maps".to_string();
            return Err(convert::failure_status(convert::failure(pb::Reason::BadBatch, false, message)));
        }
        plan = plan.refinement(&scene);
    }
    let factors = dataset_factors(&scene, &plan, d, store).map_err(|e| {
        let f = match &e {
            RenderError::Store(e) => convert::store_failure(e),
            RenderError::Cast(e) => convert::cast_failure(e),
            other => convert::failure(pb::Reason::Internal, false, other.to_string()),
        };
        convert::failure_status(f)
    })?;
    let factors = factors
        .into_iter()
        .map(|f| pb::ShadowFactors {
            lattice: f.lattice as u32,
            occluder: f.occluder as u32,
            values: convert::unit_runs(&f.values),
        })
        .collect();
    let reply = pb::ShadowReply { factors };
    // Larger than a message may be: refused by name, not failed by the transport.
    let bytes = prost::Message::encoded_len(&reply);
    if bytes > trove_proto::MAX_MESSAGE_BYTES - (1 << 16) {
        let message = format!(
            "lights: the shadow factors of dataset `{}` take {bytes} bytes, more than a farm message holds; render \
             this scene in local mode, or cast shadows from fewer lights",
            scene.datasets()[d].name(),
        );
        let mut f = convert::failure(pb::Reason::LimitExceeded, false, message);
        f.key = "lights".into();
        return Err(convert::failure_status(f));
    }
    Ok(reply)
}

#[tonic::async_trait]
impl pb::worker_server::Worker for CastService {
    type CastStream = ReceiverStream<Result<pb::CastResponse, Status>>;

    async fn shadow(&self, request: Request<pb::ShadowRequest>) -> Result<Response<pb::ShadowReply>, Status> {
        let permit = self.admit()?;
        let request = request.into_inner();
        let refine = request.refine;
        let Some(open) = request.open else {
            return Err(Status::invalid_argument("a shadow request carries an `open`"));
        };
        let (files, scenes, store) = (self.files.clone(), self.scenes.clone(), self.store.clone());
        let reply = tokio::task::spawn_blocking(move || {
            let reply = shadow_factors(&files, &scenes, &store, &open, refine);
            drop(permit);
            reply
        })
        .await
        .map_err(|e| Status::internal(format!("the shadow pass failed: {e}")))?;
        Ok(Response::new(reply?))
    }

    async fn cast(&self, request: Request<Streaming<pb::CastRequest>>) -> Result<Response<Self::CastStream>, Status> {
        // Taken before anything is read, so that streams that never send are counted too.
        let permit = self.admit()?;
        let job = request.metadata().get(JOB_HEADER).and_then(|v| v.to_str().ok()).unwrap_or("-").to_string();
        let mut inbound = request.into_inner();
        let open = match inbound.message().await? {
            Some(pb::CastRequest { kind: Some(pb::cast_request::Kind::Open(open)) }) => open,
            _ => return Err(Status::invalid_argument("a cast stream starts with an `open` message")),
        };
        let span = tracing::info_span!("cast", job = %job, dataset = open.dataset);
        let job: Arc<str> = if open.job_id.is_empty() { job.into() } else { open.job_id.as_str().into() };
        let (files, scenes) = (self.files.clone(), self.scenes.clone());
        let opened = tokio::task::spawn_blocking(move || open_job(&files, &scenes, &open))
            .await
            .map_err(|e| Status::internal(format!("opening the job failed: {e}")))?;
        let (scene, dataset) = opened?;
        span.in_scope(|| tracing::info!(name = scene.datasets()[dataset].name(), "stream open"));

        let (out_tx, out_rx) = mpsc::channel(16);
        let (batch_tx, batch_rx) = mpsc::channel::<(pb::CastBatch, Slot)>(256);
        let slots = self.slots.clone();
        let max_batches = slots.max;
        let cancelled = Arc::new(AtomicBool::new(false));
        let feeder_cancel = cancelled.clone();
        let feeder_out = out_tx.clone();
        let mut draining = self.draining.subscribe();
        tokio::spawn(async move {
            let drained = loop {
                let message = tokio::select! {
                    message = inbound.message() => message,
                    _ = draining.wait_for(|d| *d) => break true,
                };
                match message {
                    Ok(Some(pb::CastRequest { kind: Some(pb::cast_request::Kind::Batch(b)) })) => {
                        let Some(slot) = slots.take(&job) else {
                            let message = format!(
                                "this worker holds {max_batches} batches (--max-batches) over every coordinator and job, \
                                 and this job has its share; send it again later or elsewhere"
                            );
                            let mut f = convert::failure(pb::Reason::Busy, true, message);
                            f.batch_id = b.batch_id;
                            let busy = pb::CastResponse { kind: Some(pb::cast_response::Kind::Failure(f)) };
                            if feeder_out.send(Ok(busy)).await.is_err() {
                                break false;
                            }
                            continue;
                        };
                        if batch_tx.send((b, slot)).await.is_err() {
                            break false;
                        }
                    }
                    Ok(Some(_)) => {
                        let f = convert::failure(pb::Reason::BadBatch, false, "expected a batch after `open`".into());
                        let _ = feeder_out
                            .send(Ok(pb::CastResponse { kind: Some(pb::cast_response::Kind::Failure(f)) }))
                            .await;
                        break false;
                    }
                    Ok(None) | Err(_) => break false,
                }
            };
            if drained {
                // Draining: the caster casts what it holds, then its end of the queue and
                // of the answers closes, which ends the response. Batches that still arrive
                // are not taken; the coordinator gives them to another holder when the
                // stream ends. The request side is read to its end, not dropped, so the
                // answers still in flight are not reset with it.
                drop((batch_tx, feeder_out));
                while let Ok(Some(_)) = inbound.message().await {}
                return;
            }
            // The coordinator closed its side: the job is over or cancelled.
            feeder_cancel.store(true, Ordering::SeqCst);
        });
        let store = self.store.clone();
        let busy = self.busy.clone();
        std::thread::Builder::new()
            .name(format!("cast-{dataset}"))
            .spawn(move || {
                let _entered = span.enter();
                Caster { scene, dataset, store, busy, cancelled, out: out_tx }.run(batch_rx);
                tracing::debug!("stream closed");
                drop(permit);
            })
            .map_err(|e| Status::resource_exhausted(format!("cannot start a casting thread: {e}")))?;
        Ok(Response::new(ReceiverStream::new(out_rx)))
    }
}

/// The thread behind one stream.
struct Caster {
    scene: Arc<Scene>,
    dataset: usize,
    store: VolumeStore,
    busy: Arc<AtomicU64>,
    cancelled: Arc<AtomicBool>,
    out: mpsc::Sender<Result<pb::CastResponse, Status>>,
}

impl Caster {
    /// Casts the stream's batches until its queue closes; each batch's place is freed before
    /// its answer goes, so the worker never counts more than a coordinator does.
    fn run(self, mut batches: mpsc::Receiver<(pb::CastBatch, Slot)>) {
        let info = &self.scene.datasets()[self.dataset];
        while let Some((first, slot)) = batches.blocking_recv() {
            if self.cancelled.load(Ordering::SeqCst) {
                return;
            }
            let started = Instant::now();
            let pinned = match self.store.get(info) {
                Ok(p) => p,
                Err(e) => {
                    let mut f = convert::store_failure(&e);
                    f.batch_id = first.batch_id;
                    drop(slot);
                    if !self.send(pb::cast_response::Kind::Failure(f)) {
                        return;
                    }
                    continue;
                }
            };
            let loaded = if pinned.was_loaded() { info.resident_bytes() } else { 0 };
            let loading_nanos = started.elapsed().as_nanos() as u64;
            let caster = match BatchCaster::new(&self.scene, self.dataset, &pinned) {
                Ok(c) => c,
                Err(e) => {
                    let mut f = convert::cast_failure(&e);
                    f.batch_id = first.batch_id;
                    drop(slot);
                    let _ = self.send(pb::cast_response::Kind::Failure(f));
                    return;
                }
            };
            let mut next = Some((first, slot, loaded, loading_nanos));
            while let Some((batch, slot, bytes_loaded, loading_nanos)) = next.take() {
                if self.cancelled.load(Ordering::SeqCst) {
                    return;
                }
                let span = tracing::debug_span!("batch", id = batch.batch_id, attempt = batch.attempt);
                let Some(kind) = span.in_scope(|| self.cast(&caster, &batch, bytes_loaded, loading_nanos)) else {
                    return;
                };
                drop(slot);
                if !self.send(kind) {
                    return;
                }
                next = batches.try_recv().ok().map(|(b, slot)| (b, slot, 0, 0));
            }
            // The queue ran dry: release the pin so others may load under a budget.
        }
    }

    /// One batch's answer, or `None` when the stream was cancelled while casting it.
    fn cast(
        &self,
        caster: &BatchCaster,
        batch: &pb::CastBatch,
        bytes_loaded: u64,
        loading_nanos: u64,
    ) -> Option<pb::cast_response::Kind> {
        let tasks = match decode_tasks(&batch.tasks) {
            Ok(tasks) => tasks,
            Err(e) => {
                let message = format!("batch {}: {} bytes of tasks: {e}", batch.batch_id, batch.tasks.len());
                let mut f = convert::failure(pb::Reason::BadBatch, false, message);
                f.batch_id = batch.batch_id;
                return Some(pb::cast_response::Kind::Failure(f));
            }
        };
        self.busy.fetch_add(1, Ordering::Relaxed);
        let started = Instant::now();
        let mut out = vec![PieceRgba::default(); tasks.len()];
        let objects = caster.object_count();
        let cast = tasks
            .par_chunks(CHUNK_TASKS)
            .zip(out.par_chunks_mut(CHUNK_TASKS))
            .map(|(t, o)| {
                let mut shaded = Vec::new();
                if self.cancelled.load(Ordering::Relaxed) {
                    return Ok((0, shaded));
                }
                shaded.resize(objects, 0);
                caster.cast_counting(t, o, &mut shaded).map(|samples| (samples, shaded))
            })
            .try_reduce(
                || (0, Vec::new()),
                |(a, mut shaded), (b, more)| {
                    if shaded.len() < more.len() {
                        shaded.resize(more.len(), 0);
                    }
                    for (s, m) in shaded.iter_mut().zip(more) {
                        *s += m;
                    }
                    Ok((a + b, shaded))
                },
            );
        self.busy.fetch_sub(1, Ordering::Relaxed);
        if self.cancelled.load(Ordering::SeqCst) {
            return None;
        }
        Some(match cast {
            Ok((samples, shaded)) => pb::cast_response::Kind::Result(pb::BatchResult {
                batch_id: batch.batch_id,
                attempt: batch.attempt,
                results: encode_results(&out),
                samples,
                shading_evaluations: (0u32..).zip(shaded).filter(|&(_, n)| n > 0).collect(),
                bytes_loaded,
                loading_nanos,
                casting_nanos: started.elapsed().as_nanos() as u64,
            }),
            Err(e) => {
                let mut f = convert::cast_failure(&e);
                f.batch_id = batch.batch_id;
                pb::cast_response::Kind::Failure(f)
            }
        })
    }

    /// Sends an answer; false when the coordinator has gone.
    fn send(&self, kind: pb::cast_response::Kind) -> bool {
        self.out.blocking_send(Ok(pb::CastResponse { kind: Some(kind) })).is_ok()
    }
}
