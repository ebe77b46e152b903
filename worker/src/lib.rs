//! A TROVE farm worker: it holds the dataset files under its data root, registers them with
//! the coordinator, and casts the piece tasks of the datasets it holds.
//!
//! * [`files`] scans the data root once at start: every file's key (its path under the
//!   root), size and header. Keys are resolved through `trove-core`'s sandboxed catalog, so
//!   nothing outside the root is ever read.
//! * [`membership`] registers with the coordinator and sends heartbeats from a task of its
//!   own, so a worker busy casting is never declared dead.
//! * [`cast`] serves the `Worker.Cast` streams: one per job and dataset, the scene received
//!   once, then batches cast on rayon threads with `trove-core`'s `BatchCaster` over the
//!   worker's one budgeted `VolumeStore` (datasets are memory-mapped when first needed and
//!   shared by every job).
//! * [`scenes`] keeps the scenes those streams parse, so a job's scene is parsed once per
//!   worker, not once per dataset.
//! * [`metrics`] counts what the `Cast` streams answer, for Prometheus.
//! * [`server::run`] ties them together over a bound listener and a shutdown signal, so a
//!   test runs workers in-process on `127.0.0.1:0`; the `trove-worker` binary stays thin.

pub mod cast;
pub mod files;
pub mod membership;
pub mod metrics;
pub mod scenes;
pub mod server;

pub use server::{run, WorkerConfig, WorkerError, WorkerSecurity};
