//! Why a job ended early, as the driver knows it; converted to the wire's typed
//! `pb::Failure` only where the job's status is written ([`JobError::to_failure`]).

use std::ops::Range;
use std::time::Duration;

use trove_core::render::limits::LimitError;
use trove_core::render::{OutputError, ScheduleError};
use trove_proto::convert;
use trove_proto::v1 as pb;

/// A job's end other than success.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// Every worker that held one of the scene's datasets is lost (or refused for this job).
    #[error("no worker that holds dataset `{dataset}` is left to cast it")]
    NoHolder {
        /// The dataset's name in the scene.
        dataset: String,
    },
    /// A batch was handed out and given up this many times: a batch that breaks every
    /// worker it reaches fails its job instead of going round the farm forever.
    #[error("a batch of dataset `{dataset}` was given up {attempts} times (its workers were lost, refused it or answered it wrongly)")]
    TooManyAttempts {
        /// The dataset's name in the scene.
        dataset: String,
        /// Dispatches of the batch so far.
        attempts: u32,
    },
    /// A band's scheduler could not be built (too many tasks).
    #[error("the band of rows {}..{}: {source}", rows.start, rows.end)]
    Band {
        /// The band's rows.
        rows: Range<u32>,
        /// What the scheduler refused.
        #[source]
        source: ScheduleError,
    },
    /// A worker reported a failure that retrying elsewhere cannot fix (a bad scene for it,
    /// a dataset that does not match its header), as it reported it.
    #[error("worker {worker}: {}", failure.message)]
    Worker {
        /// The worker's id.
        worker: String,
        /// Its report.
        failure: Box<pb::Failure>,
    },
    /// A band made more tasks than the memory bound holds (`render::limits`).
    #[error(transparent)]
    Limit(#[from] LimitError),
    /// The job ran past its deadline.
    #[error("the job ran past its deadline of {} s (trove coordinator --job-deadline-s)", deadline.as_secs_f64())]
    DeadlineExceeded {
        /// The deadline.
        deadline: Duration,
    },
    /// A step of the job on a blocking thread panicked; only this job fails.
    #[error("the job's {step} step panicked: {message}")]
    Panicked {
        /// `intersection`, `composition` or `encoding`.
        step: &'static str,
        /// The panic's message.
        message: String,
    },
    /// The scene's shadow maps, as they go with the scene, would not fit one message.
    #[error(
        "lights: the shadows' lattices take {bytes} bytes on the wire, more than the {room} a farm message has room for; \
         render this scene in local mode, or cast shadows from fewer lights"
    )]
    ShadowMaps {
        /// Their encoded size.
        bytes: u64,
        /// What a message has room for beside the scene.
        room: u64,
    },
    /// A client cancelled the job.
    #[error("the job was cancelled")]
    Cancelled,
    /// The finished image could not be encoded.
    #[error("encoding the image: {0}")]
    Encode(#[source] OutputError),
    /// A step of the driver itself broke (a blocking step panicked, a channel closed).
    #[error("{0}")]
    Internal(String),
}

impl JobError {
    /// The failure a job's status reports, typed for clients.
    pub fn to_failure(&self) -> pb::Failure {
        let message = self.to_string();
        match self {
            JobError::NoHolder { dataset } => {
                let mut f = convert::failure(pb::Reason::WorkerLost, true, message);
                f.dataset = dataset.clone();
                f
            }
            JobError::TooManyAttempts { dataset, .. } => {
                let mut f = convert::failure(pb::Reason::WorkerLost, false, message);
                f.dataset = dataset.clone();
                f
            }
            JobError::Band { .. } => convert::failure(pb::Reason::LimitExceeded, false, message),
            JobError::ShadowMaps { .. } => {
                let mut f = convert::failure(pb::Reason::LimitExceeded, false, message);
                f.key = "lights".into();
                f
            }
            JobError::Limit(e) => convert::limit_failure(e),
            JobError::DeadlineExceeded { .. } => convert::failure(pb::Reason::DeadlineExceeded, false, message),
            JobError::Panicked { .. } => convert::failure(pb::Reason::Internal, false, message),
            JobError::Worker { worker, failure } => {
                let mut f = (**failure).clone();
                f.worker_id = worker.clone();
                f
            }
            JobError::Cancelled => convert::failure(pb::Reason::Cancelled, false, message),
            JobError::Encode(_) => convert::failure(pb::Reason::Internal, false, message),
            JobError::Internal(_) => convert::failure(pb::Reason::Internal, true, message),
        }
    }

    /// Whether the job was cancelled rather than failed.
    pub fn is_cancel(&self) -> bool {
        matches!(self, JobError::Cancelled)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn failures_keep_their_reason_dataset_and_worker() {
        let f = JobError::NoHolder { dataset: "head".into() }.to_failure();
        assert_eq!((f.reason(), f.retryable, f.dataset.as_str()), (pb::Reason::WorkerLost, true, "head"));
        assert!(f.message.contains("`head`"), "{}", f.message);
        let reported = convert::failure(pb::Reason::SceneInvalid, false, "no such key".into());
        let f = JobError::Worker { worker: "w3".into(), failure: Box::new(reported) }.to_failure();
        assert_eq!(
            (f.reason(), f.worker_id.as_str(), f.message.as_str()),
            (pb::Reason::SceneInvalid, "w3", "no such key")
        );
        let f = JobError::TooManyAttempts { dataset: "d".into(), attempts: 5 }.to_failure();
        assert!(!f.retryable && f.message.contains("5 times"), "{f:?}");
        assert_eq!(JobError::Cancelled.to_failure().reason(), pb::Reason::Cancelled);
        let f = JobError::DeadlineExceeded { deadline: Duration::from_secs(2) }.to_failure();
        assert!(f.reason() == pb::Reason::DeadlineExceeded && !f.retryable && f.message.contains("2 s"), "{f:?}");
        let f = JobError::ShadowMaps { bytes: 20, room: 10 }.to_failure();
        assert!(f.reason() == pb::Reason::LimitExceeded && f.key == "lights" && !f.retryable, "{f:?}");
        let f = JobError::Panicked { step: "composition", message: "boom".into() }.to_failure();
        assert!(f.reason() == pb::Reason::Internal && f.message.contains("composition step panicked: boom"), "{f:?}");
    }
}
