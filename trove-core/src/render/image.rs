//! The rendered image of linear values, for the library's callers that read them (accuracy,
//! numerics), and the two file forms' encoders: an 8-bit PNG (SPEC §4.4's quantisation) and
//! an unquantised Portable FloatMap. Files are written through [`Raster`], the compact form
//! the command line renders into.

use std::path::Path;

use super::error::{OutputError, RenderError};
use super::raster::{is_pfm, Raster};

/// Linear RGB pixels, row 0 at the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    width: u32,
    height: u32,
    pixels: Vec<[f64; 3]>,
}

impl Image {
    /// An image from row-major pixels; `pixels.len()` must be `width · height`.
    pub fn new(width: u32, height: u32, pixels: Vec<[f64; 3]>) -> Image {
        assert_eq!(pixels.len(), width as usize * height as usize, "pixel count");
        Image { width, height, pixels }
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Pixel (col, row).
    pub fn pixel(&self, col: u32, row: u32) -> [f64; 3] {
        self.pixels[(row * self.width + col) as usize]
    }

    /// All pixels, row-major.
    pub fn pixels(&self) -> &[[f64; 3]] {
        &self.pixels
    }

    /// All pixels, row-major, for the composition step to fill.
    pub(super) fn pixels_mut(&mut self) -> &mut [[f64; 3]] {
        &mut self.pixels
    }

    /// round(255 · clamp(C, 0, 1)) per channel, half away from zero, no gamma.
    pub fn to_rgb8(&self) -> Vec<u8> {
        self.pixels.iter().flat_map(|p| p.map(quantize)).collect()
    }

    /// The linear values as f32, row-major: what a PFM stores.
    pub fn to_rgb32f(&self) -> Vec<f32> {
        self.pixels.iter().flat_map(|p| p.map(|c| c as f32)).collect()
    }

    /// Writes a PNG, or a PFM when the path ends in `.pfm`, through [`Raster::save`].
    pub fn save(&self, path: &Path) -> Result<(), RenderError> {
        Raster::from_image(self, is_pfm(path)).save(path)
    }

    /// The PNG file's bytes.
    pub fn encode_png(&self) -> Result<Vec<u8>, OutputError> {
        encode_png(self.width, self.height, &self.to_rgb8())
    }

    /// Largest per-channel difference between two images' linear values.
    pub fn max_abs_difference(&self, other: &Image) -> f64 {
        assert_eq!((self.width, self.height), (other.width, other.height), "image sizes");
        self.pixels
            .iter()
            .zip(&other.pixels)
            .flat_map(|(p, q)| (0..3).map(move |i| (p[i] - q[i]).abs()))
            .fold(0.0, f64::max)
    }

    /// Largest per-channel difference in 8-bit levels between two images' PNG bytes.
    pub fn max_byte_difference(&self, other: &Image) -> u8 {
        self.to_rgb8().iter().zip(other.to_rgb8()).map(|(a, b)| a.abs_diff(b)).max().unwrap_or(0)
    }

    /// Peak signal-to-noise ratio in dB on the linear values (peak 1), infinite when equal.
    pub fn psnr(&self, other: &Image) -> f64 {
        let n = (self.pixels.len() * 3) as f64;
        let mse: f64 = self
            .pixels
            .iter()
            .zip(&other.pixels)
            .flat_map(|(a, b)| (0..3).map(move |i| (a[i] - b[i]).powi(2)))
            .sum::<f64>()
            / n;
        if mse == 0.0 {
            f64::INFINITY
        } else {
            -10.0 * mse.log10()
        }
    }
}

/// The PNG byte of a linear value (SPEC §4.4): round(255 · clamp(c, 0, 1)), half away from
/// zero. Every output path uses this one function, so local mode and the farm agree.
///
/// Without a call: on x86-64's baseline (no SSE4.1) `f64::round` is a call into libm, made
/// once per channel of every pixel. Rounding x ∈ [0, 255] half away from zero is its
/// integer part, plus one when the fraction is at least ½; the fraction `x − ⌊x⌋` is exact
/// in f64, so this is `f64::round`'s result for every input (NaN: 0), which the tests check
/// on every half-step boundary.
#[inline]
pub fn quantize(c: f64) -> u8 {
    let x = 255.0 * c.clamp(0.0, 1.0);
    let whole = x as u32;
    (whole + u32::from(x - whole as f64 >= 0.5)) as u8
}

/// An 8-bit RGB PNG of `rgb` (row-major, row 0 at the top).
pub fn encode_png(width: u32, height: u32, rgb: &[u8]) -> Result<Vec<u8>, OutputError> {
    let mut out = Vec::new();
    let encoder = image::codecs::png::PngEncoder::new(&mut out);
    image::ImageEncoder::write_image(encoder, rgb, width, height, image::ExtendedColorType::Rgb8)?;
    Ok(out)
}

/// A PFM of `rgb` (row-major, row 0 at the top): "PF", dimensions, a negative scale for
/// little-endian, then rows bottom to top, as pbrt and other renderers write it.
pub fn encode_pfm(width: u32, height: u32, rgb: &[f32]) -> Vec<u8> {
    let mut out = Vec::with_capacity(rgb.len() * 4 + 32);
    out.extend_from_slice(format!("PF\n{width} {height}\n-1.0\n").as_bytes());
    for row in rgb.chunks(width as usize * 3).rev() {
        for c in row {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantize_rounds_as_f64_round_does_for_every_input() {
        let mut values = vec![f64::NAN, f64::INFINITY, f64::NEG_INFINITY, -0.0, 0.0, -1.0, 2.0, f64::MIN_POSITIVE];
        // Every level and every half-step boundary of 255·c, with its neighbours in c.
        for k in 0..=510 {
            let c = k as f64 / 510.0;
            let mut lo = c;
            let mut hi = c;
            for _ in 0..4 {
                values.extend([lo, hi]);
                lo = f64::from_bits(lo.to_bits().saturating_sub(1));
                hi = f64::from_bits(hi.to_bits() + 1);
            }
            // Inputs whose scaled value lies next to a half-step, whatever c rounds to.
            let half = (k as f64) / 2.0;
            values.extend([half / 255.0, (half - 1e-12) / 255.0, (half + 1e-12) / 255.0]);
        }
        let mut next = crate::testing::numbers(0x853c_49e6_748f_ea9b);
        for _ in 0..200_000 {
            values.push(next(1 << 31) as f64 / (1u64 << 31) as f64 * 1.2 - 0.1);
        }
        for c in values {
            assert_eq!(quantize(c), (255.0 * c.clamp(0.0, 1.0)).round() as u8, "{c:e}");
        }
    }

    #[test]
    fn bytes_round_half_away_from_zero_and_clamp() {
        let img = Image::new(2, 1, vec![[0.5 / 255.0, 1.5 / 255.0, 2.0], [-1.0, 254.5 / 255.0, 0.0]]);
        assert_eq!(img.to_rgb8(), vec![1, 2, 255, 0, 255, 0]);
    }

    /// The whole round trip is checked against a reader in `trove-tests`.
    #[test]
    fn pfm_is_little_endian_and_bottom_to_top() {
        let img = Image::new(2, 2, vec![[0.1, 0.2, 0.3], [0.4, 0.5, 0.6], [0.7, 0.8, 0.9], [1.5, -0.5, 0.0]]);
        let path = std::env::temp_dir().join(format!("trove-pfm-{}.pfm", std::process::id()));
        img.save(&path).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::remove_file(&path).ok();
        assert!(bytes.starts_with(b"PF\n2 2\n-1.0\n"));
        assert_eq!(bytes.len(), 12 + 4 * 3 * 4);
        // The first stored row is the image's bottom row.
        let first = f32::from_le_bytes(bytes[12..16].try_into().unwrap());
        assert!((first - 0.7).abs() < 1e-7);
    }
}
