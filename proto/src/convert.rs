//! Translation between `trove-core` types and the wire: file headers as workers register
//! them, and every error as a typed [`pb::Failure`] (in a gRPC status's details when a call
//! is refused), so a reason is never flattened to a string on its way across a process.

use prost::Message;
use tonic::{Code, Status};
use trove_core::dataset::StoredType;
use trove_core::dataset::{
    ChannelName, ChannelSource, DataFile, DatasetError, Dims, Encoding, Endian, FileInfo, FileKind, VoxelType,
};
use trove_core::error::with_causes;
use trove_core::render::limits::LimitError;
use trove_core::render::{CastError, StoreError};
use trove_core::scene::{SceneError, SceneErrorKind};

use crate::v1 as pb;

/// Request metadata that carries a job's id to the workers, so one job can be followed
/// across the coordinator's and the workers' logs.
pub const JOB_HEADER: &str = "x-trove-job";

/// What names a job's scene on a cast stream that does not carry it (`CastOpen.scene_digest`):
/// SHA-256 of the scene's text, its name and the headers of its files, each length-prefixed,
/// so that the coordinator and every worker compute the same 32 bytes from the same fields,
/// and two different scenes never share them.
pub fn scene_digest(
    scene_toml: &str,
    scene_name: &str,
    headers: &[pb::DatasetFile],
    shadow_maps: Option<&[pb::ShadowMap]>,
) -> [u8; 32] {
    use sha2::{Digest, Sha256};
    let mut h = Sha256::new();
    for part in [scene_toml.as_bytes(), scene_name.as_bytes()] {
        h.update((part.len() as u64).to_le_bytes());
        h.update(part);
    }
    h.update((headers.len() as u64).to_le_bytes());
    for header in headers {
        h.update(header.encode_length_delimited_to_vec());
    }
    // A scene without shadow maps hashes as it did before maps existed.
    if let Some(shadow_maps) = shadow_maps {
        h.update(b"shadow maps");
        h.update((shadow_maps.len() as u64).to_le_bytes());
        for map in shadow_maps {
            h.update(map.encode_length_delimited_to_vec());
        }
    }
    h.finalize().into()
}

/// Shadow factors and maps on the wire: most of a lattice's values are exactly 1 (rays
/// that meet nothing), so the values go as runs, each a u32 count of values that are 1, a
/// u32 count n of values that follow, and those n f32s, all little-endian.
pub fn unit_runs(values: &[f32]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < values.len() {
        let ones = values[i..].iter().take_while(|&&v| v == 1.0).count();
        i += ones;
        let others = values[i..].iter().take_while(|&&v| v != 1.0).count();
        out.extend((ones as u32).to_le_bytes());
        out.extend((others as u32).to_le_bytes());
        values[i..i + others].iter().for_each(|v| out.extend(v.to_le_bytes()));
        i += others;
    }
    out
}

/// [`unit_runs`]' inverse for `len` values; `None` for bytes that are not runs of exactly
/// `len` values.
pub fn from_unit_runs(bytes: &[u8], len: usize) -> Option<Vec<f32>> {
    let mut out = Vec::with_capacity(len);
    let mut rest = bytes;
    let word = |rest: &mut &[u8]| -> Option<[u8; 4]> {
        let (w, tail) = rest.split_first_chunk::<4>()?;
        *rest = tail;
        Some(*w)
    };
    while !rest.is_empty() {
        let ones = u32::from_le_bytes(word(&mut rest)?) as usize;
        let others = u32::from_le_bytes(word(&mut rest)?) as usize;
        if out.len() + ones + others > len {
            return None;
        }
        out.resize(out.len() + ones, 1.0);
        for _ in 0..others {
            out.push(f32::from_le_bytes(word(&mut rest)?));
        }
    }
    (out.len() == len).then_some(out)
}

/// The maps of a scene's shadow plan as `CastOpen` carries them.
pub fn shadow_maps_to_wire(maps: &[Option<Vec<Option<trove_core::scene::Transmittance>>>]) -> Vec<pb::ShadowMap> {
    let mut out = Vec::new();
    for (object, per_light) in maps.iter().enumerate() {
        for (light, map) in per_light.iter().flatten().enumerate() {
            if let Some(t) = map {
                out.push(pb::ShadowMap {
                    object: object as u32,
                    light: light as u32,
                    dims: t.dims().to_vec(),
                    values: unit_runs(t.values()),
                    fine_values: unit_runs(t.fine_values()),
                });
            }
        }
    }
    out
}

/// `scene` with the maps `CastOpen` carried attached, every lit object under a shadowing
/// light given its maps (none where nothing else comes between it and the light); an error
/// names what does not fit the scene.
pub fn attach_shadow_maps(
    scene: &trove_core::scene::Scene,
    maps: &[pb::ShadowMap],
) -> Result<trove_core::scene::Scene, String> {
    let lights = scene.lights().len();
    let mut per_object: Vec<Option<Vec<Option<trove_core::scene::Transmittance>>>> =
        scene.objects().iter().map(|o| o.needs_shadow_maps().then(|| vec![None; lights])).collect();
    for m in maps {
        let (o, l) = (m.object as usize, m.light as usize);
        let slot = per_object
            .get_mut(o)
            .and_then(|p| p.as_mut())
            .and_then(|p| p.get_mut(l))
            .ok_or_else(|| format!("a shadow map for object {o} and light {l}, which the scene has no use for"))?;
        let dims: [u32; 3] =
            m.dims.as_slice().try_into().map_err(|_| format!("shadow map {o}/{l}: dims {:?}", m.dims))?;
        let len = dims.iter().map(|&n| n as usize).product();
        let values = from_unit_runs(&m.values, len)
            .ok_or_else(|| format!("shadow map {o}/{l}: {} bytes that are not {len} values", m.values.len()))?;
        let mut t =
            trove_core::scene::Transmittance::new(dims, values).map_err(|e| format!("shadow map {o}/{l}: {e}"))?;
        if !m.fine_values.is_empty() {
            let refinement = t.refinement();
            let len = refinement.points().len();
            let fine = from_unit_runs(&m.fine_values, len).ok_or_else(|| {
                format!("shadow map {o}/{l}: {} bytes of fine values that are not {len} values", m.fine_values.len())
            })?;
            t = t.with_fine(&refinement, fine).map_err(|e| format!("shadow map {o}/{l}: fine values: {e}"))?;
        }
        *slot = Some(t);
    }
    Ok(scene.with_shadow_maps(per_object))
}

/// A failure for a person and a program: `reason` and `retryable` for the program, the
/// message for the person.
pub fn failure(reason: pb::Reason, retryable: bool, message: String) -> pb::Failure {
    pb::Failure { reason: reason as i32, retryable, message, ..Default::default() }
}

/// The gRPC status that refuses a call with `f`: a code a generic client understands, and
/// `f` itself in the details for one that knows the protocol.
pub fn failure_status(f: pb::Failure) -> Status {
    let code = match f.reason() {
        pb::Reason::SceneInvalid | pb::Reason::BadBatch => Code::InvalidArgument,
        pb::Reason::DatasetNotHeld | pb::Reason::DatasetInvalid => Code::FailedPrecondition,
        pb::Reason::Cancelled => Code::Cancelled,
        pb::Reason::WorkerLost | pb::Reason::Unavailable => Code::Unavailable,
        pb::Reason::LimitExceeded | pb::Reason::Busy => Code::ResourceExhausted,
        pb::Reason::SceneUnknown => Code::FailedPrecondition,
        pb::Reason::NotFound => Code::NotFound,
        pb::Reason::DeadlineExceeded => Code::DeadlineExceeded,
        pb::Reason::Internal | pb::Reason::Unspecified => Code::Internal,
    };
    Status::with_details(code, f.message.clone(), f.encode_to_vec().into())
}

/// The typed failure a status carries, if it carries one.
pub fn status_failure(status: &Status) -> Option<pb::Failure> {
    if status.details().is_empty() {
        return None;
    }
    pb::Failure::decode(status.details()).ok()
}

/// Whether a dataset error means "not here" (another holder may have it) rather than "the
/// file is bad".
fn not_here(e: &DatasetError) -> bool {
    matches!(
        e,
        DatasetError::NotHeld { .. }
            | DatasetError::Remote { .. }
            | DatasetError::InvalidKey { .. }
            | DatasetError::OutsideRoot { .. }
            | DatasetError::DataFileOutsideRoot { .. }
    )
}

/// A scene that cannot be rendered: its file and key, and whether a dataset is at fault.
pub fn scene_failure(e: &SceneError) -> pb::Failure {
    let (reason, retryable) = match &e.kind {
        SceneErrorKind::Dataset(d) if not_here(d) => (pb::Reason::DatasetNotHeld, true),
        SceneErrorKind::Dataset(d) => (pb::Reason::DatasetInvalid, d.is_retryable()),
        _ => (pb::Reason::SceneInvalid, false),
    };
    let mut f = failure(reason, retryable, with_causes(e));
    f.file = e.file.display().to_string();
    f.key = e.key.clone().unwrap_or_default();
    f
}

/// A render over one of `trove-core`'s limits on work or image size: never retryable.
pub fn limit_failure(e: &LimitError) -> pb::Failure {
    failure(pb::Reason::LimitExceeded, false, e.to_string())
}

/// The status that refuses a submitted scene over a limit: INVALID_ARGUMENT (the request
/// cannot succeed as sent, unlike a RESOURCE_EXHAUSTED that may pass later), with `f`
/// (reason `LIMIT_EXCEEDED`) in its details.
pub fn limit_status(f: pb::Failure) -> Status {
    Status::with_details(Code::InvalidArgument, f.message.clone(), f.encode_to_vec().into())
}

/// A dataset the store could not provide.
pub fn store_failure(e: &StoreError) -> pb::Failure {
    let (reason, retryable, name) = match e {
        StoreError::BudgetTooSmall { name, .. } => (pb::Reason::LimitExceeded, false, name),
        StoreError::Load { name, source } if not_here(source) => (pb::Reason::DatasetNotHeld, true, name),
        StoreError::Load { name, source } => (pb::Reason::DatasetInvalid, source.is_retryable(), name),
    };
    let mut f = failure(reason, retryable, with_causes(e));
    f.dataset = name.clone();
    f
}

/// A batch that cannot be cast.
pub fn cast_failure(e: &CastError) -> pb::Failure {
    let reason = match e {
        CastError::Bind { .. } => pb::Reason::DatasetInvalid,
        _ => pb::Reason::BadBatch,
    };
    failure(reason, false, with_causes(e))
}

fn voxel_type(ty: VoxelType) -> pb::VoxelType {
    match ty {
        VoxelType::Bit => pb::VoxelType::Bit,
        VoxelType::U8 => pb::VoxelType::U8,
        VoxelType::U16 => pb::VoxelType::U16,
        VoxelType::U32 => pb::VoxelType::U32,
        VoxelType::F32 => pb::VoxelType::F32,
    }
}

fn from_voxel_type(ty: pb::VoxelType) -> Option<VoxelType> {
    Some(match ty {
        pb::VoxelType::Bit => VoxelType::Bit,
        pb::VoxelType::U8 => VoxelType::U8,
        pb::VoxelType::U16 => VoxelType::U16,
        pb::VoxelType::U32 => VoxelType::U32,
        pb::VoxelType::F32 => VoxelType::F32,
        pb::VoxelType::Unspecified => return None,
    })
}

fn dims(d: Dims) -> pb::Dims {
    let [x, y, z] = d.as_array();
    pb::Dims { x, y, z }
}

/// A registration entry for `key` from what a catalog found there. The byte size is
/// the file's length for raw files and 0 otherwise (callers set it from the raw answer).
pub fn dataset_file(key: &str, info: &FileInfo) -> pb::DatasetFile {
    let (bytes, header) = match info {
        FileInfo::Raw { bytes, .. } => (*bytes, None),
        FileInfo::Volume { dims: d, ty, .. } => (
            0,
            Some(pb::dataset_file::Header::Volume(pb::VolumeHeader {
                dims: Some(dims(*d)),
                r#type: voxel_type(*ty) as i32,
            })),
        ),
        FileInfo::Image { dims: d, channels } => (
            0,
            Some(pb::dataset_file::Header::Image(pb::ImageHeader {
                dims: Some(dims(*d)),
                channels: channels.iter().map(|(c, _)| c.name().to_string()).collect(),
            })),
        ),
    };
    pb::DatasetFile { key: key.to_string(), bytes, header }
}

/// A header from the wire that does not describe a volume or image TROVE can use.
fn bad_header(key: &str, what: &str) -> DatasetError {
    DatasetError::format(key, format!("the worker that holds it registered {what}"))
}

fn header_dims(key: &str, d: Option<&pb::Dims>) -> Result<Dims, DatasetError> {
    let d = d.ok_or_else(|| bad_header(key, "no dims"))?;
    Dims::new([d.x as u64, d.y as u64, d.z as u64]).map_err(|_| bad_header(key, "impossible dims"))
}

/// What `file`, registered by a worker, is as `kind` — the coordinator's (and a worker's, for
/// files it does not hold) view of a file it cannot read: every source is
/// [`DataFile::Remote`].
pub fn describe_remote(file: &pb::DatasetFile, kind: FileKind) -> Result<FileInfo, DatasetError> {
    let key = file.key.as_str();
    let remote = || DataFile::Remote(key.to_string());
    match (kind, &file.header) {
        (FileKind::Raw, _) => Ok(FileInfo::Raw { bytes: file.bytes, file: remote() }),
        (FileKind::Volume, Some(pb::dataset_file::Header::Volume(v))) => {
            let dims = header_dims(key, v.dims.as_ref())?;
            let ty = from_voxel_type(v.r#type()).ok_or_else(|| bad_header(key, "no voxel type"))?;
            let source = ChannelSource::File {
                file: remote(),
                offset: 0,
                encoding: Encoding::Raw,
                stored: StoredType::from(ty),
                endian: Endian::Little,
            };
            Ok(FileInfo::Volume { dims, ty, source })
        }
        (FileKind::Image, Some(pb::dataset_file::Header::Image(i))) => {
            let dims = header_dims(key, i.dims.as_ref())?;
            let channels = i
                .channels
                .iter()
                .map(|name| {
                    let channel = ChannelName::parse(name).ok_or_else(|| bad_header(key, "an unknown channel"))?;
                    Ok((channel, ChannelSource::Image { file: remote(), channel }))
                })
                .collect::<Result<_, DatasetError>>()?;
            Ok(FileInfo::Image { dims, channels })
        }
        (FileKind::Volume, _) => Err(DatasetError::format(key, "its worker found no NRRD or NIfTI header in it")),
        (FileKind::Image, _) => Err(DatasetError::format(key, "its worker found no PNG or JPEG header in it")),
    }
}

/// Two workers registered different files under one key: no scene may use it until they
/// agree.
pub fn workers_disagree(key: &str) -> DatasetError {
    DatasetError::format(key, "workers registered different files under this key")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A lit ball and an unlit one under a light that casts shadows.
    const SHADOWED: &str = r#"
[image]
width = 4
height = 4
background = [0.0, 0.0, 0.0]
[camera]
eye = [0.5, 0.5, 3.0]
target = [0.5, 0.5, 0.5]
up = [0.0, 1.0, 0.0]
fov_y = 30.0
[[lights]]
type = "directional"
direction = [0.0, -1.0, 0.0]
shadows = true
[[datasets]]
name = "ball"
dims = [4, 4, 4]
[datasets.channels.voxel]
generator = { kind = "sphere", radius = 0.5, profile = "radial", value = 1.0, type = "f32" }
[[objects]]
name = "lit"
dataset = "ball"
colour = { type = "constant", red = [1.0], green = [1.0], blue = [1.0] }
opacity = { type = "ramp", points = [[0.0, 0.0], [1.0, 1.0]] }
shading = {}
[[objects]]
name = "unlit"
dataset = "ball"
colour = { type = "constant", red = [1.0], green = [1.0], blue = [1.0] }
opacity = { type = "ramp", points = [[0.0, 0.0], [1.0, 1.0]] }
"#;

    #[test]
    fn shadow_maps_cross_the_wire_unchanged_and_bad_ones_are_refused() {
        let scene = trove_core::scene::Scene::parse(SHADOWED, "s.toml").unwrap();
        let t = trove_core::scene::Transmittance::new([2, 3, 2], (0..12).map(|i| i as f32 / 11.0).collect()).unwrap();
        let maps = vec![Some(vec![Some(t.clone())]), None];
        let wire = shadow_maps_to_wire(&maps);
        assert_eq!(wire.len(), 1);
        let attached = attach_shadow_maps(&scene, &wire).unwrap();
        assert_eq!(attached.objects()[0].shadow_maps(), Some(&[Some(t)][..]));
        assert_eq!(attached.objects()[1].shadow_maps(), None);
        // None sent: the lit object has nothing else between it and the light.
        assert_eq!(attach_shadow_maps(&scene, &[]).unwrap().objects()[0].shadow_maps(), Some(&[None][..]));
        let bad = |edit: fn(&mut pb::ShadowMap)| {
            let mut m = wire[0].clone();
            edit(&mut m);
            attach_shadow_maps(&scene, &[m]).unwrap_err()
        };
        assert!(bad(|m| m.object = 1).contains("no use for"));
        assert!(bad(|m| m.light = 1).contains("no use for"));
        assert!(bad(|m| m.object = 9).contains("no use for"));
        assert!(bad(|m| m.dims = vec![2, 3]).contains("dims"));
        assert!(bad(|m| m.values.truncate(45)).contains("bytes"));
        assert!(bad(|m| m.values.truncate(44)).contains("bytes"));
        assert!(bad(|m| m.values[8..12].copy_from_slice(&2.0f32.to_le_bytes())).contains("[0, 1]"));
    }

    #[test]
    fn refined_shadow_maps_cross_the_wire_with_their_fine_values() {
        let scene = trove_core::scene::Scene::parse(SHADOWED, "s.toml").unwrap();
        // A shadow edge across x: the cells it crosses are refined.
        let coarse = trove_core::scene::Transmittance::new(
            [6, 3, 3],
            (0..54).map(|n| if n % 6 < 3 { 0.25 } else { 1.0 }).collect(),
        )
        .unwrap();
        let refinement = coarse.refinement();
        let fine_len = refinement.points().len();
        assert!(fine_len > 0);
        let fine: Vec<f32> = (0..fine_len).map(|i| (i % 7) as f32 / 7.0).collect();
        let t = coarse.clone().with_fine(&refinement, fine).unwrap();
        let wire = shadow_maps_to_wire(&[Some(vec![Some(t.clone())]), None]);
        let attached = attach_shadow_maps(&scene, &wire).unwrap();
        assert_eq!(attached.objects()[0].shadow_maps(), Some(&[Some(t)][..]));
        // The first pass's maps, without fine values, cross as they are.
        let first = shadow_maps_to_wire(&[Some(vec![Some(coarse.clone())]), None]);
        assert!(first[0].fine_values.is_empty());
        assert_eq!(attach_shadow_maps(&scene, &first).unwrap().objects()[0].shadow_maps(), Some(&[Some(coarse)][..]));
        let mut short = wire[0].clone();
        short.fine_values.truncate(short.fine_values.len() - 4);
        assert!(attach_shadow_maps(&scene, &[short]).unwrap_err().contains("fine values"));
        // Fine values for a lattice that refines nothing are refused too.
        let mut flat = wire[0].clone();
        flat.values = unit_runs(&[0.5; 54]);
        assert!(attach_shadow_maps(&scene, &[flat]).unwrap_err().contains("fine values"));
    }

    #[test]
    fn unit_runs_round_trip_and_refuse_what_is_not_runs_of_the_length() {
        for values in [vec![], vec![1.0; 5], vec![0.5; 3], vec![1.0, 0.0, 0.25, 1.0, 1.0, 0.75, 1.0], vec![0.0, 1.0]] {
            let bytes = unit_runs(&values);
            assert_eq!(from_unit_runs(&bytes, values.len()), Some(values.clone()));
            assert_eq!(from_unit_runs(&bytes, values.len() + 1), None);
            if !bytes.is_empty() {
                assert_eq!(from_unit_runs(&bytes[..bytes.len() - 1], values.len()), None);
            }
        }
        // A lattice that is mostly 1 costs little.
        let mut mostly = vec![1.0f32; 10_000];
        mostly[5000..5010].fill(0.5);
        assert_eq!(unit_runs(&mostly).len(), 2 * 8 + 40);
        // Counts that overrun the length are refused without allocating them.
        let mut huge = u32::MAX.to_le_bytes().to_vec();
        huge.extend(0u32.to_le_bytes());
        assert_eq!(from_unit_runs(&huge, 4), None);
    }

    #[test]
    fn a_failure_survives_a_status_round_trip() {
        let mut f = failure(pb::Reason::SceneInvalid, false, "scenes/x.toml: camera.fov_y: expected degrees".into());
        f.file = "scenes/x.toml".into();
        f.key = "camera.fov_y".into();
        let status = failure_status(f.clone());
        assert_eq!(status.code(), Code::InvalidArgument);
        assert_eq!(status_failure(&status), Some(f));
        assert_eq!(status_failure(&Status::internal("plain")), None);
    }

    #[test]
    fn registered_headers_describe_remote_files() {
        let dims = Dims::new([4, 5, 6]).unwrap();
        let source = ChannelSource::File {
            file: DataFile::Remote("a.nhdr".into()),
            offset: 0,
            encoding: Encoding::Raw,
            stored: StoredType::from(VoxelType::U16),
            endian: Endian::Little,
        };
        let mut f = dataset_file("a.nhdr", &FileInfo::Volume { dims, ty: VoxelType::U16, source });
        f.bytes = 240;
        match describe_remote(&f, FileKind::Volume).unwrap() {
            FileInfo::Volume { dims: d, ty, source: ChannelSource::File { file, .. } } => {
                assert_eq!((d, ty, file), (dims, VoxelType::U16, DataFile::Remote("a.nhdr".into())));
            }
            other => panic!("{other:?}"),
        }
        assert!(matches!(describe_remote(&f, FileKind::Raw), Ok(FileInfo::Raw { bytes: 240, .. })));
        assert!(describe_remote(&f, FileKind::Image).is_err());
    }
}
