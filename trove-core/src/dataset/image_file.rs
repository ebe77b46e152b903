//! PNG and JPEG images as datasets (`image = "..."`, SPEC §1.1): a w×h image is a dataset of
//! dims [w, h, 1] with u8 channels `red`, `green`, `blue`, and `alpha` when the image has one.
//!
//! Pixel (x, row), row 0 at the top, becomes voxel (x, h−1−row, 0), so y points up as in
//! every other dataset. Greyscale images give red = green = blue. Images with 16-bit or float
//! samples are refused (SPEC §4.5) rather than quietly cut to 8 bits.

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use image::{ColorType, ImageDecoder, ImageReader};

use super::error::DatasetError;
use super::{Channel, ChannelName, ChannelSource, DataFile, Dims};

/// The layout of an accepted image: which byte of a pixel is which component.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Layout {
    /// Grey (1 byte per pixel).
    L,
    /// Grey and alpha.
    La,
    /// Red, green, blue.
    Rgb,
    /// Red, green, blue, alpha.
    Rgba,
}

impl Layout {
    fn from_color(path: &Path, c: ColorType) -> Result<Layout, DatasetError> {
        Ok(match c {
            ColorType::L8 => Layout::L,
            ColorType::La8 => Layout::La,
            ColorType::Rgb8 => Layout::Rgb,
            ColorType::Rgba8 => Layout::Rgba,
            other => {
                return Err(DatasetError::format(
                    path,
                    format!(
                        "{other:?} images (16-bit or float samples) are not supported; \
                         TROVE reads 8-bit images only (convert the image to 8 bits per channel)"
                    ),
                ))
            }
        })
    }

    fn bytes_per_pixel(self) -> usize {
        match self {
            Layout::L => 1,
            Layout::La => 2,
            Layout::Rgb => 3,
            Layout::Rgba => 4,
        }
    }

    fn has_alpha(self) -> bool {
        matches!(self, Layout::La | Layout::Rgba)
    }

    /// Byte of a pixel holding `channel`, or `None` if the image lacks it.
    fn component(self, channel: ChannelName) -> Option<usize> {
        let grey = matches!(self, Layout::L | Layout::La);
        match channel {
            ChannelName::Red => Some(0),
            ChannelName::Green => Some(if grey { 0 } else { 1 }),
            ChannelName::Blue => Some(if grey { 0 } else { 2 }),
            ChannelName::Alpha if self.has_alpha() => Some(self.bytes_per_pixel() - 1),
            _ => None,
        }
    }
}

fn image_error(path: &Path, e: image::ImageError) -> DatasetError {
    match e {
        image::ImageError::IoError(io) => DatasetError::io(path, io),
        e => DatasetError::format(path, format!("not a readable PNG or JPEG image: {e}")),
    }
}

/// A decoder for `path`, its format found from the content, not the file name.
fn decoder(path: &Path) -> Result<impl ImageDecoder, DatasetError> {
    let file = File::open(path).map_err(|e| DatasetError::io(path, e))?;
    ImageReader::new(BufReader::new(file))
        .with_guessed_format()
        .map_err(|e| DatasetError::io(path, e))?
        .into_decoder()
        .map_err(|e| image_error(path, e))
}

/// Reads only the image header: dims and the channels the image provides (each u8).
pub fn open(path: &Path) -> Result<(Dims, Vec<(ChannelName, ChannelSource)>), DatasetError> {
    let dec = decoder(path)?;
    let layout = Layout::from_color(path, dec.color_type())?;
    let (w, h) = dec.dimensions();
    let dims = Dims::new([w as u64, h as u64, 1]).map_err(|source| DatasetError::Dims {
        path: path.to_path_buf(),
        field: "image size",
        source,
    })?;
    let mut names = vec![ChannelName::Red, ChannelName::Green, ChannelName::Blue];
    if layout.has_alpha() {
        names.push(ChannelName::Alpha);
    }
    let channels = names
        .into_iter()
        .map(|c| (c, ChannelSource::Image { file: DataFile::Local(path.to_path_buf()), channel: c }))
        .collect();
    Ok((dims, channels))
}

/// Decodes the image and returns one channel, flipped so y points up.
pub fn load(path: &Path, channel: ChannelName, dims: Dims) -> Result<Channel, DatasetError> {
    let dec = decoder(path)?;
    let layout = Layout::from_color(path, dec.color_type())?;
    let (w, h) = dec.dimensions();
    if dims.as_array() != [w, h, 1] {
        return Err(DatasetError::format(
            path,
            format!("the image is now {w}×{h}, not {}×{} as when the scene was loaded", dims.axis(0), dims.axis(1)),
        ));
    }
    let component = layout
        .component(channel)
        .ok_or_else(|| DatasetError::format(path, format!("the image has no `{channel}` channel")))?;
    let (w, h) = (w as usize, h as usize);
    let bpp = layout.bytes_per_pixel();
    let total = usize::try_from(dec.total_bytes()).map_err(|_| DatasetError::format(path, "image too large"))?;
    if Some(total) != w.checked_mul(h).and_then(|n| n.checked_mul(bpp)) {
        return Err(DatasetError::format(path, format!("the decoder reports {total} bytes for a {w}×{h} image")));
    }
    let mut pixels = vec![0u8; total];
    dec.read_image(&mut pixels).map_err(|e| image_error(path, e))?;

    let mut out = Vec::with_capacity(w * h);
    for y in 0..h {
        let row = &pixels[(h - 1 - y) * w * bpp..(h - y) * w * bpp];
        out.extend(row.chunks_exact(bpp).map(|p| p[component]));
    }
    Channel::from_u8(out, dims).map_err(|super::ChannelSizeError { expected, actual }| DatasetError::SizeMismatch {
        path: path.to_path_buf(),
        expected,
        actual,
        what: format!("a {w}×{h} image"),
    })
}

#[cfg(test)]
mod tests {
    use super::super::raw::testutil::{data_dir, TempFile};
    use super::super::VoxelType;
    use super::*;

    fn names(chs: &[(ChannelName, ChannelSource)]) -> Vec<ChannelName> {
        chs.iter().map(|c| c.0).collect()
    }

    #[test]
    fn chelsea_png_dims_flip_and_values() {
        let Some(dir) = data_dir() else { return };
        let path = dir.join("photo_chelsea.png");
        let (dims, chs) = open(&path).unwrap();
        assert_eq!(dims.as_array(), [451, 300, 1]);
        assert_eq!(names(&chs), [ChannelName::Red, ChannelName::Green, ChannelName::Blue]);
        let reference = image::open(&path).unwrap().to_rgb8();
        let h = reference.height();
        for (c, (name, src)) in chs.iter().enumerate() {
            let ch = src.load(dims).unwrap();
            assert_eq!(ch.ty(), VoxelType::U8);
            assert_eq!(load(&path, *name, dims).unwrap().value(0), ch.value(0));
            // The top row of the picture is the last y row of the dataset.
            for x in [0, 100, 225, 450] {
                assert_eq!(ch.value(dims.index(x, 299, 0)), reference.get_pixel(x as u32, 0)[c] as f32);
            }
            for (x, row) in [(0u32, 299u32), (17, 5), (300, 150), (450, 299), (222, 77)] {
                let v = ch.value(dims.index(x as usize, (h - 1 - row) as usize, 0));
                assert_eq!(v, reference.get_pixel(x, row)[c] as f32, "{name} at pixel ({x}, {row})");
            }
        }
        // The picture is not symmetric top to bottom, so a missing flip would be caught.
        let red = load(&path, ChannelName::Red, dims).unwrap();
        assert_ne!(red.value(dims.index(225, 0, 0)), reference.get_pixel(225, 0)[0] as f32);
    }

    #[test]
    fn rgba_png_has_alpha() {
        let mut img = image::RgbaImage::new(3, 2);
        for (x, y, p) in img.enumerate_pixels_mut() {
            *p = image::Rgba([x as u8 * 10, y as u8 * 20, 7, 100 + (x + 3 * y) as u8]);
        }
        let f = TempFile::new("rgba.png");
        img.save(&f.0).unwrap();
        let (dims, chs) = open(&f.0).unwrap();
        assert_eq!(dims.as_array(), [3, 2, 1]);
        assert_eq!(names(&chs), [ChannelName::Red, ChannelName::Green, ChannelName::Blue, ChannelName::Alpha]);
        let a = load(&f.0, ChannelName::Alpha, dims).unwrap();
        let g = load(&f.0, ChannelName::Green, dims).unwrap();
        // Pixel (x, row) → voxel (x, 1 − row).
        assert_eq!(a.value(dims.index(2, 1, 0)), 102.0); // pixel (2, 0)
        assert_eq!(a.value(dims.index(0, 0, 0)), 103.0); // pixel (0, 1)
        assert_eq!(g.value(dims.index(1, 0, 0)), 20.0);
        assert_eq!(load(&f.0, ChannelName::Blue, dims).unwrap().value(4), 7.0);
    }

    #[test]
    fn greyscale_gives_equal_colour_channels() {
        let img = image::GrayImage::from_fn(4, 3, |x, y| image::Luma([(x * 50 + y) as u8]));
        let f = TempFile::new("grey.png");
        img.save(&f.0).unwrap();
        let (dims, chs) = open(&f.0).unwrap();
        assert_eq!(names(&chs), [ChannelName::Red, ChannelName::Green, ChannelName::Blue]);
        for c in [ChannelName::Red, ChannelName::Green, ChannelName::Blue] {
            let ch = load(&f.0, c, dims).unwrap();
            assert_eq!(ch.value(dims.index(3, 2, 0)), 150.0, "{c}"); // pixel (3, 0)
            assert_eq!(ch.value(dims.index(1, 0, 0)), 52.0, "{c}"); // pixel (1, 2)
        }
        let e = load(&f.0, ChannelName::Alpha, dims).unwrap_err();
        assert!(e.to_string().contains("no `alpha` channel"), "{e}");

        let img = image::GrayAlphaImage::from_fn(2, 2, |x, _| image::LumaA([9, x as u8 + 1]));
        let f = TempFile::new("greyalpha.png");
        img.save(&f.0).unwrap();
        let (dims, chs) = open(&f.0).unwrap();
        assert_eq!(chs.len(), 4);
        assert_eq!(load(&f.0, ChannelName::Blue, dims).unwrap().value(1), 9.0);
        assert_eq!(load(&f.0, ChannelName::Alpha, dims).unwrap().value(1), 2.0);
    }

    #[test]
    fn sixteen_bit_png_refused() {
        let img: image::ImageBuffer<image::Luma<u16>, Vec<u16>> =
            image::ImageBuffer::from_pixel(2, 2, image::Luma([1000]));
        let f = TempFile::new("deep.png");
        img.save(&f.0).unwrap();
        let e = open(&f.0).unwrap_err();
        let msg = e.to_string();
        assert!(matches!(e, DatasetError::Format { .. }) && msg.contains("16-bit"), "{msg}");
        assert!(msg.contains(&f.0.display().to_string()), "{msg}");
    }

    #[test]
    fn jpeg_opens() {
        let img = image::RgbImage::from_pixel(16, 8, image::Rgb([200, 100, 50]));
        let f = TempFile::new("flat.jpg");
        img.save(&f.0).unwrap();
        let (dims, chs) = open(&f.0).unwrap();
        assert_eq!((dims.as_array(), chs.len()), ([16, 8, 1], 3));
        let r = load(&f.0, ChannelName::Red, dims).unwrap();
        assert!((r.value(5) - 200.0).abs() <= 3.0, "{}", r.value(5));
    }

    #[test]
    fn not_an_image_and_changed_image() {
        let f = TempFile::with("junk.png", b"this is not a picture at all");
        assert!(matches!(open(&f.0), Err(DatasetError::Format { .. })));
        let f = TempFile::new("small.png");
        image::GrayImage::new(2, 2).save(&f.0).unwrap();
        let dims = Dims::new([3, 2, 1]).unwrap();
        assert!(load(&f.0, ChannelName::Red, dims).is_err());
    }
}
