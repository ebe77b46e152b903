//! The effects a scene may ask for (SPEC §6): lights (`[[lights]]`) and an object's
//! Blinn–Phong material (`shading = { ... }`). Each value here holds its rules by
//! construction — a light's direction is a unit vector, colours and coefficients are finite
//! and ≥ 0 — so that the sampler reads them without checking. The loader (`load.rs`) turns
//! a refusal into a [`super::SceneErrorKind`] at the key it is about.

use std::sync::Arc;

use glam::DVec3;

/// A finite vector of length 1.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UnitVector(DVec3);

impl UnitVector {
    /// `v` normalised; `None` when `v` is zero or not finite (or so small that its
    /// normalisation is not finite).
    pub fn new(v: DVec3) -> Option<UnitVector> {
        if !v.is_finite() {
            return None;
        }
        let n = v.normalize_or_zero();
        (n != DVec3::ZERO && n.is_finite()).then_some(UnitVector(n))
    }

    /// The vector.
    #[inline]
    pub fn get(self) -> DVec3 {
        self.0
    }
}

/// Where a light's rays come from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LightSource {
    /// Parallel rays travelling along `direction` (world).
    Directional {
        /// The direction the light travels.
        direction: UnitVector,
    },
    /// Rays from a world point, without distance falloff.
    Point {
        /// The light's world position (finite).
        position: DVec3,
    },
}

/// One light of `[[lights]]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Light {
    source: LightSource,
    /// intensity · colour, the E of SPEC §6: finite, each ≥ 0.
    radiance: [f64; 3],
    /// Whether it casts shadows (S of SPEC §6 is then the transmittance towards it).
    shadows: bool,
}

/// Why a light's numbers are refused (the loader names the key).
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum LightError {
    /// A colour channel that is negative or not finite.
    #[error("expected linear RGB, each a finite number ≥ 0, got {got:?}")]
    Colour {
        /// The value given.
        got: [f64; 3],
    },
    /// An intensity that is negative or not finite.
    #[error("expected a finite intensity ≥ 0, got {got}")]
    Intensity {
        /// The value given.
        got: f64,
    },
    /// A position with a NaN or infinite coordinate.
    #[error("expected a finite world position, got {got:?}")]
    Position {
        /// The value given.
        got: [f64; 3],
    },
}

impl Light {
    /// A light of `colour` (linear RGB, each ≥ 0) scaled by `intensity` (≥ 0).
    pub fn new(source: LightSource, colour: [f64; 3], intensity: f64) -> Result<Light, LightError> {
        if colour.iter().any(|c| !(c.is_finite() && *c >= 0.0)) {
            return Err(LightError::Colour { got: colour });
        }
        if !(intensity.is_finite() && intensity >= 0.0) {
            return Err(LightError::Intensity { got: intensity });
        }
        if let LightSource::Point { position } = source {
            if !position.is_finite() {
                return Err(LightError::Position { got: position.to_array() });
            }
        }
        let radiance = colour.map(|c| c * intensity);
        if radiance.iter().any(|e| !e.is_finite()) {
            return Err(LightError::Intensity { got: intensity });
        }
        Ok(Light { source, radiance, shadows: false })
    }

    /// The same light casting shadows or not (`shadows = true`).
    pub fn with_shadows(self, shadows: bool) -> Light {
        Light { shadows, ..self }
    }

    /// Whether it casts shadows.
    pub fn shadows(&self) -> bool {
        self.shadows
    }

    /// L, the unit vector from world point `x` towards the light, and how far along it the
    /// light is (∞ for a directional light); `None` at a point light's own position.
    pub fn towards(&self, x: DVec3) -> Option<(DVec3, f64)> {
        match self.source {
            LightSource::Directional { direction } => Some((-direction.get(), f64::INFINITY)),
            LightSource::Point { position } => {
                let d = position - x;
                let len = d.length();
                (len > 0.0 && len.is_finite()).then(|| (d / len, len))
            }
        }
    }

    /// Where its rays come from.
    pub fn source(&self) -> LightSource {
        self.source
    }

    /// E = intensity · colour.
    pub fn radiance(&self) -> [f64; 3] {
        self.radiance
    }
}

/// An object's Blinn–Phong coefficients (SPEC §6), each finite and ≥ 0.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Shading {
    ambient: f64,
    diffuse: f64,
    specular: f64,
    shininess: f64,
}

/// Which of a material's coefficients is refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ShadingField {
    /// `ambient`.
    Ambient,
    /// `diffuse`.
    Diffuse,
    /// `specular`.
    Specular,
    /// `shininess`.
    Shininess,
}

impl ShadingField {
    /// The key's name.
    pub fn name(self) -> &'static str {
        match self {
            ShadingField::Ambient => "ambient",
            ShadingField::Diffuse => "diffuse",
            ShadingField::Specular => "specular",
            ShadingField::Shininess => "shininess",
        }
    }
}

impl Shading {
    /// SPEC §6's defaults: ambient 0, diffuse 0.7, specular 0.2, shininess 10.
    pub const DEFAULT: Shading = Shading { ambient: 0.0, diffuse: 0.7, specular: 0.2, shininess: 10.0 };

    /// A material; the error names the first coefficient that is negative or not finite.
    pub fn new(ambient: f64, diffuse: f64, specular: f64, shininess: f64) -> Result<Shading, ShadingField> {
        for (v, field) in [
            (ambient, ShadingField::Ambient),
            (diffuse, ShadingField::Diffuse),
            (specular, ShadingField::Specular),
            (shininess, ShadingField::Shininess),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(field);
            }
        }
        Ok(Shading { ambient, diffuse, specular, shininess })
    }

    /// The ambient coefficient.
    pub fn ambient(&self) -> f64 {
        self.ambient
    }

    /// The diffuse coefficient.
    pub fn diffuse(&self) -> f64 {
        self.diffuse
    }

    /// The specular coefficient.
    pub fn specular(&self) -> f64 {
        self.specular
    }

    /// The specular exponent.
    pub fn shininess(&self) -> f64 {
        self.shininess
    }
}

/// The transmittance towards one light through the *other* objects of a scene, on a lattice
/// over one object's box (`render::shadow` computes it): lattice point (i, j, k) lies at box
/// coordinates (i/(n₀−1), j/(n₁−1), k/(n₂−1)), and a point between them takes the trilinear
/// blend ([`Transmittance::at`]). Every value is in [0, 1].
#[derive(Clone, Debug, PartialEq)]
pub struct Transmittance {
    dims: [u32; 3],
    values: Arc<[f32]>,
}

/// Why a lattice of transmittances is refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TransmittanceError {
    /// A side with fewer than two points, or more than [`Transmittance::MAX_SIDE`].
    #[error("expected 2 to {max} lattice points a side, got {got:?}", max = Transmittance::MAX_SIDE)]
    Dims {
        /// The sides given.
        got: [u32; 3],
    },
    /// Not one value per lattice point.
    #[error("expected {expected} values (one per lattice point), got {got}")]
    Length {
        /// Lattice points.
        expected: usize,
        /// Values given.
        got: usize,
    },
    /// A value outside [0, 1] (or NaN).
    #[error("expected transmittances in [0, 1], got {got} at lattice point {index}")]
    Value {
        /// Its index.
        index: usize,
        /// The value.
        got: f32,
    },
}

impl Transmittance {
    /// The most lattice points along one side.
    pub const MAX_SIDE: u32 = 1024;

    /// A lattice of `dims` points whose values are `values`, x fastest.
    pub fn new(dims: [u32; 3], values: Vec<f32>) -> Result<Transmittance, TransmittanceError> {
        if dims.iter().any(|&n| !(2..=Transmittance::MAX_SIDE).contains(&n)) {
            return Err(TransmittanceError::Dims { got: dims });
        }
        let expected = dims.iter().map(|&n| n as usize).product();
        if values.len() != expected {
            return Err(TransmittanceError::Length { expected, got: values.len() });
        }
        if let Some((index, &got)) = values.iter().enumerate().find(|(_, v)| !(0.0..=1.0).contains(*v)) {
            return Err(TransmittanceError::Value { index, got });
        }
        Ok(Transmittance { dims, values: values.into() })
    }

    /// Lattice points per side.
    pub fn dims(&self) -> [u32; 3] {
        self.dims
    }

    /// The values, x fastest.
    pub fn values(&self) -> &[f32] {
        &self.values
    }

    /// The transmittance at box coordinates `q` (clamped to the box): the trilinear blend of
    /// the eight lattice points around it.
    #[inline]
    pub fn at(&self, q: DVec3) -> f64 {
        let mut base = [0usize; 3];
        let mut frac = [0.0f64; 3];
        for a in 0..3 {
            let last = f64::from(self.dims[a] - 1);
            let u = (q[a] * last).clamp(0.0, last);
            let i = (u.floor() as usize).min(self.dims[a] as usize - 2);
            base[a] = i;
            frac[a] = u - i as f64;
        }
        let (nx, ny) = (self.dims[0] as usize, self.dims[1] as usize);
        let at = |i: usize, j: usize, k: usize| f64::from(self.values[i + nx * (j + ny * k)]);
        let [i, j, k] = base;
        let [fx, fy, fz] = frac;
        let lerp = |a: f64, b: f64, f: f64| a + (b - a) * f;
        let x00 = lerp(at(i, j, k), at(i + 1, j, k), fx);
        let x10 = lerp(at(i, j + 1, k), at(i + 1, j + 1, k), fx);
        let x01 = lerp(at(i, j, k + 1), at(i + 1, j, k + 1), fx);
        let x11 = lerp(at(i, j + 1, k + 1), at(i + 1, j + 1, k + 1), fx);
        lerp(lerp(x00, x10, fy), lerp(x01, x11, fy), fz)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unit_vectors_are_normalised_and_never_zero() {
        let u = UnitVector::new(DVec3::new(0.0, -3.0, -4.0)).unwrap();
        assert!((u.get().length() - 1.0).abs() < 1e-15);
        assert!((u.get() - DVec3::new(0.0, -0.6, -0.8)).length() < 1e-15);
        assert_eq!(UnitVector::new(DVec3::ZERO), None);
        assert_eq!(UnitVector::new(DVec3::new(f64::NAN, 1.0, 0.0)), None);
        assert_eq!(UnitVector::new(DVec3::new(f64::INFINITY, 1.0, 0.0)), None);
        // Subnormal: its square underflows, so it cannot be normalised.
        assert_eq!(UnitVector::new(DVec3::new(1e-320, 0.0, 0.0)), None);
    }

    #[test]
    fn lights_refuse_negative_or_non_finite_numbers() {
        let d = LightSource::Directional { direction: UnitVector::new(DVec3::X).unwrap() };
        assert_eq!(Light::new(d, [1.0, 0.5, 0.0], 2.0).unwrap().radiance(), [2.0, 1.0, 0.0]);
        assert!(matches!(Light::new(d, [1.0, -0.1, 0.0], 1.0), Err(LightError::Colour { .. })));
        assert!(matches!(Light::new(d, [1.0, 1.0, 1.0], -1.0), Err(LightError::Intensity { .. })));
        assert!(matches!(Light::new(d, [1e300, 1.0, 1.0], 1e300), Err(LightError::Intensity { .. })));
        let p = LightSource::Point { position: DVec3::new(0.0, f64::NAN, 0.0) };
        assert!(matches!(Light::new(p, [1.0; 3], 1.0), Err(LightError::Position { .. })));
    }

    #[test]
    fn transmittance_lattices_blend_trilinearly_and_refuse_bad_values() {
        // T = (1 + x + 2y + 4z)/8 over a 3 × 2 × 2 lattice is linear, so every blend is exact.
        let dims = [3, 2, 2];
        let f = |q: DVec3| (1.0 + q.x + 2.0 * q.y + 4.0 * q.z) / 8.0;
        let values =
            (0..12).map(|n| f(DVec3::new((n % 3) as f64 / 2.0, ((n / 3) % 2) as f64, (n / 6) as f64)) as f32).collect();
        let t = Transmittance::new(dims, values).unwrap();
        for q in [DVec3::ZERO, DVec3::ONE, DVec3::new(0.3, 0.7, 0.2), DVec3::new(0.75, 0.5, 0.9)] {
            assert!((t.at(q) - f(q)).abs() < 1e-7, "at {q}: {} vs {}", t.at(q), f(q));
        }
        // Outside the box it is clamped to the box.
        assert_eq!(t.at(DVec3::new(-1.0, 2.0, 0.5)), t.at(DVec3::new(0.0, 1.0, 0.5)));
        assert!(matches!(Transmittance::new([1, 2, 2], vec![1.0; 4]), Err(TransmittanceError::Dims { .. })));
        assert!(matches!(Transmittance::new([2, 2, 2], vec![1.0; 7]), Err(TransmittanceError::Length { .. })));
        let mut bad = vec![1.0; 8];
        bad[5] = f32::NAN;
        assert!(matches!(Transmittance::new([2, 2, 2], bad), Err(TransmittanceError::Value { index: 5, .. })));
    }

    #[test]
    fn shading_refuses_negative_coefficients_by_name() {
        assert_eq!(Shading::new(0.0, 0.7, 0.2, 10.0), Ok(Shading::DEFAULT));
        assert_eq!(Shading::new(0.0, -0.7, 0.2, 10.0), Err(ShadingField::Diffuse));
        assert_eq!(Shading::new(0.0, 0.7, 0.2, f64::NAN), Err(ShadingField::Shininess));
    }
}
