//! Front-to-back compositing (paper eq. 5, SPEC §4.4).

/// Accumulated premultiplied colour and opacity of a ray, a piece or an object's share of a
/// piece. Front-to-back compositing is associative, so a piece composited on its own and
/// then laid over the ray equals compositing its samples into the ray directly: that is what
/// lets the grouped algorithm cast pieces anywhere and combine them later.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Rgba {
    /// Σ c·α·(1 − A): colour already weighted by opacity.
    pub colour: [f64; 3],
    /// Accumulated opacity A ∈ [0, 1].
    pub alpha: f64,
}

impl Rgba {
    /// Fully transparent.
    pub const CLEAR: Rgba = Rgba { colour: [0.0; 3], alpha: 0.0 };

    /// Composites one sample of colour `c` and opacity `a` behind what is accumulated.
    #[inline(always)]
    pub fn add_sample(&mut self, c: [f64; 3], a: f64) {
        let w = a * (1.0 - self.alpha);
        for (acc, c) in self.colour.iter_mut().zip(c) {
            *acc += c * w;
        }
        self.alpha += w;
    }

    /// Composites `behind` (already accumulated on its own) behind `self`.
    #[inline]
    pub fn over(&mut self, behind: Rgba) {
        let t = 1.0 - self.alpha;
        for (acc, c) in self.colour.iter_mut().zip(behind.colour) {
            *acc += c * t;
        }
        self.alpha += behind.alpha * t;
    }

    /// Combines objects sharing one piece as co-located media (SPEC §4.4):
    /// A = 1 − Π(1 − Aᵢ), C = (Σ Cᵢ)·A / Σ Aᵢ, and C = 0 where Σ Aᵢ = 0.
    pub fn colocated(parts: impl IntoIterator<Item = Rgba>) -> Rgba {
        let mut transmittance = 1.0;
        let mut sum_c = [0.0; 3];
        let mut sum_a = 0.0;
        for p in parts {
            transmittance *= 1.0 - p.alpha;
            sum_a += p.alpha;
            for (s, c) in sum_c.iter_mut().zip(p.colour) {
                *s += c;
            }
        }
        let alpha = 1.0 - transmittance;
        if sum_a == 0.0 {
            return Rgba { colour: [0.0; 3], alpha };
        }
        Rgba { colour: sum_c.map(|c| c * alpha / sum_a), alpha }
    }

    /// The final pixel: C + background·(1 − A).
    pub fn with_background(&self, background: [f64; 3]) -> [f64; 3] {
        std::array::from_fn(|i| self.colour[i] + background[i] * (1.0 - self.alpha))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn piecewise_compositing_equals_sample_by_sample() {
        let samples = [([0.9, 0.1, 0.2], 0.3), ([0.2, 0.8, 0.1], 0.5), ([0.4, 0.4, 0.9], 0.25), ([1.0, 1.0, 1.0], 0.7)];
        let mut direct = Rgba::CLEAR;
        samples.iter().for_each(|&(c, a)| direct.add_sample(c, a));
        let (mut front, mut back) = (Rgba::CLEAR, Rgba::CLEAR);
        samples[..2].iter().for_each(|&(c, a)| front.add_sample(c, a));
        samples[2..].iter().for_each(|&(c, a)| back.add_sample(c, a));
        front.over(back);
        for i in 0..3 {
            assert!((front.colour[i] - direct.colour[i]).abs() < 1e-15);
        }
        assert!((front.alpha - direct.alpha).abs() < 1e-15);
    }

    #[test]
    fn colocated_media_multiply_transmittance_and_share_colour_by_opacity() {
        let a = Rgba { colour: [0.5, 0.0, 0.0], alpha: 0.5 };
        let b = Rgba { colour: [0.0, 0.25, 0.0], alpha: 0.25 };
        let m = Rgba::colocated([a, b]);
        assert!((m.alpha - (1.0 - 0.5 * 0.75)).abs() < 1e-15);
        assert!((m.colour[0] - 0.5 * m.alpha / 0.75).abs() < 1e-15);
        assert!((m.colour[1] - 0.25 * m.alpha / 0.75).abs() < 1e-15);
        assert_eq!(Rgba::colocated([Rgba::CLEAR, Rgba::CLEAR]), Rgba::CLEAR);
    }

    #[test]
    fn background_fills_what_is_left() {
        let p = Rgba { colour: [0.2, 0.2, 0.2], alpha: 0.6 };
        let px = p.with_background([1.0, 0.5, 0.0]);
        assert!((px[0] - 0.6).abs() < 1e-15 && (px[1] - 0.4).abs() < 1e-15 && (px[2] - 0.2).abs() < 1e-15);
    }
}
