//! The entry points of the fuzz targets (`fuzz/`, run with `cargo fuzz`) and of their short
//! proptest run in CI (`tests/tests/fuzz_inputs.rs`): one function per target, called by
//! both, so that what CI checks is what the fuzzer explores. Each takes arbitrary bytes and
//! must come back with a value or a typed error; a panic is a bug (`docs/fuzzing.md`).
//!
//! * [`scene`]: scene text through `Scene::parse_with`, over a catalog of a few fixed files.
//! * [`nrrd`] and [`nifti`]: a file's bytes under a worker's sandboxed data root, described
//!   as a worker describes it at registration, and its voxels loaded when that succeeds.
//! * [`submit_job`]: a `SubmitJobRequest` decoded by prost and planned as the coordinator
//!   plans one at `SubmitJob` (parse, PFM cap, exact work count, bands).
//! * [`cast_batch`]: a batch's tasks in `render::wire` form decoded and cast as a worker
//!   casts every batch, and the same bytes read as results as the coordinator reads answers.
//!
//! [`seeds`] gives each target's valid inputs, from which the proptests mutate and which
//! seed the fuzzer's corpus.

use std::cell::RefCell;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, OnceLock};

use crate::{scratch, Scratch};
use prost::Message;
use trove_coordinator::farm::DriverConfig;
use trove_core::dataset::{Catalog, DatasetError, FileInfo, FileKind, FsCatalog, Volume};
use trove_core::render::limits::check_pfm;
use trove_core::render::{wire, BatchCaster, CastError, PieceRgba};
use trove_core::scene::{Scene, SceneError};
use trove_proto::convert;
use trove_proto::v1 as pb;

/// The targets, by the names their fuzz targets and seed folders have.
pub const TARGETS: [&str; 5] = ["scene", "nrrd", "nifti", "submit_job", "cast_batch"];

/// The files the scene and job targets' catalog holds, as workers would register them.
fn catalog_files() -> Vec<pb::DatasetFile> {
    let dims = |x, y, z| Some(pb::Dims { x, y, z });
    let volume = |key: &str, d, ty: pb::VoxelType| pb::DatasetFile {
        key: key.into(),
        bytes: 0,
        header: Some(pb::dataset_file::Header::Volume(pb::VolumeHeader { dims: d, r#type: ty as i32 })),
    };
    vec![
        volume("head.nrrd", dims(16, 16, 8), pb::VoxelType::U8),
        volume("mri.nii.gz", dims(8, 8, 8), pb::VoxelType::U16),
        volume("flow.nhdr", dims(4, 4, 4), pb::VoxelType::F32),
        pb::DatasetFile {
            key: "photo.png".into(),
            bytes: 0,
            header: Some(pb::dataset_file::Header::Image(pb::ImageHeader {
                dims: dims(8, 4, 1),
                channels: ["red", "green", "blue", "alpha"].map(String::from).to_vec(),
            })),
        },
        pb::DatasetFile { key: "slab.raw".into(), bytes: 32, header: None },
    ]
}

/// A catalog over fixed headers, answering as a coordinator's registry does
/// ([`convert::describe_remote`]): every source is remote, nothing is read.
struct FixedCatalog(HashMap<String, pb::DatasetFile>);

impl Catalog for FixedCatalog {
    fn describe(&self, key: &str, kind: FileKind) -> Result<FileInfo, DatasetError> {
        match self.0.get(key) {
            Some(f) => convert::describe_remote(f, kind),
            None => Err(DatasetError::not_held(key)),
        }
    }
}

fn fixed_catalog() -> &'static FixedCatalog {
    static CATALOG: OnceLock<FixedCatalog> = OnceLock::new();
    CATALOG.get_or_init(|| FixedCatalog(catalog_files().into_iter().map(|f| (f.key.clone(), f)).collect()))
}

/// Scene text (invalid UTF-8 replaced, as no client could send it) parsed and validated.
pub fn scene(bytes: &[u8]) -> Result<Scene, SceneError> {
    Scene::parse_with(&String::from_utf8_lossy(bytes), "fuzz.toml", fixed_catalog())
}

/// A data root of this thread's own (the proptests run on several threads), holding a
/// 512-byte `data.raw` that a detached NRRD header may name; removed when the thread ends.
fn data_root() -> PathBuf {
    thread_local! {
        static ROOT: RefCell<Option<Scratch>> = const { RefCell::new(None) };
    }
    ROOT.with(|root| {
        root.borrow_mut()
            .get_or_insert_with(|| {
                static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
                let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let dir = scratch(&format!("fuzz-{n}"));
                let raw: Vec<u8> = (0..512u32).map(|i| (i * 7) as u8).collect();
                std::fs::write(dir.join("data.raw"), raw).expect("write data.raw");
                dir
            })
            .to_path_buf()
    })
}

/// Writes `bytes` as `key` under this thread's data root and describes it as a worker
/// does (sandboxed, header only); then loads its voxels, as a worker does for a batch.
/// Returns the voxels loaded.
fn volume_file(key: &str, bytes: &[u8]) -> Result<u64, DatasetError> {
    let root = data_root();
    std::fs::write(root.join(key), bytes).map_err(|e| DatasetError::io(root.join(key), e))?;
    let catalog = FsCatalog::sandboxed(&root)?;
    match catalog.describe(key, FileKind::Volume)? {
        FileInfo::Volume { dims, source, .. } => {
            source.load(dims)?;
            Ok(dims.as_array().iter().map(|&d| d as u64).product())
        }
        other => panic!("a volume key described as {:?}", other.kind()),
    }
}

/// An NRRD file (attached or detached header) as a worker's data root holds it.
pub fn nrrd(bytes: &[u8]) -> Result<u64, DatasetError> {
    volume_file("input.nrrd", bytes)
}

/// A NIfTI-1 file (plain or gzip, told by its bytes) as a worker's data root holds it.
pub fn nifti(bytes: &[u8]) -> Result<u64, DatasetError> {
    volume_file("input.nii", bytes)
}

/// Why the coordinator would refuse a submitted job.
#[derive(Debug)]
pub enum JobRefusal {
    /// The request is not a `SubmitJobRequest` (tonic answers INTERNAL or INVALID_ARGUMENT
    /// before the service sees it).
    Decode(prost::DecodeError),
    /// The typed failure `SubmitJob` would answer.
    Refused(Box<pb::Failure>),
}

/// What planning a job found: rows per band and piece tasks, or that the exact count was
/// not attempted (see [`submit_job`]).
#[derive(Debug, PartialEq, Eq)]
pub enum Planned {
    /// Planned in full.
    Counted {
        /// Rows per band.
        band_rows: u32,
        /// Piece tasks in the whole image.
        tasks: u64,
    },
    /// Valid, and its PFM within bounds, but with more ray–object pairs than
    /// [`COUNT_AT_MOST`]: counting them exactly is seconds of work that the limits tests
    /// cover (`tests/tests/limits.rs`), not worth a fuzzer's time per input.
    NotCounted,
}

/// The most ray–object pairs [`submit_job`] counts exactly.
pub const COUNT_AT_MOST: u64 = 1 << 18;

/// A `SubmitJobRequest`'s bytes, decoded and planned as `SubmitJob` plans it
/// (`coordinator/src/farm/api.rs`, `plan`): the scene parsed over the workers' headers,
/// then `DriverConfig::check_work` (the PFM capped, the work counted, bands sized and
/// checked against the memory bound), each refusal turned into the typed failure the client
/// would get.
pub fn submit_job(bytes: &[u8]) -> Result<Planned, JobRefusal> {
    let request = pb::SubmitJobRequest::decode(bytes).map_err(JobRefusal::Decode)?;
    let driver = DriverConfig::default();
    let name = if request.scene_name.is_empty() { "scene.toml".to_string() } else { request.scene_name };
    let refused = |mut f: pb::Failure| {
        f.file = name.clone();
        JobRefusal::Refused(Box::new(f))
    };
    let scene = Scene::parse_with(&request.scene_toml, std::path::Path::new(&name), fixed_catalog())
        .map_err(|e| JobRefusal::Refused(Box::new(convert::scene_failure(&e))))?;
    let options = request.options.unwrap_or_default();
    let (w, h) = (scene.image().width, scene.image().height);
    if w as u64 * h as u64 * scene.objects().len() as u64 > COUNT_AT_MOST {
        // Too large to count within a fuzz input's time: only what comes before counting.
        if options.want_pfm {
            check_pfm(w, h, driver.max_pfm_pixels).map_err(|e| refused(convert::limit_failure(&e)))?;
        }
        return Ok(Planned::NotCounted);
    }
    let (work, band_rows, _) = driver.check_work(&scene, &options).map_err(|e| refused(convert::limit_failure(&e)))?;
    Ok(Planned::Counted { band_rows, tasks: work.tasks_in(0..h) })
}

/// Why [`cast_batch`]'s bytes were refused.
#[derive(Debug)]
pub enum BatchRefusal {
    /// Not tasks in wire form (the worker answers `BAD_BATCH`).
    Wire(wire::WireError),
    /// Tasks, but not pieces of this dataset's objects (the worker answers `BAD_BATCH`).
    Cast(CastError),
}

/// The scene and voxels [`cast_batch`] casts against: two objects of one generated
/// dataset on a 16² image, and a third of another dataset.
fn batch_scene() -> &'static (Scene, Arc<Volume>) {
    static SCENE: OnceLock<(Scene, Arc<Volume>)> = OnceLock::new();
    SCENE.get_or_init(|| {
        let scene = Scene::parse(BATCH_SCENE, "batch.toml").expect("the batch scene is valid");
        let volume = scene.datasets()[0].load().expect("a generated dataset loads");
        (scene, volume)
    })
}

const BATCH_SCENE: &str = r#"
[image]
width = 16
height = 16
background = [0, 0, 0]
[camera]
eye = [0.5, 0.5, 3.0]
target = [0.5, 0.5, 0.5]
up = [0, 1, 0]
fov_y = 30.0
[[datasets]]
name = "ball"
dims = [8, 8, 8]
[datasets.channels.voxel]
generator = { kind = "sphere", radius = 0.5, profile = "radial", value = 1.0, type = "f32" }
[[datasets]]
name = "other"
dims = [2, 2, 2]
[datasets.channels.voxel]
generator = { kind = "constant", value = 0.5 }
[[objects]]
name = "ball"
dataset = "ball"
colour = { type = "ramp", points = [[0.0, 0.9, 0.3, 0.1], [1.0, 0.2, 0.5, 1.0]] }
opacity = { type = "ramp", points = [[0.0, 0.0], [1.0, 0.5]] }
[[objects]]
name = "cubic"
dataset = "ball"
interpolation = "cubic"
transform = { matrix = [[0.5, 0, 0, 0.25], [0, 0.5, 0, 0.25], [0, 0, 0.5, 0.25], [0, 0, 0, 1]] }
colour = { type = "ramp", points = [[0.0, 1, 1, 1], [1.0, 1, 1, 1]] }
opacity = { type = "ramp", points = [[0.0, 0.1], [1.0, 0.1]] }
[[objects]]
name = "other"
dataset = "other"
colour = { type = "ramp", points = [[0.0, 1, 1, 1], [1.0, 1, 1, 1]] }
opacity = { type = "ramp", points = [[0.0, 0.1], [1.0, 0.1]] }
"#;

/// A batch's bytes as both ends of the `Cast` stream read them: as tasks, decoded and cast
/// by a worker against its job's scene (returning the samples taken); and as results, as
/// the coordinator decodes an answer. Either decoding that succeeds must be lossless: its
/// encoding decodes to the same values, bit for bit.
pub fn cast_batch(bytes: &[u8]) -> Result<u64, BatchRefusal> {
    if let Ok(results) = wire::decode_results(bytes) {
        let again = wire::encode_results(&results);
        let decoded = wire::decode_results(&again).expect("an encoding of results decodes");
        assert!(bits(&decoded) == bits(&results), "results changed through the wire");
    }
    let tasks = wire::decode_tasks(bytes).map_err(BatchRefusal::Wire)?;
    let again = wire::encode_tasks(&tasks);
    assert!(wire::encode_tasks(&wire::decode_tasks(&again).expect("an encoding of tasks decodes")) == again);
    let (scene, volume) = batch_scene();
    let caster = BatchCaster::new(scene, 0, volume).map_err(BatchRefusal::Cast)?;
    let mut out = vec![PieceRgba::default(); tasks.len()];
    caster.cast(&tasks, &mut out).map_err(BatchRefusal::Cast)
}

fn bits(results: &[PieceRgba]) -> Vec<[u32; 4]> {
    results
        .iter()
        .map(|r| [r.colour[0].to_bits(), r.colour[1].to_bits(), r.colour[2].to_bits(), r.alpha.to_bits()])
        .collect()
}

/// Valid inputs of `target` (one of [`TARGETS`]), each accepted by its entry point: what
/// the proptests mutate and what seeds the fuzzer (`fuzz/corpus/<target>/`).
pub fn seeds(target: &str) -> Vec<Vec<u8>> {
    match target {
        "scene" => SCENES.iter().map(|s| s.as_bytes().to_vec()).collect(),
        "nrrd" => vec![
            b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n\n\x00\x10\x20\x30\x40\x50\x60\x70"
                .to_vec(),
            b"NRRD0005\n# detached\ntype: unsigned short\ndimension: 3\nsizes: 4 4 2\nendian: big\nencoding: raw\n\
              data file: data.raw\nbyte skip: 448\n"
                .to_vec(),
            b"NRRD0004\ntype: float\ndimension: 2\nsizes: 4 32\nendian: little\nencoding: raw\ndatafile: data.raw\n"
                .to_vec(),
        ],
        "nifti" => vec![
            nifti_file([3, 2, 3, 4, 1, 1, 1, 1], 2, 8, &(0..24u8).collect::<Vec<_>>()),
            nifti_file(
                [3, 2, 2, 2, 1, 1, 1, 1],
                512,
                16,
                &(0..8u16).flat_map(|v| (v * 300).to_le_bytes()).collect::<Vec<_>>(),
            ),
            nifti_file([2, 2, 2, 1, 1, 1, 1, 1], 16, 32, &[0.5f32, 1.0, -2.0, 3.5].map(f32::to_le_bytes).concat()),
        ],
        "submit_job" => SCENES
            .iter()
            .zip([false, true, false])
            .map(|(s, want_pfm)| {
                let options = pb::JobOptions { want_pfm, batch_tasks: 64, band_rows: if want_pfm { 4 } else { 0 } };
                pb::SubmitJobRequest {
                    scene_toml: s.to_string(),
                    scene_name: "job.toml".into(),
                    options: Some(options),
                }
                .encode_to_vec()
            })
            .collect(),
        "cast_batch" => {
            let scene = &batch_scene().0;
            let h = scene.image().height;
            let tasks = trove_core::render::intersection::intersect(scene, 0..h).tasks;
            let ball: Vec<_> =
                tasks.into_iter().filter(|t| scene.objects()[t.object as usize].dataset() == 0).collect();
            let results = [PieceRgba::default(), PieceRgba { colour: [0.25, 0.5, 1.0], alpha: 0.75 }];
            vec![
                wire::encode_tasks(&ball[..ball.len().min(12)]),
                wire::encode_results(&results),
                wire::encode_tasks(&[]),
            ]
        }
        other => panic!("no fuzz target `{other}` (the targets are {TARGETS:?})"),
    }
}

/// A NIfTI-1 single file (`n+1`, little endian, data at 352) of `dim`, `datatype` and
/// `bitpix`, holding `data`.
fn nifti_file(dim: [i16; 8], datatype: i16, bitpix: i16, data: &[u8]) -> Vec<u8> {
    let mut h = vec![0u8; 352];
    h[0..4].copy_from_slice(&348i32.to_le_bytes());
    for (i, d) in dim.iter().enumerate() {
        h[40 + 2 * i..42 + 2 * i].copy_from_slice(&d.to_le_bytes());
    }
    h[70..72].copy_from_slice(&datatype.to_le_bytes());
    h[72..74].copy_from_slice(&bitpix.to_le_bytes());
    h[76..80].copy_from_slice(&1f32.to_le_bytes()); // pixdim[0] (qfac)
    h[108..112].copy_from_slice(&352f32.to_le_bytes()); // vox_offset
    h[344..348].copy_from_slice(b"n+1\0");
    h.extend_from_slice(data);
    h
}

/// Valid scenes over [`catalog_files`]: a file of each kind, generators, every map kind.
const SCENES: [&str; 3] = [
    r#"
[image]
width = 12
height = 10
background = [0.1, 0.1, 0.2]
[camera]
eye = [0.5, 0.5, 3.0]
target = [0.5, 0.5, 0.5]
up = [0, 1, 0]
fov_y = 35.0
[render]
termination = 0.95
[[datasets]]
name = "head"
file = "head.nrrd"
[[datasets]]
name = "slab"
dims = [4, 4, 2]
[datasets.channels.voxel]
raw = "slab.raw"
type = "u8"
[[objects]]
name = "head"
dataset = "head"
interpolation = "cubic"
sampling_distance = 0.01
colour = { type = "ramp", points = [[0, 0.2, 0.3, 0.9], [255, 1, 1, 1]] }
opacity = { type = "ramp", points = [[0, 0.0], [40, 0.0], [255, 0.5]] }
[[objects]]
name = "slab"
dataset = "slab"
transform = { matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0.1, 0.9], [0, 0, 0, 1]] }
colour = { type = "ramp", points = [[0, 0.2, 0.3, 0.9], [255, 1, 1, 1]] }
opacity = { type = "ramp", points = [[0, 0.05], [255, 0.5]] }
"#,
    r#"
[image]
width = 8
height = 8
background = [0, 0, 0]
[camera]
eye = [0, 0, 4]
target = [0, 0, 0]
up = [0, 1, 0]
fov_y = 30.0
[[datasets]]
name = "mri"
file = "mri.nii.gz"
[[datasets]]
name = "ball"
dims = [6, 6, 6]
[datasets.channels.voxel]
generator = { kind = "sphere", radius = 0.5, profile = "radial", value = 1.0, type = "f32" }
[[objects]]
name = "mri"
dataset = "mri"
interpolation = "nearest"
transform = { matrix = [[2, 0, 0, -1], [0, 2, 0, -1], [0, 0, 2, -1], [0, 0, 0, 1]] }
colour = { type = "ramp", points = [[0, 1, 1, 1], [65535, 1, 0, 0]] }
opacity = { type = "ramp", points = [[0, 0.0], [65535, 0.3]] }
[[objects]]
name = "ball"
dataset = "ball"
colour = { type = "ramp", points = [[0.0, 0.9, 0.3, 0.1], [1.0, 0.2, 0.5, 1.0]] }
opacity = { type = "ramp", points = [[0.0, 0.0], [1.0, 0.4]] }
"#,
    r#"
[image]
width = 8
height = 4
background = [0, 0, 0]
[camera]
eye = [0.5, 0.5, 2.0]
target = [0.5, 0.5, 0.5]
up = [0, 1, 0]
fov_y = 40.0
[[datasets]]
name = "photo"
image = "photo.png"
[[datasets]]
name = "flow"
file = "flow.nhdr"
[[objects]]
name = "photo"
dataset = "photo"
colour = { type = "raw" }
opacity = { type = "constant", coefficients = [0.8] }
transform = { matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0.05, 0.5], [0, 0, 0, 1]] }
[[objects]]
name = "flow"
dataset = "flow"
sampling_distance = 0.05
colour = { type = "ramp", points = [[-1.0, 0, 0, 1], [1.0, 1, 0, 0]] }
opacity = { type = "ramp", points = [[-1.0, 0.5], [1.0, 0.5]] }
"#,
];
