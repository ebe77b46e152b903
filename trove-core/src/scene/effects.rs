//! The effects a scene may ask for (SPEC §6): lights (`[[lights]]`) and an object's
//! Blinn–Phong material (`shading = { ... }`). Each value here holds its rules by
//! construction — a light's direction is a unit vector, colours and coefficients are finite
//! and ≥ 0 — so that the sampler reads them without checking. The loader (`load.rs`) turns
//! a refusal into a [`super::SceneErrorKind`] at the key it is about.

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
    fn shading_refuses_negative_coefficients_by_name() {
        assert_eq!(Shading::new(0.0, 0.7, 0.2, 10.0), Ok(Shading::DEFAULT));
        assert_eq!(Shading::new(0.0, -0.7, 0.2, 10.0), Err(ShadingField::Diffuse));
        assert_eq!(Shading::new(0.0, 0.7, 0.2, f64::NAN), Err(ShadingField::Shininess));
    }
}
