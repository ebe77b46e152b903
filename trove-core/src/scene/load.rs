//! From TOML text to a validated [`Scene`]: every rule of SPEC §1–2 and §4.5 is checked
//! here, once, and each failure is a [`SceneErrorKind`](super::SceneErrorKind) at the key
//! path it is about. This is the edge where key paths are attached: lower layers (datasets,
//! geometry, generators) return their own error types, which become the error's source.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;
use std::sync::Arc;

use glam::{DMat3, DMat4, DVec3, DVec4};

use super::effects::{Light, LightSource, Shading, ShadingField, UnitVector};
use super::error::{SceneError, SceneErrorKind as Kind};
use super::file::{ChannelFile, DatasetFile, LightFile, ObjectFile, SceneFile, ShadingFile, TransformFile};
use super::limits::{MAX_IMAGE_SIDE, MAX_LIGHTS, MAX_OBJECTS, MAX_SAMPLES_PER_PIECE, MAX_SAMPLES_PER_RENDER};
use super::mappings::{self, KeyError};
use super::{ImageSettings, Object, RenderSettings, Scene};
use crate::dataset::generator::{Generator, GeneratorError};
use crate::dataset::raw::{self, StoredType};
use crate::dataset::{
    Catalog, ChannelName, ChannelSource, DatasetError, DatasetInfo, Dims, Encoding, Endian, FileInfo, FileKind,
    VolumeFormat, VoxelType,
};
use crate::geometry::hexahedron::Hexahedron;
use crate::geometry::{Camera, CameraField, Extent, Placement, Shape};

/// A refusal at `key`.
fn err<T>(key: impl Into<String>, kind: Kind) -> Result<T, KeyError> {
    Err(KeyError::new(key, kind))
}

/// Parses and validates a whole scene, describing its dataset keys through `catalog`.
pub(super) fn scene(text: &str, path: &Path, catalog: &dyn Catalog) -> Result<Scene, SceneError> {
    let fail = |e: KeyError| SceneError { file: path.to_path_buf(), key: Some(e.key), kind: e.kind };
    let file = deserialize(text, path)?;

    let image = image_settings(&file).map_err(fail)?;
    let camera = camera(&file).map_err(fail)?;
    let render = render_settings(&file).map_err(fail)?;
    let straight = match file.render.distorted_sampling.as_str() {
        "exact" => false,
        "straight" => true,
        other => {
            let kind = Kind::DistortedSampling { got: other.to_string() };
            return Err(fail(KeyError::new("render.distorted_sampling", kind)));
        }
    };

    for (what, got) in [("datasets", file.datasets.len()), ("objects", file.objects.len())] {
        if got > MAX_OBJECTS {
            return Err(fail(KeyError::new(what, Kind::TooMany { what, max: MAX_OBJECTS, got })));
        }
    }
    let mut datasets = Vec::with_capacity(file.datasets.len());
    let mut by_name = HashMap::new();
    for (i, d) in file.datasets.iter().enumerate() {
        let key = format!("datasets[{i}]");
        if let Some(j) = by_name.insert(d.name.clone(), i) {
            let kind = Kind::DuplicateName { what: "dataset", name: d.name.clone(), first: format!("datasets[{j}]") };
            return Err(fail(KeyError::new(format!("{key}.name"), kind)));
        }
        datasets.push(dataset(d, &key, catalog).map_err(fail)?);
    }

    if file.lights.len() > MAX_LIGHTS {
        let kind = Kind::TooMany { what: "lights", max: MAX_LIGHTS, got: file.lights.len() };
        return Err(fail(KeyError::new("lights", kind)));
    }
    let lights: Vec<Light> = file
        .lights
        .iter()
        .enumerate()
        .map(|(i, l)| light(l, &format!("lights[{i}]")))
        .collect::<Result<_, _>>()
        .map_err(fail)?;
    // Objects that are shaded share the scene's lights.
    let shared: Option<Arc<[Light]>> = (!lights.is_empty()).then(|| lights.clone().into());
    let mut objects = Vec::with_capacity(file.objects.len());
    let mut object_names = HashMap::new();
    for (i, o) in file.objects.iter().enumerate() {
        let key = format!("objects[{i}]");
        if let Some(j) = object_names.insert(o.name.clone(), i) {
            let kind = Kind::DuplicateName { what: "object", name: o.name.clone(), first: format!("objects[{j}]") };
            return Err(fail(KeyError::new(format!("{key}.name"), kind)));
        }
        let Some(&ds) = by_name.get(&o.dataset) else {
            let known = file.datasets.iter().map(|d| d.name.clone()).collect();
            let kind = Kind::UnknownDataset { name: o.dataset.clone(), known };
            return Err(fail(KeyError::new(format!("{key}.dataset"), kind)));
        };
        let mut object = object(o, &key, ds, &datasets[ds], straight).map_err(fail)?;
        if object.shading.is_some() {
            object.lights.clone_from(&shared);
        }
        objects.push(object);
    }
    render_budget(&image, &camera, &objects, &datasets).map_err(fail)?;
    Ok(Scene { path: path.to_path_buf(), image, camera, render, datasets, objects, lights })
}

/// One `[[lights]]` entry (SPEC §6): its type's keys only, each in range.
fn light(l: &LightFile, key: &str) -> Result<Light, KeyError> {
    let not_for = |field: &str, ty: &'static str, takes: &'static str| {
        err(format!("{key}.{field}"), Kind::LightKeyNotForType { ty, takes })
    };
    let missing = |field: &str| err(format!("{key}.{field}"), Kind::MissingKey { field: field.to_string() });
    let source = match l.ty.as_str() {
        "directional" => {
            if l.position.is_some() {
                return not_for("position", "directional", "`direction`");
            }
            let Some(d) = l.direction else { return missing("direction") };
            let direction = UnitVector::new(DVec3::from(d))
                .ok_or_else(|| KeyError::new(format!("{key}.direction"), Kind::LightDirection { got: d }))?;
            LightSource::Directional { direction }
        }
        "point" => {
            if l.direction.is_some() {
                return not_for("direction", "point", "`position`");
            }
            let Some(p) = l.position else { return missing("position") };
            LightSource::Point { position: DVec3::from(p) }
        }
        other => return err(format!("{key}.type"), Kind::UnknownLightType { got: other.to_string() }),
    };
    let colour = l.colour.unwrap_or([1.0; 3]);
    let intensity = l.intensity.unwrap_or(1.0);
    Light::new(source, colour, intensity).map(|light| light.with_shadows(l.shadows.unwrap_or(false))).map_err(|e| {
        let field = match e {
            super::effects::LightError::Colour { .. } => "colour",
            super::effects::LightError::Intensity { .. } => "intensity",
            super::effects::LightError::Position { .. } => "position",
        };
        KeyError::new(format!("{key}.{field}"), Kind::Light(e))
    })
}

/// An object's `shading` table (SPEC §6), its omitted coefficients at their defaults.
fn shading(s: &ShadingFile, key: &str) -> Result<Shading, KeyError> {
    let d = Shading::DEFAULT;
    let (a, di, sp, sh) = (
        s.ambient.unwrap_or(d.ambient()),
        s.diffuse.unwrap_or(d.diffuse()),
        s.specular.unwrap_or(d.specular()),
        s.shininess.unwrap_or(d.shininess()),
    );
    Shading::new(a, di, sp, sh).map_err(|field| {
        let got = match field {
            ShadingField::Ambient => a,
            ShadingField::Diffuse => di,
            ShadingField::Specular => sp,
            ShadingField::Shininess => sh,
        };
        KeyError::new(format!("{key}.{}", field.name()), Kind::ShadingCoefficient { got })
    })
}

/// `[camera]`; the camera's error says which field it is about, which gives the key.
fn camera(f: &SceneFile) -> Result<Camera, KeyError> {
    let c = &f.camera;
    Camera::new(DVec3::from(c.eye), DVec3::from(c.target), DVec3::from(c.up), c.fov_y).map_err(|e| {
        let key = match e.field() {
            CameraField::Eye => "camera.eye",
            CameraField::Target => "camera.target",
            CameraField::Up => "camera.up",
            CameraField::FovY => "camera.fov_y",
        };
        KeyError::new(key, Kind::Camera(e))
    })
}

/// The diagonal of the axis-aligned bounding box of an object's corners (world units).
fn world_diagonal(placement: &Placement) -> f64 {
    let c = placement.corners();
    let (lo, hi) = c.iter().fold((c[0], c[0]), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
    (hi - lo).length()
}

/// Refuses a scene whose worst-case sample count exceeds [`MAX_SAMPLES_PER_RENDER`]: every
/// ray that can meet an object (the pixels of its projected bounding rectangle) through its
/// bounding-box diagonal, at the object's step (its world sampling distance, or one voxel:
/// the VC diagonal of its extent). A clear refusal beats a render that cannot finish;
/// termination 1.0 cannot shorten it either.
pub(super) fn render_budget(
    image: &ImageSettings,
    camera: &Camera,
    objects: &[Object],
    datasets: &[DatasetInfo],
) -> Result<(), KeyError> {
    let per_ray: Vec<f64> = objects
        .iter()
        .map(|o| {
            if o.sampling_distance > 0.0 {
                world_diagonal(&o.placement) / o.sampling_distance
            } else {
                let e = o.placement.extent();
                let d = datasets[o.dataset].dims();
                let n = DVec3::new(d.axis(0) as f64, d.axis(1) as f64, d.axis(2) as f64);
                ((e.max - e.min) * n).length()
            }
        })
        .collect();
    let total: f64 = objects
        .iter()
        .zip(&per_ray)
        .map(|(o, n)| camera.pixels_covering(&o.placement.corners(), image.width, image.height) as f64 * n)
        .sum();
    if total <= MAX_SAMPLES_PER_RENDER {
        return Ok(());
    }
    let (worst, most) =
        per_ray.iter().enumerate().fold((0, 0.0), |(i, m), (j, &v)| if v > m { (j, v) } else { (i, m) });
    err(
        format!("objects[{worst}].sampling_distance"),
        Kind::RenderTooCostly { total, width: image.width, height: image.height, per_ray: most },
    )
}

/// TOML → plain structs, with serde's errors turned into key paths and plain words.
fn deserialize(text: &str, path: &Path) -> Result<SceneFile, SceneError> {
    let at_key = |e: KeyError| SceneError { file: path.to_path_buf(), key: Some(e.key), kind: e.kind };
    let de = toml::Deserializer::parse(text).map_err(|e| SceneError {
        file: path.to_path_buf(),
        key: None,
        kind: Kind::Syntax {
            position: e.span().map(|s| line_column(text, s.start)),
            message: e.message().trim().to_string(),
        },
    })?;
    // serde fills a struct from an array too (`image = [8, 6, [0, 0, 0]]`), which would let
    // positional values through where the SPEC wants named keys: refuse that first.
    if let Ok(value) = text.parse::<toml::Table>() {
        tables_where_expected(&value).map_err(at_key)?;
    }
    serde_path_to_error::deserialize(de).map_err(|e| {
        let mut key = e.path().to_string();
        if key == "." {
            key.clear();
        }
        let (field, kind) = in_words(e.inner().message().trim());
        // A missing field is reported at its table; name the field itself. An unknown
        // field's path already ends with it.
        if let Some(field) = field {
            key = if key.is_empty() { field } else { format!("{key}.{field}") };
        }
        SceneError { file: path.to_path_buf(), key: (!key.is_empty()).then_some(key), kind }
    })
}

/// Checks that every key the format defines as a table (or an array of tables) is one.
fn tables_where_expected(top: &toml::Table) -> Result<(), KeyError> {
    fn not_a_table(got: String) -> Kind {
        Kind::WrongType { expected: "a table of named keys".into(), got }
    }
    fn table(v: &toml::Value, key: &str) -> Result<(), KeyError> {
        match v {
            toml::Value::Table(_) => Ok(()),
            other => err(key, not_a_table(format!("{} `{other}`", other.type_str()))),
        }
    }
    fn array_of_tables<'a>(v: &'a toml::Value, key: &str) -> Result<Vec<&'a toml::Table>, KeyError> {
        let Some(items) = v.as_array() else {
            let got = format!("{} `{v}`", v.type_str());
            return err(key, Kind::NotAnArrayOfTables { table: key.to_string(), got });
        };
        items
            .iter()
            .enumerate()
            .map(|(i, item)| {
                item.as_table()
                    .ok_or_else(|| KeyError::new(format!("{key}[{i}]"), not_a_table(item.type_str().to_string())))
            })
            .collect()
    }
    for key in ["image", "camera", "render"] {
        if let Some(v) = top.get(key) {
            table(v, key)?;
        }
    }
    if let Some(v) = top.get("datasets") {
        for (i, d) in array_of_tables(v, "datasets")?.into_iter().enumerate() {
            if let Some(channels) = d.get("channels") {
                let k = format!("datasets[{i}].channels");
                table(channels, &k)?;
                for (name, c) in channels.as_table().into_iter().flatten() {
                    table(c, &format!("{k}.{name}"))?;
                    if let Some(g) = c.get("generator") {
                        table(g, &format!("{k}.{name}.generator"))?;
                    }
                }
            }
        }
    }
    if let Some(v) = top.get("lights") {
        array_of_tables(v, "lights")?;
    }
    if let Some(v) = top.get("objects") {
        for (i, o) in array_of_tables(v, "objects")?.into_iter().enumerate() {
            for key in ["transform", "extent", "shading"] {
                if let Some(v) = o.get(key) {
                    table(v, &format!("objects[{i}].{key}"))?;
                }
            }
        }
    }
    Ok(())
}

/// Line and column of byte `offset` in `text`, both counted from 1.
fn line_column(text: &str, offset: usize) -> (usize, usize) {
    let before = text.get(..offset).unwrap_or(text);
    let line = before.matches('\n').count() + 1;
    let column = before.rsplit('\n').next().unwrap_or_default().chars().count() + 1;
    (line, column)
}

/// The text between the first pair of backticks after `prefix` at the start of `s`.
fn quoted_after<'a>(s: &'a str, prefix: &str) -> Option<&'a str> {
    s.strip_prefix(prefix)?.split('`').next()
}

/// serde's message in the scene's words: the sub-key it is about (for errors reported at
/// the enclosing table), and what was expected. serde hands its errors over as text (its
/// `Error::custom` carries no structure), so this is the one place that reads a message.
fn in_words(inner: &str) -> (Option<String>, Kind) {
    if let Some(field) = quoted_after(inner, "missing field `") {
        return (Some(field.to_string()), Kind::MissingKey { field: field.to_string() });
    }
    if let Some(field) = quoted_after(inner, "unknown field `") {
        let rest = inner.split_once("`, ").map_or("", |(_, r)| r);
        let expected = rest.strip_prefix("expected ").map(str::to_string);
        return (None, Kind::UnknownKey { field: field.to_string(), expected });
    }
    // "invalid type: string \"8\", expected i64" → "expected a whole number, got string \"8\"".
    for prefix in ["invalid type: ", "invalid value: "] {
        if let Some((got, expected)) = inner.strip_prefix(prefix).and_then(|r| r.split_once(", expected ")) {
            return (None, Kind::WrongType { expected: plain_type(expected), got: got.to_string() });
        }
    }
    if let Some((n, expected)) = inner.strip_prefix("invalid length ").and_then(|r| r.split_once(", expected ")) {
        // A table given as an array reaches here as "struct ImageFile with 3 elements".
        if expected.starts_with("struct ") {
            return (None, Kind::WrongType { expected: "a table".into(), got: format!("an array of {n} entries") });
        }
        if let Ok(got) = n.parse() {
            return (None, Kind::WrongLength { expected: expected.to_string(), got });
        }
    }
    (None, Kind::Deserialize(inner.to_string()))
}

/// Rust's primitive type names in words.
fn plain_type(expected: &str) -> String {
    match expected {
        "i8" | "i16" | "i32" | "i64" => "a whole number".into(),
        "u8" | "u16" | "u32" | "u64" | "usize" => {
            let max = match expected {
                "u8" => u8::MAX as u64,
                "u16" => u16::MAX as u64,
                "u32" => u32::MAX as u64,
                _ => u64::MAX,
            };
            format!("a whole number from 0 to {max}")
        }
        "f32" | "f64" => "a number".into(),
        "a sequence" => "an array".into(),
        "a map" => "a table".into(),
        other if other.starts_with("struct ") => "a table".into(),
        other => other.into(),
    }
}

/// An image side (`image.width`, `image.height`) within 1..=[`MAX_IMAGE_SIDE`].
pub(super) fn image_side(v: i64, key: &str) -> Result<u32, KeyError> {
    if v < 1 || v > MAX_IMAGE_SIDE as i64 {
        return err(key, Kind::ImageSide { got: v });
    }
    Ok(v as u32)
}

fn image_settings(f: &SceneFile) -> Result<ImageSettings, KeyError> {
    let width = image_side(f.image.width, "image.width")?;
    let height = image_side(f.image.height, "image.height")?;
    let background = f.image.background;
    if background.iter().any(|c| !(0.0..=1.0).contains(c)) {
        return err("image.background", Kind::Background { got: background });
    }
    Ok(ImageSettings { width, height, background })
}

fn render_settings(f: &SceneFile) -> Result<RenderSettings, KeyError> {
    let t = f.render.termination;
    if !(t > 0.0 && t <= 1.0) {
        return err("render.termination", Kind::Termination { got: t });
    }
    Ok(RenderSettings { termination: t, opacity_correction: f.render.opacity_correction })
}

fn dims_of(d: [i64; 3], key: &str) -> Result<Dims, KeyError> {
    if d.iter().any(|&n| n < 1) {
        return err(key, Kind::DimsBelowOne { got: d });
    }
    Dims::new(d.map(|n| n as u64)).map_err(|e| KeyError::new(key, Kind::Dims(e)))
}

fn check_channel_type(channel: ChannelName, got: VoxelType, key: &str) -> Result<(), KeyError> {
    if channel.allowed_types().contains(&got) {
        return Ok(());
    }
    err(key, Kind::ChannelType { channel, got })
}

/// Records dims found in a file, or refuses them when they differ from dims already fixed.
fn agree(dims: &mut Option<Dims>, found: Dims, key: &str) -> Result<Dims, KeyError> {
    match *dims {
        Some(declared) if declared != found => err(key, Kind::DimsDisagree { found, declared }),
        _ => {
            *dims = Some(found);
            Ok(found)
        }
    }
}

/// A dataset file's error, at the key that names the file.
fn dataset_error(key: &str) -> impl Fn(DatasetError) -> KeyError + '_ {
    move |e| KeyError::new(key, Kind::Dataset(e))
}

/// What `catalog` says `file` (written at `key`) holds.
fn describe(catalog: &dyn Catalog, file: &str, kind: FileKind, key: &str) -> Result<FileInfo, KeyError> {
    catalog.describe(file, kind).map_err(dataset_error(key))
}

/// A catalog's answer of another kind than asked for.
fn wrong_kind(file: &str, expected: FileKind, found: &FileInfo, key: &str) -> KeyError {
    let e = DatasetError::WrongKind { key: file.to_string(), expected, found: found.kind() };
    KeyError::new(key, Kind::Dataset(e))
}

/// A volume file (`file`, or a channel's `nrrd` when `only` says so) in a format TROVE reads.
fn volume(
    catalog: &dyn Catalog,
    file: &str,
    key: &str,
    only: Option<(VolumeFormat, &'static str)>,
) -> Result<(Dims, VoxelType, ChannelSource), KeyError> {
    let format = VolumeFormat::of_key(file);
    let expected = match only {
        Some((want, expected)) if format != Some(want) => Some(expected),
        None if format.is_none() => Some(".nrrd, .nhdr, .nii or .nii.gz"),
        _ => None,
    };
    if let Some(expected) = expected {
        return err(key, Kind::VolumeExtension { file: file.to_string(), expected });
    }
    match describe(catalog, file, FileKind::Volume, key)? {
        FileInfo::Volume { dims, ty, source } => Ok((dims, ty, source)),
        other => Err(wrong_kind(file, FileKind::Volume, &other, key)),
    }
}

fn dataset(d: &DatasetFile, key: &str, catalog: &dyn Catalog) -> Result<DatasetInfo, KeyError> {
    let mut channels: BTreeMap<ChannelName, (VoxelType, ChannelSource)> = BTreeMap::new();
    let declared = d.dims.map(|v| dims_of(v, &format!("{key}.dims"))).transpose()?;
    let mut dims = declared;
    match (&d.file, &d.image) {
        (Some(_), Some(_)) => return err(format!("{key}.image"), Kind::FileAndImage),
        (Some(f), None) => {
            let k = format!("{key}.file");
            let (found, ty, source) = volume(catalog, f, &k, None)?;
            agree(&mut dims, found, &k)?;
            check_channel_type(ChannelName::Voxel, ty, &k)?;
            channels.insert(ChannelName::Voxel, (ty, source));
        }
        (None, Some(img)) => {
            let k = format!("{key}.image");
            let (found, given) = match describe(catalog, img, FileKind::Image, &k)? {
                FileInfo::Image { dims, channels } => (dims, channels),
                other => return Err(wrong_kind(img, FileKind::Image, &other, &k)),
            };
            agree(&mut dims, found, &k)?;
            for (name, source) in given {
                channels.insert(name, (VoxelType::U8, source));
            }
        }
        (None, None) => {
            if d.channels.is_empty() {
                return err(key, Kind::NoSource);
            }
            if declared.is_none() {
                return err(format!("{key}.dims"), Kind::MissingDims);
            }
        }
    }
    for (cname, c) in &d.channels {
        let ck = format!("{key}.channels.{cname}");
        let Some(name) = ChannelName::parse(cname) else {
            return err(ck, Kind::UnknownChannel);
        };
        if channels.contains_key(&name) {
            return err(ck, Kind::ChannelGivenTwice { channel: name });
        }
        let Some(dims) = dims else {
            return err(format!("{key}.dims"), Kind::MissingDims);
        };
        let (ty, source) = channel(c, &ck, name, dims, catalog)?;
        channels.insert(name, (ty, source));
    }
    let dims = dims.expect("every branch above fixes dims or returns");
    for &(ty, _) in channels.values() {
        if ty.byte_len(dims.voxel_count()).is_none() {
            return err(format!("{key}.dims"), Kind::DimsOverflow { dims, ty });
        }
    }
    Ok(DatasetInfo::new(d.name.clone(), dims, channels))
}

/// One explicit channel `name`; a type the channel does not allow is refused at the key that
/// gives it (`type` of a raw file, the NRRD file, the generator).
fn channel(
    c: &ChannelFile,
    key: &str,
    name: ChannelName,
    dims: Dims,
    catalog: &dyn Catalog,
) -> Result<(VoxelType, ChannelSource), KeyError> {
    let given = [c.raw.is_some(), c.nrrd.is_some(), c.generator.is_some()].iter().filter(|&&b| b).count();
    if given != 1 {
        return err(key, Kind::ChannelSources);
    }
    let only_raw = |field: &str, present: bool| -> Result<(), KeyError> {
        if present && c.raw.is_none() {
            return err(format!("{key}.{field}"), Kind::RawOnlyKey);
        }
        Ok(())
    };
    only_raw("type", c.ty.is_some())?;
    only_raw("endian", c.endian.is_some())?;
    only_raw("offset", c.offset.is_some())?;
    if let Some(r) = &c.raw {
        let tk = format!("{key}.type");
        let Some(t) = &c.ty else {
            return err(tk, Kind::MissingRawType);
        };
        let ty = VoxelType::parse(t).ok_or_else(|| KeyError::new(&tk, Kind::UnknownVoxelType { got: t.clone() }))?;
        check_channel_type(name, ty, &tk)?;
        let endian = match c.endian.as_deref() {
            None => Endian::Little,
            Some(e) => Endian::parse(e)
                .ok_or_else(|| KeyError::new(format!("{key}.endian"), Kind::UnknownEndian { got: e.to_string() }))?,
        };
        // A raw file has no header: its length, from the catalog, must be exactly what the
        // scene's dims, type and offset call for.
        let rk = format!("{key}.raw");
        let (bytes, file) = match describe(catalog, r, FileKind::Raw, &rk)? {
            FileInfo::Raw { bytes, file } => (bytes, file),
            other => return Err(wrong_kind(r, FileKind::Raw, &other, &rk)),
        };
        let (offset, stored) = (c.offset.unwrap_or(0), StoredType::from(ty));
        raw::check_len(file.path(), bytes, offset, stored, dims).map_err(dataset_error(&rk))?;
        return Ok((ty, ChannelSource::File { file, offset, encoding: Encoding::Raw, stored, endian }));
    }
    if let Some(n) = &c.nrrd {
        let nk = format!("{key}.nrrd");
        let (found, ty, source) = volume(catalog, n, &nk, Some((VolumeFormat::Nrrd, ".nrrd or .nhdr")))?;
        agree(&mut Some(dims), found, &nk)?;
        check_channel_type(name, ty, &nk)?;
        return Ok((ty, source));
    }
    let table = c.generator.clone().expect("exactly one source is present");
    let gk = format!("{key}.generator");
    // The generator's errors name the key they are about.
    let at_its_key = |e: GeneratorError| {
        let k = e.key().map_or_else(|| gk.clone(), |field| format!("{gk}.{field}"));
        KeyError::new(k, Kind::Generator(e))
    };
    let g = Generator::try_from(table).map_err(at_its_key)?;
    g.check(dims).map_err(at_its_key)?;
    check_channel_type(name, g.voxel_type(), &gk)?;
    Ok((g.voxel_type(), ChannelSource::Generated(g)))
}

fn object(o: &ObjectFile, key: &str, ds: usize, info: &DatasetInfo, straight: bool) -> Result<Object, KeyError> {
    let has = |c: &str| ChannelName::parse(c).is_some_and(|c| info.has(c));
    let colour = mappings::colour(&o.colour, &format!("{key}.colour"), has)?;
    let opacity = mappings::opacity(&o.opacity, &format!("{key}.opacity"), has)?;
    for (reads, k) in [(colour.reads_voxel(), "colour"), (opacity.reads_voxel(), "opacity")] {
        if reads && !info.has(ChannelName::Voxel) {
            return err(format!("{key}.{k}"), Kind::MapNeedsVoxel { dataset: info.name().to_string() });
        }
    }
    let interpolation = match &o.interpolation {
        Some(v) => mappings::interpolation(v, &format!("{key}.interpolation"))?,
        None => crate::interp::Interpolation::Trilinear,
    };
    let sampling_distance = o.sampling_distance.unwrap_or(0.0);
    if !(sampling_distance.is_finite() && sampling_distance >= 0.0) {
        return err(format!("{key}.sampling_distance"), Kind::SamplingDistance { got: sampling_distance });
    }
    let extent = extent(o, key)?;
    let shape = shape(o.transform.as_ref(), &format!("{key}.transform"), straight)?;
    let placement = Placement::new(shape, extent, info.dims());
    placement
        .check_inversion_precision()
        .map_err(|e| KeyError::new(format!("{key}.transform.corners"), Kind::Inversion(e)))?;
    // Refuse sampling so fine that one ray would take millions of samples per object.
    let diagonal = world_diagonal(&placement);
    if sampling_distance > 0.0 && diagonal / sampling_distance > MAX_SAMPLES_PER_PIECE {
        let samples = diagonal / sampling_distance;
        return err(
            format!("{key}.sampling_distance"),
            Kind::TooManySamplesPerRay { distance: sampling_distance, diagonal, samples },
        );
    }
    let shading = o.shading.as_ref().map(|s| shading(s, &format!("{key}.shading"))).transpose()?;
    Ok(Object {
        name: o.name.clone(),
        dataset: ds,
        colour,
        opacity,
        interpolation,
        sampling_distance,
        placement,
        shading,
        lights: None,
        shadow_maps: None,
    })
}

fn extent(o: &ObjectFile, key: &str) -> Result<Extent, KeyError> {
    let Some(e) = &o.extent else { return Ok(Extent::FULL) };
    let min = DVec3::from(e.min.unwrap_or([0.0; 3]));
    let max = DVec3::from(e.max.unwrap_or([1.0; 3]));
    for axis in 0..3 {
        if !(min[axis] >= 0.0 && min[axis] < max[axis] && max[axis] <= 1.0) {
            return err(format!("{key}.extent"), Kind::Extent { min: min.to_array(), max: max.to_array(), axis });
        }
    }
    Ok(Extent { min, max })
}

fn shape(t: Option<&TransformFile>, key: &str, straight: bool) -> Result<Shape, KeyError> {
    let Some(t) = t else {
        return Ok(Shape::Affine { world_from_box: DMat4::IDENTITY, box_from_world: DMat4::IDENTITY });
    };
    match (&t.matrix, &t.corners) {
        (Some(m), None) => affine(m, &format!("{key}.matrix")),
        (None, Some(c)) => {
            let k = format!("{key}.corners");
            if c.len() != 8 || c.iter().any(|p| p.len() != 3) {
                return err(k, Kind::CornerCount);
            }
            let corners: [DVec3; 8] = std::array::from_fn(|i| DVec3::new(c[i][0], c[i][1], c[i][2]));
            let hex = Hexahedron::new(corners).map_err(|e| KeyError::new(&k, Kind::Hexahedron(e)))?;
            match hex.as_affine() {
                Some(m) => affine_from(m, &k),
                None => Ok(Shape::Distorted { hex: Box::new(hex), straight }),
            }
        }
        _ => err(key, Kind::TransformSources),
    }
}

fn affine(rows: &[Vec<f64>], key: &str) -> Result<Shape, KeyError> {
    if rows.len() != 4 || rows.iter().any(|r| r.len() != 4) {
        return err(key, Kind::MatrixShape);
    }
    if rows[3] != [0.0, 0.0, 0.0, 1.0] {
        return err(key, Kind::NotAffine { last_row: rows[3].clone() });
    }
    let col = |j: usize| DVec4::new(rows[0][j], rows[1][j], rows[2][j], rows[3][j]);
    affine_from(DMat4::from_cols(col(0), col(1), col(2), col(3)), key)
}

fn affine_from(m: DMat4, key: &str) -> Result<Shape, KeyError> {
    if !m.is_finite() {
        return err(key, Kind::MatrixNotFinite);
    }
    let lin = DMat3::from_mat4(m);
    let scale = lin.x_axis.length() * lin.y_axis.length() * lin.z_axis.length();
    if scale == 0.0 || lin.determinant().abs() <= 1e-12 * scale {
        return err(key, Kind::SingularMatrix);
    }
    Ok(Shape::Affine { world_from_box: m, box_from_world: m.inverse() })
}
