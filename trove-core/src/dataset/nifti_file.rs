//! NIfTI-1 single-file volumes (`.nii`, `.nii.gz`).
//!
//! The header is parsed by the `nifti` crate (byte order is detected from `dim[0]`, so
//! big-endian files work). The voxel data is then read here through the same exact-size
//! path as raw and NRRD data: an uncompressed `.nii` of a native type without scaling is
//! memory-mapped, zero copy.
//!
//! Types: uint8, uint16, uint32 and float32 stay as stored; int8, int16, int32 and float64
//! become f32 (exact except int32 beyond 2^24 and float64, which round). Other datatypes
//! (64-bit integers, complex, RGB) are refused.
//!
//! Scaling: when `scl_slope` is finite, non-zero and not the identity (slope 1, intercept 0)
//! the channel holds `value · scl_slope + scl_inter` (computed in f64, stored as f32), which
//! is the value the file means. A zero or non-finite slope means "no scaling", as the NIfTI
//! standard and nibabel read it.
//!
//! Only dims 1 to 3 are read: `dim[0]` may be larger if every further axis has size 1.
//! Header/image pairs (`.hdr` + `.img`) are refused.

use std::fs::File;
use std::io::{self, BufReader, Read, Seek, SeekFrom};
use std::path::Path;
use std::sync::Arc;

use nifti::{NiftiHeader, NiftiType};

use super::error::DatasetError;
use super::nrrd::FileChannel;
use super::raw::{self, StoredType};
use super::{Channel, ChannelSource, DataFile, Dims, Encoding, Endian, VoxelBytes, VoxelType};

/// What the header says, reduced to what loading needs.
struct Layout {
    dims: Dims,
    stored: StoredType,
    endian: Endian,
    /// Byte offset of the voxels in the (decompressed) file.
    offset: u64,
    /// `Some((slope, inter))` when values must be scaled.
    scale: Option<(f64, f64)>,
    gzip: bool,
}

impl Layout {
    fn loaded_type(&self) -> VoxelType {
        if self.scale.is_some() {
            VoxelType::F32
        } else {
            self.stored.loaded_type()
        }
    }

    fn what(&self) -> String {
        format!("dims {} of {} (NIfTI header fields `dim` and `datatype`)", self.dims, self.stored)
    }

    fn expected(&self) -> u64 {
        self.stored.byte_len(self.dims.voxel_count()).unwrap_or(u64::MAX)
    }
}

/// Reads the header of `path` and checks the voxel data's size against it (for `.nii.gz`
/// by inflating and counting the stream once, bounded as in [`raw::load`]).
pub fn open(path: &Path) -> Result<FileChannel, DatasetError> {
    let layout = read_layout(path)?;
    if layout.gzip {
        let mut reader = raw::gzip_reader(path, 0)?;
        skip_exact(path, &mut reader, layout.offset)?;
        raw::read_counted(path, reader, layout.expected(), None, || layout.what())?;
    } else {
        let len = std::fs::metadata(path).map_err(|e| DatasetError::io(path, e))?.len();
        let actual = len.saturating_sub(layout.offset);
        if len < layout.offset || actual != layout.expected() {
            return Err(DatasetError::SizeMismatch {
                path: path.to_path_buf(),
                expected: layout.expected(),
                actual,
                what: format!("{} after the {}-byte header (`vox_offset`)", layout.what(), layout.offset),
            });
        }
    }
    Ok(FileChannel {
        dims: layout.dims,
        ty: layout.loaded_type(),
        source: ChannelSource::Nifti { file: DataFile::Local(path.to_path_buf()) },
    })
}

/// Decodes the volume; `dims` is what [`open`] found, checked again in case the file changed.
pub fn load(path: &Path, dims: Dims) -> Result<Channel, DatasetError> {
    let layout = read_layout(path)?;
    if layout.dims != dims {
        return Err(DatasetError::format(
            path,
            format!("the header now gives dims {}, not {dims} as when the scene was loaded", layout.dims),
        ));
    }
    if !layout.gzip && layout.scale.is_none() {
        return raw::load(path, layout.offset, Encoding::Raw, layout.stored, layout.endian, dims);
    }
    let mut bytes = Vec::new();
    if layout.gzip {
        let mut reader = raw::gzip_reader(path, 0)?;
        skip_exact(path, &mut reader, layout.offset)?;
        raw::read_counted(path, reader, layout.expected(), Some(&mut bytes), || layout.what())?;
    } else {
        let mut file = File::open(path).map_err(|e| DatasetError::io(path, e))?;
        file.seek(SeekFrom::Start(layout.offset)).map_err(|e| DatasetError::io(path, e))?;
        raw::read_counted(path, BufReader::new(file), layout.expected(), Some(&mut bytes), || layout.what())?;
    }
    let voxels =
        usize::try_from(dims.voxel_count()).map_err(|_| DatasetError::format(path, "volume too large for memory"))?;
    let (ty, endian, bytes) = match layout.scale {
        Some((slope, inter)) => {
            let f = raw::convert_to_f32(&bytes, layout.stored, layout.endian, voxels, |v| (v * slope + inter) as f32);
            (VoxelType::F32, Endian::Little, f)
        }
        None if layout.stored.is_native() => (layout.stored.loaded_type(), layout.endian, bytes),
        None => {
            let f = raw::convert_to_f32(&bytes, layout.stored, layout.endian, voxels, |v| v as f32);
            (VoxelType::F32, Endian::Little, f)
        }
    };
    Channel::new(ty, endian, VoxelBytes::Owned(Arc::new(bytes)), dims).map_err(
        |super::ChannelSizeError { expected, actual }| DatasetError::SizeMismatch {
            path: path.to_path_buf(),
            expected,
            actual,
            what: layout.what(),
        },
    )
}

/// Discards exactly `n` bytes (the header and extensions inside a gzip stream).
fn skip_exact(path: &Path, reader: &mut impl Read, n: u64) -> Result<(), DatasetError> {
    let skipped = io::copy(&mut reader.take(n), &mut io::sink()).map_err(|e| DatasetError::io(path, e))?;
    if skipped != n {
        return Err(DatasetError::format(
            path,
            format!("the file ends after {skipped} bytes, before the voxel data at `vox_offset` {n}"),
        ));
    }
    Ok(())
}

/// What the header says, checked field by field.
fn read_layout(path: &Path) -> Result<Layout, DatasetError> {
    let (header, gzip) = read_header(path)?;
    check_magic(path, &header)?;
    let endian = match header.endianness {
        nifti::Endianness::Little => Endian::Little,
        nifti::Endianness::Big => Endian::Big,
    };
    Ok(Layout {
        dims: dims(path, &header)?,
        stored: stored_type(path, &header)?,
        endian,
        offset: vox_offset(path, &header)?,
        scale: scaling(path, &header)?,
        gzip,
    })
}

/// A refusal of header field `field`.
fn field_error(path: &Path, field: &str, message: impl std::fmt::Display) -> DatasetError {
    DatasetError::format(path, format!("NIfTI header field `{field}`: {message}"))
}

/// The parsed header, and whether the file is gzip-compressed.
fn read_header(path: &Path) -> Result<(NiftiHeader, bool), DatasetError> {
    // Compression is told by the gzip magic bytes, not the file name, so a misnamed file
    // still reads (or fails with a header error rather than garbage).
    let mut magic = [0u8; 2];
    let mut file = File::open(path).map_err(|e| DatasetError::io(path, e))?;
    let n = file.read(&mut magic).map_err(|e| DatasetError::io(path, e))?;
    let gzip = n == 2 && magic == [0x1f, 0x8b];
    let parsed = if gzip {
        NiftiHeader::from_reader(raw::gzip_reader(path, 0)?)
    } else {
        file.seek(SeekFrom::Start(0)).map_err(|e| DatasetError::io(path, e))?;
        NiftiHeader::from_reader(BufReader::new(file))
    };
    let header = parsed.map_err(|e| match e {
        nifti::NiftiError::Io(io) if io.kind() == io::ErrorKind::UnexpectedEof => {
            DatasetError::format(path, "the file is too short for a NIfTI-1 header (348 bytes)")
        }
        nifti::NiftiError::Io(io) => DatasetError::io(path, io),
        e => DatasetError::format(path, format!("not a readable NIfTI-1 header: {e}")),
    })?;
    Ok((header, gzip))
}

/// Only single-file NIfTI-1 (`n+1`).
fn check_magic(path: &Path, header: &NiftiHeader) -> Result<(), DatasetError> {
    if &header.magic == b"ni1\0" {
        return Err(field_error(
            path,
            "magic",
            "`ni1` (header and image in separate .hdr/.img files) is not supported; use a single .nii file",
        ));
    }
    if &header.magic != b"n+1\0" {
        return Err(field_error(path, "magic", format!("{:?} is not `n+1`", String::from_utf8_lossy(&header.magic))));
    }
    Ok(())
}

/// `dim`: 1 to 3 axes; more only if every further axis has size 1.
fn dims(path: &Path, header: &NiftiHeader) -> Result<Dims, DatasetError> {
    let ndim = header.dim[0] as usize;
    if !(1..=7).contains(&ndim) {
        return Err(field_error(path, "dim", format!("dim[0] = {ndim} is not between 1 and 7")));
    }
    // The file stores dims as signed 16-bit; the crate hands them back as u16.
    let d = |i: usize| -> Result<u64, DatasetError> {
        let v = header.dim[i];
        if v == 0 || v > i16::MAX as u16 {
            return Err(field_error(path, "dim", format!("dim[{i}] = {} is not a size ≥ 1", v as i16)));
        }
        Ok(v as u64)
    };
    let mut sizes = [1u64; 3];
    for (i, s) in sizes.iter_mut().enumerate().take(ndim.min(3)) {
        *s = d(i + 1)?;
    }
    for i in 4..=ndim {
        if d(i)? != 1 {
            return Err(field_error(
                path,
                "dim",
                format!("{ndim} dimensions with dim[{i}] = {}: only 3-D scalar volumes are read", header.dim[i]),
            ));
        }
    }
    Dims::new(sizes).map_err(|source| DatasetError::Dims {
        path: path.to_path_buf(),
        field: "NIfTI header field `dim`",
        source,
    })
}

/// `datatype`: scalar 8/16/32-bit integers, float32 and float64.
fn stored_type(path: &Path, header: &NiftiHeader) -> Result<StoredType, DatasetError> {
    let dt = header
        .data_type()
        .map_err(|_| field_error(path, "datatype", format!("unknown datatype code {}", header.datatype)))?;
    Ok(match dt {
        NiftiType::Uint8 => StoredType::U8,
        NiftiType::Uint16 => StoredType::U16,
        NiftiType::Uint32 => StoredType::U32,
        NiftiType::Float32 => StoredType::F32,
        NiftiType::Int8 => StoredType::I8,
        NiftiType::Int16 => StoredType::I16,
        NiftiType::Int32 => StoredType::I32,
        NiftiType::Float64 => StoredType::F64,
        other => {
            return Err(field_error(
                path,
                "datatype",
                format!(
                    "{other:?} (code {}) is not supported; scalar 8/16/32-bit integers, float32 and float64 are",
                    header.datatype
                ),
            ))
        }
    })
}

/// `vox_offset`: a whole byte offset past the 352-byte header.
fn vox_offset(path: &Path, header: &NiftiHeader) -> Result<u64, DatasetError> {
    let vo = header.vox_offset;
    if !vo.is_finite() || vo < 352.0 || vo.fract() != 0.0 || vo > u32::MAX as f32 {
        return Err(field_error(path, "vox_offset", format!("{vo} is not a whole byte offset ≥ 352")));
    }
    Ok(vo as u64)
}

/// `scl_slope`, `scl_inter`: `Some((slope, inter))` when values must be scaled (see the
/// module documentation for what counts as "no scaling").
fn scaling(path: &Path, header: &NiftiHeader) -> Result<Option<(f64, f64)>, DatasetError> {
    let (slope, inter) = (header.scl_slope as f64, header.scl_inter as f64);
    if slope == 0.0 || !slope.is_finite() || (slope == 1.0 && inter == 0.0) {
        Ok(None)
    } else if !inter.is_finite() {
        Err(field_error(path, "scl_inter", format!("{inter} is not finite")))
    } else {
        Ok(Some((slope, inter)))
    }
}

#[cfg(test)]
mod tests {
    use super::super::raw::testutil::{data_dir, gzip, TempFile};
    use super::*;

    /// Header fields read by hand from a big-endian NIfTI-1 header (offsets from nifti1.h).
    struct Hand {
        dim: [i16; 8],
        datatype: i16,
        vox_offset: f32,
        slope: f32,
        inter: f32,
    }

    fn hand_parse_be(b: &[u8]) -> Hand {
        let i16_at = |o: usize| i16::from_be_bytes([b[o], b[o + 1]]);
        let f32_at = |o: usize| f32::from_be_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]]);
        assert_eq!(i32::from_be_bytes([b[0], b[1], b[2], b[3]]), 348, "sizeof_hdr, big-endian");
        assert_eq!(&b[344..348], b"n+1\0");
        Hand {
            dim: std::array::from_fn(|i| i16_at(40 + 2 * i)),
            datatype: i16_at(70),
            vox_offset: f32_at(108),
            slope: f32_at(112),
            inter: f32_at(116),
        }
    }

    #[test]
    fn anatomical_int16_big_endian() {
        let Some(dir) = data_dir() else { return };
        let path = dir.join("anatomical_33x41x25_int16_be.nii");
        let bytes = std::fs::read(&path).unwrap();
        let h = hand_parse_be(&bytes);
        assert_eq!(h.dim[..4], [3, 33, 41, 25]);
        assert_eq!(h.datatype, 4); // int16
        assert_eq!((h.slope, h.inter), (1.0, 0.0)); // identity scaling: values used as stored
        let fc = open(&path).unwrap();
        assert_eq!(fc.dims.as_array(), [33, 41, 25]);
        assert_eq!(fc.ty, VoxelType::F32);
        assert!(matches!(&fc.source, ChannelSource::Nifti { file: DataFile::Local(p) } if *p == path));
        let ch = fc.source.load(fc.dims).unwrap();
        assert_eq!(ch.ty(), VoxelType::F32);
        let off = h.vox_offset as usize;
        let at = |i: usize| i16::from_be_bytes([bytes[off + 2 * i], bytes[off + 2 * i + 1]]) as f32;
        for idx in [0, 1, 500, fc.dims.index(16, 20, 12), fc.dims.index(10, 30, 5), 33 * 41 * 25 - 1] {
            assert_eq!(ch.value(idx), at(idx), "index {idx}");
        }
        // PROVENANCE: values −610..30393 (little-endian reading would not give this range).
        let r = ch.reader();
        let (lo, hi) =
            (0..33 * 41 * 25).map(|i| r.read(i)).fold((f32::MAX, f32::MIN), |(a, b), v| (a.min(v), b.max(v)));
        assert_eq!((lo, hi), (-610.0, 30393.0));
    }

    #[test]
    fn avg152_gzip_uint8_big_endian() {
        let Some(dir) = data_dir() else { return };
        let path = dir.join("avg152T1_RL_91x109x91_uint8_be.nii.gz");
        let mut bytes = Vec::new();
        flate2::read::GzDecoder::new(File::open(&path).unwrap()).read_to_end(&mut bytes).unwrap();
        let h = hand_parse_be(&bytes);
        assert_eq!(h.dim[..4], [3, 91, 109, 91]);
        assert_eq!(h.datatype, 2); // uint8
        assert_eq!(h.slope, 0.0); // 0 = no scaling
        let fc = open(&path).unwrap();
        assert_eq!(fc.dims.as_array(), [91, 109, 91]);
        assert_eq!(fc.ty, VoxelType::U8);
        let ch = fc.source.load(fc.dims).unwrap();
        let off = h.vox_offset as usize;
        let r = ch.reader();
        assert!((0..91 * 109 * 91).all(|i| r.read(i) == bytes[off + i] as f32));
        assert!(ch.value(fc.dims.index(45, 54, 45)) > 0.0, "the middle of the brain is not empty");
    }

    /// A little-endian NIfTI-1 header for a single file.
    fn header(dim: [i16; 8], datatype: i16, bitpix: i16, slope: f32, inter: f32, magic: &[u8; 4]) -> Vec<u8> {
        let mut h = vec![0u8; 352];
        h[0..4].copy_from_slice(&348i32.to_le_bytes());
        for (i, d) in dim.iter().enumerate() {
            h[40 + 2 * i..42 + 2 * i].copy_from_slice(&d.to_le_bytes());
        }
        h[70..72].copy_from_slice(&datatype.to_le_bytes());
        h[72..74].copy_from_slice(&bitpix.to_le_bytes());
        h[76..80].copy_from_slice(&1f32.to_le_bytes()); // pixdim[0] (qfac)
        h[108..112].copy_from_slice(&352f32.to_le_bytes());
        h[112..116].copy_from_slice(&slope.to_le_bytes());
        h[116..120].copy_from_slice(&inter.to_le_bytes());
        h[344..348].copy_from_slice(magic);
        h
    }

    fn nii(h: Vec<u8>, data: &[u8], gz: bool) -> TempFile {
        let mut b = h;
        b.extend_from_slice(data);
        if gz {
            TempFile::with("t.nii.gz", &gzip(&b))
        } else {
            TempFile::with("t.nii", &b)
        }
    }

    #[test]
    fn native_little_endian_is_mapped_and_scaling_converts() {
        let data: Vec<u8> = (0..24u16).flat_map(|v| (v * 100).to_le_bytes()).collect();
        let f = nii(header([3, 2, 3, 4, 1, 1, 1, 1], 512, 16, 0.0, 0.0, b"n+1\0"), &data, false);
        let fc = open(&f.0).unwrap();
        assert_eq!(fc.ty, VoxelType::U16);
        let ch = load(&f.0, fc.dims).unwrap();
        assert!(ch.is_mapped());
        assert_eq!(ch.value(23), 2300.0);

        // slope 0.5, intercept −3: value · slope + inter, as f32.
        let f = nii(header([3, 2, 3, 4, 1, 1, 1, 1], 512, 16, 0.5, -3.0, b"n+1\0"), &data, true);
        let fc = open(&f.0).unwrap();
        assert_eq!(fc.ty, VoxelType::F32);
        let ch = load(&f.0, fc.dims).unwrap();
        assert_eq!(ch.value(23), 2300.0 * 0.5 - 3.0);
        assert_eq!(ch.value(0), -3.0);
    }

    #[test]
    fn trailing_unit_dims_accepted_others_refused() {
        let f = nii(header([5, 2, 2, 1, 1, 1, 1, 1], 2, 8, 0.0, 0.0, b"n+1\0"), &[1, 2, 3, 4], false);
        assert_eq!(open(&f.0).unwrap().dims.as_array(), [2, 2, 1]);
        let f = nii(header([2, 4, 1, 1, 1, 1, 1, 1], 2, 8, 0.0, 0.0, b"n+1\0"), &[1, 2, 3, 4], false);
        assert_eq!(open(&f.0).unwrap().dims.as_array(), [4, 1, 1]);
        let f = nii(header([4, 2, 1, 1, 2, 1, 1, 1], 2, 8, 0.0, 0.0, b"n+1\0"), &[1, 2, 3, 4], false);
        let msg = open(&f.0).unwrap_err().to_string();
        assert!(msg.contains("`dim`") && msg.contains("dim[4] = 2"), "{msg}");
    }

    #[test]
    fn refusals() {
        let d = [3, 2, 2, 1, 1, 1, 1, 1];
        let cases: [(Vec<u8>, &str); 4] = [
            (header(d, 1024, 64, 0.0, 0.0, b"n+1\0"), "`datatype`"),
            (header(d, 128, 24, 0.0, 0.0, b"n+1\0"), "`datatype`"),
            (header(d, 2, 8, 0.0, 0.0, b"ni1\0"), "`magic`"),
            (header(d, 2, 8, 2.0, f32::NAN, b"n+1\0"), "`scl_inter`"),
        ];
        for (h, needle) in cases {
            let f = nii(h, &[0u8; 32], false);
            let e = open(&f.0).unwrap_err();
            let msg = e.to_string();
            assert!(matches!(e, DatasetError::Format { .. }) && msg.contains(needle), "{msg}");
            assert!(msg.contains(&f.0.display().to_string()), "{msg}");
        }
    }

    #[test]
    fn size_mismatch_both_encodings() {
        let h = || header([3, 2, 2, 2, 1, 1, 1, 1], 4, 16, 0.0, 0.0, b"n+1\0");
        for gz in [false, true] {
            let f = nii(h(), &[0u8; 15], gz);
            let e = open(&f.0).unwrap_err();
            assert!(matches!(e, DatasetError::SizeMismatch { expected: 16, actual: 15, .. }), "{e:?}");
            let f = nii(h(), &[0u8; 17], gz);
            assert!(matches!(open(&f.0), Err(DatasetError::SizeMismatch { expected: 16, actual: 17, .. })));
            // The file shrank after open.
            let f = nii(h(), &[0u8; 16], gz);
            let fc = open(&f.0).unwrap();
            let mut shrunk = h();
            shrunk.extend_from_slice(&[0u8; 8]);
            std::fs::write(&f.0, if gz { gzip(&shrunk) } else { shrunk }).unwrap();
            let e = load(&f.0, fc.dims).unwrap_err();
            assert!(matches!(e, DatasetError::SizeMismatch { expected: 16, actual: 8, .. }), "{e:?}");
        }
    }

    #[test]
    fn not_nifti() {
        let f = TempFile::with("junk.nii", &[1u8; 400]);
        assert!(matches!(open(&f.0), Err(DatasetError::Format { .. })));
        let f = TempFile::with("short.nii", &[1u8; 10]);
        let e = open(&f.0).unwrap_err();
        assert!(e.to_string().contains("too short"), "{e}");
    }

    #[test]
    fn compression_is_sniffed_not_named() {
        let data = [1u8, 2, 3, 4];
        let h = || header([3, 2, 2, 1, 1, 1, 1, 1], 2, 8, 0.0, 0.0, b"n+1\0");
        let mut plain = h();
        plain.extend_from_slice(&data);
        let gz_named_nii = TempFile::with("gz.nii", &gzip(&plain));
        let plain_named_gz = TempFile::with("plain.nii.gz", &plain);
        for f in [&gz_named_nii, &plain_named_gz] {
            let fc = open(&f.0).unwrap();
            let ch = load(&f.0, fc.dims).unwrap();
            assert_eq!(ch.value(3), 4.0);
        }
    }
}
