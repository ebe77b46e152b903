//! The TROVE render farm's wire protocol, package `trove.v1` (`trove.proto` beside this
//! crate), and the edge where it meets `trove-core`: only this crate, the coordinator and
//! the worker see protobuf types, and they translate here ([`convert`]), so `trove-core`
//! never does. [`edge`] holds what both farm binaries need at their own edge (byte counts
//! on the command line, logging, shutdown on a signal); [`auth`], [`tls`] and [`connect`]
//! how their connections are secured (bearer tokens, TLS, keepalive), on both sides;
//! [`metrics_http`] the HTTP endpoint both serve their Prometheus metrics on, and
//! [`reflection`] their gRPC server reflection.

pub mod auth;
pub mod connect;
pub mod convert;
pub mod edge;
pub mod metrics_http;
pub mod reflection;
pub mod tls;

pub use edge::{init_logging, parse_bytes, shutdown_signal, BytesError};
pub use metrics_http::serve_metrics;

/// Generated messages and services.
#[allow(missing_docs, clippy::all)]
pub mod v1 {
    tonic::include_proto!("trove.v1");
}

/// `trove.proto` compiled, as an encoded `FileDescriptorSet`: what server reflection
/// (`tonic-reflection`) answers with, so that `grpcurl` and other generic clients can list
/// and call the services without the file.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("trove_descriptor");

/// The longest worker id a coordinator accepts.
pub const MAX_WORKER_ID_BYTES: usize = 128;

/// Whether `id` is a worker id a coordinator accepts: 1 to [`MAX_WORKER_ID_BYTES`] letters,
/// digits, `-`, `_` or `.` (safe in logs, metrics labels and pod names). The coordinator
/// checks it at registration and `trove-worker` at start, with this one rule.
pub fn is_usable_worker_id(id: &str) -> bool {
    !id.is_empty()
        && id.len() <= MAX_WORKER_ID_BYTES
        && id.bytes().all(|b| b.is_ascii_alphanumeric() || b"-_.".contains(&b))
}

/// Largest message either side accepts. Batches are far smaller (a batch of the largest
/// size, [`MAX_BATCH_TASKS`] tasks, is 384 KiB of tasks and 256 KiB of results); scenes and
/// registrations of large data roots are what could grow.
pub const MAX_MESSAGE_BYTES: usize = 16 << 20;

/// Most tasks in one batch: keeps every cast message well under the gRPC message limit.
pub const MAX_BATCH_TASKS: usize = 16_384;

/// Bytes of result image data per `ResultChunk`.
pub const RESULT_CHUNK_BYTES: usize = 1 << 20;
