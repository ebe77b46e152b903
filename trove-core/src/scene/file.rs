//! The scene file's shape, as serde sees it. Unknown keys are refused everywhere; values
//! whose shape depends on a `type` key (mappings, interpolation) stay TOML values here and
//! are checked by hand in `mappings`, where each error can name its exact key.

use std::collections::BTreeMap;

use serde::Deserialize;

use crate::dataset::generator::GeneratorTable;

#[derive(Deserialize, Debug)]
#[serde(deny_unknown_fields)]
pub(super) struct SceneFile {
    pub image: ImageFile,
    pub camera: CameraFile,
    #[serde(default)]
    pub render: RenderFile,
    #[serde(default)]
    pub datasets: Vec<DatasetFile>,
    #[serde(default)]
    pub objects: Vec<ObjectFile>,
    /// SPEC §6: the scene's lights (none: nothing is lit).
    #[serde(default)]
    pub lights: Vec<LightFile>,
}

/// `[[lights]]` (SPEC §6); which keys a type takes is checked in `load`.
#[derive(Deserialize, Debug)]
#[serde(deny_unknown_fields)]
pub(super) struct LightFile {
    #[serde(rename = "type")]
    pub ty: String,
    pub direction: Option<[f64; 3]>,
    pub position: Option<[f64; 3]>,
    pub colour: Option<[f64; 3]>,
    pub intensity: Option<f64>,
    pub shadows: Option<bool>,
}

/// An object's `shading = { ... }` (SPEC §6): every coefficient optional.
#[derive(Deserialize, Debug)]
#[serde(deny_unknown_fields)]
pub(super) struct ShadingFile {
    pub ambient: Option<f64>,
    pub diffuse: Option<f64>,
    pub specular: Option<f64>,
    pub shininess: Option<f64>,
}

#[derive(Deserialize, Debug)]
#[serde(deny_unknown_fields)]
pub(super) struct ImageFile {
    pub width: i64,
    pub height: i64,
    pub background: [f64; 3],
}

#[derive(Deserialize, Debug)]
#[serde(deny_unknown_fields)]
pub(super) struct CameraFile {
    pub eye: [f64; 3],
    pub target: [f64; 3],
    pub up: [f64; 3],
    pub fov_y: f64,
}

#[derive(Deserialize, Debug)]
#[serde(deny_unknown_fields, default)]
pub(super) struct RenderFile {
    pub termination: f64,
    pub opacity_correction: bool,
    /// Extension: `exact` (default) or `straight` (the paper's fast approximation).
    pub distorted_sampling: String,
}

impl Default for RenderFile {
    fn default() -> Self {
        RenderFile { termination: 0.999, opacity_correction: true, distorted_sampling: "exact".into() }
    }
}

#[derive(Deserialize, Debug)]
#[serde(deny_unknown_fields)]
pub(super) struct DatasetFile {
    pub name: String,
    pub file: Option<String>,
    pub image: Option<String>,
    pub dims: Option<[i64; 3]>,
    #[serde(default)]
    pub channels: BTreeMap<String, ChannelFile>,
}

#[derive(Deserialize, Debug)]
#[serde(deny_unknown_fields)]
pub(super) struct ChannelFile {
    pub raw: Option<String>,
    pub nrrd: Option<String>,
    pub generator: Option<GeneratorTable>,
    #[serde(rename = "type")]
    pub ty: Option<String>,
    pub endian: Option<String>,
    /// Extension: bytes to skip at the start of a raw file.
    pub offset: Option<u64>,
}

#[derive(Deserialize, Debug)]
#[serde(deny_unknown_fields)]
pub(super) struct ObjectFile {
    pub name: String,
    pub dataset: String,
    pub colour: toml::Value,
    pub opacity: toml::Value,
    pub interpolation: Option<toml::Value>,
    pub sampling_distance: Option<f64>,
    pub transform: Option<TransformFile>,
    pub extent: Option<ExtentFile>,
    pub shading: Option<ShadingFile>,
}

#[derive(Deserialize, Debug)]
#[serde(deny_unknown_fields)]
pub(super) struct TransformFile {
    pub matrix: Option<Vec<Vec<f64>>>,
    pub corners: Option<Vec<Vec<f64>>>,
}

#[derive(Deserialize, Debug)]
#[serde(deny_unknown_fields)]
pub(super) struct ExtentFile {
    pub min: Option<[f64; 3]>,
    pub max: Option<[f64; 3]>,
}
