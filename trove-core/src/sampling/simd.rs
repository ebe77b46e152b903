//! Which instruction set the sampler's f32 packet loop ([`super::packet`]) runs in, and the
//! vector operations that loop is written in, once, over a width.
//!
//! [`Simd`] is a handful of f32 and i32 lane operations: arithmetic, comparisons giving lane
//! masks, selects, gathers and a small table lookup. Each instruction set implements it for
//! its own registers ([`avx512`]: sixteen lanes, [`avx2`]: eight with FMA, [`neon`]: four,
//! [`scalar`]: four lanes in plain arrays that any target compiles), and the packet loop is
//! one generic body monomorphised per implementation. Every method is `#[inline(always)]` and
//! every entry point into the body carries its instruction set's `#[target_feature]`, so the
//! intrinsics inline into one loop per instruction set (as Open VKL's ISPC targets do, and
//! as `pulp` and `macerator` do at run time). A value of an implementing type is a token: it
//! can only be made where the processor has the instructions ([`Simd::detect`]), which is
//! what makes the safe methods sound.
//!
//! The operations mean the same on every implementation, NaN included: `min(a, b)` is
//! `a < b ? a : b` and `max(a, b)` is `a > b ? a : b` (x86's `minps`/`maxps`, whose operand
//! order the loop relies on to send a NaN position to the grid's last cell), comparisons
//! other than [`Simd::ne`] and [`Simd::is_nan`] are false on NaN, and conversions to i32
//! truncate. Only rounding differs: fused multiply-adds where the instruction set has them,
//! which the f32 loop's error bounds already allow for.
//!
//! [`SimdPath`] names the implementations. The one that runs is the widest the processor
//! has, unless `TROVE_SIMD` names another ([`SimdPath::configured`]): a path the processor
//! lacks is refused with [`SimdError::Unavailable`], not quietly replaced.

use std::fmt;
use std::str::FromStr;
use std::sync::OnceLock;

pub(super) mod avx2;
pub(super) mod avx512;
pub(super) mod neon;
pub(super) mod scalar;

/// An instruction set the sampler's f32 packet loop can run in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum SimdPath {
    /// Plain arrays, no target-specific instructions: every processor.
    Scalar,
    /// x86-64 AVX2 with FMA: eight f32 lanes.
    Avx2,
    /// x86-64 AVX-512 F, DQ and VL: sixteen f32 lanes.
    Avx512,
    /// AArch64 NEON (Advanced SIMD): four f32 lanes.
    Neon,
}

/// The environment variable that forces a path.
pub const SIMD_VARIABLE: &str = "TROVE_SIMD";

impl SimdPath {
    /// Every path, widest first among each architecture's.
    pub const ALL: [SimdPath; 4] = [SimdPath::Avx512, SimdPath::Avx2, SimdPath::Neon, SimdPath::Scalar];

    /// The name `TROVE_SIMD` and `--stats` use.
    pub fn name(self) -> &'static str {
        match self {
            SimdPath::Scalar => "scalar",
            SimdPath::Avx2 => "avx2",
            SimdPath::Avx512 => "avx512",
            SimdPath::Neon => "neon",
        }
    }

    /// f32 lanes per register.
    pub fn lanes(self) -> usize {
        match self {
            SimdPath::Scalar => scalar::LANES,
            SimdPath::Avx2 => 8,
            SimdPath::Avx512 => 16,
            SimdPath::Neon => 4,
        }
    }

    /// What the processor must have for this path, in words.
    pub fn needs(self) -> &'static str {
        match self {
            SimdPath::Scalar => "nothing",
            SimdPath::Avx2 => "x86-64 AVX2 and FMA",
            SimdPath::Avx512 => "x86-64 AVX-512 F, DQ and VL (and AVX2 and FMA)",
            SimdPath::Neon => "AArch64 NEON",
        }
    }

    /// Whether this processor can run the path.
    pub fn is_available(self) -> bool {
        match self {
            SimdPath::Scalar => true,
            SimdPath::Avx2 => avx2::Avx2::detect().is_some(),
            SimdPath::Avx512 => avx512::Avx512::detect().is_some(),
            SimdPath::Neon => neon::Neon::detect().is_some(),
        }
    }

    /// The paths this processor can run, widest first (`scalar` always last).
    pub fn available() -> Vec<SimdPath> {
        SimdPath::ALL.into_iter().filter(|p| p.is_available()).collect()
    }

    /// The widest path this processor can run.
    pub fn best() -> SimdPath {
        SimdPath::available()[0]
    }

    /// `self`, if this processor can run it.
    pub fn checked(self) -> Result<SimdPath, SimdError> {
        if self.is_available() {
            Ok(self)
        } else {
            let available = SimdPath::available().iter().map(|p| p.name()).collect::<Vec<_>>().join(", ");
            Err(SimdError::Unavailable { path: self, needs: self.needs(), available })
        }
    }

    /// The path renders take: the one `TROVE_SIMD` names if it is set (and not empty), else
    /// [`SimdPath::best`]. Read once per process; an unknown name, or a path this processor
    /// lacks, is an error every time it is asked for.
    pub fn configured() -> Result<SimdPath, SimdError> {
        static CONFIGURED: OnceLock<Result<SimdPath, SimdError>> = OnceLock::new();
        CONFIGURED
            .get_or_init(|| match std::env::var(SIMD_VARIABLE) {
                Ok(name) if !name.trim().is_empty() => name.parse::<SimdPath>()?.checked(),
                _ => Ok(SimdPath::best()),
            })
            .clone()
    }
}

impl fmt::Display for SimdPath {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for SimdPath {
    type Err = SimdError;

    fn from_str(s: &str) -> Result<SimdPath, SimdError> {
        let s = s.trim();
        SimdPath::ALL
            .into_iter()
            .find(|p| p.name().eq_ignore_ascii_case(s))
            .ok_or_else(|| SimdError::Unknown { given: s.to_string() })
    }
}

/// Why a SIMD path cannot be used.
#[derive(Debug, thiserror::Error, Clone, PartialEq, Eq)]
pub enum SimdError {
    /// The name is none of [`SimdPath::ALL`]'s.
    #[error("`{given}` is not a SIMD path ({SIMD_VARIABLE}): use scalar, avx2, avx512 or neon")]
    Unknown {
        /// The name given.
        given: String,
    },
    /// The processor lacks the path's instructions.
    #[error("SIMD path `{path}` is refused: this processor lacks {needs} (it can run: {available})")]
    Unavailable {
        /// The path asked for.
        path: SimdPath,
        /// What it needs.
        needs: &'static str,
        /// The paths this processor can run, widest first.
        available: String,
    },
}

/// The lane operations the packet loop is written in, for one instruction set. A value is
/// a token proving the processor has the instructions; see the module doc for what each
/// operation means on every implementation.
pub(super) trait Simd: Copy + Send + Sync + 'static {
    /// f32 (and i32) lanes per register.
    const LANES: usize;
    /// `LANES` f32.
    type F: Copy;
    /// `LANES` i32.
    type I: Copy;
    /// One bit (or lane of ones) per lane.
    type M: Copy;

    /// The token, where the processor has the instructions.
    fn detect() -> Option<Self>;

    fn splat(self, x: f32) -> Self::F;
    /// Lanes `a[0..LANES]`.
    fn load(self, a: &[f32]) -> Self::F;
    /// Into `a[0..LANES]`.
    fn store(self, a: &mut [f32], v: Self::F);
    fn add(self, a: Self::F, b: Self::F) -> Self::F;
    fn sub(self, a: Self::F, b: Self::F) -> Self::F;
    fn mul(self, a: Self::F, b: Self::F) -> Self::F;
    /// a·b + c (fused where the instruction set can).
    fn mul_add(self, a: Self::F, b: Self::F, c: Self::F) -> Self::F;
    /// c − a·b (fused where the instruction set can).
    fn neg_mul_add(self, a: Self::F, b: Self::F, c: Self::F) -> Self::F;
    /// `a < b ? a : b`.
    fn min(self, a: Self::F, b: Self::F) -> Self::F;
    /// `a > b ? a : b`.
    fn max(self, a: Self::F, b: Self::F) -> Self::F;
    fn floor(self, a: Self::F) -> Self::F;
    fn ceil(self, a: Self::F) -> Self::F;
    fn abs(self, a: Self::F) -> Self::F;
    /// √a, correctly rounded (the normals and half vectors of shading).
    fn sqrt(self, a: Self::F) -> Self::F;
    /// a / b, correctly rounded.
    fn div(self, a: Self::F, b: Self::F) -> Self::F;
    fn lt(self, a: Self::F, b: Self::F) -> Self::M;
    fn le(self, a: Self::F, b: Self::F) -> Self::M;
    fn gt(self, a: Self::F, b: Self::F) -> Self::M;
    fn ge(self, a: Self::F, b: Self::F) -> Self::M;
    /// a ≠ b, true where either is NaN.
    fn ne(self, a: Self::F, b: Self::F) -> Self::M;
    fn is_nan(self, a: Self::F) -> Self::M;
    /// `m ? a : b` per lane.
    fn select(self, m: Self::M, a: Self::F, b: Self::F) -> Self::F;
    /// Truncated toward zero (in range: lanes here hold grid coordinates).
    fn to_i32(self, a: Self::F) -> Self::I;
    fn to_f32(self, a: Self::I) -> Self::F;

    fn splat_i(self, x: i32) -> Self::I;
    fn load_i(self, a: &[i32]) -> Self::I;
    fn store_i(self, a: &mut [i32], v: Self::I);
    fn add_i(self, a: Self::I, b: Self::I) -> Self::I;
    /// The low 32 bits of a·b.
    fn mul_i(self, a: Self::I, b: Self::I) -> Self::I;
    fn and_i(self, a: Self::I, b: Self::I) -> Self::I;
    /// Logical right shift of every lane by `n` < 32.
    fn shr_i(self, a: Self::I, n: u32) -> Self::I;
    /// Left shift of every lane by `n` < 32.
    fn shl_i(self, a: Self::I, n: u32) -> Self::I;
    /// The bits of each f32 lane as an i32 (no conversion).
    fn to_bits(self, a: Self::F) -> Self::I;
    /// The bits of each i32 lane as an f32 (no conversion).
    fn bits_to_f32(self, a: Self::I) -> Self::F;
    /// Logical right shift of each lane by its own count (< 32).
    fn shr_each_i(self, a: Self::I, n: Self::I) -> Self::I;
    fn gt_i(self, a: Self::I, b: Self::I) -> Self::M;
    /// a + 1 in the lanes of `m`.
    fn count_i(self, a: Self::I, m: Self::M) -> Self::I;
    /// The four bytes at `base + SCALE·i` per lane, as a little-endian i32.
    ///
    /// # Safety
    /// Each lane's four bytes must lie inside one allocation that `base` points into.
    unsafe fn gather<const SCALE: i32>(self, base: *const u8, i: Self::I) -> Self::I;
    /// [`Simd::gather`] in the lanes of `m` only: the others are 0 and read no memory, so
    /// that a lane whose value is not wanted brings no cache line in.
    ///
    /// # Safety
    /// As [`Simd::gather`], for the lanes of `m`.
    unsafe fn gather_in<const SCALE: i32>(self, base: *const u8, i: Self::I, m: Self::M) -> Self::I;
    /// `table[i]` per lane, for indices below `used` ≤ 32.
    fn lookup(self, table: &[f32; 32], used: usize, i: Self::I) -> Self::F;

    /// Bit l for lane l.
    fn bits(self, m: Self::M) -> u32;
    /// Lane l set where bit l is.
    fn mask(self, bits: u32) -> Self::M;
    fn and_m(self, a: Self::M, b: Self::M) -> Self::M;
    fn or_m(self, a: Self::M, b: Self::M) -> Self::M;
}

/// One lane of [`Simd::gather`] read as plain memory: the four bytes at `base + SCALE·i`, a
/// little-endian i32. The paths without a gather instruction (scalar, NEON) read each lane
/// with it.
///
/// # Safety
/// The four bytes must lie inside one allocation that `base` points into.
#[inline(always)]
pub(super) unsafe fn word<const SCALE: i32>(base: *const u8, i: i32) -> i32 {
    // SAFETY: the caller's promise.
    i32::from_le(unsafe { base.offset(SCALE as isize * i as isize).cast::<i32>().read_unaligned() })
}
