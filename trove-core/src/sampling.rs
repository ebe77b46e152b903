//! Casting one object over one piece of one ray (paper `VolumeRayCasting()`, SPEC
//! §4.2–4.4). This is the only sampler: the per-ray and grouped algorithms both call
//! [`ObjectCaster::cast`], and differ only in when and where they do.

use crate::composite::Rgba;
use crate::dataset::{ChannelName, ChannelReader, Volume};
use crate::geometry::Ray;
use crate::interp::Stencil;
use crate::mapping::{ColourMap, OpacityMap, RawColour};
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
}

/// What one object contributed over one piece.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PieceResult {
    /// Accumulated colour and opacity of this object's samples over the piece.
    pub rgba: Rgba,
    /// Samples evaluated (interpolated and mapped).
    pub samples: u64,
}

/// An object bound to its resident volume, with the channel readers its maps need
/// resolved once: a map that does not read a channel never touches it.
pub struct ObjectCaster<'a> {
    object: &'a Object,
    volume: &'a Volume,
    voxel: Option<ChannelReader<'a>>,
    raw_rgb: Option<(RawColour, [ChannelReader<'a>; 3])>,
    alpha: Option<ChannelReader<'a>>,
    constant_colour: Option<[f64; 3]>,
    opacity_correction: bool,
}

impl<'a> ObjectCaster<'a> {
    /// Binds `object` to `volume`, its dataset's voxels; refuses a volume that lacks a
    /// channel the object's maps read or has other dims than the object was placed with.
    pub fn new(
        object: &'a Object,
        volume: &'a Volume,
        opacity_correction: bool,
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
        let constant_colour = match object.colour() {
            ColourMap::Polynomial(_) if !object.colour().reads_voxel() => object.colour().map(0.0),
            _ => None,
        };
        Ok(ObjectCaster {
            object,
            volume,
            voxel: if needs_voxel { Some(reader(ChannelName::Voxel)?) } else { None },
            raw_rgb,
            alpha: if matches!(object.opacity(), OpacityMap::Raw) { Some(reader(ChannelName::Alpha)?) } else { None },
            constant_colour,
            opacity_correction,
        })
    }

    /// Composites this object's samples over [t0, t1] front to back. The ray arrives with
    /// opacity `alpha_in`; once `alpha_in + (1 − alpha_in)·A` reaches `stop_at` the cast
    /// stops (pass `f64::INFINITY` to sample the whole piece, as pieces shared by several
    /// objects must, SPEC §4.5).
    pub fn cast(&self, ray: &Ray, t0: f64, t1: f64, alpha_in: f64, stop_at: f64) -> PieceResult {
        let mut acc = Rgba::CLEAR;
        let mut samples = 0;
        // A constant-zero opacity contributes nothing anywhere: skip the walk entirely.
        if self.object.opacity().constant() == Some(0.0) {
            return PieceResult { rgba: acc, samples };
        }
        let dims = self.volume.dims();
        let interp = &self.object.interpolation();
        // Maps that read no channel (constant colour and opacity) need no stencil at all.
        let reads_channels = self.voxel.is_some() || self.raw_rgb.is_some() || self.alpha.is_some();
        for (vc, ell) in self.object.placement().walk(ray, t0, t1, self.object.sampling_distance()) {
            let Some(vc) = vc else { continue };
            samples += 1;
            let stencil = reads_channels.then(|| Stencil::new(interp, dims, vc));
            let read = |r: &ChannelReader<'_>| stencil.as_ref().map_or(0.0, |s| s.apply(r));
            let v = match &self.voxel {
                Some(r) => {
                    let v = read(r);
                    if !v.is_finite() {
                        continue;
                    }
                    v
                }
                None => 0.0,
            };
            let colour = match (&self.raw_rgb, self.constant_colour) {
                (Some((kind, rgb)), _) => ColourMap::map_raw(*kind, rgb.each_ref().map(read)),
                (None, Some(c)) => Some(c),
                (None, None) => self.object.colour().map(v),
            };
            let opacity = match &self.alpha {
                Some(a) => OpacityMap::map_raw(read(a)),
                None => self.object.opacity().map(v),
            };
            let (Some(colour), Some(opacity)) = (colour, opacity) else { continue };
            let alpha = if self.opacity_correction { corrected_opacity(opacity, ell) } else { opacity };
            acc.add_sample(colour, alpha);
            if alpha_in + (1.0 - alpha_in) * acc.alpha >= stop_at {
                break;
            }
        }
        PieceResult { rgba: acc, samples }
    }
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
mod tests {
    use super::*;

    #[test]
    fn opacity_correction_is_exact_at_the_ends_and_precise_for_tiny_values() {
        assert_eq!(corrected_opacity(0.0, 3.0), 0.0);
        assert_eq!(corrected_opacity(1.0, 0.25), 1.0);
        assert_eq!(corrected_opacity(1.0, 0.0), 0.0);
        assert_eq!(corrected_opacity(0.3, 1.0), 0.3);
        let a = corrected_opacity(0.5, 2.0);
        assert!((a - 0.75).abs() < 1e-15);
        // 1 − (1 − 1e-12)^1e-3 ≈ 1e-15: the naive formula loses every digit here.
        let tiny = corrected_opacity(1e-12, 1e-3);
        assert!((tiny / 1e-15 - 1.0).abs() < 1e-9, "{tiny}");
    }
}
