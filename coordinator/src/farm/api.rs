//! The coordinator's two gRPC services: `Coordinator` for clients (jobs) and `Membership`
//! for workers (registration, heartbeats). Both translate at this edge: requests become
//! `trove-core` scenes and jobs, failures become typed `Failure`s in gRPC statuses.

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};
use trove_core::render::limits::{check_pfm, LimitError, Work};
use trove_core::scene::Scene;
use trove_proto::convert;
use trove_proto::v1 as pb;

use super::driver::{self, DriverConfig, JobPlan};
use super::jobs::{is_final, Admission, Jobs};
use super::registry::Registry;

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
    let (w, h) = (scene.image().width, scene.image().height);
    if options.want_pfm {
        check_pfm(w, h, farm.driver.max_pfm_pixels).map_err(limited)?;
    }
    let work = Work::count(&scene).map_err(limited)?;
    let band_rows = farm.driver.band_rows(&scene, &work, &options).map_err(limited)?;
    work.check_bands(band_rows, farm.driver.memory_bound).map_err(limited)?;
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
    })
}

#[tonic::async_trait]
impl pb::coordinator_server::Coordinator for CoordinatorService {
    async fn submit_job(
        &self,
        request: Request<pb::SubmitJobRequest>,
    ) -> Result<Response<pb::SubmitJobResponse>, Status> {
        let farm = self.0.clone();
        let request = request.into_inner();
        let planned = {
            let farm = farm.clone();
            tokio::task::spawn_blocking(move || plan(&farm, request))
                .await
                .map_err(|e| Status::internal(format!("validating the scene failed: {e}")))?
        };
        let plan = planned?;
        let job = farm.jobs.create(&plan.scene_name);
        farm.admission.enqueue(job.clone());
        tracing::info!(job = %job.id, scene = %plan.scene_name, queued = farm.admission.waiting(), "job submitted");
        let id = job.id.clone();
        let (registry, jobs, config) = (farm.registry.clone(), farm.jobs.clone(), farm.driver.clone());
        let admission = farm.admission.clone();
        tokio::spawn(async move {
            let job_id = job.id.clone();
            match admission.admit(&job).await {
                Some(slot) => {
                    // The driver runs as a task of its own, so that a panic in it fails this
                    // job (and frees its room) instead of leaving it RUNNING.
                    let ran = tokio::spawn(driver::run(plan, job.clone(), registry, config)).await;
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
            }
            jobs.finished(&job_id);
        });
        Ok(Response::new(pb::SubmitJobResponse { job_id: id }))
    }

    type WatchJobStream = ReceiverStream<Result<pb::JobStatus, Status>>;

    async fn watch_job(&self, request: Request<pb::WatchJobRequest>) -> Result<Response<Self::WatchJobStream>, Status> {
        let id = request.into_inner().job_id;
        let job = self.0.jobs.get(&id).ok_or_else(|| not_found(&id))?;
        let mut updates = job.watch();
        let (tx, rx) = mpsc::channel(16);
        tokio::spawn(async move {
            loop {
                let status = updates.borrow_and_update().clone();
                let done = is_final(status.state());
                if tx.send(Ok(status)).await.is_err() || done {
                    return;
                }
                if updates.changed().await.is_err() {
                    return;
                }
                // Coalesce bursts: a watcher needs the latest state, not every step.
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        });
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
        let Some(output) = job.output() else {
            let state = status.state();
            let failure = status.failure.unwrap_or_else(|| {
                convert::failure(pb::Reason::NotFound, true, format!("job `{id}` has no result yet ({state:?})"))
            });
            return Err(convert::failure_status(failure));
        };
        let (tx, rx) = mpsc::channel(4);
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
        Ok(Response::new(pb::ListJobsResponse { jobs: self.0.jobs.list() }))
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
        let id = registry
            .register(request)
            .map_err(|e| Status::invalid_argument(format!("the worker's address is not usable: {e}")))?;
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
}
