//! Generated channels: `generator = { kind = "...", ... }` in a scene (SPEC §1.1).
//!
//! Generators make test volumes without data files: shapes whose correct rendering is known,
//! and the standard Marschner–Lobb function for judging interpolation. Every key but `kind`
//! is optional unless marked *required*; unknown keys are errors.
//!
//! **Coordinates.** Each voxel is evaluated at its centre in normalised volume coordinates
//! (SPEC §2): voxel (i, j, k) of dims (nx, ny, nz) is the point
//! p = ((i + ½)/nx, (j + ½)/ny, (k + ½)/nz) of the unit cube. Distances are measured in these
//! coordinates, so on a non-cubic dataset a "sphere" is an ellipsoid in voxels, and fills the
//! same part of the unit cube whatever the resolution.
//!
//! **Types.** `type` is one of `bit`, `u8`, `u16`, `u32`, `f32`. Integer types round half
//! away from zero and clamp to the type's range; the checks below refuse a value that would
//! not fit, so clamping only removes rounding overshoot.
//!
//! | kind | keys (default) | value at p |
//! |---|---|---|
//! | `sphere` | `centre` ([0.5, 0.5, 0.5]), `radius` (0.5), `value` (255), `profile` (`"solid"`), `type` (`"u8"`) | d = \|p − centre\|; `solid`: `value` where d ≤ `radius`, else 0; `radial`: `value` · max(0, 1 − d/`radius`), a cone of nested shells that shows lookup-table bands as onion layers |
//! | `chessboard` | `squares` ([8, 8, 1]) | bit channel: (⌊p.x·sx⌋ + ⌊p.y·sy⌋ + ⌊p.z·sz⌋) mod 2 |
//! | `ramp` | `axis` (`"x"`; or `"y"`, `"z"`, or 0, 1, 2), `from` (0), `to` (1), `type` (`"f32"`) | `from` + (`to` − `from`) · p\[`axis`\] |
//! | `marschner_lobb` | `fm` (6), `alpha` (0.25) | f32: with (x, y, z) = 2p − 1 and r = √(x² + y²), (1 − sin(πz/2) + α(1 + cos(2π·fm·cos(πr/2)))) / (2(1 + α)), in [0, 1] |
//! | `gaussian` | `centre` ([0.5, 0.5, 0.5]), `sigma` (0.15), `peak` (1) | f32: `peak` · exp(−\|p − centre\|² / (2`sigma`²)) |
//! | `constant` | `value` (*required*), `type` (`"f32"`) | `value` everywhere |
//!
//! Refused: non-finite numbers; `radius` or `sigma` ≤ 0; `alpha` < 0; a `squares` entry of 0;
//! a `value`, `from` or `to` that does not fit `type` once rounded (bit: 0 or 1; u8: 0..255;
//! u16: 0..65535; u32: 0..4294967295; f32: the finite f32 range).
//!
//! Example: `generator = { kind = "sphere", radius = 0.4, profile = "radial", type = "f32", value = 1.0 }`.

use std::sync::Arc;

use serde::Deserialize;
use thiserror::Error;

use super::{Channel, Dims, Endian, VoxelBytes, VoxelType};

/// Largest value `ty` stores: the integer types' maximum, or the largest finite f32.
fn max_value(ty: VoxelType) -> f64 {
    match ty {
        VoxelType::Bit => 1.0,
        VoxelType::U8 => u8::MAX as f64,
        VoxelType::U16 => u16::MAX as f64,
        VoxelType::U32 => u32::MAX as f64,
        VoxelType::F32 => f32::MAX as f64,
    }
}

/// Whether `v` is stored in `ty` without clamping (after rounding, for integer types).
fn fits(ty: VoxelType, v: f64) -> bool {
    match ty {
        VoxelType::F32 => v.is_finite() && v.abs() <= max_value(ty),
        _ => v.is_finite() && (0.0..=max_value(ty)).contains(&v.round()),
    }
}

/// The range a value of `ty` must lie in, for messages.
struct Range(VoxelType);

impl std::fmt::Display for Range {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0 {
            VoxelType::F32 => f.write_str("the finite f32 range"),
            ty => write!(f, "0..={} once rounded", max_value(ty)),
        }
    }
}

/// Why a generator table or its parameters were refused. Each names the key it is about
/// ([`GeneratorError::key`]), so the scene loader can extend the key path without reading
/// the message.
#[derive(Clone, Debug, PartialEq, Error)]
pub enum GeneratorError {
    /// A key that another kind takes.
    #[error("key `{key}` does not apply to kind `{kind}` (its keys: {})", keys.join(", "))]
    KeyNotForKind {
        /// The key given.
        key: &'static str,
        /// The generator's kind.
        kind: &'static str,
        /// The keys this kind takes.
        keys: &'static [&'static str],
    },
    /// A required key is absent.
    #[error("kind `{kind}` needs key `{key}`")]
    MissingKey {
        /// The generator's kind.
        kind: &'static str,
        /// The key it needs.
        key: &'static str,
    },
    /// `type` is not a storage type.
    #[error("expected bit, u8, u16, u32 or f32, got \"{got}\"")]
    UnknownType {
        /// The text given.
        got: String,
    },
    /// A NaN or infinite number.
    #[error("`{key}` = {value}: must be a finite number")]
    NotFinite {
        /// The key.
        key: &'static str,
        /// Its value.
        value: f64,
    },
    /// A radius or width that must be positive is not.
    #[error("`{key}` = {value}: must be greater than 0")]
    NotPositive {
        /// The key.
        key: &'static str,
        /// Its value.
        value: f64,
    },
    /// A weight that must not be negative is.
    #[error("`{key}` = {value}: must be at least 0")]
    Negative {
        /// The key.
        key: &'static str,
        /// Its value.
        value: f64,
    },
    /// A value the storage type cannot hold.
    #[error("`{key}` = {value} does not fit type {ty}: must be within {}", Range(*ty))]
    DoesNotFit {
        /// The key.
        key: &'static str,
        /// Its value.
        value: f64,
        /// The storage type.
        ty: VoxelType,
    },
    /// A chessboard with zero squares along an axis.
    #[error("`squares` = {squares:?}: every entry must be at least 1")]
    ZeroSquares {
        /// The value given.
        squares: [u32; 3],
    },
    /// The generated channel would not fit in memory.
    #[error("dims {dims} of {ty} do not fit in memory")]
    TooLarge {
        /// The dataset's dims.
        dims: Dims,
        /// The channel's type.
        ty: VoxelType,
    },
}

impl GeneratorError {
    /// The generator key the error is about; `None` when it concerns the generator as a whole.
    pub fn key(&self) -> Option<&'static str> {
        match self {
            GeneratorError::KeyNotForKind { key, .. }
            | GeneratorError::MissingKey { key, .. }
            | GeneratorError::NotFinite { key, .. }
            | GeneratorError::NotPositive { key, .. }
            | GeneratorError::Negative { key, .. }
            | GeneratorError::DoesNotFit { key, .. } => Some(key),
            GeneratorError::UnknownType { .. } => Some("type"),
            GeneratorError::ZeroSquares { .. } => Some("squares"),
            GeneratorError::TooLarge { .. } => None,
        }
    }
}

/// How a sphere's value falls off from its centre (`profile` key).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Profile {
    /// `value` inside the sphere, 0 outside.
    #[default]
    Solid,
    /// `value` at the centre falling linearly to 0 at the surface.
    Radial,
}

/// A coordinate axis (`axis` key): `"x"`, `"y"` or `"z"`, or equally 0, 1 or 2.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Axis {
    /// The x axis (index 0).
    #[default]
    X,
    /// The y axis (index 1).
    Y,
    /// The z axis (index 2).
    Z,
}

impl<'de> Deserialize<'de> for Axis {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Axis, D::Error> {
        struct V;
        impl serde::de::Visitor<'_> for V {
            type Value = Axis;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("an axis: \"x\", \"y\", \"z\", 0, 1 or 2")
            }
            fn visit_str<E: serde::de::Error>(self, s: &str) -> Result<Axis, E> {
                match s {
                    "x" => Ok(Axis::X),
                    "y" => Ok(Axis::Y),
                    "z" => Ok(Axis::Z),
                    _ => Err(E::invalid_value(serde::de::Unexpected::Str(s), &self)),
                }
            }
            fn visit_u64<E: serde::de::Error>(self, n: u64) -> Result<Axis, E> {
                match n {
                    0 => Ok(Axis::X),
                    1 => Ok(Axis::Y),
                    2 => Ok(Axis::Z),
                    _ => Err(E::invalid_value(serde::de::Unexpected::Unsigned(n), &self)),
                }
            }
            fn visit_i64<E: serde::de::Error>(self, n: i64) -> Result<Axis, E> {
                match u64::try_from(n) {
                    Ok(n) => self.visit_u64(n),
                    Err(_) => Err(E::invalid_value(serde::de::Unexpected::Signed(n), &self)),
                }
            }
        }
        d.deserialize_any(V)
    }
}

impl Axis {
    /// 0, 1 or 2.
    pub fn index(self) -> usize {
        match self {
            Axis::X => 0,
            Axis::Y => 1,
            Axis::Z => 2,
        }
    }
}

/// A generated channel; see the module documentation for the reference.
///
/// Read from a scene through a flat `GeneratorTable` (`kind` plus every key any kind
/// takes) rather than a serde internally tagged enum: a tagged enum buffers its fields, and
/// the scene's error path (SPEC §1: `datasets[0].channels.voxel.generator.radius`) would then
/// stop at `generator`. The table is converted by `TryFrom`, outside serde, so that its
/// errors stay typed and name their key.
#[derive(Clone, Debug, PartialEq)]
pub enum Generator {
    /// A solid or radially graded sphere.
    Sphere {
        /// Centre in NVC.
        centre: [f64; 3],
        /// Radius in NVC (> 0).
        radius: f64,
        /// Value inside (solid) or at the centre (radial).
        value: f64,
        /// Solid or radial.
        profile: Profile,
        /// Storage type (the `type` key).
        ty: VoxelType,
    },
    /// A 3-D chessboard as a bit channel.
    Chessboard {
        /// Squares per axis (each ≥ 1).
        squares: [u32; 3],
    },
    /// A linear ramp along one axis.
    Ramp {
        /// The axis the value grows along.
        axis: Axis,
        /// Value at NVC 0 of the axis.
        from: f64,
        /// Value at NVC 1 of the axis.
        to: f64,
        /// Storage type (the `type` key).
        ty: VoxelType,
    },
    /// The Marschner–Lobb test function (f32, values in [0, 1]).
    MarschnerLobb {
        /// Frequency fM of the radial ripples.
        fm: f64,
        /// Weight α of the ripples (≥ 0).
        alpha: f64,
    },
    /// A Gaussian blob (f32).
    Gaussian {
        /// Centre in NVC.
        centre: [f64; 3],
        /// Standard deviation in NVC (> 0).
        sigma: f64,
        /// Value at the centre.
        peak: f64,
    },
    /// The same value everywhere.
    Constant {
        /// The value (required).
        value: f64,
        /// Storage type (the `type` key).
        ty: VoxelType,
    },
}

/// The kinds, as spelt in a scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
enum Kind {
    Sphere,
    Chessboard,
    Ramp,
    MarschnerLobb,
    Gaussian,
    Constant,
}

/// A generator as written in a scene: `kind` and any keys, checked against the kind by
/// `Generator::try_from`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GeneratorTable {
    kind: Kind,
    centre: Option<[f64; 3]>,
    radius: Option<f64>,
    value: Option<f64>,
    profile: Option<Profile>,
    #[serde(rename = "type")]
    ty: Option<String>,
    squares: Option<[u32; 3]>,
    axis: Option<Axis>,
    from: Option<f64>,
    to: Option<f64>,
    fm: Option<f64>,
    alpha: Option<f64>,
    sigma: Option<f64>,
    peak: Option<f64>,
}

impl TryFrom<GeneratorTable> for Generator {
    type Error = GeneratorError;

    fn try_from(t: GeneratorTable) -> Result<Generator, GeneratorError> {
        let (kind, keys): (&str, &[&str]) = match t.kind {
            Kind::Sphere => ("sphere", &["centre", "radius", "value", "profile", "type"]),
            Kind::Chessboard => ("chessboard", &["squares"]),
            Kind::Ramp => ("ramp", &["axis", "from", "to", "type"]),
            Kind::MarschnerLobb => ("marschner_lobb", &["fm", "alpha"]),
            Kind::Gaussian => ("gaussian", &["centre", "sigma", "peak"]),
            Kind::Constant => ("constant", &["value", "type"]),
        };
        let given = [
            ("centre", t.centre.is_some()),
            ("radius", t.radius.is_some()),
            ("value", t.value.is_some()),
            ("profile", t.profile.is_some()),
            ("type", t.ty.is_some()),
            ("squares", t.squares.is_some()),
            ("axis", t.axis.is_some()),
            ("from", t.from.is_some()),
            ("to", t.to.is_some()),
            ("fm", t.fm.is_some()),
            ("alpha", t.alpha.is_some()),
            ("sigma", t.sigma.is_some()),
            ("peak", t.peak.is_some()),
        ];
        if let Some(&(key, _)) = given.iter().find(|(k, g)| *g && !keys.contains(k)) {
            return Err(GeneratorError::KeyNotForKind { key, kind, keys });
        }
        let ty = |default: VoxelType| match &t.ty {
            None => Ok(default),
            Some(text) => VoxelType::parse(text).ok_or_else(|| GeneratorError::UnknownType { got: text.clone() }),
        };
        Ok(match t.kind {
            Kind::Sphere => Generator::Sphere {
                centre: t.centre.unwrap_or([0.5; 3]),
                radius: t.radius.unwrap_or(0.5),
                value: t.value.unwrap_or(255.0),
                profile: t.profile.unwrap_or_default(),
                ty: ty(VoxelType::U8)?,
            },
            Kind::Chessboard => Generator::Chessboard { squares: t.squares.unwrap_or([8, 8, 1]) },
            Kind::Ramp => Generator::Ramp {
                axis: t.axis.unwrap_or_default(),
                from: t.from.unwrap_or(0.0),
                to: t.to.unwrap_or(1.0),
                ty: ty(VoxelType::F32)?,
            },
            Kind::MarschnerLobb => Generator::MarschnerLobb { fm: t.fm.unwrap_or(6.0), alpha: t.alpha.unwrap_or(0.25) },
            Kind::Gaussian => Generator::Gaussian {
                centre: t.centre.unwrap_or([0.5; 3]),
                sigma: t.sigma.unwrap_or(0.15),
                peak: t.peak.unwrap_or(1.0),
            },
            Kind::Constant => Generator::Constant {
                value: t.value.ok_or(GeneratorError::MissingKey { kind, key: "value" })?,
                ty: ty(VoxelType::F32)?,
            },
        })
    }
}

impl Generator {
    /// The generated channel's storage type.
    pub fn voxel_type(&self) -> VoxelType {
        match self {
            Generator::Sphere { ty, .. } | Generator::Ramp { ty, .. } | Generator::Constant { ty, .. } => *ty,
            Generator::Chessboard { .. } => VoxelType::Bit,
            Generator::MarschnerLobb { .. } | Generator::Gaussian { .. } => VoxelType::F32,
        }
    }

    /// Checks the parameters (and that `dims` of this type fit in memory); the error names the
    /// offending key and says what is expected.
    pub fn check(&self, dims: Dims) -> Result<(), GeneratorError> {
        fn finite(key: &'static str, value: f64) -> Result<(), GeneratorError> {
            if value.is_finite() {
                Ok(())
            } else {
                Err(GeneratorError::NotFinite { key, value })
            }
        }
        fn positive(key: &'static str, value: f64) -> Result<(), GeneratorError> {
            finite(key, value)?;
            if value > 0.0 {
                Ok(())
            } else {
                Err(GeneratorError::NotPositive { key, value })
            }
        }
        fn fits_type(key: &'static str, value: f64, ty: VoxelType) -> Result<(), GeneratorError> {
            finite(key, value)?;
            if fits(ty, value) {
                Ok(())
            } else {
                Err(GeneratorError::DoesNotFit { key, value, ty })
            }
        }
        fn centre(c: &[f64; 3]) -> Result<(), GeneratorError> {
            c.iter().try_for_each(|&v| finite("centre", v))
        }
        match self {
            Generator::Sphere { centre: c, radius, value, ty, .. } => {
                centre(c)?;
                positive("radius", *radius)?;
                fits_type("value", *value, *ty)?;
            }
            Generator::Chessboard { squares } => {
                if squares.contains(&0) {
                    return Err(GeneratorError::ZeroSquares { squares: *squares });
                }
            }
            Generator::Ramp { from, to, ty, .. } => {
                fits_type("from", *from, *ty)?;
                fits_type("to", *to, *ty)?;
            }
            Generator::MarschnerLobb { fm, alpha } => {
                finite("fm", *fm)?;
                finite("alpha", *alpha)?;
                if *alpha < 0.0 {
                    return Err(GeneratorError::Negative { key: "alpha", value: *alpha });
                }
            }
            Generator::Gaussian { centre: c, sigma, peak } => {
                centre(c)?;
                positive("sigma", *sigma)?;
                fits_type("peak", *peak, VoxelType::F32)?;
            }
            Generator::Constant { value, ty } => fits_type("value", *value, *ty)?,
        }
        let ty = self.voxel_type();
        let bytes = ty.byte_len(dims.voxel_count());
        if bytes.is_none_or(|b| b > isize::MAX as u64) {
            return Err(GeneratorError::TooLarge { dims, ty });
        }
        Ok(())
    }

    /// The kind and every parameter, numbers by their bits: equal exactly when two
    /// generators make the same channel (`DatasetInfo::id`).
    pub(crate) fn identity(&self) -> Vec<u64> {
        let bits = |xs: &[f64]| xs.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let ty = |t: VoxelType| t as u64;
        match self {
            Generator::Sphere { centre, radius, value, profile, ty: t } => {
                let mut v = vec![0, *profile as u64, ty(*t)];
                v.extend(bits(centre));
                v.extend(bits(&[*radius, *value]));
                v
            }
            Generator::Chessboard { squares } => vec![1, squares[0] as u64, squares[1] as u64, squares[2] as u64],
            Generator::Ramp { axis, from, to, ty: t } => {
                let mut v = vec![2, axis.index() as u64, ty(*t)];
                v.extend(bits(&[*from, *to]));
                v
            }
            Generator::MarschnerLobb { fm, alpha } => [vec![3], bits(&[*fm, *alpha])].concat(),
            Generator::Gaussian { centre, sigma, peak } => [vec![4], bits(centre), bits(&[*sigma, *peak])].concat(),
            Generator::Constant { value, ty: t } => vec![5, ty(*t), value.to_bits()],
        }
    }

    /// The value at NVC point `p` (before storage rounding).
    fn eval(&self, p: [f64; 3]) -> f64 {
        let dist2 = |c: &[f64; 3]| (0..3).map(|a| (p[a] - c[a]).powi(2)).sum::<f64>();
        match self {
            Generator::Sphere { centre, radius, value, profile, .. } => {
                let d = dist2(centre).sqrt();
                match profile {
                    Profile::Solid if d <= *radius => *value,
                    Profile::Solid => 0.0,
                    Profile::Radial => value * (1.0 - d / radius).max(0.0),
                }
            }
            Generator::Chessboard { squares } => {
                let s: i64 = (0..3).map(|a| (p[a] * squares[a] as f64).floor() as i64).sum();
                s.rem_euclid(2) as f64
            }
            Generator::Ramp { axis, from, to, .. } => from + (to - from) * p[axis.index()],
            Generator::MarschnerLobb { fm, alpha } => marschner_lobb(p, *fm, *alpha),
            Generator::Gaussian { centre, sigma, peak } => peak * (-dist2(centre) / (2.0 * sigma * sigma)).exp(),
            Generator::Constant { value, .. } => *value,
        }
    }

    /// Generates the channel. Call [`Generator::check`] first: unchecked parameters still give
    /// a channel, but a non-finite or out-of-range value is clamped (NaN stores as 0).
    ///
    /// Sequential on purpose: the per-ray renderer loads datasets from inside its rayon jobs
    /// while other jobs wait on the store for that very load. A parallel loop here would let
    /// the loading thread, idle in a join, steal one of those waiting jobs and block on its
    /// own unfinished load — a deadlock seen in the budget tests.
    pub fn generate(&self, dims: Dims) -> Channel {
        let ty = self.voxel_type();
        let [nx, ny, nz] = dims.as_array().map(|n| n as usize);
        let centre = |i: usize, n: usize| (i as f64 + 0.5) / n as f64;
        let bytes = if ty == VoxelType::Bit {
            let count = nx * ny * nz;
            let mut out = vec![0u8; count.div_ceil(8)];
            out.iter_mut().enumerate().for_each(|(byte, b)| {
                for bit in 0..8 {
                    let idx = byte * 8 + bit;
                    if idx >= count {
                        break;
                    }
                    let (i, j, k) = (idx % nx, (idx / nx) % ny, idx / (nx * ny));
                    let v = self.eval([centre(i, nx), centre(j, ny), centre(k, nz)]);
                    *b |= (encode_int(v, 1.0) as u8) << bit;
                }
            });
            out
        } else {
            let bpv = if ty == VoxelType::U8 {
                1
            } else if ty == VoxelType::U16 {
                2
            } else {
                4
            };
            let mut out = vec![0u8; nx * ny * nz * bpv];
            out.chunks_mut(nx * bpv).enumerate().for_each(|(row, line)| {
                let (j, k) = (row % ny, row / ny);
                let (py, pz) = (centre(j, ny), centre(k, nz));
                for (i, dst) in line.chunks_exact_mut(bpv).enumerate() {
                    let v = self.eval([centre(i, nx), py, pz]);
                    match ty {
                        VoxelType::U8 => dst[0] = encode_int(v, 255.0) as u8,
                        VoxelType::U16 => dst.copy_from_slice(&(encode_int(v, 65535.0) as u16).to_le_bytes()),
                        VoxelType::U32 => dst.copy_from_slice(&(encode_int(v, u32::MAX as f64) as u32).to_le_bytes()),
                        _ => dst.copy_from_slice(&(v as f32).to_le_bytes()),
                    }
                }
            });
            out
        };
        Channel::new(ty, Endian::Little, VoxelBytes::Owned(Arc::new(bytes)), dims)
            .expect("a generated channel has exactly dims voxels")
    }
}

/// Round half away from zero, clamp to [0, max] (NaN → 0).
fn encode_int(v: f64, max: f64) -> f64 {
    if v.is_nan() {
        0.0
    } else {
        v.round().clamp(0.0, max)
    }
}

/// The Marschner–Lobb function at NVC point `p` (the cube [−1, 1]³ mapped onto [0, 1]³).
fn marschner_lobb(p: [f64; 3], fm: f64, alpha: f64) -> f64 {
    use std::f64::consts::PI;
    let [x, y, z] = p.map(|c| 2.0 * c - 1.0);
    let r = (x * x + y * y).sqrt();
    let rho_r = (2.0 * PI * fm * (PI * r / 2.0).cos()).cos();
    (1.0 - (PI * z / 2.0).sin() + alpha * (1.0 + rho_r)) / (2.0 * (1.0 + alpha))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dims(x: u64, y: u64, z: u64) -> Dims {
        Dims::new([x, y, z]).unwrap()
    }

    /// The table as serde reads it; its own refusals (unknown keys, wrong types) are serde's.
    fn table(s: &str) -> Result<GeneratorTable, toml::de::Error> {
        toml::from_str::<GeneratorTable>(s)
    }

    fn parse(s: &str) -> Result<Generator, GeneratorError> {
        Generator::try_from(table(s).unwrap_or_else(|e| panic!("{s:?}: {e}")))
    }

    #[test]
    fn toml_defaults_and_refusals() {
        assert_eq!(
            parse("kind = \"sphere\"").unwrap(),
            Generator::Sphere {
                centre: [0.5; 3],
                radius: 0.5,
                value: 255.0,
                profile: Profile::Solid,
                ty: VoxelType::U8
            }
        );
        assert_eq!(parse("kind = \"chessboard\"").unwrap(), Generator::Chessboard { squares: [8, 8, 1] });
        assert_eq!(
            parse("kind = \"ramp\"\naxis = \"y\"\nto = 10").unwrap(),
            Generator::Ramp { axis: Axis::Y, from: 0.0, to: 10.0, ty: VoxelType::F32 }
        );
        assert_eq!(
            parse("kind = \"ramp\"\naxis = 2").unwrap().clone(),
            parse("kind = \"ramp\"\naxis = \"z\"").unwrap()
        );
        assert_eq!(parse("kind = \"marschner_lobb\"").unwrap(), Generator::MarschnerLobb { fm: 6.0, alpha: 0.25 });
        assert_eq!(
            parse("kind = \"gaussian\"\nsigma = 0.2").unwrap(),
            Generator::Gaussian { centre: [0.5; 3], sigma: 0.2, peak: 1.0 }
        );
        assert_eq!(
            parse("kind = \"constant\"\nvalue = 3\ntype = \"u16\"").unwrap(),
            Generator::Constant { value: 3.0, ty: VoxelType::U16 }
        );
        assert_eq!(
            parse("kind = \"sphere\"\nprofile = \"radial\"\ntype = \"f32\"\nvalue = 1.5").unwrap().voxel_type(),
            VoxelType::F32
        );
        // Refused by serde while reading the table (its messages, reported at the key's path).
        for (bad, needle) in [
            ("kind = \"sphere\"\nradius = 0.3\nradious = 1", "radious"),
            ("kind = \"cube\"", "cube"),
            ("kind = \"ramp\"\naxis = 3", "axis"),
            ("kind = \"ramp\"\naxis = \"w\"", "axis"),
            ("kind = \"sphere\"\nprofile = \"hollow\"", "hollow"),
            ("kind = \"chessboard\"\nsquares = [1, 2]", "squares"),
            ("radius = 1.0", "kind"),
        ] {
            let e = table(bad).unwrap_err().to_string();
            assert!(e.contains(needle), "{bad:?}: {e}");
        }
        // Refused by the conversion, each naming its key.
        let e = parse("kind = \"constant\"").unwrap_err();
        assert_eq!(e, GeneratorError::MissingKey { kind: "constant", key: "value" });
        let e = parse("kind = \"sphere\"\ntype = \"i16\"").unwrap_err();
        assert_eq!((e.key(), e), (Some("type"), GeneratorError::UnknownType { got: "i16".into() }));
        let e = parse("kind = \"chessboard\"\nradius = 1.0").unwrap_err();
        assert!(matches!(e, GeneratorError::KeyNotForKind { key: "radius", kind: "chessboard", .. }), "{e:?}");
        assert_eq!(e.to_string(), "key `radius` does not apply to kind `chessboard` (its keys: squares)");
        let e = parse("kind = \"gaussian\"\ntype = \"u8\"").unwrap_err();
        assert!(matches!(e, GeneratorError::KeyNotForKind { key: "type", kind: "gaussian", .. }), "{e:?}");
    }

    /// The scene reports errors by TOML path (SPEC §1); it must reach the generator's key.
    #[test]
    fn error_paths_reach_the_key() {
        #[derive(Deserialize, Debug)]
        #[allow(dead_code)]
        struct Scene {
            generator: GeneratorTable,
        }
        for (text, path) in [
            ("generator = { kind = \"chessboard\", squares = [1, 2] }", "generator.squares"),
            ("generator = { kind = \"sphere\", radius = \"a\" }", "generator.radius"),
            ("generator = { kind = \"ramp\", axis = 7 }", "generator.axis"),
            ("generator = { kind = \"cube\" }", "generator.kind"),
            ("generator = { kind = \"sphere\", centre = [0.5, 0.5] }", "generator.centre"),
        ] {
            let de = toml::Deserializer::parse(text).unwrap();
            let e = serde_path_to_error::deserialize::<_, Scene>(de).unwrap_err();
            assert_eq!(e.path().to_string(), path, "{text}");
        }
    }

    #[test]
    fn sphere_centre_and_outside() {
        let g = parse("kind = \"sphere\"\nradius = 0.3").unwrap();
        let d = dims(11, 11, 11);
        g.check(d).unwrap();
        let ch = g.generate(d);
        assert_eq!(ch.ty(), VoxelType::U8);
        assert_eq!(ch.value(d.index(5, 5, 5)), 255.0);
        assert_eq!(ch.value(d.index(0, 0, 0)), 0.0);
        // Voxel 8 along x has p.x = 8.5/11, d = 0.2727 ≤ 0.3: inside; voxel 9: d = 0.3636: outside.
        assert_eq!(ch.value(d.index(8, 5, 5)), 255.0);
        assert_eq!(ch.value(d.index(9, 5, 5)), 0.0);
        // NVC distances: on a flat dataset the sphere still spans 0.3 of each axis.
        let d2 = dims(11, 22, 1);
        let ch = g.generate(d2);
        assert_eq!(ch.value(d2.index(5, 17, 0)), 255.0); // p.y = 17.5/22, d = 0.295
        assert_eq!(ch.value(d2.index(5, 18, 0)), 0.0); // d = 0.341

        let g = Generator::Sphere {
            centre: [0.5; 3],
            radius: 0.5,
            value: 200.0,
            profile: Profile::Radial,
            ty: VoxelType::F32,
        };
        let d = dims(10, 1, 1);
        let ch = g.generate(d);
        for i in 0..10 {
            let dist = ((i as f64 + 0.5) / 10.0 - 0.5f64).abs();
            assert_eq!(ch.value(i), (200.0 * (1.0 - dist / 0.5)) as f32, "voxel {i}");
        }
        // A bit sphere.
        let g = Generator::Sphere {
            centre: [0.5; 3],
            radius: 0.25,
            value: 1.0,
            profile: Profile::Solid,
            ty: VoxelType::Bit,
        };
        let d = dims(4, 4, 1);
        let ch = g.generate(d);
        assert_eq!(ch.ty(), VoxelType::Bit);
        let inside: Vec<usize> = (0..16).filter(|&i| ch.value(i) == 1.0).collect();
        assert_eq!(inside, [5, 6, 9, 10]);
    }

    #[test]
    fn chessboard_parity() {
        let g = Generator::Chessboard { squares: [8, 8, 1] };
        assert_eq!(g.voxel_type(), VoxelType::Bit);
        let d = dims(8, 8, 1);
        let ch = g.generate(d);
        assert_eq!(ch.byte_len(), 8);
        for (i, j) in [(0, 0), (1, 0), (0, 1), (3, 5), (7, 7), (6, 1)] {
            assert_eq!(ch.value(d.index(i, j, 0)), ((i + j) % 2) as f32, "({i}, {j})");
        }
        // Two voxels per square, and z alternates with two squares along z.
        let g = Generator::Chessboard { squares: [8, 8, 2] };
        let d = dims(16, 16, 3); // 17 bytes of bits: crosses byte and slice boundaries unevenly
        let ch = g.generate(d);
        assert_eq!(ch.byte_len(), (16 * 16 * 3usize).div_ceil(8));
        for (i, j, k) in [(0, 0, 0), (1, 0, 0), (2, 0, 0), (3, 3, 0), (5, 2, 2), (15, 15, 2), (4, 9, 1)] {
            let z = ((k as f64 + 0.5) / 3.0 * 2.0).floor() as usize;
            assert_eq!(ch.value(d.index(i, j, k)), ((i / 2 + j / 2 + z) % 2) as f32, "({i}, {j}, {k})");
        }
    }

    #[test]
    fn ramp_exact_values_and_rounding() {
        let g = Generator::Ramp { axis: Axis::X, from: 0.0, to: 1.0, ty: VoxelType::F32 };
        let ch = g.generate(dims(4, 2, 1));
        assert_eq!((0..4).map(|i| ch.value(i)).collect::<Vec<_>>(), [0.125, 0.375, 0.625, 0.875]);
        assert_eq!(ch.value(5), 0.375);
        let g = Generator::Ramp { axis: Axis::Z, from: 10.0, to: -10.0, ty: VoxelType::F32 };
        let d = dims(1, 1, 5);
        let ch = g.generate(d);
        assert_eq!((0..5).map(|k| ch.value(k)).collect::<Vec<_>>(), [8.0, 4.0, 0.0, -4.0, -8.0]);
        // u8: 255 · 0.25 = 63.75 → 64; 255 · 0.75 = 191.25 → 191.
        let g = Generator::Ramp { axis: Axis::Y, from: 0.0, to: 255.0, ty: VoxelType::U8 };
        let ch = g.generate(dims(1, 2, 1));
        assert_eq!((ch.value(0), ch.value(1)), (64.0, 191.0));
        // Half away from zero: 2.5 → 3; u16 and u32 storage.
        let ch = Generator::Constant { value: 2.5, ty: VoxelType::U8 }.generate(dims(2, 1, 1));
        assert_eq!(ch.value(1), 3.0);
        let ch = Generator::Constant { value: 65535.0, ty: VoxelType::U16 }.generate(dims(2, 1, 1));
        assert_eq!((ch.ty(), ch.value(1)), (VoxelType::U16, 65535.0));
        let ch = Generator::Constant { value: 70000.0, ty: VoxelType::U32 }.generate(dims(2, 1, 1));
        assert_eq!((ch.ty(), ch.value(1)), (VoxelType::U32, 70000.0));
    }

    #[test]
    fn marschner_lobb_known_points() {
        let g = Generator::MarschnerLobb { fm: 6.0, alpha: 0.25 };
        let d = dims(3, 3, 3);
        let ch = g.generate(d);
        // Centre: x = y = z = 0, r = 0, ρr = cos(12π) = 1 → (1 + 0.25·2) / 2.5 = 0.6.
        assert!((ch.value(d.index(1, 1, 1)) - 0.6).abs() < 1e-6);
        // Voxel (2, 1, 2): x = 2/3, y = 0, z = 2/3.
        let pi = std::f64::consts::PI;
        let (x, z) = (2.0 / 3.0, 2.0f64 / 3.0);
        let rho_r = (2.0 * pi * 6.0 * (pi * x / 2.0).cos()).cos();
        let expected = (1.0 - (pi * z / 2.0).sin() + 0.25 * (1.0 + rho_r)) / (2.0 * 1.25);
        assert_eq!(ch.value(d.index(2, 1, 2)), expected as f32);
        let r = ch.reader();
        assert!((0..27).all(|i| (0.0..=1.0).contains(&r.read(i))));
    }

    #[test]
    fn gaussian_values() {
        let g = Generator::Gaussian { centre: [0.25, 0.5, 0.5], sigma: 0.1, peak: 2.0 };
        let ch = g.generate(dims(2, 1, 1));
        assert_eq!(ch.value(0), 2.0); // p = (0.25, 0.5, 0.5), the centre
        let expected = 2.0 * (-(0.5f64 * 0.5) / (2.0 * 0.1 * 0.1)).exp();
        assert_eq!(ch.value(1), expected as f32);
        let ch = g.generate(dims(4, 1, 1)); // p.x = 0.375: distance 0.125
        assert_eq!(ch.value(1), (2.0 * (-(0.125f64 * 0.125) / 0.02).exp()) as f32);
    }

    #[test]
    fn check_refusals_name_the_field() {
        let d = dims(4, 4, 4);
        let sphere = |radius: f64, value: f64, ty: VoxelType| Generator::Sphere {
            centre: [0.5; 3],
            radius,
            value,
            profile: Profile::Solid,
            ty,
        };
        use GeneratorError::*;
        type Expected = fn(&GeneratorError) -> bool;
        let refusals: [(Generator, Expected); 17] = [
            (sphere(0.0, 1.0, VoxelType::U8), |e| *e == NotPositive { key: "radius", value: 0.0 }),
            (sphere(-1.0, 1.0, VoxelType::U8), |e| *e == NotPositive { key: "radius", value: -1.0 }),
            (sphere(f64::NAN, 1.0, VoxelType::U8), |e| matches!(e, NotFinite { key: "radius", .. })),
            (sphere(0.5, 256.0, VoxelType::U8), |e| *e == DoesNotFit { key: "value", value: 256.0, ty: VoxelType::U8 }),
            (sphere(0.5, -0.6, VoxelType::U8), |e| matches!(e, DoesNotFit { key: "value", .. })),
            (sphere(0.5, 2.0, VoxelType::Bit), |e| matches!(e, DoesNotFit { key: "value", ty: VoxelType::Bit, .. })),
            (sphere(0.5, 65536.0, VoxelType::U16), |e| matches!(e, DoesNotFit { key: "value", .. })),
            (sphere(0.5, 1e39, VoxelType::F32), |e| matches!(e, DoesNotFit { key: "value", ty: VoxelType::F32, .. })),
            (
                Generator::Sphere {
                    centre: [0.5, f64::INFINITY, 0.5],
                    radius: 0.5,
                    value: 1.0,
                    profile: Profile::Solid,
                    ty: VoxelType::U8,
                },
                |e| matches!(e, NotFinite { key: "centre", .. }),
            ),
            (Generator::Chessboard { squares: [8, 0, 1] }, |e| *e == ZeroSquares { squares: [8, 0, 1] }),
            (Generator::Ramp { axis: Axis::X, from: -1.0, to: 255.0, ty: VoxelType::U8 }, |e| {
                matches!(e, DoesNotFit { key: "from", .. })
            }),
            (Generator::Ramp { axis: Axis::X, from: 0.0, to: f64::NAN, ty: VoxelType::F32 }, |e| {
                matches!(e, NotFinite { key: "to", .. })
            }),
            (Generator::MarschnerLobb { fm: 6.0, alpha: -0.5 }, |e| *e == Negative { key: "alpha", value: -0.5 }),
            (Generator::MarschnerLobb { fm: f64::INFINITY, alpha: 0.25 }, |e| matches!(e, NotFinite { key: "fm", .. })),
            (Generator::Gaussian { centre: [0.5; 3], sigma: 0.0, peak: 1.0 }, |e| {
                matches!(e, NotPositive { key: "sigma", .. })
            }),
            (Generator::Gaussian { centre: [0.5; 3], sigma: 0.1, peak: f64::NAN }, |e| {
                matches!(e, NotFinite { key: "peak", .. })
            }),
            (Generator::Constant { value: 4294967296.0, ty: VoxelType::U32 }, |e| {
                matches!(e, DoesNotFit { key: "value", .. })
            }),
        ];
        for (g, expected) in refusals {
            let e = g.check(d).unwrap_err();
            assert!(expected(&e), "{g:?}: {e:?}");
        }
        // The wording a user sees after the key path.
        let e = sphere(0.5, 256.0, VoxelType::U8).check(d).unwrap_err();
        assert_eq!(e.to_string(), "`value` = 256 does not fit type u8: must be within 0..=255 once rounded");
        for ok in [
            sphere(0.5, 255.4, VoxelType::U8),
            sphere(0.5, -0.4, VoxelType::U8),
            sphere(0.5, 1.0, VoxelType::Bit),
            sphere(0.5, -3.0, VoxelType::F32),
            Generator::Constant { value: 4294967295.0, ty: VoxelType::U32 },
        ] {
            ok.check(d).unwrap();
        }
    }
}
