//! Why a scene file cannot be rendered as written (SPEC §1: every error names the file, the
//! TOML path of the offending key, and what was expected).
//!
//! The rules live in `load.rs` and `mappings.rs`; each refusal there is one
//! [`SceneErrorKind`] at one key path. Causes found by lower layers — a dataset file
//! ([`DatasetError`]), a camera, a box, a generator — keep their own types and become the
//! error's [`source`](std::error::Error::source): the key path is attached here, at the
//! scene-loading edge, and nowhere below.

use std::error::Error;
use std::fmt;
use std::path::PathBuf;

use thiserror::Error;

use super::effects::LightError;
use super::limits::{
    INTERPOLATIONS, MAX_IMAGE_SIDE, MAX_POLYNOMIAL_TERMS, MAX_SAMPLES_PER_PIECE, MAX_SAMPLES_PER_RENDER,
    MAX_TABLE_ENTRIES,
};
use super::DataRoot;
use crate::dataset::generator::GeneratorError;
use crate::dataset::{ChannelName, DatasetError, Dims, DimsError, VoxelType};
use crate::geometry::hexahedron::HexahedronError;
use crate::geometry::{CameraError, InversionPrecisionError};

/// A scene file that cannot be rendered as written.
///
/// Displayed as `FILE: KEY: WHAT` (`FILE: WHAT` for the file as a whole). When a lower layer
/// found the problem, `WHAT` is that cause, which is the [`source`](Error::source) rather
/// than part of this error's own text: print the chain (`{:#}` with anyhow) to see it all,
/// e.g. `scenes/x.toml: datasets[0].file: cannot read data/x.nhdr: Permission denied (os error 13)`.
#[derive(Debug)]
pub struct SceneError {
    /// The scene file.
    pub file: PathBuf,
    /// TOML path of the offending key, e.g. `objects[3].opacity.bounds`; `None` when the
    /// file as a whole is at fault (unreadable, not TOML).
    pub key: Option<String>,
    /// What was wrong.
    pub kind: SceneErrorKind,
}

impl SceneError {
    /// The lower layer's error this one wraps, if any.
    fn cause(&self) -> Option<&(dyn Error + 'static)> {
        match &self.kind {
            SceneErrorKind::Camera(e) => Some(e),
            SceneErrorKind::Dims(e) => Some(e),
            SceneErrorKind::Dataset(e) => Some(e),
            SceneErrorKind::Generator(e) => Some(e),
            SceneErrorKind::Hexahedron(e) => Some(e),
            SceneErrorKind::Inversion(e) => Some(e),
            SceneErrorKind::Light(e) => Some(e),
            _ => None,
        }
    }
}

impl fmt::Display for SceneError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file.display())?;
        if let Some(key) = &self.key {
            write!(f, ": {key}")?;
        }
        if self.cause().is_none() {
            write!(f, ": {}", self.kind)?;
        }
        Ok(())
    }
}

impl Error for SceneError {
    fn source(&self) -> Option<&(dyn Error + 'static)> {
        self.cause().or_else(|| self.kind.source())
    }
}

/// What was wrong with a scene, one variant per rule (SPEC §1–4.5 and README's limits).
/// The wording says what was expected and what was found.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum SceneErrorKind {
    // ----------------------------------------------------------------- the file and its TOML
    /// The scene file could not be read.
    #[error("cannot read the scene file")]
    Read(#[source] std::io::Error),
    /// Not valid TOML.
    #[error("not valid TOML{}: {message}", At(*position))]
    Syntax {
        /// Line and column (from 1) where the parser stopped, when it says.
        position: Option<(usize, usize)>,
        /// The parser's explanation.
        message: String,
    },
    /// A required key is absent.
    #[error("missing; `{field}` is required here")]
    MissingKey {
        /// The key's own name.
        field: String,
    },
    /// A key the format does not define here (a typo must not silently change a render).
    #[error("unknown key `{field}`; {}", expected.as_deref().map_or("expected no keys here".to_string(), |e| format!("expected {e}")))]
    UnknownKey {
        /// The key's own name.
        field: String,
        /// The keys allowed here, as the parser lists them.
        expected: Option<String>,
    },
    /// A value of the wrong type or shape.
    #[error("expected {expected}, got {got}")]
    WrongType {
        /// What the format wants here.
        expected: String,
        /// What the scene gives.
        got: String,
    },
    /// An array of the wrong length.
    #[error("expected {expected}, got {got} entries")]
    WrongLength {
        /// What the format wants here.
        expected: String,
        /// Entries given.
        got: usize,
    },
    /// Positional values where the format wants `[[name]]` tables.
    #[error("expected an array of tables ([[{table}]]), got {got}")]
    NotAnArrayOfTables {
        /// The key (`datasets`, `objects`).
        table: String,
        /// What the scene gives.
        got: String,
    },
    /// Any other refusal by the TOML reader, in its words.
    #[error("{0}")]
    Deserialize(String),

    // ----------------------------------------------------------------- [image], [camera], [render]
    /// An image side outside 1..=[`MAX_IMAGE_SIDE`].
    #[error("expected a pixel count from 1 to {MAX_IMAGE_SIDE}, got {got}")]
    ImageSide {
        /// The value given.
        got: i64,
    },
    /// A background colour outside [0, 1].
    #[error("expected linear RGB in [0, 1], got {got:?}")]
    Background {
        /// The value given.
        got: [f64; 3],
    },
    /// The camera refused its inputs.
    #[error(transparent)]
    Camera(CameraError),
    /// A termination opacity outside (0, 1].
    #[error("expected an opacity in (0, 1], got {got}")]
    Termination {
        /// The value given.
        got: f64,
    },
    /// `distorted_sampling` other than `exact` or `straight`.
    #[error("expected \"exact\" or \"straight\", got \"{got}\"")]
    DistortedSampling {
        /// The value given.
        got: String,
    },
    /// More datasets or objects than the documented limit.
    #[error("at most {max} {what}, got {got}")]
    TooMany {
        /// `datasets` or `objects`.
        what: &'static str,
        /// The limit.
        max: usize,
        /// How many the scene has.
        got: usize,
    },
    /// A name used twice.
    #[error("duplicate {what} name \"{name}\" (also {first})")]
    DuplicateName {
        /// `dataset` or `object`.
        what: &'static str,
        /// The name.
        name: String,
        /// The key path of its first use.
        first: String,
    },
    /// An object names a dataset the scene does not define.
    #[error("no dataset named \"{name}\"; the scene defines {known:?}")]
    UnknownDataset {
        /// The name given.
        name: String,
        /// The datasets the scene defines.
        known: Vec<String>,
    },
    /// The worst-case sample count of the whole render exceeds the documented cap.
    #[error(
        "the render could take up to {total:.3e} samples ({width}×{height} pixels, up to {per_ray:.3e} per ray in \
         this object); at most {max:.3e} are allowed: use a larger sampling distance or a smaller image",
        max = MAX_SAMPLES_PER_RENDER
    )]
    RenderTooCostly {
        /// Worst-case samples of the render.
        total: f64,
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
        /// Worst-case samples per ray through the costliest object.
        per_ray: f64,
    },

    // ----------------------------------------------------------------- datasets and channels
    /// Dims with an entry below 1.
    #[error("expected three voxel counts ≥ 1, got {got:?}")]
    DimsBelowOne {
        /// The value given.
        got: [i64; 3],
    },
    /// Dims that [`Dims`] refuses.
    #[error(transparent)]
    Dims(DimsError),
    /// Dims whose byte size overflows for a channel's type.
    #[error("dims {dims} of {ty} overflow the addressable size")]
    DimsOverflow {
        /// The dims.
        dims: Dims,
        /// The channel type.
        ty: VoxelType,
    },
    /// A file, image or channel whose dims differ from the dataset's.
    #[error("holds dims {found}, but the dataset's dims are {declared}")]
    DimsDisagree {
        /// What the file holds.
        found: Dims,
        /// What the dataset says.
        declared: Dims,
    },
    /// A dataset with neither `file`, `image` nor explicit channels.
    #[error("a dataset needs `file`, `image`, or `dims` with `channels`")]
    NoSource,
    /// Both `file` and `image`.
    #[error("give either `file` or `image`, not both")]
    FileAndImage,
    /// Explicit channels without the dataset's dims.
    #[error("missing; explicit channels need the dataset's dims")]
    MissingDims,
    /// A `file` (or a channel's `nrrd`) whose extension names no format TROVE reads there.
    #[error("\"{file}\": expected a {expected} file")]
    VolumeExtension {
        /// The key as written.
        file: String,
        /// The extensions allowed there.
        expected: &'static str,
    },
    /// A dataset file refused by the catalog or its reader.
    #[error(transparent)]
    Dataset(DatasetError),
    /// A dataset key whose file does not exist under the data root of a local load
    /// ([`Scene::load_in`](super::Scene::load_in)). The most common first-day error — a
    /// scene whose data lives elsewhere — so it says where it looked and how to look
    /// elsewhere rather than only the OS's "No such file or directory".
    #[error("dataset key \"{key}\" names no file: looked for {}; {root}", looked_for.display())]
    DataNotFound {
        /// The key as written.
        key: String,
        /// The path it resolved to.
        looked_for: PathBuf,
        /// The data root it resolved under, and who chose it (boxed: it keeps
        /// [`SceneError`] small, which every `Result` of the scene loader carries).
        root: Box<DataRoot>,
    },
    /// A channel name outside SPEC §1.1.
    #[error("unknown channel; expected one of {}", ChannelName::ALL.map(|c| c.name()).join(", "))]
    UnknownChannel,
    /// A channel given explicitly that the file or image already gives.
    #[error("channel `{channel}` is already given by the dataset's file or image")]
    ChannelGivenTwice {
        /// The channel.
        channel: ChannelName,
    },
    /// A channel with none or several of `raw`, `nrrd`, `generator`.
    #[error("expected exactly one of `raw`, `nrrd` or `generator`")]
    ChannelSources,
    /// `type`, `endian` or `offset` on a channel that is not `raw`.
    #[error("only a `raw` channel takes this key")]
    RawOnlyKey,
    /// A raw channel without its type.
    #[error("missing; a raw channel needs its type: bit, u8, u16, u32 or f32")]
    MissingRawType,
    /// A raw channel type that is not a storage type.
    #[error("expected bit, u8, u16, u32 or f32, got \"{got}\"")]
    UnknownVoxelType {
        /// The value given.
        got: String,
    },
    /// An endianness other than `little` or `big`.
    #[error("expected \"little\" or \"big\", got \"{got}\"")]
    UnknownEndian {
        /// The value given.
        got: String,
    },
    /// Data of a type the channel does not allow (`red` must be u8, ...).
    #[error("channel `{channel}` must be {}, but its data is {got}", channel.allowed_types().iter().map(|t| t.name()).collect::<Vec<_>>().join(" or "))]
    ChannelType {
        /// The channel.
        channel: ChannelName,
        /// The type its data has.
        got: VoxelType,
    },
    /// A generator refused its keys or parameters.
    #[error(transparent)]
    Generator(GeneratorError),

    // ----------------------------------------------------------------- objects
    /// A map that reads the `voxel` channel on a dataset without one.
    #[error("this map reads the `voxel` channel, which dataset \"{dataset}\" does not have; use raw or constant")]
    MapNeedsVoxel {
        /// The dataset's name.
        dataset: String,
    },
    /// A negative or non-finite sampling distance.
    #[error("expected a finite world distance ≥ 0 (0 = one voxel), got {got:?}")]
    SamplingDistance {
        /// The value given.
        got: f64,
    },
    /// A sampling distance that could take more samples per ray than the documented cap.
    #[error(
        "{distance:?} would take up to {samples:.3e} samples per ray through a box {diagonal:.3e} across; at most \
         {max:.3e} are allowed",
        max = MAX_SAMPLES_PER_PIECE
    )]
    TooManySamplesPerRay {
        /// The sampling distance.
        distance: f64,
        /// The box's bounding-box diagonal.
        diagonal: f64,
        /// Samples one ray along that diagonal would take.
        samples: f64,
    },
    /// An extent that is not a sub-box of the unit cube.
    #[error("expected 0 ≤ min < max ≤ 1 on every axis, got min {min:?}, max {max:?} (axis {axis})")]
    Extent {
        /// Lower corner given (or defaulted).
        min: [f64; 3],
        /// Upper corner given (or defaulted).
        max: [f64; 3],
        /// The first axis that breaks the rule.
        axis: usize,
    },
    /// A transform with neither or both of `matrix` and `corners`.
    #[error("expected exactly one of `matrix` or `corners`")]
    TransformSources,
    /// A matrix that is not four rows of four numbers.
    #[error("expected a 4×4 matrix, as four rows of four numbers")]
    MatrixShape,
    /// A matrix whose last row is not `0 0 0 1`.
    #[error("expected an affine matrix (last row 0 0 0 1), got last row {last_row:?}")]
    NotAffine {
        /// The last row given.
        last_row: Vec<f64>,
    },
    /// A matrix with a NaN or infinite entry.
    #[error("expected finite numbers")]
    MatrixNotFinite,
    /// A matrix (or parallelepiped) without volume.
    #[error("expected a non-singular matrix; this one is singular (the box has no volume)")]
    SingularMatrix,
    /// Not eight corners of three numbers each.
    #[error("expected eight [x, y, z] corners, index x + 2y + 4z")]
    CornerCount,
    /// Eight corners that do not make a box (they fold, or enclose no volume).
    #[error(transparent)]
    Hexahedron(HexahedronError),
    /// A box too close to folding to sample within the SPEC's precision.
    #[error(transparent)]
    Inversion(InversionPrecisionError),

    // ----------------------------------------------------------------- colour and opacity maps
    /// A map given as something other than a table.
    #[error("expected a table such as {{ type = \"lut\", ... }}, got {got}")]
    NotAMap {
        /// The TOML type given.
        got: &'static str,
    },
    /// A map without `type`.
    #[error("missing; expected one of {expected}")]
    MissingMapType {
        /// The types allowed.
        expected: &'static str,
    },
    /// A map type this map does not have.
    #[error("unknown {map} map type \"{got}\"; expected one of {expected}")]
    UnknownMapType {
        /// `colour` or `opacity`.
        map: &'static str,
        /// The type given.
        got: String,
        /// The types allowed.
        expected: &'static str,
    },
    /// A key this map type does not take.
    #[error("unknown key for this type; expected {}", if allowed.is_empty() { "no other keys".to_string() } else { allowed.join(", ") })]
    UnknownMapKey {
        /// The keys the type takes besides `type`.
        allowed: &'static [&'static str],
    },
    /// A key this map type needs.
    #[error("missing; this type requires it")]
    MissingMapKey,
    /// A NaN or infinite number.
    #[error("expected a finite number, got {got}")]
    NotFinite {
        /// The value given.
        got: f64,
    },
    /// A list of the wrong number of numbers.
    #[error("expected {expected} numbers{}, got {got}", layout.map(|l| format!(" {l}")).unwrap_or_default())]
    NumberCount {
        /// How many are needed.
        expected: usize,
        /// Their meaning, e.g. `[value, r, g, b]`.
        layout: Option<&'static str>,
        /// How many were given.
        got: usize,
    },
    /// A LUT with too many bounds.
    #[error("expected fewer than {MAX_TABLE_ENTRIES} bounds, got {got}")]
    TooManyBounds {
        /// How many were given.
        got: usize,
    },
    /// LUT bounds that do not strictly increase.
    #[error("bounds must be strictly increasing, but [{index}] = {value} follows {previous}")]
    BoundsNotIncreasing {
        /// Index of the offending bound.
        index: usize,
        /// Its value.
        value: f64,
        /// The bound before it.
        previous: f64,
    },
    /// A LUT whose entries are not one more than its bounds.
    #[error("expected {} entries (one more than the {bounds} bounds), got {got}", bounds + 1)]
    LutEntries {
        /// Number of bounds.
        bounds: usize,
        /// Number of entries given.
        got: usize,
    },
    /// A named polynomial (`linear`, ...) with the wrong number of coefficients.
    #[error("a {ty} map takes exactly {expected} coefficient{}, got {got}", if *expected == 1 { "" } else { "s" })]
    CoefficientCount {
        /// The map type.
        ty: &'static str,
        /// How many it takes.
        expected: usize,
        /// How many were given.
        got: usize,
    },
    /// A general polynomial with none or too many coefficients.
    #[error("expected 1 to {MAX_POLYNOMIAL_TERMS} coefficients (ascending powers), got {got}")]
    PolynomialTerms {
        /// How many were given.
        got: usize,
    },
    /// A ramp with no points or too many.
    #[error("expected 1 to {MAX_TABLE_ENTRIES} points, got {got}")]
    RampPointCount {
        /// How many were given.
        got: usize,
    },
    /// Ramp points out of order.
    #[error("points must be ordered by value, but {value} follows {previous}")]
    RampNotOrdered {
        /// The offending point's value.
        value: f64,
        /// The value before it.
        previous: f64,
    },
    /// A raw colour map on a dataset without colour channels.
    #[error("a raw colour map needs the dataset to have red, green and blue channels, or grey, or bit")]
    RawColourChannels,
    /// A raw opacity map on a dataset without an alpha channel.
    #[error("a raw opacity map needs the dataset to have an alpha channel")]
    RawOpacityAlpha,

    // ----------------------------------------------------------------- interpolation
    /// An interpolation name TROVE does not have.
    #[error("unknown interpolation \"{got}\"; expected {INTERPOLATIONS}")]
    UnknownInterpolation {
        /// The name given.
        got: String,
    },
    /// `"nonlinear"` without its coefficients.
    #[error("nonlinear interpolation needs its coefficients: {{ type = \"nonlinear\", omega = [w0, w1, w2] }}")]
    NonlinearNeedsOmega,

    // ----------------------------------------------------------------- effects (SPEC §6)
    /// A light type other than `directional` or `point`.
    #[error("unknown light type \"{got}\"; expected \"directional\" or \"point\"")]
    UnknownLightType {
        /// The type given.
        got: String,
    },
    /// A key the light's type does not take (`position` on a directional light,
    /// `direction` on a point light).
    #[error("a {ty} light does not take this key; it takes {takes}")]
    LightKeyNotForType {
        /// The light's type.
        ty: &'static str,
        /// The key it takes instead.
        takes: &'static str,
    },
    /// A light direction that is zero or not finite.
    #[error("expected a finite, non-zero direction, got {got:?}")]
    LightDirection {
        /// The value given.
        got: [f64; 3],
    },
    /// A light's colour, intensity or position refused.
    #[error(transparent)]
    Light(LightError),
    /// A shading coefficient that is negative or not finite.
    #[error("expected a finite number ≥ 0, got {got}")]
    ShadingCoefficient {
        /// The value given.
        got: f64,
    },
}

/// ` at line L, column C`, or nothing.
struct At(Option<(usize, usize)>);

impl fmt::Display for At {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            Some((line, column)) => write!(f, " at line {line}, column {column}"),
            None => Ok(()),
        }
    }
}
