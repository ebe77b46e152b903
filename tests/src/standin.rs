//! A stand-in worker: it speaks the worker's side of the farm's protocol — registers with
//! `Membership.Register` and heartbeats, serves `Worker.Cast` (a `CastOpen` with the scene,
//! then batches in `render::wire` form) — but answers each batch at once from a table of
//! results recorded from a real cast, so that a farm of them costs the coordinator what real
//! workers would while costing almost nothing itself. `trove-bench coordinator` measures the
//! coordinator alone this way.
//!
//! The table is honest: a task seen for the first time is cast for real, by `trove-core`'s
//! [`BatchCaster`] over the stand-ins' own [`VolumeStore`], and its result and samples are
//! kept, keyed by the whole task (pixel, object, front and both bounds, bit for bit). A
//! task's result depends on nothing else — not on the batch it comes in, nor on timing (its
//! front is the scheduler's deterministic bound) — so a table filled by one render answers
//! the next render of the same job with the real results, and the image the coordinator
//! composites stays local mode's byte for byte (`tests/tests/standin.rs`, and
//! `trove-bench coordinator` checks every scene it measures). A task not in the table is cast
//! then, and counted ([`Answers::counts`]), so a measurement can say whether any casting
//! happened during it.
//!
//! Every stand-in of a process shares one [`Answers`] (one data root, one table, one rayon
//! pool for the casting of misses), so a job's table is recorded once whichever stand-in a
//! batch goes to.

use std::collections::HashMap;
use std::future::Future;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::Duration;

use rayon::prelude::*;
use tokio::net::TcpListener;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status, Streaming};
use trove_core::render::wire::{decode_tasks, encode_results};
use trove_core::render::CastError;
use trove_core::render::{BatchCaster, PieceRgba, PieceTask, VolumeStore};
use trove_core::scene::Scene;
use trove_proto::convert;
use trove_proto::v1 as pb;
use trove_proto::v1::membership_client::MembershipClient;
use trove_proto::v1::worker_server::{Worker, WorkerServer};
use trove_worker::files::{DataFiles, ScanError};

/// A task as the table knows it: every field, the bounds by their bits.
type TaskKey = (u32, u16, u16, u64, u64);

fn key(t: &PieceTask) -> TaskKey {
    (t.ray, t.object, t.front, t.t0.to_bits(), t.t1.to_bits())
}

/// A task's recorded answer.
#[derive(Clone, Copy)]
struct Answer {
    rgba: PieceRgba,
    samples: u64,
}

/// One job's scene as the stand-ins parsed it, and per dataset its recorded answers.
struct SceneAnswers {
    scene: Arc<Scene>,
    tables: Vec<RwLock<HashMap<TaskKey, Answer>>>,
}

/// The recorded answers shared by the stand-ins of one data root.
pub struct Answers {
    files: Arc<DataFiles>,
    store: VolumeStore,
    pool: Arc<rayon::ThreadPool>,
    /// By digest (`convert::scene_digest`), as a worker keeps them.
    scenes: Mutex<HashMap<[u8; 32], Arc<SceneAnswers>>>,
    /// Scenes are let go as soon as a stream opened on them ([`Answers::forget_scenes`]).
    forgetful: AtomicBool,
    /// Opens refused because they named by digest a scene not held.
    unknown: AtomicU64,
    answered: AtomicU64,
    cast: AtomicU64,
    /// Batches answered after a batch of their stream that was sent later.
    overtaken: AtomicU64,
}

impl Answers {
    /// Answers over the files under `root` (scanned now, blocking), casting what is not yet
    /// recorded on `pool`.
    pub fn new(root: &Path, pool: Arc<rayon::ThreadPool>) -> Result<Answers, ScanError> {
        Ok(Answers {
            files: Arc::new(DataFiles::scan(root)?),
            store: VolumeStore::new(None),
            pool,
            scenes: Mutex::new(HashMap::new()),
            answered: AtomicU64::new(0),
            cast: AtomicU64::new(0),
            overtaken: AtomicU64::new(0),
            forgetful: AtomicBool::new(false),
            unknown: AtomicU64::new(0),
        })
    }

    /// Tasks answered so far, and how many of them had to be cast (were not recorded yet).
    pub fn counts(&self) -> (u64, u64) {
        (self.answered.load(Ordering::Relaxed), self.cast.load(Ordering::Relaxed))
    }

    /// Batches answered after a later batch of the same stream ([`Order::Shuffled`]): a
    /// test of arrival order can check that the order really changed.
    pub fn overtaken(&self) -> u64 {
        self.overtaken.load(Ordering::Relaxed)
    }

    /// From now on, lets each scene go as soon as a stream opened on it, as a worker that
    /// restarts (or evicts the scene) between two streams of a job would: every open that
    /// names a scene by digest alone is then refused as unknown, and the coordinator must
    /// send the scene again.
    pub fn forget_scenes(&self) {
        let mut scenes = self.scenes.lock().unwrap_or_else(|e| e.into_inner());
        self.forgetful.store(true, Ordering::Relaxed);
        scenes.clear();
    }

    /// Opens refused so far because they named a scene not held.
    pub fn scenes_unknown(&self) -> u64 {
        self.unknown.load(Ordering::Relaxed)
    }

    /// The job's scene and its tables, parsed on the first stream that names it.
    fn open(&self, open: &pb::CastOpen) -> Result<(Arc<SceneAnswers>, usize), Status> {
        let mut scenes = self.scenes.lock().unwrap_or_else(|e| e.into_inner());
        // As a worker keeps them: by digest, which streams after the first name alone.
        let id: [u8; 32] = if open.scene_toml.is_empty() {
            open.scene_digest.as_slice().try_into().unwrap_or_default()
        } else {
            convert::scene_digest(
                &open.scene_toml,
                &open.scene_name,
                &open.headers,
                open.shadow_maps_computed.then_some(&open.shadow_maps[..]),
            )
        };
        let answers = match scenes.get(&id) {
            Some(a) => a.clone(),
            None if open.scene_toml.is_empty() => {
                self.unknown.fetch_add(1, Ordering::Relaxed);
                let message = "the stand-in holds no scene of that digest".to_string();
                return Err(convert::failure_status(convert::failure(pb::Reason::SceneUnknown, true, message)));
            }
            None => {
                let scene = trove_worker::cast::parse_job_scene(&self.files, open)?;
                let tables = scene.datasets().iter().map(|_| RwLock::new(HashMap::new())).collect();
                let a = Arc::new(SceneAnswers { scene: Arc::new(scene), tables });
                if !self.forgetful.load(Ordering::Relaxed) {
                    scenes.insert(id, a.clone());
                }
                a
            }
        };
        let d = open.dataset as usize;
        match answers.scene.datasets().get(d) {
            Some(info) if info.is_local() => Ok((answers, d)),
            _ => Err(convert::failure_status(convert::failure(
                pb::Reason::DatasetNotHeld,
                true,
                format!("the stand-in cannot cast dataset {d}"),
            ))),
        }
    }

    /// The recorded results of `tasks`, or `None` when one of them is not recorded yet.
    fn look_up(&self, job: &SceneAnswers, d: usize, tasks: &[PieceTask]) -> Option<(Vec<PieceRgba>, u64)> {
        let table = job.tables[d].read().unwrap_or_else(|e| e.into_inner());
        let mut samples = 0;
        let mut out = Vec::with_capacity(tasks.len());
        for t in tasks {
            let a = table.get(&key(t))?;
            samples += a.samples;
            out.push(a.rgba);
        }
        self.answered.fetch_add(tasks.len() as u64, Ordering::Relaxed);
        Some((out, samples))
    }

    /// Casts the tasks not recorded yet, one task at a time (so each has its own sample
    /// count), records them, and answers every task (blocking).
    fn cast_and_look_up(
        &self,
        job: &SceneAnswers,
        d: usize,
        tasks: &[PieceTask],
    ) -> Result<(Vec<PieceRgba>, u64), Box<pb::Failure>> {
        let missing: Vec<PieceTask> = {
            let table = job.tables[d].read().unwrap_or_else(|e| e.into_inner());
            tasks.iter().filter(|t| !table.contains_key(&key(t))).copied().collect()
        };
        let pinned = self.store.get(&job.scene.datasets()[d]).map_err(|e| Box::new(convert::store_failure(&e)))?;
        let caster = BatchCaster::new(&job.scene, d, &pinned).map_err(|e| Box::new(convert::cast_failure(&e)))?;
        let cast: Vec<Answer> = self
            .pool
            .install(|| {
                missing
                    .par_iter()
                    .map(|t| {
                        let mut out = [PieceRgba::default()];
                        let samples = caster.cast(std::slice::from_ref(t), &mut out)?;
                        Ok(Answer { rgba: out[0], samples })
                    })
                    .collect::<Result<Vec<Answer>, CastError>>()
            })
            .map_err(|e| Box::new(convert::cast_failure(&e)))?;
        self.cast.fetch_add(missing.len() as u64, Ordering::Relaxed);
        {
            let mut table = job.tables[d].write().unwrap_or_else(|e| e.into_inner());
            table.extend(missing.iter().map(key).zip(cast));
        }
        Ok(self.look_up(job, d, tasks).expect("every task was recorded above"))
    }
}

/// One batch's answer (blocking only when something must be cast).
async fn answer(answers: &Arc<Answers>, job: &Arc<SceneAnswers>, d: usize, batch: pb::CastBatch) -> pb::CastResponse {
    let failure = |mut f: pb::Failure| {
        f.batch_id = batch.batch_id;
        pb::cast_response::Kind::Failure(f)
    };
    let kind = match decode_tasks(&batch.tasks) {
        Err(e) => failure(convert::failure(pb::Reason::BadBatch, false, format!("batch {}: {e}", batch.batch_id))),
        Ok(tasks) => {
            let found = match answers.look_up(job, d, &tasks) {
                Some(found) => Ok(found),
                None => {
                    let (answers, job) = (answers.clone(), job.clone());
                    tokio::task::spawn_blocking(move || answers.cast_and_look_up(&job, d, &tasks))
                        .await
                        .unwrap_or_else(|e| Err(Box::new(convert::failure(pb::Reason::Internal, false, e.to_string()))))
                }
            };
            match found {
                Ok((results, samples)) => pb::cast_response::Kind::Result(pb::BatchResult {
                    batch_id: batch.batch_id,
                    attempt: batch.attempt,
                    results: encode_results(&results),
                    samples,
                    bytes_loaded: 0,
                    loading_nanos: 0,
                    casting_nanos: 0,
                    // Recorded results carry no shading counts.
                    shading_evaluations: Default::default(),
                }),
                Err(f) => failure(*f),
            }
        }
    };
    pb::CastResponse { kind: Some(kind) }
}

/// In what order a stand-in answers the batches of one stream.
#[derive(Clone, Copy, Debug)]
pub enum Order {
    /// Each batch as it arrives (a worker with one thread).
    AsReceived,
    /// Batches held until `hold` have arrived (or none arrives for a millisecond), then
    /// answered in an order drawn from `seed`: what a worker of many threads does, and the
    /// harshest arrival order a coordinator may meet. The order is the only thing timing
    /// changes; a correct coordinator composites the same image whatever it is.
    Shuffled {
        /// Seeds the order (per stream, mixed with its dataset).
        seed: u64,
        /// Batches held before answering.
        hold: usize,
    },
    /// No stream is ever accepted: each open waits forever, as on a worker alive to the
    /// coordinator and stuck (its disk hung, its process starved). A coordinator must go on
    /// with other holders.
    Never,
}

/// A small deterministic generator for [`Order::Shuffled`] (xorshift64*).
struct Draws(u64);

impl Draws {
    fn below(&mut self, n: usize) -> usize {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 33) as usize % n.max(1)
    }
}

/// The `Worker` service of a stand-in.
struct StandInService {
    answers: Arc<Answers>,
    order: Order,
}

#[tonic::async_trait]
impl Worker for StandInService {
    type CastStream = ReceiverStream<Result<pb::CastResponse, Status>>;

    /// Stand-ins answer recorded batches; a scene with shadows is not one they were recorded
    /// from.
    async fn shadow(&self, _: Request<pb::ShadowRequest>) -> Result<Response<pb::ShadowReply>, Status> {
        Err(Status::unimplemented("stand-in workers do not run the shadow pass"))
    }

    async fn cast(&self, request: Request<Streaming<pb::CastRequest>>) -> Result<Response<Self::CastStream>, Status> {
        if matches!(self.order, Order::Never) {
            std::future::pending::<()>().await;
        }
        let mut inbound = request.into_inner();
        let open = match inbound.message().await? {
            Some(pb::CastRequest { kind: Some(pb::cast_request::Kind::Open(open)) }) => open,
            _ => return Err(Status::invalid_argument("a cast stream starts with an `open` message")),
        };
        let answers = self.answers.clone();
        let (job, d) = tokio::task::spawn_blocking(move || answers.open(&open))
            .await
            .map_err(|e| Status::internal(format!("opening the job failed: {e}")))??;
        let (out, out_rx) = mpsc::channel(64);
        let (answers, order) = (self.answers.clone(), self.order);
        tokio::spawn(async move {
            let (hold, mut draws) = match order {
                Order::AsReceived | Order::Never => (1, Draws(1)),
                Order::Shuffled { seed, hold } => (hold.max(1), Draws((seed ^ (d as u64 + 1) << 32) | 1)),
            };
            let mut held = Vec::new();
            let mut latest = 0;
            loop {
                // Held batches wait for more only briefly: a coordinator with nothing more
                // to send waits for these answers.
                let next = if held.is_empty() {
                    Some(inbound.message().await)
                } else {
                    tokio::time::timeout(Duration::from_millis(1), inbound.message()).await.ok()
                };
                let timed_out = next.is_none();
                let ended = match next {
                    Some(Ok(Some(pb::CastRequest { kind: Some(pb::cast_request::Kind::Batch(batch)) }))) => {
                        held.push(batch);
                        false
                    }
                    // Nothing arrived in time: answer what is held.
                    None => false,
                    _ => true,
                };
                if held.len() >= hold || timed_out || ended {
                    while !held.is_empty() {
                        let batch = held.swap_remove(draws.below(held.len()));
                        if batch.batch_id < latest {
                            answers.overtaken.fetch_add(1, Ordering::Relaxed);
                        }
                        latest = latest.max(batch.batch_id);
                        if out.send(Ok(answer(&answers, &job, d, batch).await)).await.is_err() {
                            return;
                        }
                    }
                }
                if ended {
                    return;
                }
            }
        });
        Ok(Response::new(ReceiverStream::new(out_rx)))
    }
}

/// Serves one stand-in on `listener` until `shutdown` resolves, registered with the
/// coordinator at `coordinator` (a URL) as a worker of `threads` threads that holds every
/// file of `answers`' data root, at the listener's address.
pub async fn serve(
    listener: TcpListener,
    shutdown: impl Future<Output = ()>,
    coordinator: &str,
    threads: u32,
    answers: Arc<Answers>,
) -> Result<(), tonic::transport::Error> {
    serve_in_order(listener, shutdown, coordinator, threads, answers, Order::AsReceived).await
}

/// As [`serve`], answering each stream's batches in `order`.
pub async fn serve_in_order(
    listener: TcpListener,
    shutdown: impl Future<Output = ()>,
    coordinator: &str,
    threads: u32,
    answers: Arc<Answers>,
    order: Order,
) -> Result<(), tonic::transport::Error> {
    let address = listener.local_addr().map(|a| a.to_string()).unwrap_or_default();
    // Plaintext and without a token, as the coordinators it serves are configured.
    let deadline = Duration::from_secs(5);
    let channel = tonic::transport::Endpoint::from_shared(coordinator.to_string())?
        .connect_timeout(deadline)
        .timeout(deadline)
        .connect_lazy();
    let files = answers.files.registration();
    let serve = tonic::transport::Server::builder()
        .add_service(
            WorkerServer::new(StandInService { answers, order })
                .max_decoding_message_size(trove_proto::MAX_MESSAGE_BYTES)
                .max_encoding_message_size(trove_proto::MAX_MESSAGE_BYTES),
        )
        .serve_with_incoming_shutdown(trove_proto::connect::incoming(listener), shutdown);
    tokio::select! {
        served = serve => served,
        () = stay_registered(MembershipClient::new(channel), address, files, threads) => Ok(()),
    }
}

/// Registers, then heartbeats, registering again whenever the coordinator forgets it
/// (`trove-worker`'s membership, with the thread count given rather than rayon's).
async fn stay_registered(
    mut client: MembershipClient<tonic::transport::Channel>,
    address: String,
    files: Vec<pb::DatasetFile>,
    threads: u32,
) {
    loop {
        // No id of its own, as an older worker: the coordinator assigns one.
        let request = pb::RegisterRequest {
            address: address.clone(),
            files: files.clone(),
            threads,
            memory_budget: 0,
            worker_id: String::new(),
        };
        let registered = match client.register(request).await {
            Ok(r) => r.into_inner(),
            Err(_) => {
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let every = Duration::from_millis(registered.heartbeat_millis.max(10) as u64);
        loop {
            tokio::time::sleep(every).await;
            let beat = pb::HeartbeatRequest { worker_id: registered.worker_id.clone(), batches_in_flight: 0 };
            match client.heartbeat(beat).await {
                Ok(r) if r.get_ref().known => {}
                Ok(_) => break,
                Err(_) => {}
            }
        }
    }
}
