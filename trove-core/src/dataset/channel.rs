//! One channel of a dataset: a typed, endian-tagged byte array of exactly `dims` voxels.

use std::fmt;
use std::sync::Arc;

use memmap2::Mmap;
use thiserror::Error;

use super::Dims;

/// Bytes that do not hold exactly `dims` voxels of a channel's type ([`Channel::new`]).
/// Callers that know the file add its name (`DatasetError::SizeMismatch`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Error)]
#[error("{actual} bytes do not hold the voxels, which need exactly {expected} bytes")]
pub struct ChannelSizeError {
    /// Bytes `dims` voxels of the type need.
    pub expected: u64,
    /// Bytes given.
    pub actual: u64,
}

/// How one voxel of a channel is stored (SPEC §1.1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum VoxelType {
    /// One bit per voxel, one LSB-first stream, x fastest, no row padding.
    Bit,
    /// Unsigned 8-bit.
    U8,
    /// Unsigned 16-bit.
    U16,
    /// Unsigned 32-bit.
    U32,
    /// IEEE single precision.
    F32,
}

impl VoxelType {
    /// Parses the scene's spelling (`bit`, `u8`, `u16`, `u32`, `f32`).
    pub fn parse(s: &str) -> Option<VoxelType> {
        Some(match s {
            "bit" => VoxelType::Bit,
            "u8" => VoxelType::U8,
            "u16" => VoxelType::U16,
            "u32" => VoxelType::U32,
            "f32" => VoxelType::F32,
            _ => return None,
        })
    }

    /// The scene's spelling.
    pub fn name(self) -> &'static str {
        match self {
            VoxelType::Bit => "bit",
            VoxelType::U8 => "u8",
            VoxelType::U16 => "u16",
            VoxelType::U32 => "u32",
            VoxelType::F32 => "f32",
        }
    }

    /// Bytes needed for `voxels` voxels, or `None` on overflow.
    pub fn byte_len(self, voxels: u64) -> Option<u64> {
        match self {
            VoxelType::Bit => Some(voxels.div_ceil(8)),
            VoxelType::U8 => Some(voxels),
            VoxelType::U16 => voxels.checked_mul(2),
            VoxelType::U32 | VoxelType::F32 => voxels.checked_mul(4),
        }
    }
}

impl fmt::Display for VoxelType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Byte order of multi-byte voxels.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum Endian {
    /// Least significant byte first (the default).
    #[default]
    Little,
    /// Most significant byte first.
    Big,
}

impl Endian {
    /// Parses `little` or `big`.
    pub fn parse(s: &str) -> Option<Endian> {
        match s {
            "little" => Some(Endian::Little),
            "big" => Some(Endian::Big),
            _ => None,
        }
    }
}

/// The channels of SPEC §1.1 (paper §2.3.1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum ChannelName {
    /// Raw data the mapping functions read (bit, u8, u16, u32 or f32).
    Voxel,
    /// Colour as a binary field.
    Bit,
    /// 256 grey levels.
    Grey,
    /// Red (u8).
    Red,
    /// Green (u8).
    Green,
    /// Blue (u8).
    Blue,
    /// Raw opacity (u8).
    Alpha,
    /// 7-colour model: second red.
    Red2,
    /// 7-colour model: second green.
    Green2,
    /// 7-colour model: second blue.
    Blue2,
    /// 7-colour model: beta.
    Beta,
    /// Per-voxel choice of interpolation function.
    Interp,
    /// User channel 1..=4.
    User(u8),
}

impl ChannelName {
    /// Every channel name, in storage order.
    pub const ALL: [ChannelName; 16] = [
        ChannelName::Voxel,
        ChannelName::Bit,
        ChannelName::Grey,
        ChannelName::Red,
        ChannelName::Green,
        ChannelName::Blue,
        ChannelName::Alpha,
        ChannelName::Red2,
        ChannelName::Green2,
        ChannelName::Blue2,
        ChannelName::Beta,
        ChannelName::Interp,
        ChannelName::User(1),
        ChannelName::User(2),
        ChannelName::User(3),
        ChannelName::User(4),
    ];

    /// Parses the scene's spelling (`voxel`, `red2`, `user3`, ...).
    pub fn parse(s: &str) -> Option<ChannelName> {
        ChannelName::ALL.into_iter().find(|c| c.name() == s)
    }

    /// The scene's spelling.
    pub fn name(self) -> &'static str {
        match self {
            ChannelName::Voxel => "voxel",
            ChannelName::Bit => "bit",
            ChannelName::Grey => "grey",
            ChannelName::Red => "red",
            ChannelName::Green => "green",
            ChannelName::Blue => "blue",
            ChannelName::Alpha => "alpha",
            ChannelName::Red2 => "red2",
            ChannelName::Green2 => "green2",
            ChannelName::Blue2 => "blue2",
            ChannelName::Beta => "beta",
            ChannelName::Interp => "interp",
            ChannelName::User(1) => "user1",
            ChannelName::User(2) => "user2",
            ChannelName::User(3) => "user3",
            ChannelName::User(_) => "user4",
        }
    }

    /// The storage types this channel accepts.
    pub fn allowed_types(self) -> &'static [VoxelType] {
        use VoxelType::*;
        match self {
            ChannelName::Voxel | ChannelName::User(_) => &[Bit, U8, U16, U32, F32],
            ChannelName::Bit => &[Bit],
            _ => &[U8],
        }
    }

    /// Whether raw use divides the stored value by 255 (SPEC §3.1).
    pub fn is_colour_byte(self) -> bool {
        matches!(
            self,
            ChannelName::Grey | ChannelName::Red | ChannelName::Green | ChannelName::Blue | ChannelName::Alpha
        )
    }
}

impl fmt::Display for ChannelName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Where a channel's bytes live: a read-only file mapping (zero copy) or memory we own.
#[derive(Clone)]
pub enum VoxelBytes {
    /// A window of a memory-mapped file.
    Mapped {
        /// The mapping, shared by every channel cut from the same file.
        map: Arc<Mmap>,
        /// First byte of the channel in the mapping.
        offset: usize,
        /// Length in bytes.
        len: usize,
    },
    /// Decoded, converted or generated bytes.
    Owned(Arc<Vec<u8>>),
}

impl VoxelBytes {
    /// The bytes.
    pub fn as_slice(&self) -> &[u8] {
        match self {
            VoxelBytes::Mapped { map, offset, len } => &map[*offset..*offset + *len],
            VoxelBytes::Owned(v) => v,
        }
    }
}

impl fmt::Debug for VoxelBytes {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            VoxelBytes::Mapped { len, .. } => write!(f, "Mapped({len} bytes)"),
            VoxelBytes::Owned(v) => write!(f, "Owned({} bytes)", v.len()),
        }
    }
}

/// A channel: exactly `dims` voxels of one type. The length is checked at construction, so
/// every index below `dims.voxel_count()` is readable.
#[derive(Clone, Debug)]
pub struct Channel {
    ty: VoxelType,
    endian: Endian,
    bytes: VoxelBytes,
    voxels: usize,
}

impl Channel {
    /// Wraps `bytes`, refusing them unless they hold exactly `dims` voxels of `ty`.
    pub fn new(ty: VoxelType, endian: Endian, bytes: VoxelBytes, dims: Dims) -> Result<Channel, ChannelSizeError> {
        let expected = ty.byte_len(dims.voxel_count()).unwrap_or(u64::MAX);
        let actual = bytes.as_slice().len() as u64;
        if expected != actual {
            return Err(ChannelSizeError { expected, actual });
        }
        Ok(Channel { ty, endian, bytes, voxels: dims.voxel_count() as usize })
    }

    /// An owned f32 channel (little-endian storage).
    pub fn from_f32(values: &[f32], dims: Dims) -> Result<Channel, ChannelSizeError> {
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        Channel::new(VoxelType::F32, Endian::Little, VoxelBytes::Owned(Arc::new(bytes)), dims)
    }

    /// An owned u8 channel.
    pub fn from_u8(values: Vec<u8>, dims: Dims) -> Result<Channel, ChannelSizeError> {
        Channel::new(VoxelType::U8, Endian::Little, VoxelBytes::Owned(Arc::new(values)), dims)
    }

    /// Storage type.
    pub fn ty(&self) -> VoxelType {
        self.ty
    }

    /// Byte order.
    pub fn endian(&self) -> Endian {
        self.endian
    }

    /// Resident size in bytes.
    pub fn byte_len(&self) -> usize {
        self.bytes.as_slice().len()
    }

    /// Whether the bytes are a file mapping rather than a copy.
    pub fn is_mapped(&self) -> bool {
        matches!(self.bytes, VoxelBytes::Mapped { .. })
    }

    /// The same channel in memory it owns: a mapped channel's bytes are copied (which
    /// reads every page of the file), an owned one is shared as is. A memory budget needs
    /// this so that loading really brings the bytes in and eviction really frees them.
    pub fn owned_copy(&self) -> Channel {
        let bytes = match &self.bytes {
            VoxelBytes::Mapped { .. } => VoxelBytes::Owned(Arc::new(self.bytes.as_slice().to_vec())),
            owned @ VoxelBytes::Owned(_) => owned.clone(),
        };
        Channel { ty: self.ty, endian: self.endian, bytes, voxels: self.voxels }
    }

    /// The stored number at linear index `i` as f32 (SPEC §3.1). Panics if `i` is out of
    /// range; hot loops use [`Channel::reader`] instead.
    pub fn value(&self, i: usize) -> f32 {
        assert!(i < self.voxels, "voxel index {i} out of range");
        self.reader().read(i)
    }

    /// A reader that decodes this channel's storage; dispatch once, then read many voxels.
    pub fn reader(&self) -> ChannelReader<'_> {
        let b = self.bytes.as_slice();
        match (self.ty, self.endian) {
            (VoxelType::Bit, _) => ChannelReader::Bit(b),
            (VoxelType::U8, _) => ChannelReader::U8(b),
            (VoxelType::U16, Endian::Little) => ChannelReader::U16Le(b),
            (VoxelType::U16, Endian::Big) => ChannelReader::U16Be(b),
            (VoxelType::U32, Endian::Little) => ChannelReader::U32Le(b),
            (VoxelType::U32, Endian::Big) => ChannelReader::U32Be(b),
            (VoxelType::F32, Endian::Little) => ChannelReader::F32Le(b),
            (VoxelType::F32, Endian::Big) => ChannelReader::F32Be(b),
        }
    }
}

/// Random access to a channel's voxels as f32 (SPEC §3.1), for the sampler and the
/// macrocell scan. [`ChannelReader`] implements it by matching on the storage type at every
/// read; the typed views below ([`U8Voxels`], [`U16LeVoxels`], ...) decode one type only,
/// so code made generic over `Voxels` is compiled once per type with no dispatch per voxel.
pub trait Voxels: Copy + Send + Sync {
    /// Whether every value is finite (integer types), so scans need not test.
    const ALWAYS_FINITE: bool = false;

    /// The value at linear index `i` (x fastest, then y, then z). Panics if out of range.
    fn get(&self, i: usize) -> f32;

    /// [`Voxels::get`] widened to f64 (the same value: integer types convert directly).
    #[inline(always)]
    fn get_f64(&self, i: usize) -> f64 {
        self.get(i) as f64
    }

    /// Decodes `out.len()` consecutive voxels from index `start` (a row, for scans).
    #[inline]
    fn decode(&self, start: usize, out: &mut [f32]) {
        for (k, o) in out.iter_mut().enumerate() {
            *o = self.get(start + k);
        }
    }

    /// The values at `i` and `i + dx` (`dx` 0 or 1: a voxel and its neighbour along x, or
    /// the voxel twice on a single-voxel axis), as f64: the x pairs of a trilinear stencil,
    /// read with one bounds check and one load where the type allows.
    #[inline(always)]
    fn pair(&self, i: usize, dx: usize) -> [f64; 2] {
        [self.get_f64(i), self.get_f64(i + dx)]
    }
}

impl Voxels for ChannelReader<'_> {
    #[inline(always)]
    fn get(&self, i: usize) -> f32 {
        self.read(i)
    }
}

macro_rules! typed_voxels {
    ($(#[$doc:meta])* $name:ident, $variant:ident, $ty:ty, $bytes:literal, $from:ident, $finite:literal) => {
        $(#[$doc])*
        #[derive(Clone, Copy, Debug)]
        pub struct $name<'a>(&'a [u8]);

        impl<'a> $name<'a> {
            /// The typed view of `reader`, or `None` when it stores another type.
            pub fn of(reader: ChannelReader<'a>) -> Option<$name<'a>> {
                match reader {
                    ChannelReader::$variant(b) => Some($name(b)),
                    _ => None,
                }
            }

            /// The stored bytes (little-endian numbers, `size_of::<$ty>()` each), which the
            /// AVX2 loop gathers from (it has none for f32).
            #[allow(dead_code)]
            pub(crate) fn bytes(&self) -> &'a [u8] {
                self.0
            }

            #[inline(always)]
            fn number(&self, i: usize) -> $ty {
                <$ty>::$from(self.0[$bytes * i..$bytes * i + $bytes].try_into().expect("one voxel"))
            }
        }

        impl Voxels for $name<'_> {
            const ALWAYS_FINITE: bool = $finite;

            #[inline(always)]
            fn get(&self, i: usize) -> f32 {
                self.number(i) as f32
            }

            #[inline(always)]
            fn get_f64(&self, i: usize) -> f64 {
                // u8 and u16 widen exactly, to the value `get` gives; f32 too.
                self.number(i) as f64
            }

            #[inline]
            fn decode(&self, start: usize, out: &mut [f32]) {
                let bytes = &self.0[$bytes * start..$bytes * (start + out.len())];
                for (o, b) in out.iter_mut().zip(bytes.chunks_exact($bytes)) {
                    let mut number = [0u8; $bytes];
                    number.copy_from_slice(b);
                    *o = <$ty>::$from(number) as f32;
                }
            }

            #[inline(always)]
            fn pair(&self, i: usize, dx: usize) -> [f64; 2] {
                if dx == 1 {
                    let b: &[u8; 2 * $bytes] = self.0[$bytes * i..$bytes * i + 2 * $bytes].try_into().expect("two voxels");
                    let (lo, hi) = b.split_at($bytes);
                    [
                        <$ty>::$from(lo.try_into().expect("one voxel")) as f64,
                        <$ty>::$from(hi.try_into().expect("one voxel")) as f64,
                    ]
                } else {
                    [self.get_f64(i), self.get_f64(i + dx)]
                }
            }
        }
    };
}

typed_voxels!(
    /// A `u8` channel.
    U8Voxels, U8, u8, 1, from_le_bytes, true
);
typed_voxels!(
    /// A little-endian `u16` channel.
    U16LeVoxels, U16Le, u16, 2, from_le_bytes, true
);
typed_voxels!(
    /// A little-endian `f32` channel.
    F32LeVoxels, F32Le, f32, 4, from_le_bytes, false
);

/// A `bit` channel: one LSB-first bit per voxel.
#[derive(Clone, Copy, Debug)]
pub struct BitVoxels<'a>(&'a [u8]);

impl<'a> BitVoxels<'a> {
    /// The typed view of `reader`, or `None` when it stores another type.
    pub fn of(reader: ChannelReader<'a>) -> Option<BitVoxels<'a>> {
        match reader {
            ChannelReader::Bit(b) => Some(BitVoxels(b)),
            _ => None,
        }
    }
}

impl Voxels for BitVoxels<'_> {
    const ALWAYS_FINITE: bool = true;

    #[inline(always)]
    fn get(&self, i: usize) -> f32 {
        ((self.0[i >> 3] >> (i & 7)) & 1) as f32
    }
}

/// A borrowed, decoded view of a channel's bytes.
#[derive(Clone, Copy, Debug)]
pub enum ChannelReader<'a> {
    /// Bits, LSB first.
    Bit(&'a [u8]),
    /// u8.
    U8(&'a [u8]),
    /// u16 little-endian.
    U16Le(&'a [u8]),
    /// u16 big-endian.
    U16Be(&'a [u8]),
    /// u32 little-endian.
    U32Le(&'a [u8]),
    /// u32 big-endian.
    U32Be(&'a [u8]),
    /// f32 little-endian.
    F32Le(&'a [u8]),
    /// f32 big-endian.
    F32Be(&'a [u8]),
}

impl ChannelReader<'_> {
    /// The value at linear index `i` (x fastest, then y, then z).
    #[inline(always)]
    pub fn read(&self, i: usize) -> f32 {
        #[inline(always)]
        fn w<const N: usize>(b: &[u8], i: usize) -> [u8; N] {
            b[i * N..i * N + N].try_into().expect("slice of N bytes")
        }
        match *self {
            ChannelReader::Bit(b) => ((b[i >> 3] >> (i & 7)) & 1) as f32,
            ChannelReader::U8(b) => b[i] as f32,
            ChannelReader::U16Le(b) => u16::from_le_bytes(w(b, i)) as f32,
            ChannelReader::U16Be(b) => u16::from_be_bytes(w(b, i)) as f32,
            ChannelReader::U32Le(b) => u32::from_le_bytes(w(b, i)) as f32,
            ChannelReader::U32Be(b) => u32::from_be_bytes(w(b, i)) as f32,
            ChannelReader::F32Le(b) => f32::from_le_bytes(w(b, i)),
            ChannelReader::F32Be(b) => f32::from_be_bytes(w(b, i)),
        }
    }
}
