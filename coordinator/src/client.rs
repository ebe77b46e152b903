//! A client of a farm's job API: what `trove render --coordinator URL` does, as a library
//! (submit a scene, follow the job, fetch its files), so tests drive a farm the way a user
//! does. It connects through a [`Connector`]: `https://` verified against a CA, and the
//! client token on every call.
//!
//! Following a job survives a coordinator restart or a dropped stream: a call that fails
//! at the transport level (not a typed failure of the job) is tried again on a reconnecting
//! channel, with capped exponential backoff, until [`REATTACH_DEADLINE`]; a coordinator
//! with a state folder still knows the job by its id, resumes it and serves its files.

use std::time::{Duration, Instant};

use thiserror::Error;
use tonic::{Code, Status};
use trove_proto::connect::{AuthChannel, ConnectError, Connector};
use trove_proto::convert;
use trove_proto::v1 as pb;
use trove_proto::v1::coordinator_client::CoordinatorClient;

/// Deadline of a call that does not stream.
const CALL_DEADLINE: Duration = Duration::from_secs(60);

/// How long a client keeps trying to re-attach to its job (a coordinator restarting).
pub const REATTACH_DEADLINE: Duration = Duration::from_secs(300);
/// The first and the longest wait between re-attach attempts.
const BACKOFF: (Duration, Duration) = (Duration::from_millis(50), Duration::from_secs(2));

/// Why a farm render failed, as the user should read it.
#[derive(Debug, Error)]
pub enum ClientError {
    /// The coordinator cannot be reached (or its URL and the TLS options disagree).
    #[error(transparent)]
    Connect(#[from] ConnectError),
    /// The coordinator refused the client's token, or its lack of one.
    #[error(
        "the coordinator refused {}: {message}; the token is read from --token-file FILE, which must hold \
         the coordinator's --client-token-file token",
        if *.sent { "this client's token" } else { "a client without a token" }
    )]
    Unauthenticated {
        /// Whether a token was sent.
        sent: bool,
        /// The coordinator's reason.
        message: String,
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
    /// Whether the call failed on its way (a coordinator restarting, a broken connection or
    /// stream) rather than with an answer: worth trying again on a new connection. A typed
    /// `Failure` is an answer, never this.
    pub fn is_transport(&self) -> bool {
        match self {
            ClientError::Connect { .. } => true,
            ClientError::Rpc(status) => match status.code() {
                tonic::Code::Unavailable | tonic::Code::Unknown | tonic::Code::Cancelled => true,
                // An HTTP/2 stream reset on its way; the coordinator's own INTERNAL answers
                // carry a typed failure.
                tonic::Code::Internal => status.message().contains("h2 protocol error"),
                _ => false,
            },
            ClientError::Failed(_) | ClientError::Unauthenticated { .. } | ClientError::Incomplete => false,
        }
    }

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
    inner: CoordinatorClient<AuthChannel>,
    sends_token: bool,
}

impl FarmClient {
    /// Connects to the coordinator at `url` (e.g. `http://127.0.0.1:7000`), plaintext and
    /// without a token.
    pub async fn connect(url: &str) -> Result<FarmClient, ClientError> {
        FarmClient::connect_with(url, &Connector::default()).await
    }

    /// Connects to the coordinator at `url` through `connector` (its CA for `https://`,
    /// its token).
    pub async fn connect_with(url: &str, connector: &Connector) -> Result<FarmClient, ClientError> {
        let endpoint = connector.endpoint(url)?.connect_timeout(Duration::from_secs(10));
        let channel = connector.connect(endpoint).await?;
        let limit = trove_proto::MAX_MESSAGE_BYTES;
        Ok(FarmClient {
            inner: CoordinatorClient::new(channel).max_decoding_message_size(limit).max_encoding_message_size(limit),
            sends_token: connector.sends_token(),
        })
    }

    /// A status as this client's error: a refused token says which flag sets it.
    fn error(&self, status: Status) -> ClientError {
        if status.code() == Code::Unauthenticated {
            return ClientError::Unauthenticated { sent: self.sends_token, message: status.message().to_string() };
        }
        ClientError::from(status)
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
        let response = self.inner.submit_job(request).await;
        Ok(response.map_err(|s| self.error(s))?.into_inner().job_id)
    }

    /// Follows job `id` until it ends and fetches its files, as [`FarmClient::watch`] and
    /// [`FarmClient::result`] do, re-attaching after a transport error (a coordinator
    /// restart, a dropped stream) with capped exponential backoff, within
    /// [`REATTACH_DEADLINE`] of the first such error since the last answer. A job that
    /// fails or is cancelled is final: its typed failure is returned.
    pub async fn follow(
        &mut self,
        id: &str,
        mut progress: impl FnMut(&pb::JobStatus),
    ) -> Result<JobFiles, ClientError> {
        let mut lost: Option<(Instant, Duration)> = None;
        loop {
            let mut heard = false;
            let attempt = self
                .watch_and_fetch(id, &mut |status| {
                    heard = true;
                    progress(status)
                })
                .await;
            let error = match attempt {
                Ok(files) => return Ok(files),
                Err(e) if e.is_transport() => e,
                Err(e) => return Err(e),
            };
            if heard {
                lost = None;
            }
            let (since, wait) = lost.get_or_insert((Instant::now(), BACKOFF.0));
            if since.elapsed() >= REATTACH_DEADLINE {
                return Err(error);
            }
            tracing::warn!(job = %id, error = %error, retry_in = ?*wait, "lost the coordinator; re-attaching");
            tokio::time::sleep(*wait).await;
            *wait = (*wait * 2).min(BACKOFF.1);
        }
    }

    /// One attempt of [`FarmClient::follow`].
    async fn watch_and_fetch(
        &mut self,
        id: &str,
        progress: &mut impl FnMut(&pb::JobStatus),
    ) -> Result<JobFiles, ClientError> {
        let last = self.watch(id, progress).await?;
        match last.state() {
            pb::JobState::Succeeded => self.result(id).await,
            // A stream that ended before the job did (a coordinator shutting down).
            pb::JobState::Queued | pb::JobState::Running => Err(ClientError::Rpc(Box::new(Status::unavailable(
                format!("the status stream of job {id} ended before the job"),
            )))),
            state => Err(ClientError::Failed(Box::new(last.failure.unwrap_or_else(|| {
                convert::failure(pb::Reason::Internal, false, format!("job {id} ended as {state:?}"))
            })))),
        }
    }

    /// Follows job `id` until it ends, calling `progress` with every status; returns the
    /// last one.
    pub async fn watch(
        &mut self,
        id: &str,
        mut progress: impl FnMut(&pb::JobStatus),
    ) -> Result<pb::JobStatus, ClientError> {
        let response = self.inner.watch_job(pb::WatchJobRequest { job_id: id.to_string() }).await;
        let mut stream = response.map_err(|s| self.error(s))?.into_inner();
        let mut last = None;
        while let Some(status) = stream.message().await? {
            progress(&status);
            last = Some(status);
        }
        last.ok_or(ClientError::Incomplete)
    }

    /// Job `id`'s status now.
    pub async fn status(&mut self, id: &str) -> Result<pb::JobStatus, ClientError> {
        let mut request = tonic::Request::new(pb::WatchJobRequest { job_id: id.to_string() });
        request.set_timeout(CALL_DEADLINE);
        let mut stream = self.inner.watch_job(request).await?.into_inner();
        stream.message().await?.ok_or(ClientError::Incomplete)
    }

    /// The files of finished job `id`.
    pub async fn result(&mut self, id: &str) -> Result<JobFiles, ClientError> {
        let mut request = tonic::Request::new(pb::GetResultRequest { job_id: id.to_string() });
        request.set_timeout(Duration::from_secs(600));
        let response = self.inner.get_result(request).await;
        let mut stream = response.map_err(|s| self.error(s))?.into_inner();
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
        let response = self.inner.cancel_job(request).await;
        Ok(response.map_err(|s| self.error(s))?.into_inner().state())
    }

    /// The workers the coordinator knows.
    pub async fn workers(&mut self) -> Result<Vec<pb::WorkerInfo>, ClientError> {
        let mut request = tonic::Request::new(pb::ListWorkersRequest {});
        request.set_timeout(CALL_DEADLINE);
        let response = self.inner.list_workers(request).await;
        Ok(response.map_err(|s| self.error(s))?.into_inner().workers)
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
        // A draining coordinator refuses new jobs as UNAVAILABLE (retryable, and no job was
        // made): its successor, or the same one restarted, takes the job.
        let mut wait = (Instant::now(), BACKOFF.0);
        let id = loop {
            match self.submit(scene_toml.clone(), scene_name.clone(), options).await {
                Err(ClientError::Failed(f))
                    if f.reason() == pb::Reason::Unavailable && wait.0.elapsed() < REATTACH_DEADLINE =>
                {
                    tracing::warn!(message = %f.message, retry_in = ?wait.1, "the coordinator takes no new jobs; retrying");
                    tokio::time::sleep(wait.1).await;
                    wait.1 = (wait.1 * 2).min(BACKOFF.1);
                }
                submitted => break submitted?,
            }
        };
        self.follow(&id, progress).await
    }
}
