//! Headerless voxel files (`raw = "..."` channels) and the byte-level reading every file
//! format here shares: NRRD data, NIfTI volumes and raw files all end up as "`dims` numbers
//! of one stored type, from byte `offset`, raw or gzip".
//!
//! Sizes are checked exactly, never "at least": a file one slice too long is as likely a
//! wrong `dims` as a file one slice too short, and rendering it anyway would give a sheared
//! picture instead of an error (SPEC §1.1).
//!
//! Types TROVE stores natively (bit, u8, u16, u32, f32) stay as stored; uncompressed ones are
//! memory-mapped, zero copy, in either byte order (the [`Channel`] reader swaps on read).
//! The other types files commonly hold (i8, i16, i32, f64) are converted to f32 on load,
//! because the renderer reads every value as f32 anyway (SPEC §3.1): the conversion is exact
//! for i8 and i16, exact for i32 up to a magnitude of 2^24 (beyond that it rounds to the
//! nearest f32, as reading a u32 channel does), and rounds f64 to the nearest f32.

use std::fmt;
use std::fs::File;
use std::io::{self, BufReader, Read, Seek, SeekFrom};
use std::path::Path;
use std::sync::Arc;

use flate2::read::MultiGzDecoder;

use super::error::DatasetError;
use super::{Channel, ChannelSource, DataFile, Dims, Encoding, Endian, VoxelBytes, VoxelType};

/// How numbers are stored in a file, including the types converted to f32 on load.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum StoredType {
    /// One bit per voxel, LSB first, x fastest, no row padding.
    Bit,
    /// Unsigned 8-bit.
    U8,
    /// Unsigned 16-bit.
    U16,
    /// Unsigned 32-bit.
    U32,
    /// IEEE single precision.
    F32,
    /// Signed 8-bit, converted to f32 on load (exact).
    I8,
    /// Signed 16-bit, converted to f32 on load (exact).
    I16,
    /// Signed 32-bit, converted to f32 on load (exact up to magnitude 2^24).
    I32,
    /// IEEE double precision, rounded to f32 on load.
    F64,
}

impl StoredType {
    /// Bytes one voxel occupies; `None` for [`StoredType::Bit`], which packs 8 per byte.
    pub fn bytes_per_voxel(self) -> Option<u64> {
        match self {
            StoredType::Bit => None,
            StoredType::U8 | StoredType::I8 => Some(1),
            StoredType::U16 | StoredType::I16 => Some(2),
            StoredType::U32 | StoredType::I32 | StoredType::F32 => Some(4),
            StoredType::F64 => Some(8),
        }
    }

    /// Bytes `voxels` voxels occupy in the file (bit: ⌈voxels/8⌉), `None` on overflow.
    pub fn byte_len(self, voxels: u64) -> Option<u64> {
        match self.bytes_per_voxel() {
            None => Some(voxels.div_ceil(8)),
            Some(b) => voxels.checked_mul(b),
        }
    }

    /// The type the channel has once loaded: native types map to themselves, the others to
    /// f32 (see the module documentation for exactness).
    pub fn loaded_type(self) -> VoxelType {
        match self {
            StoredType::Bit => VoxelType::Bit,
            StoredType::U8 => VoxelType::U8,
            StoredType::U16 => VoxelType::U16,
            StoredType::U32 => VoxelType::U32,
            StoredType::F32 | StoredType::I8 | StoredType::I16 | StoredType::I32 | StoredType::F64 => VoxelType::F32,
        }
    }

    /// Whether loading keeps the stored bytes as they are (no conversion).
    pub fn is_native(self) -> bool {
        matches!(self, StoredType::Bit | StoredType::U8 | StoredType::U16 | StoredType::U32 | StoredType::F32)
    }

    /// Short name used in messages (`u16`, `i16`, `f64`, ...).
    pub fn name(self) -> &'static str {
        match self {
            StoredType::Bit => "bit",
            StoredType::U8 => "u8",
            StoredType::U16 => "u16",
            StoredType::U32 => "u32",
            StoredType::F32 => "f32",
            StoredType::I8 => "i8",
            StoredType::I16 => "i16",
            StoredType::I32 => "i32",
            StoredType::F64 => "f64",
        }
    }
}

impl fmt::Display for StoredType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl From<VoxelType> for StoredType {
    fn from(t: VoxelType) -> StoredType {
        match t {
            VoxelType::Bit => StoredType::Bit,
            VoxelType::U8 => StoredType::U8,
            VoxelType::U16 => StoredType::U16,
            VoxelType::U32 => StoredType::U32,
            VoxelType::F32 => StoredType::F32,
        }
    }
}

/// What a size check expects, for messages: `dims [256, 256, 113] of u16`.
fn what(dims: Dims, ty: StoredType) -> String {
    format!("dims {dims} of {ty}")
}

/// Bytes `dims` voxels of `ty` need. [`Dims`] guarantees this fits in u64 for every type
/// (at most 2^40 voxels of at most 8 bytes).
fn expected_bytes(dims: Dims, ty: StoredType) -> u64 {
    ty.byte_len(dims.voxel_count()).unwrap_or(u64::MAX)
}

/// Checks that `path` holds exactly the bytes `dims` voxels of `ty` need after `offset`
/// uncompressed bytes, and describes it as a channel source. Raw data is only measured; a
/// gzip stream is inflated and counted (not kept), so a wrong size is an error at scene load
/// rather than in the middle of a render; inflation stops once the stream is clearly too
/// long (see [`load`]).
pub fn open_with(
    path: &Path,
    offset: u64,
    encoding: Encoding,
    ty: StoredType,
    endian: Endian,
    dims: Dims,
) -> Result<ChannelSource, DatasetError> {
    match encoding {
        Encoding::Raw => check_file_size(path, offset, ty, dims)?,
        Encoding::Gzip => {
            let reader = gzip_reader(path, offset)?;
            read_counted(path, reader, expected_bytes(dims, ty), None, || what(dims, ty))?;
        }
    }
    Ok(ChannelSource::File { file: DataFile::Local(path.to_path_buf()), offset, encoding, stored: ty, endian })
}

/// Reads one channel: `dims` numbers stored as `stored` from byte `offset` of `path`.
///
/// Raw native data is memory-mapped (zero copy, byte order kept as stored). Raw data of a
/// converted type is read and converted to little-endian f32. Gzip data is inflated,
/// stopping as soon as more than the expected count arrives, then kept or converted. Sizes
/// are checked again here: the file may have changed since the scene was loaded.
pub fn load(
    path: &Path,
    offset: u64,
    encoding: Encoding,
    stored: StoredType,
    endian: Endian,
    dims: Dims,
) -> Result<Channel, DatasetError> {
    let expected = expected_bytes(dims, stored);
    let voxels =
        usize::try_from(dims.voxel_count()).map_err(|_| DatasetError::format(path, "volume too large for memory"))?;
    let bytes = match (encoding, stored.is_native()) {
        (Encoding::Raw, true) => {
            check_file_size(path, offset, stored, dims)?;
            let map = super::mmap::map_file(path)?;
            let actual = (map.len() as u64).saturating_sub(offset);
            if actual != expected {
                return Err(mismatch(path, expected, actual, what(dims, stored)));
            }
            let too_big = || DatasetError::format(path, "file too large to map on this machine");
            let offset = usize::try_from(offset).map_err(|_| too_big())?;
            let len = usize::try_from(expected).map_err(|_| too_big())?;
            VoxelBytes::Mapped { map, offset, len }
        }
        (Encoding::Raw, false) => {
            check_file_size(path, offset, stored, dims)?;
            let mut file = File::open(path).map_err(|e| DatasetError::io(path, e))?;
            file.seek(SeekFrom::Start(offset)).map_err(|e| DatasetError::io(path, e))?;
            let mut buf = Vec::new();
            read_counted(path, BufReader::new(file), expected, Some(&mut buf), || what(dims, stored))?;
            VoxelBytes::Owned(Arc::new(convert_to_f32(&buf, stored, endian, voxels, |v| v as f32)))
        }
        (Encoding::Gzip, native) => {
            let mut buf = Vec::new();
            read_counted(path, gzip_reader(path, offset)?, expected, Some(&mut buf), || what(dims, stored))?;
            if native {
                VoxelBytes::Owned(Arc::new(buf))
            } else {
                VoxelBytes::Owned(Arc::new(convert_to_f32(&buf, stored, endian, voxels, |v| v as f32)))
            }
        }
    };
    let endian = if stored.is_native() { endian } else { Endian::Little };
    Channel::new(stored.loaded_type(), endian, bytes, dims)
        .map_err(|e| mismatch(path, e.expected, e.actual, what(dims, stored.loaded_type().into())))
}

fn mismatch(path: &Path, expected: u64, actual: u64, what: String) -> DatasetError {
    DatasetError::SizeMismatch { path: path.to_path_buf(), expected, actual, what }
}

/// Checks an uncompressed file's length against [`check_len`].
fn check_file_size(path: &Path, offset: u64, ty: StoredType, dims: Dims) -> Result<(), DatasetError> {
    let len = std::fs::metadata(path).map_err(|e| DatasetError::io(path, e))?.len();
    check_len(path, len, offset, ty, dims)
}

/// Checks that an uncompressed file of `len` bytes holds exactly `dims` voxels of `ty` after
/// `offset` bytes (SPEC §1.1: never "at least"). `path` names the file in the error. The
/// scene loader calls this with the length a catalog reported for a raw channel's file.
pub(crate) fn check_len(path: &Path, len: u64, offset: u64, ty: StoredType, dims: Dims) -> Result<(), DatasetError> {
    if len < offset {
        return Err(DatasetError::ShorterThanOffset { path: path.to_path_buf(), len, offset });
    }
    let expected = expected_bytes(dims, ty);
    if len - offset != expected {
        return Err(mismatch(path, expected, len - offset, what(dims, ty)));
    }
    Ok(())
}

/// A gzip decoder over `path` from byte `offset`. Concatenated gzip members are one stream
/// (as `gzip -c a b` writes them), hence `MultiGzDecoder`.
pub(crate) fn gzip_reader(path: &Path, offset: u64) -> Result<impl Read, DatasetError> {
    let mut file = File::open(path).map_err(|e| DatasetError::io(path, e))?;
    file.seek(SeekFrom::Start(offset)).map_err(|e| DatasetError::io(path, e))?;
    Ok(MultiGzDecoder::new(BufReader::new(file)))
}

/// Reads `reader` to its end, keeping the first `expected` bytes in `keep` (when given), and
/// fails unless exactly `expected` bytes arrive.
///
/// A stream that is too long is not read to its end, since a small gzip file can inflate
/// without bound: once more than `expected` bytes arrived, counting goes on only up to twice
/// the expected size (at least 1 MiB more). If the stream ends within that, the message gives
/// its exact size; otherwise it says reading stopped there.
pub(crate) fn read_counted(
    path: &Path,
    mut reader: impl Read,
    expected: u64,
    mut keep: Option<&mut Vec<u8>>,
    what: impl Fn() -> String,
) -> Result<(), DatasetError> {
    let cap = expected.saturating_add(expected.max(1 << 20));
    if let Some(buf) = keep.as_deref_mut() {
        let n = usize::try_from(expected).map_err(|_| DatasetError::format(path, "volume too large for memory"))?;
        buf.clear();
        buf.try_reserve_exact(n).map_err(|_| DatasetError::format(path, format!("cannot allocate {n} bytes")))?;
    }
    let mut chunk = vec![0u8; 1 << 16];
    let mut total: u64 = 0;
    loop {
        let n = match reader.read(&mut chunk) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(DatasetError::io(path, e)),
        };
        if let Some(buf) = keep.as_deref_mut() {
            let room = expected.saturating_sub(total).min(n as u64) as usize;
            buf.extend_from_slice(&chunk[..room]);
        }
        total += n as u64;
        if total > cap {
            let what = format!("{} (reading stopped after {total} bytes; the stream is longer)", what());
            return Err(mismatch(path, expected, total, what));
        }
    }
    if total != expected {
        return Err(mismatch(path, expected, total, what()));
    }
    Ok(())
}

/// Converts `voxels` stored numbers to little-endian f32 bytes, passing each value (exact
/// as f64) through `map` first. Plain conversion is `|v| v as f32`: for every stored type
/// that rounds once, exactly as a direct cast would.
pub(crate) fn convert_to_f32(
    bytes: &[u8],
    stored: StoredType,
    endian: Endian,
    voxels: usize,
    map: impl Fn(f64) -> f32,
) -> Vec<u8> {
    fn go<const N: usize>(
        bytes: &[u8],
        voxels: usize,
        decode: impl Fn([u8; N]) -> f64,
        map: impl Fn(f64) -> f32,
    ) -> Vec<u8> {
        let mut out = Vec::with_capacity(voxels * 4);
        for c in bytes.chunks_exact(N).take(voxels) {
            let mut a = [0u8; N];
            a.copy_from_slice(c);
            out.extend_from_slice(&map(decode(a)).to_le_bytes());
        }
        out
    }
    let big = endian == Endian::Big;
    match stored {
        StoredType::I8 => go::<1>(bytes, voxels, |b| b[0] as i8 as f64, map),
        StoredType::U8 => go::<1>(bytes, voxels, |b| b[0] as f64, map),
        StoredType::I16 => {
            go::<2>(bytes, voxels, |b| if big { i16::from_be_bytes(b) } else { i16::from_le_bytes(b) } as f64, map)
        }
        StoredType::U16 => {
            go::<2>(bytes, voxels, |b| if big { u16::from_be_bytes(b) } else { u16::from_le_bytes(b) } as f64, map)
        }
        StoredType::I32 => {
            go::<4>(bytes, voxels, |b| if big { i32::from_be_bytes(b) } else { i32::from_le_bytes(b) } as f64, map)
        }
        StoredType::U32 => {
            go::<4>(bytes, voxels, |b| if big { u32::from_be_bytes(b) } else { u32::from_le_bytes(b) } as f64, map)
        }
        StoredType::F32 => {
            go::<4>(bytes, voxels, |b| if big { f32::from_be_bytes(b) } else { f32::from_le_bytes(b) } as f64, map)
        }
        StoredType::F64 => {
            go::<8>(bytes, voxels, |b| if big { f64::from_be_bytes(b) } else { f64::from_le_bytes(b) }, map)
        }
        StoredType::Bit => {
            let mut out = Vec::with_capacity(voxels * 4);
            for i in 0..voxels.min(bytes.len() * 8) {
                let bit = (bytes[i >> 3] >> (i & 7)) & 1;
                out.extend_from_slice(&map(bit as f64).to_le_bytes());
            }
            out
        }
    }
}

/// Helpers shared by the dataset tests: temporary files and the shared data folder.
#[cfg(test)]
pub(crate) mod testutil {
    use std::path::PathBuf;
    use std::sync::atomic::{AtomicU32, Ordering};

    /// A file in the system temp folder, unique to this process and call, removed on drop.
    pub struct TempFile(pub PathBuf);

    impl TempFile {
        /// A fresh path ending in `suffix` (nothing is created).
        pub fn new(suffix: &str) -> TempFile {
            static N: AtomicU32 = AtomicU32::new(0);
            let n = N.fetch_add(1, Ordering::Relaxed);
            TempFile(std::env::temp_dir().join(format!("trove-test-{}-{n}-{suffix}", std::process::id())))
        }

        /// A fresh file holding `bytes`.
        pub fn with(suffix: &str, bytes: &[u8]) -> TempFile {
            let t = TempFile::new(suffix);
            std::fs::write(&t.0, bytes).expect("write temp file");
            t
        }
    }

    impl Drop for TempFile {
        fn drop(&mut self) {
            let _ = std::fs::remove_file(&self.0);
        }
    }

    /// The shared test data folder (`../shared/data`, docs/data.md), or `None` when it is
    /// absent: then the calling test returns early, and the skip is reported on the terminal
    /// past libtest's output capture (which shows `eprintln!` only for failing tests, so a
    /// skip would look like a pass). With `TROVE_REQUIRE_DATA=1` (CI, which always has the
    /// data) an absent folder fails the test instead. `trove_tests::skip` does the same for
    /// the integration tests.
    pub fn data_dir() -> Option<PathBuf> {
        use std::io::Write;
        let d = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data"));
        if d.is_dir() {
            return Some(d);
        }
        let test = std::thread::current().name().unwrap_or("a test").to_string();
        if std::env::var_os("TROVE_REQUIRE_DATA").is_some_and(|v| !v.is_empty() && v != "0") {
            panic!("{test}: ../shared/data is absent and TROVE_REQUIRE_DATA is set: a failure, not a skip");
        }
        let _ = writeln!(
            std::io::stderr().lock(),
            "SKIPPED in {test}: ../shared/data, the real datasets, is absent; \
             see docs/data.md, or set TROVE_REQUIRE_DATA=1 to fail instead"
        );
        None
    }

    /// Gzip-compresses `bytes`.
    pub fn gzip(bytes: &[u8]) -> Vec<u8> {
        use std::io::Write;
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        e.write_all(bytes).expect("gzip to memory");
        e.finish().expect("gzip to memory")
    }
}

#[cfg(test)]
mod tests {
    use super::testutil::{gzip, TempFile};
    use super::*;

    fn dims(x: u64, y: u64, z: u64) -> Dims {
        Dims::new([x, y, z]).unwrap()
    }

    /// Test values of each type, as f64, with their stored bytes in `endian`.
    fn encode(ty: StoredType, endian: Endian, n: usize) -> (Vec<u8>, Vec<f64>) {
        let big = endian == Endian::Big;
        let mut bytes = Vec::new();
        let mut vals = Vec::new();
        macro_rules! put {
            ($t:ty, $v:expr) => {{
                let v: $t = $v;
                bytes.extend_from_slice(&if big { v.to_be_bytes() } else { v.to_le_bytes() });
                vals.push(v as f64);
            }};
        }
        for i in 0..n {
            let s = i as i64 * 7919 - 20_000;
            match ty {
                StoredType::Bit => {
                    vals.push(((i * 5 + i / 3) % 2) as f64);
                }
                StoredType::U8 => put!(u8, (i * 37 % 256) as u8),
                StoredType::I8 => put!(i8, (s % 128) as i8),
                StoredType::U16 => put!(u16, (i * 7919 % 65536) as u16),
                StoredType::I16 => put!(i16, (s % 32768) as i16),
                StoredType::U32 => put!(u32, (i as u32).wrapping_mul(2_654_435_761) >> 8),
                StoredType::I32 => put!(i32, (s * 301) as i32 % (1 << 24)),
                StoredType::F32 => put!(f32, s as f32 * 0.37),
                StoredType::F64 => put!(f64, s as f64 * 0.125 + 0.5),
            }
        }
        if ty == StoredType::Bit {
            bytes = vec![0u8; n.div_ceil(8)];
            for (i, v) in vals.iter().enumerate() {
                bytes[i / 8] |= (*v as u8) << (i % 8);
            }
        }
        (bytes, vals)
    }

    const ALL: [StoredType; 9] = [
        StoredType::Bit,
        StoredType::U8,
        StoredType::U16,
        StoredType::U32,
        StoredType::F32,
        StoredType::I8,
        StoredType::I16,
        StoredType::I32,
        StoredType::F64,
    ];

    #[test]
    fn byte_lengths_and_loaded_types() {
        assert_eq!(StoredType::Bit.byte_len(17), Some(3));
        assert_eq!(StoredType::Bit.byte_len(16), Some(2));
        assert_eq!(StoredType::U16.byte_len(10), Some(20));
        assert_eq!(StoredType::F64.byte_len(10), Some(80));
        assert_eq!(StoredType::F64.byte_len(u64::MAX), None);
        assert_eq!(StoredType::I16.loaded_type(), VoxelType::F32);
        assert_eq!(StoredType::U16.loaded_type(), VoxelType::U16);
        assert_eq!(StoredType::Bit.loaded_type(), VoxelType::Bit);
    }

    #[test]
    fn round_trip_every_type_and_endianness_raw_and_gzip() {
        let d = dims(5, 4, 3);
        let n = 60;
        for ty in ALL {
            for endian in [Endian::Little, Endian::Big] {
                let (bytes, vals) = encode(ty, endian, n);
                // A 7-byte prefix exercises the offset.
                let mut with_header = b"HEADER\n".to_vec();
                with_header.extend_from_slice(&bytes);
                let raw_file = TempFile::with("rt.raw", &with_header);
                let gz_file = TempFile::with("rt.raw.gz", &gzip(&bytes));
                for (file, offset, enc) in [(&raw_file, 7, Encoding::Raw), (&gz_file, 0, Encoding::Gzip)] {
                    let src = open_with(&file.0, offset, enc, ty, endian, d).unwrap();
                    let ChannelSource::File { encoding, .. } = src else { panic!("not a file source") };
                    assert_eq!(encoding, enc);
                    let ch = load(&file.0, offset, enc, ty, endian, d).unwrap();
                    assert_eq!(ch.ty(), ty.loaded_type(), "{ty} {endian:?} {enc:?}");
                    assert_eq!(ch.is_mapped(), enc == Encoding::Raw && ty.is_native(), "{ty} {enc:?}");
                    for (i, v) in vals.iter().enumerate() {
                        assert_eq!(ch.value(i), *v as f32, "{ty} {endian:?} {enc:?} voxel {i}");
                    }
                }
            }
        }
    }

    #[test]
    fn mapped_load_is_zero_copy_and_keeps_big_endian() {
        let d = dims(4, 2, 1);
        let (bytes, vals) = encode(StoredType::U16, Endian::Big, 8);
        let f = TempFile::with("be.raw", &bytes);
        let ch = load(&f.0, 0, Encoding::Raw, StoredType::U16, Endian::Big, d).unwrap();
        assert!(ch.is_mapped());
        assert_eq!(ch.endian(), Endian::Big);
        assert_eq!(ch.byte_len(), 16);
        assert_eq!(ch.value(3), vals[3] as f32);
    }

    #[test]
    fn wrong_sizes_name_both_sizes() {
        let d = dims(4, 4, 2);
        let f = TempFile::with("short.raw", &[0u8; 63]);
        let e = open_with(&f.0, 0, Encoding::Raw, StoredType::U16, Endian::Little, d).unwrap_err();
        match &e {
            DatasetError::SizeMismatch { expected: 64, actual: 63, what, .. } => {
                assert_eq!(what, "dims [4, 4, 2] of u16")
            }
            e => panic!("unexpected {e:?}"),
        }
        let msg = e.to_string();
        assert!(msg.contains("63") && msg.contains("64") && msg.contains("short.raw"), "{msg}");
        // Too long by one byte is refused too.
        let f = TempFile::with("long.raw", &[0u8; 65]);
        assert!(matches!(
            open_with(&f.0, 0, Encoding::Raw, StoredType::U16, Endian::Little, d),
            Err(DatasetError::SizeMismatch { expected: 64, actual: 65, .. })
        ));
        // Load re-checks: the file may have been truncated since open.
        let f = TempFile::with("trunc.raw", &[0u8; 64]);
        open_with(&f.0, 0, Encoding::Raw, StoredType::U16, Endian::Little, d).unwrap();
        std::fs::write(&f.0, [0u8; 40]).unwrap();
        for ty in [StoredType::U16, StoredType::I16] {
            assert!(matches!(
                load(&f.0, 0, Encoding::Raw, ty, Endian::Little, d),
                Err(DatasetError::SizeMismatch { expected: 64, actual: 40, .. })
            ));
        }
        // An offset past the end of the file.
        assert!(matches!(
            open_with(&f.0, 100, Encoding::Raw, StoredType::U8, Endian::Little, d),
            Err(DatasetError::ShorterThanOffset { len: 40, offset: 100, .. })
        ));
        // The check a scene loader makes from a catalog's length alone.
        assert!(check_len(&f.0, 64, 0, StoredType::U16, d).is_ok());
        assert!(matches!(
            check_len(&f.0, 70, 4, StoredType::U16, d),
            Err(DatasetError::SizeMismatch { expected: 64, actual: 66, .. })
        ));
    }

    #[test]
    fn gzip_too_short_and_too_long() {
        let d = dims(10, 10, 10);
        let short = TempFile::with("short.gz", &gzip(&[1u8; 999]));
        let long = TempFile::with("long.gz", &gzip(&[1u8; 1001]));
        for ty in [StoredType::U8, StoredType::I8] {
            let e = open_with(&short.0, 0, Encoding::Gzip, ty, Endian::Little, d).unwrap_err();
            assert!(matches!(e, DatasetError::SizeMismatch { expected: 1000, actual: 999, .. }), "{e:?}");
            let e = load(&long.0, 0, Encoding::Gzip, ty, Endian::Little, d).unwrap_err();
            assert!(matches!(e, DatasetError::SizeMismatch { expected: 1000, actual: 1001, .. }), "{e:?}");
        }
        // A stream far longer than expected is not inflated to its end.
        let huge = TempFile::with("huge.gz", &gzip(&vec![0u8; 8 << 20]));
        let e = open_with(&huge.0, 0, Encoding::Gzip, StoredType::U8, Endian::Little, d).unwrap_err();
        match e {
            DatasetError::SizeMismatch { expected: 1000, actual, what, .. } => {
                assert!(actual > 1000 && actual < 3 << 20, "{actual}");
                assert!(what.contains("stream is longer"), "{what}");
            }
            e => panic!("unexpected {e:?}"),
        }
        // Not gzip at all.
        let junk = TempFile::with("junk.gz", &[7u8; 100]);
        assert!(matches!(
            open_with(&junk.0, 0, Encoding::Gzip, StoredType::U8, Endian::Little, d),
            Err(DatasetError::Io { .. })
        ));
    }

    #[test]
    fn concatenated_gzip_members_are_one_stream() {
        let d = dims(8, 1, 1);
        let mut bytes = gzip(&[1, 2, 3]);
        bytes.extend(gzip(&[4, 5, 6, 7, 8]));
        let f = TempFile::with("multi.gz", &bytes);
        let ch = load(&f.0, 0, Encoding::Gzip, StoredType::U8, Endian::Little, d).unwrap();
        assert_eq!((0..8).map(|i| ch.value(i)).collect::<Vec<_>>(), [1., 2., 3., 4., 5., 6., 7., 8.]);
    }

    #[test]
    fn missing_file_is_an_io_error() {
        let f = TempFile::new("absent.raw");
        let e = open_with(&f.0, 0, Encoding::Raw, StoredType::U8, Endian::Little, dims(1, 1, 1)).unwrap_err();
        assert!(
            matches!(&e, DatasetError::Io { path, source } if *path == f.0 && source.kind() == io::ErrorKind::NotFound)
        );
        assert!(!e.is_retryable());
    }
}
