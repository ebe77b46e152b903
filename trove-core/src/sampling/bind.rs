//! Choosing an object's loop once, when it is bound to its volume: interpolation × stored
//! type of the `voxel` channel × colour map × opacity map.
//!
//! LUTs and ramps are one kind of map here ([`Piecewise`]), so four map combinations cover
//! every object whose maps read the `voxel` channel; they are specialised for nearest and
//! trilinear over u8, little-endian u16 and f32 channels (what scenes and benchmarks use),
//! and piecewise colour and opacity also for nonlinear and cubic. A piecewise colour map and
//! a piecewise opacity map are merged into one ([`JointPiecewise`]: one segment lookup per
//! sample instead of two, the same arithmetic). Raw colour (images) with
//! raw or constant opacity, and maps that read no channel at all, have their own loops.
//! Everything else — big-endian or u32 voxels, bit voxels, mixed raw and voxel maps —
//! takes the general loop, which is the same generic code deciding per sample.

use super::kernel::{
    Cast, ColourFn, GeneralColour, GeneralOpacity, Kernel, Maps, MaybeVoxel, NoVoxel, OpacityFn, RawAlpha, RawRgb,
    Read, Separate,
};
use std::sync::Arc;

use super::lanes::Trilinear4;
use super::packed::Stored;
use super::packet::Packets;
use super::shade::{LaneShading, NoShade, Shaded, Shadows};
use super::simd::SimdPath;
use super::skip::Skipper;
use super::ClassificationCache;
use crate::dataset::macrocell::Macrocells;
use crate::dataset::{ChannelReader, F32LeVoxels, U16LeVoxels, U8Voxels};
use crate::geometry::GradientToWorld;
use crate::interp::{Cubic, DynInterp, Identity, Interp, Interpolation, Linear, Nearest, NoInterp, Omega};
use crate::mapping::{ColourMap, JointPiecewise, OpacityMap, Piecewise, RawColour};
use crate::scene::{Light, Object, Shading};

/// A bound loop.
pub(super) type Bound<'a> = Box<dyn Cast + 'a>;

/// A specialised loop, or (when the combination has none) the skipper back for the general one.
type Choice<'a> = Result<Bound<'a>, Option<Skipper<'a>>>;

/// What every loop of one object shares.
pub(super) struct Parts<'a> {
    pub object: &'a Object,
    pub dims: crate::dataset::Dims,
    pub voxel: Option<ChannelReader<'a>>,
    /// The `voxel` channel's macrocell ranges, where the volume has them: the range of its
    /// values, which f32 voxels need for the packet loop when no empty-space
    /// classification gives it.
    pub voxel_cells: Option<&'a Macrocells>,
    pub raw_rgb: Option<(RawColour, [ChannelReader<'a>; 3])>,
    pub alpha: Option<ChannelReader<'a>>,
    pub correction: bool,
    /// Classify every macrocell now ([`Skipper::classified`]).
    pub classify_upfront: bool,
    /// Where the volume's classifications are kept, if anywhere.
    pub cache: Option<&'a dyn ClassificationCache>,
    /// The instruction set the vector loops run in (one this processor has).
    pub path: SimdPath,
    /// How the object is lit, when it is shaded (SPEC §6); `None`: the unlit loops.
    pub lighting: Option<Lighting<'a>>,
}

/// What a shaded object's loop needs besides its unlit parts.
pub(super) struct Lighting<'a> {
    pub material: Shading,
    pub lights: &'a [Light],
    pub to_world: GradientToWorld<'a>,
    /// The channel normals come from: the one the opacity map reads (`alpha` for a raw
    /// opacity, else `voxel`).
    pub field: GradientField<'a>,
    /// Where some light casts shadows: how S is found (the one-piece f64 loops only).
    pub shadows: Option<Arc<Shadows<'a>>>,
}

/// The channel a shaded object's gradient is taken over.
#[derive(Clone, Copy)]
pub(super) enum GradientField<'a> {
    /// `voxel`, which the loop's voxel source already reads.
    Voxel,
    /// `alpha` (a raw opacity map).
    Alpha(ChannelReader<'a>),
}

impl<'a> Parts<'a> {
    /// `skip` as the loop over `interp` will use it: classified up front when asked, or
    /// when a cache holds the classification or has room to keep it (a classification
    /// found kept is what classifying now would give: its key holds everything it depends
    /// on besides the volume's macrocells).
    fn prepared<I: Interp>(&self, interp: &I, skip: Option<Skipper<'a>>) -> Option<Skipper<'a>> {
        let skip = skip?;
        let Some(cache) = self.cache else {
            return Some(if self.classify_upfront { skip.classified(interp) } else { skip });
        };
        let key = skip.key(self.object.interpolation());
        if let Some(classes) = cache.find(&key) {
            return Some(skip.with_classes(classes));
        }
        if !self.classify_upfront && !cache.has_room(skip.classes_bytes()) {
            return Some(skip);
        }
        let classes = Arc::new(skip.classify(interp));
        cache.keep(key, &classes);
        Some(skip.with_classes(classes))
    }

    /// The loop over `voxels`, whose values are also the gradient's field when the object
    /// is shaded.
    fn kernel<I, V, M>(&self, interp: I, voxels: V, maps: M, skip: Option<Skipper<'a>>) -> Bound<'a>
    where
        I: Interp + 'a,
        V: super::kernel::VoxelSource + Copy + 'a,
        M: Maps + 'a,
    {
        debug_assert!(
            !matches!(self.lighting, Some(Lighting { field: GradientField::Alpha(_), .. })),
            "an alpha gradient takes the raw or general loop"
        );
        self.kernel_with_lanes(interp, voxels, maps, skip, None, None)
    }

    /// [`Parts::kernel`] with the AVX2 loop for its lines and the packet loop for many
    /// pieces, where there are (the AVX2 lines are unlit: a shaded object has none, and
    /// casts single pieces in the generic loop, many in the lit packet loop).
    fn kernel_with_lanes<I, V, M>(
        &self,
        interp: I,
        voxels: V,
        maps: M,
        skip: Option<Skipper<'a>>,
        lanes: Option<Trilinear4<'a>>,
        packets: Option<Packets<'a>>,
    ) -> Bound<'a>
    where
        I: Interp + 'a,
        V: super::kernel::VoxelSource + Copy + 'a,
        M: Maps + 'a,
    {
        self.build(interp, voxels, maps, skip, lanes, packets, voxels, true)
    }

    /// The loop, unlit or (when the object is shaded) lit with the gradient of `field`.
    #[allow(clippy::too_many_arguments)]
    fn build<I, V, M, F>(
        &self,
        interp: I,
        voxels: V,
        maps: M,
        skip: Option<Skipper<'a>>,
        lanes: Option<Trilinear4<'a>>,
        packets: Option<Packets<'a>>,
        field: F,
        specialised: bool,
    ) -> Bound<'a>
    where
        I: Interp + 'a,
        V: super::kernel::VoxelSource + 'a,
        M: Maps + 'a,
        F: super::kernel::VoxelSource + 'a,
    {
        let skip = self.prepared(&interp, skip);
        let correction = self.correction;
        match &self.lighting {
            None => {
                Box::new(Kernel { interp, voxels, maps, shade: NoShade, skip, correction, specialised, lanes, packets })
            }
            Some(l) => {
                debug_assert!(lanes.is_none(), "the AVX2 lines are unlit");
                Box::new(Kernel {
                    interp,
                    voxels,
                    maps,
                    shade: Shaded::new(field, l.material, l.lights, l.to_world).with_shadows(l.shadows.clone()),
                    skip,
                    correction,
                    specialised,
                    lanes: None,
                    packets,
                })
            }
        }
    }

    /// The general loop.
    pub(super) fn general(&self, skip: Option<Skipper<'a>>) -> Bound<'a> {
        let constant_colour = match self.object.colour() {
            ColourMap::Polynomial(_) if !self.object.colour().reads_voxel() => self.object.colour().map(0.0),
            _ => None,
        };
        let interp = DynInterp::new(&self.object.interpolation(), self.dims);
        let field = match &self.lighting {
            Some(Lighting { field: GradientField::Alpha(a), .. }) => MaybeVoxel(Some(*a)),
            _ => MaybeVoxel(self.voxel),
        };
        let maps = Separate {
            colour: GeneralColour { map: self.object.colour(), raw: self.raw_rgb, constant: constant_colour },
            opacity: GeneralOpacity { map: self.object.opacity(), alpha: self.alpha },
        };
        self.build(interp, MaybeVoxel(self.voxel), maps, skip, None, None, field, false)
    }

    /// The specialised loop for this object, or `None` when its combination has none.
    pub(super) fn specialised(&self, skip: Option<Skipper<'a>>) -> Choice<'a> {
        let object = self.object;
        let reads_channels = self.voxel.is_some() || self.raw_rgb.is_some() || self.alpha.is_some();
        if !reads_channels {
            if let (ColourMap::Polynomial(c), OpacityMap::Polynomial(o)) = (object.colour(), object.opacity()) {
                return Ok(self.kernel(NoInterp, NoVoxel, Separate { colour: c, opacity: o }, skip));
            }
            return Err(skip);
        }
        match (object.colour(), object.opacity()) {
            (ColourMap::Raw(kind), opacity) if self.voxel.is_none() => self.raw(*kind, opacity, skip),
            (ColourMap::Lut(c), OpacityMap::Lut(o)) => self.joint(c.piecewise(), o.piecewise(), skip),
            (ColourMap::Lut(c), OpacityMap::Ramp(o)) => self.joint(c.piecewise(), o.piecewise(), skip),
            (ColourMap::Ramp(c), OpacityMap::Lut(o)) => self.joint(c.piecewise(), o.piecewise(), skip),
            (ColourMap::Ramp(c), OpacityMap::Ramp(o)) => self.joint(c.piecewise(), o.piecewise(), skip),
            (ColourMap::Polynomial(c), OpacityMap::Lut(o)) => self.separate(c, o.piecewise(), skip),
            (ColourMap::Polynomial(c), OpacityMap::Ramp(o)) => self.separate(c, o.piecewise(), skip),
            // A constant opacity (a floor, a photograph one voxel deep) is a piecewise map
            // of one segment, so the object takes the joint map's loops, packets included.
            (ColourMap::Lut(c), OpacityMap::Polynomial(o)) => match o.as_constant() {
                Some(y) => self.joint(c.piecewise(), &Piecewise::constant([y]), skip),
                None => self.separate(c.piecewise(), o, skip),
            },
            (ColourMap::Ramp(c), OpacityMap::Polynomial(o)) => match o.as_constant() {
                Some(y) => self.joint(c.piecewise(), &Piecewise::constant([y]), skip),
                None => self.separate(c.piecewise(), o, skip),
            },
            (ColourMap::Polynomial(c), OpacityMap::Polynomial(o)) => self.separate(c, o, skip),
            _ => Err(skip),
        }
    }

    /// LUT or ramp colour and opacity, merged into one map (one segment lookup per sample),
    /// with every interpolation.
    fn joint(&self, colour: &Piecewise<3>, opacity: &Piecewise<1>, skip: Option<Skipper<'a>>) -> Choice<'a> {
        let maps = JointPiecewise::new(colour, opacity);
        if let (Interpolation::Trilinear, Some(voxel)) = (self.object.interpolation(), self.voxel) {
            // Trilinear over u8 or u16: lines in AVX2 where the path is AVX2 or AVX-512, and
            // many pieces at once in f32 lanes on every path; over f32, those many pieces
            // where the channel's range of values is known (from its macrocells).
            let interp = Linear::new(self.dims, Identity);
            let stored = match (U8Voxels::of(voxel), U16LeVoxels::of(voxel), F32LeVoxels::of(voxel)) {
                (Some(v), ..) => Some(Stored::U8(v)),
                (None, Some(v), _) => Some(Stored::U16(v)),
                // Lit f32 voxels' gradients are rescaled before their length is taken
                // ([`LaneShading::rescaled`]).
                (None, None, Some(v)) => Some(Stored::F32(v)),
                _ => None,
            };
            // A shaded object has the packet loop lit where its box is affine (one normal
            // matrix) and its lighting fits f32, and no AVX2 lines (they are unlit); else
            // it takes the one-piece loops.
            let lit = match &self.lighting {
                None => None,
                // The packet loop's gradient is of the `voxel` values it reads, which is
                // the channel a LUT or ramp opacity map reads.
                // Shadow rays are cast one at a time, in f64: such an object keeps the
                // one-piece loops.
                Some(l) if l.shadows.is_some() => return self.with_maps(maps, true, skip),
                Some(l) => match LaneShading::new(l.material, l.lights, l.to_world) {
                    Some(shading) => Some(shading),
                    None => return self.with_maps(maps, true, skip),
                },
            };
            if let Some(stored) = stored {
                let avx2 = matches!(self.path, SimdPath::Avx2 | SimdPath::Avx512) && lit.is_none();
                let lanes = if avx2 { Trilinear4::new(&interp, stored, &maps) } else { None };
                let range = skip.as_ref().and_then(Skipper::value_range).or_else(|| match stored {
                    Stored::F32(_) => self.voxel_cells.and_then(Macrocells::value_range),
                    // u8 and u16 fall back on their type's range.
                    Stored::U8(_) | Stored::U16(_) => None,
                });
                let packets = Packets::new(&interp, stored, &maps, range, self.path);
                let packets = match lit {
                    Some(shading) => packets.map(|p| p.lit(shading)),
                    None => packets,
                };
                if lanes.is_some() || packets.is_some() {
                    return Ok(match stored {
                        Stored::U8(v) => self.kernel_with_lanes(interp, Read(v), maps, skip, lanes, packets),
                        Stored::U16(v) => self.kernel_with_lanes(interp, Read(v), maps, skip, lanes, packets),
                        Stored::F32(v) => self.kernel_with_lanes(interp, Read(v), maps, skip, lanes, packets),
                    });
                }
            }
        }
        self.with_maps(maps, true, skip)
    }

    /// Maps of which at least one is a polynomial, evaluated apart, with nearest and trilinear.
    fn separate<C, O>(&self, colour: C, opacity: O, skip: Option<Skipper<'a>>) -> Choice<'a>
    where
        C: ColourFn + 'a,
        O: OpacityFn + 'a,
    {
        self.with_maps(Separate { colour, opacity }, false, skip)
    }

    /// Maps over the `voxel` channel; `all_interpolations` adds nonlinear and cubic loops.
    fn with_maps<M: Maps + 'a>(&self, maps: M, all_interpolations: bool, skip: Option<Skipper<'a>>) -> Choice<'a> {
        let Some(voxel) = self.voxel else { return Err(skip) };
        match self.object.interpolation() {
            Interpolation::Nearest => self.typed(Nearest::new(self.dims), voxel, maps, skip),
            Interpolation::Trilinear => self.typed(Linear::new(self.dims, Identity), voxel, maps, skip),
            Interpolation::Nonlinear { omega } if all_interpolations => {
                self.typed(Linear::new(self.dims, Omega(omega)), voxel, maps, skip)
            }
            Interpolation::Cubic if all_interpolations => self.typed(Cubic::new(self.dims), voxel, maps, skip),
            _ => Err(skip),
        }
    }

    /// The loop for the channel's stored type.
    fn typed<I, M>(&self, interp: I, voxel: ChannelReader<'a>, maps: M, skip: Option<Skipper<'a>>) -> Choice<'a>
    where
        I: Interp + 'a,
        M: Maps + 'a,
    {
        if let Some(v) = U8Voxels::of(voxel) {
            Ok(self.kernel(interp, Read(v), maps, skip))
        } else if let Some(v) = U16LeVoxels::of(voxel) {
            Ok(self.kernel(interp, Read(v), maps, skip))
        } else if let Some(v) = F32LeVoxels::of(voxel) {
            Ok(self.kernel(interp, Read(v), maps, skip))
        } else {
            Err(skip)
        }
    }

    /// Raw colour (rgb or grey, u8) with raw or constant opacity: photographs as volumes.
    fn raw(&self, kind: RawColour, opacity: &'a OpacityMap, skip: Option<Skipper<'a>>) -> Choice<'a> {
        let Some((_, readers)) = self.raw_rgb else { return Err(skip) };
        let (Some(r), Some(g), Some(b)) =
            (U8Voxels::of(readers[0]), U8Voxels::of(readers[1]), U8Voxels::of(readers[2]))
        else {
            return Err(skip);
        };
        let colour = RawRgb { kind, channels: [r, g, b] };
        let alpha = self.alpha.and_then(U8Voxels::of);
        match (self.object.interpolation(), opacity, alpha) {
            // A raw opacity's gradient is the alpha channel's.
            (Interpolation::Nearest, OpacityMap::Raw, Some(a)) => {
                let maps = Separate { colour, opacity: RawAlpha(a) };
                Ok(self.build(Nearest::new(self.dims), NoVoxel, maps, skip, None, None, Read(a), true))
            }
            (Interpolation::Trilinear, OpacityMap::Raw, Some(a)) => {
                let maps = Separate { colour, opacity: RawAlpha(a) };
                Ok(self.build(Linear::new(self.dims, Identity), NoVoxel, maps, skip, None, None, Read(a), true))
            }
            (Interpolation::Nearest, OpacityMap::Polynomial(p), None) if !opacity.reads_voxel() => {
                Ok(self.kernel(Nearest::new(self.dims), NoVoxel, Separate { colour, opacity: p }, skip))
            }
            (Interpolation::Trilinear, OpacityMap::Polynomial(p), None) if !opacity.reads_voxel() => {
                Ok(self.kernel(Linear::new(self.dims, Identity), NoVoxel, Separate { colour, opacity: p }, skip))
            }
            _ => Err(skip),
        }
    }
}
