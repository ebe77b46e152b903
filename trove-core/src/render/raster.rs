//! The image a render writes, as compact as its file: 8-bit RGB (SPEC §4.4's quantisation)
//! always, and the linear values as f32 only when a PFM is asked for. Both drivers fill one
//! band of rows at a time with [`Raster::composite_rows`], the one composition step: the
//! farm's into a band-sized raster on a blocking thread, placed into the job's image as it
//! arrives ([`Raster::place`]); local mode's straight into the image. So an 8192² PNG
//! render holds 3 bytes a pixel (192 MiB), not the 24 of [`Image`]'s f64 values (1.5 GiB),
//! and the two modes quantise the same f64 composite with the same rounding ([`quantize`](super::quantize)), byte
//! for byte.
//!
//! [`Image`] stays the library's form where linear values are read (accuracy, numerics);
//! it is composited by the same step ([`Canvas`]), and written through this type.

use std::path::Path;

use rayon::prelude::*;

use super::error::{OutputError, RenderError};
use super::image::{encode_pfm, encode_png, quantize, Image};
use super::schedule::Scheduler;

/// Pixels, row 0 at the top: 8-bit RGB, and linear f32 RGB when asked for.
#[derive(Clone, Debug, PartialEq)]
pub struct Raster {
    width: u32,
    height: u32,
    rgb8: Vec<u8>,
    rgb32f: Option<Vec<f32>>,
}

impl Raster {
    /// A black raster; `linear` keeps the f32 values a PFM needs beside the bytes.
    pub fn new(width: u32, height: u32, linear: bool) -> Raster {
        let values = width as usize * height as usize * 3;
        Raster { width, height, rgb8: vec![0; values], rgb32f: linear.then(|| vec![0.0; values]) }
    }

    /// `image` quantised (and its linear values as f32 when `linear`), as the composition
    /// step would have written it.
    pub fn from_image(image: &Image, linear: bool) -> Raster {
        Raster {
            width: image.width(),
            height: image.height(),
            rgb8: image.to_rgb8(),
            rgb32f: linear.then(|| image.to_rgb32f()),
        }
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The 8-bit values, row-major RGB: what a PNG stores.
    pub fn rgb8(&self) -> &[u8] {
        &self.rgb8
    }

    /// The linear values as f32, row-major RGB, when the raster keeps them.
    pub fn rgb32f(&self) -> Option<&[f32]> {
        self.rgb32f.as_deref()
    }

    /// Bytes the raster holds on the heap: what a render's image costs in memory.
    pub fn heap_bytes(&self) -> usize {
        self.rgb8.capacity() + self.rgb32f.as_ref().map_or(0, |f| f.capacity() * size_of::<f32>())
    }

    /// Composites every ray of `scheduler` (a band whose every task is cast or culled) over
    /// `background` into rows `first_row..` (in parallel, never holding the band's f64
    /// values): the one composition step of both drivers.
    pub fn composite_rows(&mut self, first_row: u32, scheduler: &Scheduler, background: [f64; 3]) {
        let values = self.band_values(first_row, scheduler);
        let rgb8 = &mut self.rgb8[values.clone()];
        // Runs of pixels per parallel item, each pixel composited as alone: the same bytes,
        // without a rayon item (and its splitting) per pixel.
        const RUN: usize = 256;
        match &mut self.rgb32f {
            Some(all) => rgb8
                .par_chunks_mut(3 * RUN)
                .zip(all[values].par_chunks_mut(3 * RUN))
                .enumerate()
                .for_each(|(run, (run8, run32))| composite_run(scheduler, run * RUN, background, run8, Some(run32))),
            None => rgb8
                .par_chunks_mut(3 * RUN)
                .enumerate()
                .for_each(|(run, run8)| composite_run(scheduler, run * RUN, background, run8, None)),
        }
    }

    /// Copies `band` (a raster as wide as this one, composited apart) into rows `first_row..`.
    pub fn place(&mut self, first_row: u32, band: &Raster) {
        assert_eq!(band.width, self.width, "band width");
        assert!(first_row + band.height <= self.height, "band rows inside the image");
        let start = first_row as usize * self.width as usize * 3;
        self.rgb8[start..start + band.rgb8.len()].copy_from_slice(&band.rgb8);
        if let (Some(all), Some(part)) = (&mut self.rgb32f, &band.rgb32f) {
            all[start..start + part.len()].copy_from_slice(part);
        }
    }

    /// The PNG file's bytes.
    pub fn encode_png(&self) -> Result<Vec<u8>, OutputError> {
        encode_png(self.width, self.height, &self.rgb8)
    }

    /// The PFM file's bytes, when the raster keeps linear values.
    pub fn encode_pfm(&self) -> Option<Vec<u8>> {
        self.rgb32f.as_ref().map(|f| encode_pfm(self.width, self.height, f))
    }

    /// Writes a PNG, or a PFM when the path ends in `.pfm` (which needs the linear values:
    /// make the raster with them).
    pub fn save(&self, path: &Path) -> Result<(), RenderError> {
        let bytes = if is_pfm(path) {
            self.encode_pfm().ok_or_else(|| {
                OutputError::Io(std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    "a PFM needs linear values, and this image kept only 8-bit ones",
                ))
            })
        } else {
            self.encode_png()
        };
        bytes
            .and_then(|b| std::fs::write(path, b).map_err(OutputError::from))
            .map_err(|source| RenderError::Output { path: path.to_path_buf(), source })
    }

    /// The range of values (3 per pixel) that `scheduler`'s rays cover from `first_row`.
    fn band_values(&self, first_row: u32, scheduler: &Scheduler) -> std::ops::Range<usize> {
        band_values(self.width, self.height, first_row, scheduler, 3)
    }
}

/// Whether `path` names a PFM (else a PNG is written).
pub(super) fn is_pfm(path: &Path) -> bool {
    path.extension().is_some_and(|e| e.eq_ignore_ascii_case("pfm"))
}

/// The pixels of rays `first..` (as many as `rgb8` holds) composited into `rgb8`, and
/// into `rgb32f` as f32 where given: one run of [`Raster::composite_rows`], a loop of its
/// own rather than the body of rayon's closure.
#[inline(never)]
fn composite_run(
    scheduler: &Scheduler,
    first: usize,
    background: [f64; 3],
    rgb8: &mut [u8],
    rgb32f: Option<&mut [f32]>,
) {
    let pixel = |i: usize| composite(scheduler, first + i, background);
    match rgb32f {
        Some(rgb32f) => {
            for (i, (px8, px32)) in rgb8.chunks_exact_mut(3).zip(rgb32f.chunks_exact_mut(3)).enumerate() {
                let c = pixel(i);
                px8.copy_from_slice(&c.map(quantize));
                px32.copy_from_slice(&c.map(|v| v as f32));
            }
        }
        None => {
            for (i, px) in rgb8.chunks_exact_mut(3).enumerate() {
                px.copy_from_slice(&pixel(i).map(quantize));
            }
        }
    }
}

/// Ray `r`'s pixel: its pieces front to back over `background`.
#[inline]
fn composite(scheduler: &Scheduler, r: usize, background: [f64; 3]) -> [f64; 3] {
    scheduler.composite_ray(r).with_background(background)
}

/// The range of an image's `per_pixel` values that a band's rays cover from `first_row`:
/// its rays are the rows' pixels in order.
fn band_values(
    width: u32,
    height: u32,
    first_row: u32,
    scheduler: &Scheduler,
    per_pixel: usize,
) -> std::ops::Range<usize> {
    let rays = scheduler.intersections().rays();
    let start = first_row as usize * width as usize;
    assert!(
        rays.is_multiple_of(width.max(1) as usize) && start + rays <= width as usize * height as usize,
        "a band is whole rows inside the image"
    );
    start * per_pixel..(start + rays) * per_pixel
}

/// What local mode renders onto: an [`Image`] of linear values for the library's callers,
/// a [`Raster`] for files.
pub(super) trait Canvas: Sized {
    /// A black canvas; `linear` asks a [`Raster`] to keep f32 values.
    fn blank(width: u32, height: u32, linear: bool) -> Self;
    /// The canvas holding `image`, which Algorithm 1 renders whole.
    fn from_image(image: Image, linear: bool) -> Self;
    /// [`Raster::composite_rows`]: the band's pixels, composited into rows `first_row..`.
    fn composite_rows(&mut self, first_row: u32, scheduler: &Scheduler, background: [f64; 3]);
}

impl Canvas for Raster {
    fn blank(width: u32, height: u32, linear: bool) -> Raster {
        Raster::new(width, height, linear)
    }

    fn from_image(image: Image, linear: bool) -> Raster {
        Raster::from_image(&image, linear)
    }

    fn composite_rows(&mut self, first_row: u32, scheduler: &Scheduler, background: [f64; 3]) {
        Raster::composite_rows(self, first_row, scheduler, background)
    }
}

impl Canvas for Image {
    fn blank(width: u32, height: u32, _linear: bool) -> Image {
        Image::new(width, height, vec![[0.0; 3]; width as usize * height as usize])
    }

    fn from_image(image: Image, _linear: bool) -> Image {
        image
    }

    fn composite_rows(&mut self, first_row: u32, scheduler: &Scheduler, background: [f64; 3]) {
        let values = band_values(self.width(), self.height(), first_row, scheduler, 1);
        self.pixels_mut()[values]
            .par_iter_mut()
            .enumerate()
            .for_each(|(r, px)| *px = composite(scheduler, r, background));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::{render, render_raster, Algorithm, RenderOptions};
    use crate::scene::Scene;

    /// Two overlapping objects of one 32³ radial sphere, partly translucent, with values
    /// that quantise to many levels.
    fn spheres(width: u32, height: u32) -> Scene {
        let text = format!(
            "[image]\nwidth = {width}\nheight = {height}\nbackground = [0.1, 0.2, 0.3]\n\
             [camera]\neye = [0.6, 0.7, 3.0]\ntarget = [0.5, 0.5, 0.0]\nup = [0, 1, 0]\nfov_y = 40.0\n\
             [[datasets]]\nname = \"ball\"\ndims = [32, 32, 32]\n[datasets.channels.voxel]\n\
             generator = {{ kind = \"sphere\", radius = 0.45, profile = \"radial\", value = 255 }}\n\
             [[objects]]\nname = \"front\"\ndataset = \"ball\"\n\
             colour = {{ type = \"ramp\", points = [[0, 1, 0.5, 0], [255, 1, 1, 1]] }}\n\
             opacity = {{ type = \"ramp\", points = [[0, 0], [60, 0.05], [255, 0.4]] }}\n\
             [[objects]]\nname = \"back\"\ndataset = \"ball\"\n\
             colour = {{ type = \"ramp\", points = [[0, 0, 0.5, 1], [255, 1, 1, 1]] }}\n\
             opacity = {{ type = \"ramp\", points = [[0, 0], [60, 0.05], [255, 0.4]] }}\n\
             transform = {{ matrix = [[1, 0, 0, 0.4], [0, 1, 0, 0.1], [0, 0, 1, -1.2], [0, 0, 0, 1]] }}\n"
        );
        Scene::parse(&text, "spheres.toml").unwrap()
    }

    /// The raster a file render writes is the linear render quantised, byte for byte, and
    /// its f32 values the linear ones cast: in one band, in one-row bands, and for
    /// Algorithm 1, whose whole image is converted.
    #[test]
    fn a_raster_render_is_the_linear_render_quantised() {
        let scene = spheres(37, 23);
        for (algorithm, band_memory) in
            [(Algorithm::Grouped, None), (Algorithm::Grouped, Some(1)), (Algorithm::PerRay, None)]
        {
            let options = RenderOptions { algorithm, band_memory, ..RenderOptions::default() };
            let linear = render(&scene, &options).unwrap().image;
            assert!(linear.pixels().iter().flatten().any(|&c| c > 0.2 && c < 0.8), "the scene has mid tones");
            let raster = render_raster(&scene, &options, true).unwrap().image;
            assert_eq!(raster, Raster::from_image(&linear, true), "{algorithm:?}, band memory {band_memory:?}");
            assert_eq!(raster.encode_png().unwrap(), linear.encode_png().unwrap());
            let bytes_only = render_raster(&scene, &options, false).unwrap().image;
            assert_eq!(bytes_only.rgb8(), raster.rgb8());
            assert_eq!(bytes_only.rgb32f(), None);
        }
    }

    /// A PNG render's image costs 3 bytes a pixel, a PFM render's 15; the f64 image, 24.
    #[test]
    fn a_raster_holds_three_bytes_a_pixel_and_floats_only_when_asked() {
        let scene = spheres(64, 48);
        let png = render_raster(&scene, &RenderOptions::default(), false).unwrap().image;
        assert_eq!(png.heap_bytes(), 64 * 48 * 3);
        let pfm = render_raster(&scene, &RenderOptions::default(), true).unwrap().image;
        assert_eq!(pfm.heap_bytes(), 64 * 48 * (3 + 3 * 4));
        assert_eq!((png.width(), png.height()), (64, 48));
    }

    /// A band composited apart and placed lands on its rows; the rows around it stay.
    #[test]
    fn a_placed_band_fills_its_rows_only() {
        let mut image = Raster::new(2, 3, true);
        let band = Raster { width: 2, height: 1, rgb8: vec![1, 2, 3, 4, 5, 6], rgb32f: Some(vec![0.5; 6]) };
        image.place(1, &band);
        assert_eq!(image.rgb8(), &[0, 0, 0, 0, 0, 0, 1, 2, 3, 4, 5, 6, 0, 0, 0, 0, 0, 0][..]);
        assert_eq!(image.rgb32f().unwrap()[6..12], [0.5; 6]);
        assert_eq!(image.rgb32f().unwrap()[..6], [0.0; 6]);
    }

    /// A PFM needs the linear values: a raster without them refuses to write one, and one
    /// with them writes what the f64 image's PFM holds.
    #[test]
    fn a_pfm_is_written_only_from_linear_values() {
        let linear = render(&spheres(9, 7), &RenderOptions::default()).unwrap().image;
        let dir = std::env::temp_dir().join(format!("trove-raster-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("x.pfm");
        let refused = Raster::from_image(&linear, false).save(&path);
        assert!(matches!(refused, Err(RenderError::Output { .. })), "{refused:?}");
        assert!(!path.exists());
        Raster::from_image(&linear, true).save(&path).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), encode_pfm(9, 7, &linear.to_rgb32f()));
        std::fs::remove_dir_all(&dir).ok();
    }
}
