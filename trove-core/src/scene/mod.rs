//! The scene: a TOML file (SPEC §1) turned into a validated model.
//!
//! Loading happens in two steps. [`file`] deserialises the TOML into plain structs that
//! mirror the format, refusing unknown keys and wrong types with the key's path. `load`
//! then checks everything a user can get wrong and builds the model below, in which every
//! invariant holds: a [`Scene`] is never half-valid, so renderers do not re-check.

mod data_root;
mod effects;
mod error;
mod file;
mod limits;
mod load;
mod mappings;
#[cfg(test)]
mod tests;
pub mod transmittance;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::dataset::{Catalog, DatasetInfo};
use crate::geometry::{Camera, Placement};
use crate::interp::Interpolation;
use crate::mapping::{ColourMap, OpacityMap};

pub use data_root::{DataRoot, DATA_ROOT_ENV};
pub use effects::{Light, LightError, LightSource, Shading, ShadingField, UnitVector};
pub use error::{SceneError, SceneErrorKind};
pub use limits::{MAX_IMAGE_SIDE, MAX_LIGHTS, MAX_OBJECTS, MAX_SAMPLES_PER_PIECE, MAX_SAMPLES_PER_RENDER};
pub use transmittance::{Transmittance, TransmittanceError};

/// `[image]`: the output raster.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageSettings {
    /// Pixels across.
    pub width: u32,
    /// Pixels down.
    pub height: u32,
    /// Linear RGB in [0, 1], shown where rays are not fully opaque.
    pub background: [f64; 3],
}

/// `[render]`: scene-wide rendering settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderSettings {
    /// A ray stops once its accumulated opacity reaches this; 1.0 never stops early.
    pub termination: f64,
    /// Whether sample opacity is corrected for the step length (SPEC §4.3).
    pub opacity_correction: bool,
}

/// One volumetric object ⟨V, 𝒞, 𝒪, ℐ, 𝒯⟩ (paper §2.1), valid for its scene's dataset: its
/// maps read channels the dataset has, and its placement was checked (not folding,
/// invertible to the SPEC's precision, a bounded number of samples per ray). Built only by
/// the scene loader, hence the private fields.
#[derive(Clone, Debug)]
pub struct Object {
    name: String,
    dataset: usize,
    colour: ColourMap,
    opacity: OpacityMap,
    interpolation: Interpolation,
    sampling_distance: f64,
    placement: Placement,
    /// Its Blinn–Phong material, when the scene asks for one (SPEC §6).
    shading: Option<Shading>,
    /// The scene's lights, when it has some and this object is shaded.
    lights: Option<Arc<[Light]>>,
    /// Per light, the transmittance through the other objects on a lattice over this one's
    /// box (`None` for a light without shadows, or where nothing else comes between);
    /// attached by [`Scene::with_shadow_maps`] once computed.
    shadow_maps: Option<Arc<[Option<Transmittance>]>>,
}

/// Objects built without a scene, for unit tests of the sampler, which construct the maps and
/// placements a scene file would (the loader alone builds objects outside tests).
#[cfg(test)]
impl Object {
    pub(crate) fn for_tests(
        colour: ColourMap,
        opacity: OpacityMap,
        interpolation: Interpolation,
        sampling_distance: f64,
        placement: Placement,
    ) -> Object {
        Object {
            name: "o".into(),
            dataset: 0,
            colour,
            opacity,
            interpolation,
            sampling_distance,
            placement,
            shading: None,
            lights: None,
            shadow_maps: None,
        }
    }

    /// `self` shaded with `material` under `lights` (SPEC §6).
    pub(crate) fn lit_for_tests(self, material: Shading, lights: &[Light]) -> Object {
        Object { shading: Some(material), lights: Some(lights.into()), ..self }
    }
}

impl Object {
    /// Unique name in the scene.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Index into [`Scene::datasets`].
    pub fn dataset(&self) -> usize {
        self.dataset
    }

    /// Colour mapping.
    pub fn colour(&self) -> &ColourMap {
        &self.colour
    }

    /// Opacity mapping.
    pub fn opacity(&self) -> &OpacityMap {
        &self.opacity
    }

    /// Interpolation function.
    pub fn interpolation(&self) -> Interpolation {
        self.interpolation
    }

    /// World distance between samples; 0 means one voxel (paper §3.2.2).
    pub fn sampling_distance(&self) -> f64 {
        self.sampling_distance
    }

    /// Box, extent and the world → VC map.
    pub fn placement(&self) -> &Placement {
        &self.placement
    }

    /// Its Blinn–Phong material (`shading = { ... }`), if the scene gives one. Whether it is
    /// shaded also depends on the scene having lights: [`Object::lighting`].
    pub fn shading(&self) -> Option<&Shading> {
        self.shading.as_ref()
    }

    /// Its material and the scene's lights, when it is shaded: it has `shading` and the
    /// scene has lights. A scene without lights renders as SPEC §4 says (§6: effects are
    /// opt-in), so its objects are unlit whatever their `shading` says.
    pub fn lighting(&self) -> Option<(&Shading, &[Light])> {
        Some((self.shading.as_ref()?, self.lights.as_deref()?))
    }

    /// Whether it is lit by a light that casts shadows: then its casts need the transmittance
    /// through the other objects ([`Object::shadow_maps`]).
    pub fn needs_shadow_maps(&self) -> bool {
        self.lighting().is_some_and(|(_, lights)| lights.iter().any(Light::shadows))
    }

    /// Per light, the transmittance through the other objects (SPEC §6's S without this
    /// object's own share), once [`Scene::with_shadow_maps`] attached it.
    pub fn shadow_maps(&self) -> Option<&[Option<Transmittance>]> {
        self.shadow_maps.as_deref()
    }

    /// The most a sample's colour channel can be, mapped colours being at most 1: 1 unlit;
    /// lit, SPEC §6's c' ≤ ambient + Σ (diffuse + specular)·E per channel, which can exceed
    /// 1 (c' is not clamped before the final image). A piece's premultiplied colour is at
    /// most this times its opacity, which is how a scheduler checks a result it is handed.
    pub fn colour_gain(&self) -> f64 {
        let Some((m, lights)) = self.lighting() else { return 1.0 };
        (0..3)
            .map(|i| m.ambient() + lights.iter().map(|l| (m.diffuse() + m.specular()) * l.radiance()[i]).sum::<f64>())
            .fold(1.0, f64::max)
    }
}

/// A validated scene: every rule of SPEC §1–4.5 holds (checked once, in `load.rs` and
/// `mappings.rs`), so renderers do not re-check. The fields are private so that it stays
/// so; the few changes a caller may make ([`Scene::with_image_size`],
/// [`Scene::set_straight_distorted_sampling`]) keep it valid.
#[derive(Clone, Debug)]
pub struct Scene {
    path: PathBuf,
    image: ImageSettings,
    camera: Camera,
    render: RenderSettings,
    datasets: Vec<DatasetInfo>,
    objects: Vec<Object>,
    /// `[[lights]]` (SPEC §6).
    lights: Vec<Light>,
}

impl Scene {
    /// Reads and validates a scene file, opening every dataset's headers so that size
    /// mismatches are reported before anything renders. Dataset keys are paths relative to
    /// the scene's folder ([`DataRoot::SceneFolder`]).
    pub fn load(path: impl AsRef<Path>) -> Result<Scene, SceneError> {
        Scene::load_in(path, &DataRoot::SceneFolder)
    }

    /// [`Scene::load`] with dataset keys resolved under `root`, the folder a local render's
    /// `--data-root` / `TROVE_DATA` / scene-folder rule chose (keys are trusted paths there:
    /// `..` and absolute paths allowed, [`FsCatalog::trusting`]). A key whose file does not
    /// exist is [`SceneErrorKind::DataNotFound`], naming the key, the path looked for and the
    /// root.
    ///
    /// [`FsCatalog::trusting`]: crate::dataset::FsCatalog::trusting
    pub fn load_in(path: impl AsRef<Path>, root: &DataRoot) -> Result<Scene, SceneError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|e| SceneError {
            file: path.to_path_buf(),
            key: None,
            kind: SceneErrorKind::Read(e),
        })?;
        Scene::parse_in(&text, path, root)
    }

    /// Validates scene text as if read from `path` (relative dataset paths resolve against
    /// its folder, [`DataRoot::SceneFolder`]).
    pub fn parse(text: &str, path: impl AsRef<Path>) -> Result<Scene, SceneError> {
        Scene::parse_in(text, path, &DataRoot::SceneFolder)
    }

    /// [`Scene::parse`] with dataset keys resolved under `root` (see [`Scene::load_in`]).
    pub fn parse_in(text: &str, path: impl AsRef<Path>, root: &DataRoot) -> Result<Scene, SceneError> {
        data_root::parse_in(text, path.as_ref(), root)
    }

    /// Validates scene text, describing its dataset keys through `catalog` (a sandboxed
    /// data root, or a farm coordinator's registry); `path` names the scene in messages.
    pub fn parse_with(text: &str, path: impl AsRef<Path>, catalog: &dyn Catalog) -> Result<Scene, SceneError> {
        load::scene(text, path.as_ref(), catalog)
    }

    /// The scene file, for messages (its dataset keys were resolved under the data root,
    /// which is its folder unless one was given).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Output raster.
    pub fn image(&self) -> &ImageSettings {
        &self.image
    }

    /// The camera.
    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// Rendering settings.
    pub fn render(&self) -> &RenderSettings {
        &self.render
    }

    /// The voxel level: each dataset once.
    pub fn datasets(&self) -> &[DatasetInfo] {
        &self.datasets
    }

    /// The object level.
    pub fn objects(&self) -> &[Object] {
        &self.objects
    }

    /// The lights (SPEC §6); none in a scene that asks for no lighting.
    pub fn lights(&self) -> &[Light] {
        &self.lights
    }

    /// The same scene rendered at `width` × `height` pixels (tests and benchmarks shrink
    /// scenes this way). The image limits and the render's sample budget are checked again,
    /// with the keys they concern (`image.width`, `objects[i].sampling_distance`).
    pub fn with_image_size(mut self, width: u32, height: u32) -> Result<Scene, SceneError> {
        let fail = |e: mappings::KeyError| SceneError { file: self.path.clone(), key: Some(e.key), kind: e.kind };
        let width = load::image_side(width.into(), "image.width").map_err(fail)?;
        let height = load::image_side(height.into(), "image.height").map_err(fail)?;
        let image = ImageSettings { width, height, ..self.image };
        load::render_budget(&image, &self.camera, &self.objects, &self.datasets).map_err(fail)?;
        self.image = image;
        Ok(self)
    }

    /// Switches every distorted box between exact inversion and the paper's straight-line
    /// approximation (`[render] distorted_sampling`), e.g. to compare the two on one scene.
    pub fn set_straight_distorted_sampling(&mut self, straight: bool) {
        for o in &mut self.objects {
            o.placement.set_straight(straight);
        }
    }

    /// Whether some light casts shadows onto some lit object (SPEC §6): the scene's objects
    /// then need [`Scene::with_shadow_maps`] before they can be cast.
    pub fn casts_shadows(&self) -> bool {
        self.objects.iter().any(Object::needs_shadow_maps)
    }

    /// The same scene with `maps[i]` (one entry per light, see [`Object::shadow_maps`])
    /// attached to object `i` where `maps[i]` is `Some`.
    ///
    /// # Panics
    /// If `maps` has not one entry per object, or an entry has not one per light.
    pub fn with_shadow_maps(&self, maps: Vec<Option<Vec<Option<Transmittance>>>>) -> Scene {
        assert_eq!(maps.len(), self.objects.len(), "one entry per object");
        let mut scene = self.clone();
        for (o, m) in scene.objects.iter_mut().zip(maps) {
            if let Some(m) = m {
                assert_eq!(m.len(), self.lights.len(), "one map per light");
                o.shadow_maps = Some(m.into());
            }
        }
        scene
    }

    /// The datasets some object uses, in order of first use.
    pub fn used_datasets(&self) -> Vec<usize> {
        let mut seen = vec![false; self.datasets.len()];
        let mut out = Vec::new();
        for o in &self.objects {
            if !std::mem::replace(&mut seen[o.dataset], true) {
                out.push(o.dataset);
            }
        }
        out
    }
}
