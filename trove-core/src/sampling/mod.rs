//! Casting one object over one piece of one ray (paper `VolumeRayCasting()`, SPEC
//! §4.2–4.4). This is the only sampler: the per-ray and grouped algorithms (and a farm
//! worker) all call [`ObjectCaster::cast`], and differ only in when and where they do.
//!
//! Binding an object ([`ObjectCaster::new`]) chooses the loop compiled for its combination
//! of interpolation, stored channel type, colour map and opacity map (`bind`, `kernel`), and
//! its empty-space classification (`skip`): macrocells of its dataset whose values its
//! opacity map sends to 0 are passed over without interpolating. Neither changes a single
//! sample's value or position, so images are the same bit for bit as the general loop
//! without skipping, which stays available ([`CastOptions`]) and is what tests compare with.
//!
//! # Which file does what
//!
//! * `bind.rs` picks, once per object, the loop compiled for its interpolation × stored
//!   type × colour and opacity maps.
//! * `kernel.rs` is that generic loop. Along a straight line it locates, interpolates and
//!   maps four samples at a time and composites them one by one (each waits for the
//!   opacity in front of it).
//! * `lanes.rs` does a group's work in AVX2 registers (two registers of four f64 lanes) for
//!   the commonest combination: trilinear over u8 or u16 voxels with LUT or ramp maps that
//!   merge into a small joint map. It runs the generic loop's operations in its order, so
//!   it changes no sample.
//! * `packet.rs` casts a batch's straight pieces of such an object (and of one over f32
//!   voxels whose range of values is known and within 10³⁰) many at a time, one per
//!   f32 lane, two registers side by side, pipelined one sample ahead
//!   ([`ObjectCaster::cast_many`], what `BatchCaster` calls): across rays there is no
//!   compositing chain to wait on. `packed.rs` holds the f32 forms of the object's grid and
//!   map and the steps over them (cells, index, trilinear value, segment, classification,
//!   opacity correction).
//!   In f32 a piece's result agrees with the f64 loops to rounding (tests hold it to 1e-5
//!   per piece, and images to 1/255, on every path), a value within rounding of a LUT bound
//!   takes its segment from its f64 value so that no sample changes class, and jumps over
//!   empty cells widen their margins by f32's rounding.
//! * `simd.rs` is what `packet.rs` and `packed.rs` are written in, once: a [`simd`] trait
//!   of lane operations with one implementation per instruction set (`simd/avx512.rs`:
//!   sixteen lanes, `simd/avx2.rs`: eight, with FMA, `simd/neon.rs`: four,
//!   `simd/scalar.rs`: four in plain arrays), each entry point compiled with its
//!   instruction set's `#[target_feature]` so that the intrinsics inline into one loop per
//!   set. [`SimdPath`] names them: the widest the processor has runs unless `TROVE_SIMD`
//!   names another, and a path the processor lacks is refused ([`BindError::Simd`]), never
//!   quietly replaced; [`ObjectCaster::on_path`] forces one in-process (tests and benchmarks
//!   run every path the machine has), and `--stats` reports the path (`simd`).
//! * `shade.rs` is the axis of effects (SPEC §6): each loop is compiled for `NoShade`, the
//!   unlit loop as it was before effects existed, or for `Shaded`, which lights each sample
//!   that contributes with Blinn–Phong from the gradient of the object's own interpolation
//!   (central differences, taken to world space by the inverse transpose of the box's
//!   Jacobian at the sample). Whether an object is lit is decided at bind; no loop tests it
//!   per sample. One lit piece at a time is cast in f64: straight pieces by the generic
//!   line loop (groups of four, jumps over empty space), which shades each contributing
//!   sample before compositing it, exact distorted walks sample by sample. Many lit pieces
//!   at a time take the f32 packet loop compiled lit (a constant parameter of the loop, so
//!   the unlit one is unchanged), where the object is one it casts and its box is affine:
//!   the gradient from the neighbours of the sample's cell (six trilinear values near the
//!   grid's faces), Blinn–Phong in lanes (`shade.rs`'s `LaneShading`), within 1e-5 per
//!   piece of the f64 lit loop on every path. Only the lanes that use them read voxels
//!   (`Simd::gather_in`): a lane leaping over empty cells or idle gathers no corners, a
//!   lane whose sample is clear no gradient. The AVX2 f64 lanes serve unlit objects only.
//! * `skip.rs` jumps over empty macrocells: walking cells, or, where cells were classified
//!   at bind, leaping out of a cube of empty ones by each cell's distance to the nearest
//!   non-empty cell; its margins keep every jump from passing a sample that is not empty.
//!
//! On the AVX2 and AVX-512 paths single pieces ([`ObjectCaster::cast`]) go through
//! `lanes.rs`; on the scalar and NEON paths, and for other combinations, through the
//! generic loop. The packet loop runs on every path. The NEON implementation has passed
//! the sampler's tests under emulation (`qemu-aarch64`, BENCHMARKS.md) but has never run on
//! ARM hardware: its speed there is unmeasured.

mod bind;
mod kernel;
mod lanes;
mod packed;
mod packet;
mod shade;
pub mod simd;
mod skip;

use std::sync::Arc;

pub use shade::SHADOW_STOP;
pub use simd::{SimdError, SimdPath};
pub(crate) use skip::{ClassKey, Classes};

use crate::composite::Rgba;
use crate::dataset::{ChannelName, Volume, VoxelType};
use crate::geometry::Ray;
use crate::mapping::{ColourMap, OpacityMap};
use crate::scene::Object;

/// Why an object cannot be bound to a volume: the volume is not the object's dataset (a
/// worker handed the wrong dataset, or a stale one). The scene validator guarantees that an
/// object's own dataset has every channel its maps read, so a scene renderer never sees this;
/// a farm worker fed a bad message does, and answers with an error instead of panicking.
#[derive(Debug, thiserror::Error, Clone, PartialEq, Eq)]
pub enum BindError {
    /// A channel the object's maps read is missing from the volume.
    #[error("the volume has no `{channel}` channel, which the object's maps read")]
    MissingChannel {
        /// The missing channel.
        channel: ChannelName,
    },
    /// The volume's dims differ from the dims the object was placed with.
    #[error("the volume's dims {found} differ from the dims {expected} the object was placed with")]
    DimsMismatch {
        /// Dims the placement assumes.
        expected: crate::dataset::Dims,
        /// Dims of the volume handed in.
        found: crate::dataset::Dims,
    },
    /// The SIMD path asked for (`TROVE_SIMD`, or [`ObjectCaster::on_path`]) is unknown or
    /// not one this processor has.
    #[error(transparent)]
    Simd(#[from] SimdError),
    /// The object is lit by a light that casts shadows, and the transmittance through the
    /// other objects was not computed first (`render::shadow`, [`Scene::with_shadow_maps`]):
    /// refused rather than rendered without shadows.
    ///
    /// [`Scene::with_shadow_maps`]: crate::scene::Scene::with_shadow_maps
    #[error("object `{object}` is lit by a light that casts shadows, and its shadow maps were not computed")]
    ShadowMapsMissing {
        /// The object's name.
        object: String,
    },
}

/// What one object contributed over one piece.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PieceResult {
    /// Accumulated colour and opacity of this object's samples over the piece.
    pub rgba: Rgba,
    /// Samples evaluated (interpolated and mapped).
    pub samples: u64,
    /// Of those, the samples shaded (SPEC §6: lit, a gradient computed): 0 for an unlit
    /// object.
    pub shaded: u64,
}

/// One piece for [`ObjectCaster::cast_many`]: the arguments of [`ObjectCaster::cast`].
#[derive(Clone, Copy, Debug)]
pub struct PieceRequest {
    /// The ray the piece lies on.
    pub ray: Ray,
    /// Where the piece starts and ends along the ray.
    pub t0: f64,
    pub t1: f64,
    /// The opacity in front of the piece.
    pub alpha_in: f64,
    /// The opacity at which the cast may stop.
    pub stop_at: f64,
}

/// How an object's loop is chosen. The defaults are what renderers use; the others exist so
/// that tests (and benchmarks) can check the specialised loops and empty-space skipping
/// against the general loop without skipping, which must render the same image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CastOptions {
    /// Use the loop compiled for the object's combination when there is one.
    pub specialise: bool,
    /// Jump over macrocells where the object's opacity map is zero.
    pub skip_empty_space: bool,
    /// Classify every macrocell when binding ([`ObjectCaster::for_many_pieces`]) instead of
    /// each when a ray first enters it.
    pub classify_upfront: bool,
}

impl Default for CastOptions {
    fn default() -> CastOptions {
        CastOptions { specialise: true, skip_empty_space: true, classify_upfront: false }
    }
}

/// Where classifications worked out at bind are kept for later binds of objects over the
/// same loaded dataset (a [`crate::render::VolumeStore`]'s resident dataset, through its
/// [`crate::render::Pinned`] guard): a caster that finds its object's classification there
/// uses it instead of classifying again, and gets the same classes and distances.
pub(crate) trait ClassificationCache {
    /// The classification kept under `key`, if any (counted as a hit or a miss).
    fn find(&self, key: &ClassKey) -> Option<Arc<Classes>>;
    /// Whether a classification of `bytes` would be kept now.
    fn has_room(&self, bytes: u64) -> bool;
    /// Offers `classes`, worked out for `key`, for keeping; the cache may decline.
    fn keep(&self, key: ClassKey, classes: &Arc<Classes>);
}

/// An object bound to its resident volume: the loop for its combination of interpolation,
/// stored type and maps chosen once, the channel readers its maps need resolved once (a map
/// that does not read a channel never touches it), and its empty-space classification
/// prepared. It is `Sync`: one caster serves every thread casting that object.
pub struct ObjectCaster<'a> {
    object: &'a Object,
    /// The opacity map is the constant 0: nothing to cast.
    transparent: bool,
    kernel: Box<dyn kernel::Cast + 'a>,
    /// Its loop shades ([`ObjectCaster::is_shaded`]).
    shaded: bool,
}

impl<'a> ObjectCaster<'a> {
    /// Binds `object` to `volume`, its dataset's voxels; refuses a volume that lacks a
    /// channel the object's maps read or has other dims than the object was placed with.
    pub fn new(
        object: &'a Object,
        volume: &'a Volume,
        opacity_correction: bool,
    ) -> Result<ObjectCaster<'a>, BindError> {
        ObjectCaster::with_options(object, volume, opacity_correction, CastOptions::default())
    }

    /// [`ObjectCaster::new`] for a caster that will cast many pieces (a dataset's turn in
    /// Algorithm 2, a farm batch): it also classifies every macrocell of the dataset for the
    /// object now, a few milliseconds for a 256³ dataset, so that casting tests one bit per
    /// cell. Algorithm 1, which binds per piece, uses [`ObjectCaster::new`].
    pub fn for_many_pieces(
        object: &'a Object,
        volume: &'a Volume,
        opacity_correction: bool,
    ) -> Result<ObjectCaster<'a>, BindError> {
        let options = CastOptions { classify_upfront: true, ..CastOptions::default() };
        ObjectCaster::with_options(object, volume, opacity_correction, options)
    }

    /// [`ObjectCaster::new`] with the loop chosen by `options`.
    pub fn with_options(
        object: &'a Object,
        volume: &'a Volume,
        opacity_correction: bool,
        options: CastOptions,
    ) -> Result<ObjectCaster<'a>, BindError> {
        ObjectCaster::bind(object, volume, opacity_correction, options, None, SimdPath::configured()?)
    }

    /// [`ObjectCaster::with_options`] with the vector loops in `path` instead of the
    /// configured one ([`SimdPath::configured`]); refused where the processor lacks it.
    /// What tests and benchmarks use to run every path in one process.
    pub fn on_path(
        object: &'a Object,
        volume: &'a Volume,
        opacity_correction: bool,
        options: CastOptions,
        path: SimdPath,
    ) -> Result<ObjectCaster<'a>, BindError> {
        ObjectCaster::bind(object, volume, opacity_correction, options, None, path.checked()?)
    }

    /// [`ObjectCaster::with_options`] for a volume whose classifications `cache` keeps: the
    /// kept classification is used when there is one; otherwise the cells are classified
    /// now, and kept, if `options` asks for it or the cache has room to keep them.
    pub(crate) fn with_cache(
        object: &'a Object,
        volume: &'a Volume,
        opacity_correction: bool,
        options: CastOptions,
        cache: &'a dyn ClassificationCache,
    ) -> Result<ObjectCaster<'a>, BindError> {
        ObjectCaster::bind(object, volume, opacity_correction, options, Some(cache), SimdPath::configured()?)
    }

    /// `object` bound for shadow rays (SPEC §6): unlit whatever its lighting (a shadow ray
    /// reads opacity only), every macrocell classified now or found in `cache`.
    pub(crate) fn opacity_only(
        object: &'a Object,
        volume: &'a Volume,
        opacity_correction: bool,
        cache: Option<&'a dyn ClassificationCache>,
    ) -> Result<ObjectCaster<'a>, BindError> {
        let options = CastOptions { classify_upfront: true, ..CastOptions::default() };
        ObjectCaster::bind_lit(object, volume, opacity_correction, options, cache, SimdPath::configured()?, false)
    }

    /// Binds with the vector loops in `path`, which the processor has.
    fn bind(
        object: &'a Object,
        volume: &'a Volume,
        opacity_correction: bool,
        options: CastOptions,
        cache: Option<&'a dyn ClassificationCache>,
        path: SimdPath,
    ) -> Result<ObjectCaster<'a>, BindError> {
        ObjectCaster::bind_lit(object, volume, opacity_correction, options, cache, path, true)
    }

    /// [`ObjectCaster::bind`], unlit whatever the object's lighting when `lit` is false (the
    /// object's own share of its shadows: opacity only).
    fn bind_lit(
        object: &'a Object,
        volume: &'a Volume,
        opacity_correction: bool,
        options: CastOptions,
        cache: Option<&'a dyn ClassificationCache>,
        path: SimdPath,
        lit: bool,
    ) -> Result<ObjectCaster<'a>, BindError> {
        let expected = object.placement().dims();
        if volume.dims() != expected {
            return Err(BindError::DimsMismatch { expected, found: volume.dims() });
        }
        let reader = |channel: ChannelName| {
            volume.channel(channel).map(|ch| ch.reader()).ok_or(BindError::MissingChannel { channel })
        };
        let needs_voxel = object.colour().reads_voxel() || object.opacity().reads_voxel();
        let raw_rgb = match object.colour() {
            ColourMap::Raw(kind) => {
                let [r, g, b] = kind.channels();
                Some((*kind, [reader(r)?, reader(g)?, reader(b)?]))
            }
            _ => None,
        };
        // SPEC §6: the gradient is taken over the channel the opacity map reads; a constant
        // opacity borrows `voxel` from the colour map, and with neither the object is unlit.
        let lighting = match (object.lighting(), gradient_channel(object)) {
            (Some((material, lights)), Some(channel)) if lit => Some(bind::Lighting {
                material: *material,
                lights,
                to_world: object.placement().gradient_to_world(),
                field: match channel {
                    ChannelName::Alpha => bind::GradientField::Alpha(reader(ChannelName::Alpha)?),
                    _ => bind::GradientField::Voxel,
                },
                shadows: if object.needs_shadow_maps() {
                    let Some(maps) = object.shadow_maps() else {
                        return Err(BindError::ShadowMapsMissing { object: object.name().to_string() });
                    };
                    let own = ObjectCaster::bind_lit(object, volume, opacity_correction, options, cache, path, false)?;
                    let per_light = lights.iter().zip(maps).map(|(l, m)| l.shadows().then(|| m.clone())).collect();
                    Some(Arc::new(shade::Shadows { own, placement: object.placement(), per_light }))
                } else {
                    None
                },
            }),
            _ => None,
        };
        let shaded = lighting.is_some();
        let parts = bind::Parts {
            object,
            dims: volume.dims(),
            voxel: if needs_voxel { Some(reader(ChannelName::Voxel)?) } else { None },
            voxel_cells: volume.macrocells(ChannelName::Voxel),
            raw_rgb,
            alpha: if matches!(object.opacity(), OpacityMap::Raw) { Some(reader(ChannelName::Alpha)?) } else { None },
            correction: opacity_correction,
            classify_upfront: options.classify_upfront,
            cache,
            path,
            lighting,
        };
        let skip = if options.skip_empty_space { skipper(object, volume) } else { None };
        let kernel = if options.specialise {
            parts.specialised(skip).unwrap_or_else(|skip| parts.general(skip))
        } else {
            parts.general(skip)
        };
        Ok(ObjectCaster { object, transparent: object.opacity().constant() == Some(0.0), kernel, shaded })
    }

    /// Whether the object's samples are shaded (SPEC §6): it has `shading`, the scene has
    /// lights, and its opacity (or colour) map reads a channel to take normals from.
    pub fn is_shaded(&self) -> bool {
        self.shaded
    }

    /// Whether the object's combination has a specialised loop and it was chosen.
    pub fn is_specialised(&self) -> bool {
        self.kernel.is_specialised()
    }

    /// Whether straight lines are cast eight samples at a time in AVX2 registers (trilinear
    /// over u8 or u16 with LUT or ramp maps, on the AVX2 and AVX-512 paths).
    pub fn uses_avx2(&self) -> bool {
        self.kernel.uses_avx2()
    }

    /// Whether [`ObjectCaster::cast_many`] casts straight pieces many at a time in f32 lanes
    /// (trilinear over u8 or u16 with a small LUT or ramp map whose numbers fit f32; over f32
    /// too where its channel's range is known and within 10³⁰).
    pub fn casts_packets(&self) -> bool {
        self.kernel.packet_path().is_some()
    }

    /// The instruction set [`ObjectCaster::cast_many`] casts in, where it casts packets.
    pub fn packet_path(&self) -> Option<SimdPath> {
        self.kernel.packet_path()
    }

    /// Whether the cast jumps over empty macrocells (off when the opacity map is zero
    /// nowhere, or reads no channel).
    pub fn skips_empty_space(&self) -> bool {
        self.kernel.skips()
    }

    /// Composites this object's samples over [t0, t1] front to back. The ray arrives with
    /// opacity `alpha_in`; once `alpha_in + (1 − alpha_in)·A` reaches `stop_at` the cast
    /// stops (pass `f64::INFINITY` to sample the whole piece, as pieces shared by several
    /// objects must, SPEC §4.5), and a ray that arrives with `alpha_in ≥ stop_at` casts
    /// nothing. `samples` counts the samples interpolated and mapped: those skipped as
    /// empty space are not.
    pub fn cast(&self, ray: &Ray, t0: f64, t1: f64, alpha_in: f64, stop_at: f64) -> PieceResult {
        if self.transparent || alpha_in >= stop_at {
            return PieceResult::default();
        }
        let walk = self.object.placement().walk(ray, t0, t1, self.object.sampling_distance());
        self.kernel.cast(walk, alpha_in, stop_at)
    }

    /// [`ObjectCaster::cast`] for each of `pieces`, result `i` into `out[i]`, computed
    /// several pieces at a time where the object's loop can (straight pieces in f32 lanes,
    /// sixteen to a register on AVX-512, [`ObjectCaster::casts_packets`], whose results
    /// differ from `cast`'s by rounding).
    ///
    /// # Panics
    /// If `out` is shorter than `pieces`.
    pub fn cast_many(&self, pieces: &[PieceRequest], out: &mut [PieceResult]) {
        assert!(out.len() >= pieces.len(), "{} results for {} pieces", out.len(), pieces.len());
        // Pieces with nothing to cast first; the rest are walked as the kernel takes them,
        // not gathered into a list of their own.
        let skipped = |p: &PieceRequest| self.transparent || p.alpha_in >= p.stop_at;
        for (slot, p) in pieces.iter().enumerate() {
            if skipped(p) {
                out[slot] = PieceResult::default();
            }
        }
        let (placement, sampling_distance) = (self.object.placement(), self.object.sampling_distance());
        let mut walks = pieces
            .iter()
            .enumerate()
            .filter(|(_, p)| !skipped(p))
            .map(|(slot, p)| (slot, placement.walk(&p.ray, p.t0, p.t1, sampling_distance), p.alpha_in, p.stop_at));
        self.kernel.cast_many(&mut walks, out);
    }
}

/// The channel a shaded object's normals come from (SPEC §6): the one its opacity map reads
/// (`alpha` for a raw opacity, else `voxel`); for a constant opacity `voxel` if the colour
/// map reads it; else none, and the object is unlit.
fn gradient_channel(object: &Object) -> Option<ChannelName> {
    match object.opacity() {
        OpacityMap::Raw => Some(ChannelName::Alpha),
        o if o.reads_voxel() || object.colour().reads_voxel() => Some(ChannelName::Voxel),
        _ => None,
    }
}

/// Whether `object`'s samples are shaded when it is cast: it has `shading`, its scene has
/// lights, and it has a channel to take normals from ([`ObjectCaster::is_shaded`] once bound).
pub fn shades(object: &Object) -> bool {
    object.lighting().is_some() && gradient_channel(object).is_some()
}

/// The object's empty-space classification over `volume`, if its opacity map reads a
/// channel with macrocell ranges and is zero somewhere.
fn skipper<'a>(object: &'a Object, volume: &'a Volume) -> Option<skip::Skipper<'a>> {
    let channel = match object.opacity() {
        OpacityMap::Raw => ChannelName::Alpha,
        map if map.reads_voxel() => ChannelName::Voxel,
        _ => return None,
    };
    let cells = volume.macrocells(channel)?;
    let integer = volume.channel(channel)?.ty() != VoxelType::F32;
    skip::Skipper::new(cells, channel, object.opacity().zero_set(), integer)
}

/// α = 1 − (1 − O)^ℓ (SPEC §4.3), computed as −expm1(ℓ·ln(1 − O)) so small opacities and
/// short steps keep their precision; O = 1 gives 1 and ℓ = 0 gives 0 without 0·∞.
#[inline]
pub fn corrected_opacity(opacity: f64, ell: f64) -> f64 {
    if opacity <= 0.0 || ell <= 0.0 {
        0.0
    } else if opacity >= 1.0 {
        1.0
    } else {
        -(ell * (-opacity).ln_1p()).exp_m1()
    }
}

#[cfg(test)]
mod simd_tests;
#[cfg(test)]
mod tests;
