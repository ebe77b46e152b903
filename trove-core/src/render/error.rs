//! How rendering a valid scene can fail, and how a batch of work units can be refused.
//!
//! The farm sends these across process boundaries, so each says whether trying again can
//! help ([`RenderError::is_retryable`]): a worker must be able to tell "the file is being
//! replaced, try later" from "this batch can never be cast".

use std::path::PathBuf;
use std::sync::Arc;

use thiserror::Error;

use super::limits::LimitError;
use crate::dataset::DatasetError;
use crate::sampling::BindError;

/// A failure while rendering a valid scene.
#[derive(Debug, Error)]
pub enum RenderError {
    /// The voxel store could not provide a dataset.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// A batch of work units was refused; in a local render this means the scene changed
    /// under the renderer (a file was replaced by another of different shape).
    #[error(transparent)]
    Cast(#[from] CastError),
    /// The scheduler refused a result; in a local render this is a bug, never bad input.
    #[error(transparent)]
    Schedule(#[from] ScheduleError),
    /// The render would exceed a limit on its work or memory (`render::limits`); refused
    /// before any of it is done.
    #[error(transparent)]
    Limit(#[from] LimitError),
    /// Writing the output failed.
    #[error("cannot write {}: {source}", path.display())]
    Output {
        /// The output file.
        path: PathBuf,
        /// Why.
        #[source]
        source: OutputError,
    },
}

impl RenderError {
    /// Whether the same render may succeed if tried again unchanged.
    pub fn is_retryable(&self) -> bool {
        match self {
            RenderError::Store(e) => e.is_retryable(),
            RenderError::Cast(_) | RenderError::Schedule(_) | RenderError::Limit(_) => false,
            RenderError::Output { source: OutputError::Io(e), .. } => io_is_transient(e.kind()),
            RenderError::Output { .. } => false,
        }
    }
}

/// Why an image could not be written.
#[derive(Debug, Error)]
pub enum OutputError {
    /// The file system refused.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// The PNG encoder refused.
    #[error(transparent)]
    Encode(#[from] image::ImageError),
}

/// Why the voxel store could not hand out a dataset.
#[derive(Debug, Error, Clone)]
pub enum StoreError {
    /// The budget is smaller than the dataset: with whole-dataset residency it can never
    /// be loaded.
    #[error("the memory budget of {budget} bytes cannot hold dataset `{name}` ({needed} bytes); raise the budget")]
    BudgetTooSmall {
        /// The dataset's name in the scene.
        name: String,
        /// Its resident size.
        needed: u64,
        /// The budget.
        budget: u64,
    },
    /// Loading the dataset's voxels failed (a file changed since the scene was validated,
    /// or is not held by this process).
    #[error("dataset `{name}`: {source}")]
    Load {
        /// The dataset's name in the scene.
        name: String,
        /// Why; shared, since every thread waiting for the same load gets the same error.
        #[source]
        source: Arc<DatasetError>,
    },
}

impl StoreError {
    /// Whether asking again may succeed.
    pub fn is_retryable(&self) -> bool {
        match self {
            StoreError::BudgetTooSmall { .. } => false,
            StoreError::Load { source, .. } => match source.as_ref() {
                DatasetError::Io { source, .. } => io_is_transient(source.kind()),
                _ => false,
            },
        }
    }
}

/// I/O failures that say nothing about the file itself, so the same read may succeed later.
fn io_is_transient(kind: std::io::ErrorKind) -> bool {
    use std::io::ErrorKind::*;
    matches!(kind, Interrupted | TimedOut | WouldBlock | ResourceBusy | OutOfMemory)
}

/// Why a batch of piece tasks cannot be cast. Tasks come from the network in the farm, so
/// every field is checked before it is used: a bad batch is refused, never a panic.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum CastError {
    /// `tasks` and `out` differ in length.
    #[error("{tasks} tasks but room for {results} results")]
    LengthMismatch {
        /// Tasks given.
        tasks: usize,
        /// Result slots given.
        results: usize,
    },
    /// A dataset index outside the scene.
    #[error("dataset {dataset} does not exist (the scene has {datasets})")]
    DatasetOutOfRange {
        /// The index given.
        dataset: usize,
        /// Datasets in the scene.
        datasets: usize,
    },
    /// An object index outside the scene.
    #[error("task {task}: object {object} does not exist (the scene has {objects})")]
    ObjectOutOfRange {
        /// Position of the task in its batch.
        task: usize,
        /// The object index given.
        object: u16,
        /// Objects in the scene.
        objects: usize,
    },
    /// A task of an object whose dataset is not the batch's.
    #[error("task {task}: object {object} uses dataset {uses}, not the batch's dataset {batch}")]
    WrongDataset {
        /// Position of the task in its batch.
        task: usize,
        /// The object.
        object: u16,
        /// The object's dataset.
        uses: usize,
        /// The batch's dataset.
        batch: usize,
    },
    /// A pixel index outside the image.
    #[error("task {task}: ray {ray} is outside the {pixels}-pixel image")]
    RayOutOfRange {
        /// Position of the task in its batch.
        task: usize,
        /// The pixel index given.
        ray: u32,
        /// Pixels in the image.
        pixels: u64,
    },
    /// A piece that is not a finite interval 0 ≤ t0 ≤ t1, or one so long that casting it
    /// would take more samples than any piece of the object can.
    #[error("task {task}: piece [{t0}, {t1}] is not a piece of object {object} ({reason})")]
    BadPiece {
        /// Position of the task in its batch.
        task: usize,
        /// The object.
        object: u16,
        /// Start given.
        t0: f64,
        /// End given.
        t1: f64,
        /// What is wrong with it.
        reason: &'static str,
    },
    /// The volume is not the dataset of one of its objects.
    #[error("object `{object}`: {source}")]
    Bind {
        /// The object's name.
        object: String,
        /// Why.
        #[source]
        source: BindError,
    },
}

/// Why the scheduler refused an answer.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
pub enum ScheduleError {
    /// No batch with this id is awaiting results: never handed out, already recorded, or
    /// abandoned (a late answer from a worker given up on).
    #[error("no batch {id} is awaiting results")]
    UnknownBatch {
        /// The id given.
        id: u64,
    },
    /// A batch answered with another number of results than it had tasks.
    #[error("batch {id} had {expected} tasks but {got} results came back")]
    ResultCount {
        /// The batch.
        id: u64,
        /// Its tasks.
        expected: usize,
        /// Results received.
        got: usize,
    },
    /// A result that no cast can produce (not finite, opacity outside [0, 1], or colour
    /// not premultiplied by it, allowing for what lighting adds).
    #[error("batch {id}: result {index} is not a premultiplied colour and opacity in [0, 1]")]
    BadResult {
        /// The batch.
        id: u64,
        /// Position of the result in the batch.
        index: usize,
    },
    /// A region with more tasks than a scheduler indexes; use smaller regions.
    #[error("{tasks} piece tasks in one region; at most {max} are supported")]
    TooManyTasks {
        /// Tasks in the region.
        tasks: u64,
        /// The most a scheduler indexes (2³¹).
        max: u64,
    },
}
