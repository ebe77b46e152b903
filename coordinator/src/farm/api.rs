//! The coordinator's two gRPC services: `Coordinator` for clients (jobs) and `Membership`
//! for workers (registration, heartbeats). Both translate at this edge: requests become
//! `trove-core` scenes and jobs, failures become typed `Failure`s in gRPC statuses.
//!
//! A job is validated (`plan.rs`) before it is accepted, then waits for its turn and runs
//! on a task of its own. Jobs a restarted coordinator finds unfinished in its state store
//! ([`resume`]) are queued again in submission order and validated again once the
//! workers are back: a dataset not held yet is waited for, a while, before the job fails.

use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};
use trove_core::render::limits::LimitError;
use trove_core::scene::Scene;
use trove_proto::convert;
use trove_proto::v1 as pb;

use super::drain::Drain;
use super::driver::{self, DriverConfig, JobPlan};
use super::jobs::{forward_statuses, is_final, Admission, Job, Jobs};
use super::registry::{RegisterError, Registry};
use super::state::StateError;

/// What both services share.
pub struct Farm {
    /// The workers.
    pub registry: Arc<Registry>,
    /// The jobs.
    pub jobs: Arc<Jobs>,
    /// How jobs treat workers.
    pub driver: DriverConfig,
    /// How many jobs run at once; the others wait in order.
    pub admission: Arc<Admission>,
    /// Whether the coordinator is stopping, and the jobs it waits for.
    pub drain: Arc<Drain>,
}

impl Farm {
    /// How long a resumed job waits for a worker holding its datasets: workers register
    /// again within a heartbeat or two of a restart.
    pub fn resume_grace(&self) -> Duration {
        (self.registry.heartbeat() * 10).max(Duration::from_secs(5))
    }
}

/// The client-facing service.
pub struct CoordinatorService(pub Arc<Farm>);

/// The worker-facing service.
pub struct MembershipService(pub Arc<Farm>);

fn not_found(job: &str) -> Status {
    convert::failure_status(convert::failure(pb::Reason::NotFound, false, format!("no job `{job}`")))
}

/// Validates a submitted scene against the files alive workers hold (blocking: it parses
/// and checks geometry, never reads a voxel).
fn plan(farm: &Farm, request: pb::SubmitJobRequest) -> Result<JobPlan, Status> {
    let catalog = farm.registry.catalog();
    let name = if request.scene_name.is_empty() { "scene.toml".to_string() } else { request.scene_name };
    let scene = Scene::parse_with(&request.scene_toml, std::path::Path::new(&name), &catalog)
        .map_err(|e| convert::failure_status(convert::scene_failure(&e)))?;
    // The work and memory the job would take, checked before it is queued: its tasks
    // counted without storing one, each band as the driver will size it, and its PFM.
    let options = request.options.unwrap_or_default();
    let limited = |e: LimitError| {
        let mut f = convert::limit_failure(&e);
        f.file = name.clone();
        convert::limit_status(f)
    };
    let counting = std::time::Instant::now();
    let (_, band_rows, kept) = farm.driver.check_work(&scene, &options).map_err(limited)?;
    let counting_seconds = counting.elapsed().as_secs_f64();
    let dataset_keys: Vec<Vec<String>> = scene.datasets().iter().map(|d| d.file_keys()).collect();
    for d in scene.used_datasets() {
        if farm.registry.holders(&dataset_keys[d]).is_empty() {
            let info = &scene.datasets()[d];
            let mut f = convert::failure(
                pb::Reason::DatasetNotHeld,
                true,
                format!(
                    "{name}: dataset `{}`: no worker holds all of its files ({})",
                    info.name(),
                    dataset_keys[d].join(", ")
                ),
            );
            f.file = name.clone();
            f.dataset = info.name().to_string();
            return Err(convert::failure_status(f));
        }
    }
    let mut headers: Vec<pb::DatasetFile> =
        dataset_keys.iter().flatten().filter_map(|k| catalog.file(k).cloned()).collect();
    headers.sort_by(|a, b| a.key.cmp(&b.key));
    headers.dedup_by(|a, b| a.key == b.key);
    Ok(JobPlan {
        scene: Arc::new(scene),
        scene_toml: request.scene_toml,
        scene_name: name,
        options,
        headers,
        dataset_keys,
        band_rows,
        kept: kept.into_iter().map(Some).collect(),
        counting_seconds,
    })
}

/// A state store that cannot be read or written, as a typed status (retryable: the disk may
/// come back).
fn state_status(e: &StateError) -> Status {
    convert::failure_status(convert::failure(pb::Reason::Internal, true, format!("the coordinator's state: {e}")))
}

/// Where a job's plan comes from.
enum Pending {
    /// Validated at submission.
    Planned(JobPlan),
    /// Resumed after a restart: validated again once workers hold its datasets.
    Resumed(pb::SubmitJobRequest),
}

/// Runs `job` (already in the admission queue) on a task of its own: its turn, its driver,
/// and its end written down.
fn spawn_job(farm: Arc<Farm>, job: Arc<Job>, pending: Pending) {
    // Held until the job's end is written down: a draining coordinator waits for it.
    let tracked = farm.drain.track(job.clone());
    tokio::spawn(async move {
        let job_id = job.id.clone();
        let plan = match pending {
            Pending::Planned(plan) => Some(plan),
            Pending::Resumed(request) => replan(&farm, &job, request).await,
        };
        let (registry, config, admission) = (farm.registry.clone(), farm.driver.clone(), farm.admission.clone());
        match plan {
            None => admission.leave(&job),
            Some(mut plan) => match {
                // A job that must wait for its turn drops the bands its count kept: waiting
                // jobs hold no pieces, so the queue's memory does not grow with its length.
                let mut admit = std::pin::pin!(admission.admit(&job));
                tokio::select! {
                    biased;
                    slot = &mut admit => slot,
                    () = std::future::ready(()) => {
                        plan.kept.clear();
                        admit.await
                    }
                }
            } {
                Some(slot) => {
                    // The start is written while the job runs, not before: the record only
                    // changes what a restart reports (a QUEUED or RUNNING job runs again from
                    // the start either way), and its commit waits on the disk. It is written
                    // before the end is (awaited below), so it never overwrites the end.
                    let jobs = farm.jobs.clone();
                    let running = job.clone();
                    let start_written = tokio::task::spawn_blocking(move || jobs.started(&running));
                    // The driver runs as a task of its own, so that a panic in it fails this
                    // job (and frees its room) instead of leaving it RUNNING.
                    let ran = tokio::spawn(driver::run(plan, job.clone(), registry, config)).await;
                    match start_written.await {
                        Ok(Err(e)) => tracing::error!(job = %job_id, error = %e, "cannot write the job's start"),
                        Err(e) => tracing::error!(job = %job_id, error = %e, "cannot write the job's start"),
                        Ok(Ok(())) => {}
                    }
                    if let Err(e) = ran {
                        let message = match e.try_into_panic() {
                            Ok(payload) => format!("the job's driver panicked: {}", driver::panic_message(&*payload)),
                            Err(e) => format!("the job's driver stopped: {e}"),
                        };
                        tracing::error!(job = %job_id, %message, "job ended");
                        job.update(|s| {
                            s.state = pb::JobState::Failed as i32;
                            s.failure = Some(convert::failure(pb::Reason::Internal, false, message));
                        });
                    }
                    drop(slot);
                }
                None => job.update(|s| {
                    s.state = pb::JobState::Cancelled as i32;
                    let message = "the job was cancelled while queued".to_string();
                    s.failure = Some(convert::failure(pb::Reason::Cancelled, false, message));
                }),
            },
        }
        let jobs = farm.jobs.clone();
        if let Err(e) = tokio::task::spawn_blocking(move || jobs.finished(&job_id)).await {
            tracing::error!(error = %e, "recording a job's end failed");
        }
        drop(tracked);
    });
}

/// Validates a resumed job again, waiting up to [`Farm::resume_grace`] from now while the
/// only trouble is a dataset that no worker holds yet (workers re-register after a
/// restart); any other refusal, or one past the grace, fails the job as a submission
/// would have been refused. `None` when it failed or was cancelled.
async fn replan(farm: &Arc<Farm>, job: &Arc<Job>, request: pb::SubmitJobRequest) -> Option<JobPlan> {
    let until = Instant::now() + farm.resume_grace();
    let retry = farm.registry.heartbeat().clamp(Duration::from_millis(20), Duration::from_secs(1));
    let mut cancelled = job.cancelled();
    loop {
        let planned = {
            let (farm, request) = (farm.clone(), request.clone());
            tokio::task::spawn_blocking(move || plan(&farm, request)).await
        };
        let status = match planned {
            Ok(Ok(plan)) => return Some(plan),
            Ok(Err(status)) => status,
            Err(e) => Status::internal(format!("validating the scene failed: {e}")),
        };
        let failure = convert::status_failure(&status).unwrap_or_else(|| {
            convert::failure(pb::Reason::Internal, false, format!("{}: {}", status.code(), status.message()))
        });
        if failure.reason() != pb::Reason::DatasetNotHeld || Instant::now() >= until {
            tracing::warn!(job = %job.id, reason = ?failure.reason(), message = %failure.message, "resumed job cannot run");
            job.update(|s| {
                s.state = pb::JobState::Failed as i32;
                s.failure = Some(failure);
            });
            return None;
        }
        tokio::select! {
            _ = tokio::time::sleep(retry) => {}
            _ = cancelled.wait_for(|c| *c) => {
                job.update(|s| {
                    s.state = pb::JobState::Cancelled as i32;
                    let message = "the job was cancelled while it waited for its workers".to_string();
                    s.failure = Some(convert::failure(pb::Reason::Cancelled, false, message));
                });
                return None;
            }
        }
    }
}

/// Queues again, in submission order, every job the state store holds that had not ended
/// (QUEUED or RUNNING when the coordinator stopped); they run again from the start. Returns
/// how many. Blocking: it reads the store.
pub fn resume(farm: &Arc<Farm>) -> Result<usize, StateError> {
    let Some(store) = farm.jobs.store() else { return Ok(0) };
    let mut resumed = 0;
    for record in store.jobs()? {
        if is_final(record.state()) {
            continue;
        }
        let job = farm.jobs.resume(&record);
        tracing::info!(job = %job.id, scene = %record.scene_name, was = ?record.state(), "job resumed");
        farm.admission.enqueue(job.clone());
        let request = pb::SubmitJobRequest {
            scene_toml: record.scene_toml,
            scene_name: record.scene_name,
            options: record.options,
        };
        spawn_job(farm.clone(), job, Pending::Resumed(request));
        resumed += 1;
    }
    Ok(resumed)
}

#[tonic::async_trait]
impl pb::coordinator_server::Coordinator for CoordinatorService {
    async fn submit_job(
        &self,
        request: Request<pb::SubmitJobRequest>,
    ) -> Result<Response<pb::SubmitJobResponse>, Status> {
        let farm = self.0.clone();
        if farm.drain.is_draining() {
            return Err(Drain::refusal());
        }
        let request = request.into_inner();
        let planned = {
            let farm = farm.clone();
            // Validated, then written down before its id is answered.
            tokio::task::spawn_blocking(move || {
                let plan = plan(&farm, request)?;
                let job = farm
                    .jobs
                    .submit(&plan.scene_toml, &plan.scene_name, &plan.options)
                    .map_err(|e| state_status(&e))?;
                Ok::<_, Status>((plan, job))
            })
            .await
            .map_err(|e| Status::internal(format!("validating the scene failed: {e}")))?
        };
        let (plan, job) = planned?;
        farm.admission.enqueue(job.clone());
        tracing::info!(job = %job.id, scene = %plan.scene_name, queued = farm.admission.waiting(), "job submitted");
        let id = job.id.clone();
        spawn_job(farm, job, Pending::Planned(plan));
        Ok(Response::new(pb::SubmitJobResponse { job_id: id }))
    }

    type WatchJobStream = ReceiverStream<Result<pb::JobStatus, Status>>;

    async fn watch_job(&self, request: Request<pb::WatchJobRequest>) -> Result<Response<Self::WatchJobStream>, Status> {
        let id = request.into_inner().job_id;
        let job = self.0.jobs.get(&id).ok_or_else(|| not_found(&id))?;
        let (tx, rx) = mpsc::channel(16);
        tokio::spawn(forward_statuses(job.watch(), tx, Ok));
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    type GetResultStream = ReceiverStream<Result<pb::ResultChunk, Status>>;

    async fn get_result(
        &self,
        request: Request<pb::GetResultRequest>,
    ) -> Result<Response<Self::GetResultStream>, Status> {
        let id = request.into_inner().job_id;
        let job = self.0.jobs.get(&id).ok_or_else(|| not_found(&id))?;
        let status = job.status();
        let output = {
            let (jobs, job) = (self.0.jobs.clone(), job.clone());
            tokio::task::spawn_blocking(move || jobs.output(&job))
                .await
                .map_err(|e| Status::internal(format!("reading the result failed: {e}")))?
                .map_err(|e| state_status(&e))?
        };
        let Some(output) = output else {
            let state = status.state();
            let failure = status.failure.unwrap_or_else(|| {
                convert::failure(pb::Reason::NotFound, true, format!("job `{id}` has no result yet ({state:?})"))
            });
            return Err(convert::failure_status(failure));
        };
        let (tx, rx) = mpsc::channel(4);
        let drain = self.0.drain.clone();
        tokio::spawn(async move {
            let parts = [
                (pb::ResultPart::Png, Some(&output.png)),
                (pb::ResultPart::Pfm, output.pfm.as_ref()),
                (pb::ResultPart::StatsJson, Some(&output.stats_json)),
            ];
            for (part, bytes) in parts {
                let Some(bytes) = bytes else { continue };
                let total = bytes.len() as u64;
                for (i, chunk) in bytes.chunks(trove_proto::RESULT_CHUNK_BYTES).enumerate() {
                    let message = pb::ResultChunk {
                        part: part as i32,
                        offset: (i * trove_proto::RESULT_CHUNK_BYTES) as u64,
                        total,
                        data: chunk.to_vec(),
                    };
                    if tx.send(Ok(message)).await.is_err() {
                        return;
                    }
                }
            }
            drain.fetched(&id);
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn cancel_job(
        &self,
        request: Request<pb::CancelJobRequest>,
    ) -> Result<Response<pb::CancelJobResponse>, Status> {
        let id = request.into_inner().job_id;
        let job = self.0.jobs.get(&id).ok_or_else(|| not_found(&id))?;
        if job.cancel() {
            tracing::info!(job = %id, "cancel requested");
        }
        Ok(Response::new(pb::CancelJobResponse { state: job.status().state }))
    }

    async fn list_workers(
        &self,
        _: Request<pb::ListWorkersRequest>,
    ) -> Result<Response<pb::ListWorkersResponse>, Status> {
        Ok(Response::new(pb::ListWorkersResponse { workers: self.0.registry.list() }))
    }

    async fn list_jobs(&self, _: Request<pb::ListJobsRequest>) -> Result<Response<pb::ListJobsResponse>, Status> {
        let jobs = self.0.jobs.clone();
        let listed = tokio::task::spawn_blocking(move || jobs.list())
            .await
            .map_err(|e| Status::internal(format!("listing the jobs failed: {e}")))?;
        Ok(Response::new(pb::ListJobsResponse { jobs: listed }))
    }
}

#[tonic::async_trait]
impl pb::membership_server::Membership for MembershipService {
    async fn register(&self, request: Request<pb::RegisterRequest>) -> Result<Response<pb::RegisterResponse>, Status> {
        let request = request.into_inner();
        if request.address.is_empty() {
            return Err(Status::invalid_argument("a worker registers with the address it listens on"));
        }
        let registry = &self.0.registry;
        let id = registry.register(request).map_err(|e| match e {
            RegisterError::IdTaken { .. } => Status::already_exists(e.to_string()),
            RegisterError::Address { .. } | RegisterError::BadId { .. } => Status::invalid_argument(e.to_string()),
        })?;
        Ok(Response::new(pb::RegisterResponse {
            worker_id: id,
            heartbeat_millis: registry.heartbeat().as_millis() as u32,
        }))
    }

    async fn heartbeat(
        &self,
        request: Request<pb::HeartbeatRequest>,
    ) -> Result<Response<pb::HeartbeatResponse>, Status> {
        let known = self.0.registry.heartbeat_from(&request.into_inner().worker_id);
        Ok(Response::new(pb::HeartbeatResponse { known }))
    }

    async fn deregister(
        &self,
        request: Request<pb::DeregisterRequest>,
    ) -> Result<Response<pb::DeregisterResponse>, Status> {
        let id = request.into_inner().worker_id;
        if !self.0.registry.deregister(&id) {
            tracing::debug!(worker = %id, "an unknown worker deregistered");
        }
        Ok(Response::new(pb::DeregisterResponse {}))
    }
}
