//! A client of a farm's job API: what `trove render --coordinator URL` does, as a library
//! (submit a scene, follow the job, fetch its files), so tests drive a farm the way a user
//! does.

use std::time::Duration;

use thiserror::Error;
use tonic::transport::{Channel, Endpoint};
use tonic::Status;
use trove_proto::convert;
use trove_proto::v1 as pb;
use trove_proto::v1::coordinator_client::CoordinatorClient;

/// Deadline of a call that does not stream.
const CALL_DEADLINE: Duration = Duration::from_secs(60);

/// Why a farm render failed, as the user should read it.
#[derive(Debug, Error)]
pub enum ClientError {
    /// The coordinator cannot be reached.
    #[error("cannot reach the coordinator at {url}: {source}")]
    Connect {
        /// Its URL.
        url: String,
        /// Why.
        #[source]
        source: tonic::transport::Error,
    },
    /// The coordinator or the job refused, with a typed reason.
    #[error("{}", .0.message)]
    Failed(Box<pb::Failure>),
    /// A call failed without a typed reason (network, protocol).
    #[error("the coordinator answered {}: {}", .0.code(), .0.message())]
    Rpc(Box<Status>),
    /// The result stream was incomplete.
    #[error("the job's result arrived incomplete")]
    Incomplete,
}

impl From<Status> for ClientError {
    fn from(status: Status) -> ClientError {
        match convert::status_failure(&status) {
            Some(f) => ClientError::Failed(Box::new(f)),
            None => ClientError::Rpc(Box::new(status)),
        }
    }
}

impl ClientError {
    /// The typed failure, when there is one.
    pub fn failure(&self) -> Option<&pb::Failure> {
        match self {
            ClientError::Failed(f) => Some(f),
            _ => None,
        }
    }
}

/// A finished job's files.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct JobFiles {
    /// The 8-bit image, as a PNG file.
    pub png: Vec<u8>,
    /// The unquantised image as a PFM file, when asked for.
    pub pfm: Option<Vec<u8>>,
    /// Statistics as JSON.
    pub stats_json: Vec<u8>,
}

/// A connection to a coordinator's job API.
#[derive(Clone)]
pub struct FarmClient {
    inner: CoordinatorClient<Channel>,
}

impl FarmClient {
    /// Connects to the coordinator at `url` (e.g. `http://127.0.0.1:7000`).
    pub async fn connect(url: &str) -> Result<FarmClient, ClientError> {
        let connect = |source| ClientError::Connect { url: url.to_string(), source };
        let channel = Endpoint::from_shared(url.to_string())
            .map_err(connect)?
            .connect_timeout(Duration::from_secs(10))
            .tcp_nodelay(true)
            .connect()
            .await
            .map_err(connect)?;
        let limit = trove_proto::MAX_MESSAGE_BYTES;
        Ok(FarmClient {
            inner: CoordinatorClient::new(channel).max_decoding_message_size(limit).max_encoding_message_size(limit),
        })
    }

    /// Submits a scene; returns the job's id.
    pub async fn submit(
        &mut self,
        scene_toml: String,
        scene_name: String,
        options: pb::JobOptions,
    ) -> Result<String, ClientError> {
        let mut request = tonic::Request::new(pb::SubmitJobRequest { scene_toml, scene_name, options: Some(options) });
        request.set_timeout(CALL_DEADLINE);
        Ok(self.inner.submit_job(request).await?.into_inner().job_id)
    }

    /// Follows job `id` until it ends, calling `progress` with every status; returns the
    /// last one.
    pub async fn watch(
        &mut self,
        id: &str,
        mut progress: impl FnMut(&pb::JobStatus),
    ) -> Result<pb::JobStatus, ClientError> {
        let mut stream = self.inner.watch_job(pb::WatchJobRequest { job_id: id.to_string() }).await?.into_inner();
        let mut last = None;
        while let Some(status) = stream.message().await? {
            progress(&status);
            last = Some(status);
        }
        last.ok_or(ClientError::Incomplete)
    }

    /// The files of finished job `id`.
    pub async fn result(&mut self, id: &str) -> Result<JobFiles, ClientError> {
        let mut request = tonic::Request::new(pb::GetResultRequest { job_id: id.to_string() });
        request.set_timeout(Duration::from_secs(600));
        let mut stream = self.inner.get_result(request).await?.into_inner();
        let mut files = JobFiles::default();
        while let Some(chunk) = stream.message().await? {
            let part = match chunk.part() {
                pb::ResultPart::Png => &mut files.png,
                pb::ResultPart::Pfm => files.pfm.get_or_insert_with(Vec::new),
                pb::ResultPart::StatsJson => &mut files.stats_json,
                pb::ResultPart::Unspecified => continue,
            };
            if part.len() as u64 != chunk.offset {
                return Err(ClientError::Incomplete);
            }
            part.extend_from_slice(&chunk.data);
        }
        if files.png.is_empty() {
            return Err(ClientError::Incomplete);
        }
        Ok(files)
    }

    /// Asks the coordinator to stop job `id`.
    pub async fn cancel(&mut self, id: &str) -> Result<pb::JobState, ClientError> {
        let mut request = tonic::Request::new(pb::CancelJobRequest { job_id: id.to_string() });
        request.set_timeout(CALL_DEADLINE);
        Ok(self.inner.cancel_job(request).await?.into_inner().state())
    }

    /// The workers the coordinator knows.
    pub async fn workers(&mut self) -> Result<Vec<pb::WorkerInfo>, ClientError> {
        let mut request = tonic::Request::new(pb::ListWorkersRequest {});
        request.set_timeout(CALL_DEADLINE);
        Ok(self.inner.list_workers(request).await?.into_inner().workers)
    }

    /// The jobs the coordinator holds, oldest submission first.
    pub async fn jobs(&mut self) -> Result<Vec<pb::JobSummary>, ClientError> {
        let mut request = tonic::Request::new(pb::ListJobsRequest {});
        request.set_timeout(CALL_DEADLINE);
        Ok(self.inner.list_jobs(request).await?.into_inner().jobs)
    }

    /// Submits, follows and fetches: a whole render through the farm.
    pub async fn render(
        &mut self,
        scene_toml: String,
        scene_name: String,
        options: pb::JobOptions,
        progress: impl FnMut(&pb::JobStatus),
    ) -> Result<JobFiles, ClientError> {
        let id = self.submit(scene_toml, scene_name, options).await?;
        let last = self.watch(&id, progress).await?;
        match last.state() {
            pb::JobState::Succeeded => self.result(&id).await,
            state => Err(ClientError::Failed(Box::new(last.failure.unwrap_or_else(|| {
                convert::failure(pb::Reason::Internal, false, format!("job {id} ended as {state:?}"))
            })))),
        }
    }
}
