//! Colour and opacity mapping functions (paper §2.3.2–2.3.3, SPEC §3.2).
//!
//! Classification happens after interpolation: the sampler interpolates the channel a map
//! reads, then calls [`ColourMap::map`] or [`OpacityMap::map`]. Results are clamped to
//! [0, 1]; a non-finite result is `None` and the sample contributes nothing.

use crate::dataset::ChannelName;

/// Which channels a raw colour map reads, decided once at scene load from what the
/// dataset has (SPEC §3.2: red/green/blue, else grey, else bit).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RawColour {
    /// `red`, `green`, `blue`, each /255.
    Rgb,
    /// `grey` /255 as (g, g, g).
    Grey,
    /// `bit` as (b, b, b).
    Bit,
}

impl RawColour {
    /// The channels read, in r, g, b order (repeated for grey and bit).
    pub fn channels(self) -> [ChannelName; 3] {
        match self {
            RawColour::Rgb => [ChannelName::Red, ChannelName::Green, ChannelName::Blue],
            RawColour::Grey => [ChannelName::Grey; 3],
            RawColour::Bit => [ChannelName::Bit; 3],
        }
    }
}

/// A look-up table: `s − 1` strictly increasing bounds split the line into `s` domains.
#[derive(Clone, Debug, PartialEq)]
pub struct Lut<T> {
    bounds: Vec<f64>,
    entries: Vec<T>,
}

impl<T: Copy> Lut<T> {
    /// `entries.len() == bounds.len() + 1` and strictly increasing finite bounds are checked
    /// by the scene validator; this constructor trusts them.
    pub(crate) fn new(bounds: Vec<f64>, entries: Vec<T>) -> Lut<T> {
        debug_assert_eq!(entries.len(), bounds.len() + 1);
        Lut { bounds, entries }
    }

    /// v < d1 → e1; d(i−1) ≤ v < d(i) → e(i); v ≥ d(s−1) → es. A value equal to a bound
    /// maps to the upper domain.
    #[inline]
    pub fn lookup(&self, v: f64) -> T {
        self.entries[self.bounds.partition_point(|&d| d <= v)]
    }
}

/// Polynomial coefficients in ascending powers, evaluated by Horner in f64.
#[derive(Clone, Debug, PartialEq)]
pub struct Polynomial(pub Vec<f64>);

impl Polynomial {
    /// p(v).
    #[inline]
    pub fn eval(&self, v: f64) -> f64 {
        self.0.iter().rev().fold(0.0, |acc, &c| acc * v + c)
    }
}

/// A piecewise-linear ramp through points with non-decreasing abscissae, constant beyond
/// the ends. Where two points share an abscissa the ramp steps there, taking the later
/// point's value at the step itself (as a LUT takes its upper domain at a bound).
#[derive(Clone, Debug, PartialEq)]
pub struct Ramp<const N: usize> {
    xs: Vec<f64>,
    ys: Vec<[f64; N]>,
}

impl<const N: usize> Ramp<N> {
    /// Points are validated (finite, non-decreasing, at least one) by the scene validator.
    pub(crate) fn new(points: Vec<(f64, [f64; N])>) -> Ramp<N> {
        let (xs, ys) = points.into_iter().unzip();
        Ramp { xs, ys }
    }

    /// The ramp's value at `v`.
    #[inline]
    pub fn eval(&self, v: f64) -> [f64; N] {
        let i = self.xs.partition_point(|&x| x <= v);
        if i == 0 {
            return self.ys[0];
        }
        if i == self.xs.len() {
            return self.ys[i - 1];
        }
        let (x0, x1) = (self.xs[i - 1], self.xs[i]);
        // x0 <= v < x1, so the denominator is positive.
        let t = (v - x0) / (x1 - x0);
        std::array::from_fn(|c| self.ys[i - 1][c] + t * (self.ys[i][c] - self.ys[i - 1][c]))
    }
}

/// A colour mapping function 𝒞(v) (SPEC §3.2).
#[derive(Clone, Debug, PartialEq)]
pub enum ColourMap {
    /// Colour stored in the dataset's colour channels.
    Raw(RawColour),
    /// A look-up table over the voxel channel.
    Lut(Lut<[f64; 3]>),
    /// One polynomial per component over the voxel channel (also `constant` … `cubic`).
    Polynomial([Polynomial; 3]),
    /// A piecewise-linear ramp over the voxel channel.
    Ramp(Ramp<3>),
}

impl ColourMap {
    /// Whether the map reads the `voxel` channel.
    pub fn reads_voxel(&self) -> bool {
        match self {
            ColourMap::Raw(_) => false,
            ColourMap::Polynomial(p) => p.iter().any(|p| p.0.len() > 1),
            _ => true,
        }
    }

    /// 𝒞(v) for an interpolated voxel value, clamped to [0, 1]; `None` when not finite.
    /// For `Raw`, `v` is ignored: use [`ColourMap::map_raw`].
    #[inline]
    pub fn map(&self, v: f64) -> Option<[f64; 3]> {
        let c = match self {
            ColourMap::Raw(_) => return None,
            ColourMap::Lut(l) => l.lookup(v),
            ColourMap::Polynomial(p) => [p[0].eval(v), p[1].eval(v), p[2].eval(v)],
            ColourMap::Ramp(r) => r.eval(v),
        };
        clamp3(c)
    }

    /// Raw colour from interpolated channel values (bytes /255, bits as is).
    #[inline]
    pub fn map_raw(kind: RawColour, rgb: [f64; 3]) -> Option<[f64; 3]> {
        let scale = if kind == RawColour::Bit { 1.0 } else { 1.0 / 255.0 };
        clamp3(rgb.map(|c| c * scale))
    }
}

/// An opacity mapping function 𝒪(v) (SPEC §3.2).
#[derive(Clone, Debug, PartialEq)]
pub enum OpacityMap {
    /// Opacity from the `alpha` channel, /255.
    Raw,
    /// A look-up table over the voxel channel.
    Lut(Lut<f64>),
    /// A polynomial over the voxel channel (also `constant` … `cubic`).
    Polynomial(Polynomial),
    /// A piecewise-linear ramp over the voxel channel.
    Ramp(Ramp<1>),
}

impl OpacityMap {
    /// Whether the map reads the `voxel` channel.
    pub fn reads_voxel(&self) -> bool {
        match self {
            OpacityMap::Raw => false,
            OpacityMap::Polynomial(p) => p.0.len() > 1,
            _ => true,
        }
    }

    /// The opacity when the map ignores the data (a constant), so empty space can be
    /// recognised without interpolating.
    pub fn constant(&self) -> Option<f64> {
        match self {
            OpacityMap::Polynomial(p) if p.0.len() <= 1 => Some(p.eval(0.0).clamp(0.0, 1.0)),
            _ => None,
        }
    }

    /// 𝒪(v), clamped to [0, 1]; `None` when not finite. For `Raw`, pass alpha /255 through
    /// [`OpacityMap::map_raw`].
    #[inline]
    pub fn map(&self, v: f64) -> Option<f64> {
        let a = match self {
            OpacityMap::Raw => return None,
            OpacityMap::Lut(l) => l.lookup(v),
            OpacityMap::Polynomial(p) => p.eval(v),
            OpacityMap::Ramp(r) => r.eval(v)[0],
        };
        clamp1(a)
    }

    /// Raw opacity from an interpolated alpha byte value.
    #[inline]
    pub fn map_raw(alpha: f64) -> Option<f64> {
        clamp1(alpha / 255.0)
    }
}

#[inline]
fn clamp1(a: f64) -> Option<f64> {
    a.is_finite().then(|| a.clamp(0.0, 1.0))
}

#[inline]
fn clamp3(c: [f64; 3]) -> Option<[f64; 3]> {
    c.iter().all(|x| x.is_finite()).then(|| c.map(|x| x.clamp(0.0, 1.0)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lut_bound_maps_to_upper_domain() {
        let l = Lut::new(vec![10.0, 20.0], vec![0.1, 0.2, 0.3]);
        assert_eq!(l.lookup(9.999), 0.1);
        assert_eq!(l.lookup(10.0), 0.2);
        assert_eq!(l.lookup(19.99), 0.2);
        assert_eq!(l.lookup(20.0), 0.3);
        assert_eq!(l.lookup(f64::INFINITY), 0.3);
        assert_eq!(l.lookup(f64::NEG_INFINITY), 0.1);
    }

    #[test]
    fn polynomial_is_horner_in_ascending_powers_and_clamps() {
        let p = Polynomial(vec![1.0, -2.0, 3.0]); // 1 - 2v + 3v^2
        assert_eq!(p.eval(2.0), 9.0);
        let o = OpacityMap::Polynomial(p);
        assert_eq!(o.map(2.0), Some(1.0));
        assert_eq!(o.map(0.5), Some(0.75));
        assert_eq!(OpacityMap::Polynomial(Polynomial(vec![-0.5])).map(3.0), Some(0.0));
        assert_eq!(o.map(f64::NAN), None);
    }

    #[test]
    fn ramp_is_piecewise_linear_constant_beyond_ends_and_steps_upward() {
        let r = Ramp::new(vec![(0.0, [0.0]), (10.0, [1.0]), (10.0, [0.2]), (20.0, [0.4])]);
        assert_eq!(r.eval(-5.0), [0.0]);
        assert_eq!(r.eval(5.0), [0.5]);
        assert_eq!(r.eval(10.0), [0.2]);
        assert!((r.eval(15.0)[0] - 0.3).abs() < 1e-15);
        assert_eq!(r.eval(25.0), [0.4]);
        let o = OpacityMap::Ramp(Ramp::new(vec![(0.0, [-1.0]), (1.0, [2.0])]));
        assert_eq!(o.map(-3.0), Some(0.0));
        assert_eq!(o.map(9.0), Some(1.0));
    }

    #[test]
    fn raw_colour_scales_bytes_but_not_bits() {
        assert_eq!(ColourMap::map_raw(RawColour::Rgb, [255.0, 0.0, 51.0]), Some([1.0, 0.0, 0.2]));
        assert_eq!(ColourMap::map_raw(RawColour::Bit, [1.0, 1.0, 1.0]), Some([1.0; 3]));
        assert_eq!(ColourMap::map_raw(RawColour::Grey, [f64::NAN, 0.0, 0.0]), None);
    }
}
