//! [`Simd`] in NEON registers: four f32 lanes, masks as lanes of ones. NEON has no gather
//! and no table lookup of f32 across registers, so those go lane by lane through memory.
//! `min` and `max` are a comparison and a select, for x86's operand order (NEON's own
//! `fmin`/`fmax` propagate NaN).

#[cfg(target_arch = "aarch64")]
pub(in crate::sampling) use imp::Neon;

/// Where NEON cannot be: no token is ever made.
#[cfg(not(target_arch = "aarch64"))]
#[derive(Clone, Copy, Debug)]
pub(in crate::sampling) enum Neon {}

#[cfg(not(target_arch = "aarch64"))]
impl Neon {
    pub(in crate::sampling) fn detect() -> Option<Neon> {
        None
    }
}

#[cfg(target_arch = "aarch64")]
mod imp {
    use std::arch::aarch64::*;

    use super::super::{word, Simd};

    /// The token: the processor has NEON.
    #[derive(Clone, Copy, Debug)]
    pub(in crate::sampling) struct Neon(());

    // SAFETY (every `unsafe` block below): a `Neon` exists only where `detect` found the
    // instructions, and loads and stores stay inside the slices they are given.
    impl Simd for Neon {
        const LANES: usize = 4;
        type F = float32x4_t;
        type I = int32x4_t;
        type M = uint32x4_t;

        fn detect() -> Option<Neon> {
            std::arch::is_aarch64_feature_detected!("neon").then_some(Neon(()))
        }

        #[inline(always)]
        fn splat(self, x: f32) -> float32x4_t {
            unsafe { vdupq_n_f32(x) }
        }
        #[inline(always)]
        fn load(self, a: &[f32]) -> float32x4_t {
            let a = &a[..4];
            unsafe { vld1q_f32(a.as_ptr()) }
        }
        #[inline(always)]
        fn store(self, a: &mut [f32], v: float32x4_t) {
            let a = &mut a[..4];
            unsafe { vst1q_f32(a.as_mut_ptr(), v) }
        }
        #[inline(always)]
        fn add(self, a: float32x4_t, b: float32x4_t) -> float32x4_t {
            unsafe { vaddq_f32(a, b) }
        }
        #[inline(always)]
        fn sub(self, a: float32x4_t, b: float32x4_t) -> float32x4_t {
            unsafe { vsubq_f32(a, b) }
        }
        #[inline(always)]
        fn mul(self, a: float32x4_t, b: float32x4_t) -> float32x4_t {
            unsafe { vmulq_f32(a, b) }
        }
        #[inline(always)]
        fn mul_add(self, a: float32x4_t, b: float32x4_t, c: float32x4_t) -> float32x4_t {
            unsafe { vfmaq_f32(c, a, b) }
        }
        #[inline(always)]
        fn neg_mul_add(self, a: float32x4_t, b: float32x4_t, c: float32x4_t) -> float32x4_t {
            unsafe { vfmsq_f32(c, a, b) }
        }
        #[inline(always)]
        fn min(self, a: float32x4_t, b: float32x4_t) -> float32x4_t {
            unsafe { vbslq_f32(vcltq_f32(a, b), a, b) }
        }
        #[inline(always)]
        fn max(self, a: float32x4_t, b: float32x4_t) -> float32x4_t {
            unsafe { vbslq_f32(vcgtq_f32(a, b), a, b) }
        }
        #[inline(always)]
        fn floor(self, a: float32x4_t) -> float32x4_t {
            unsafe { vrndmq_f32(a) }
        }
        #[inline(always)]
        fn ceil(self, a: float32x4_t) -> float32x4_t {
            unsafe { vrndpq_f32(a) }
        }
        #[inline(always)]
        fn abs(self, a: float32x4_t) -> float32x4_t {
            unsafe { vabsq_f32(a) }
        }
        #[inline(always)]
        fn sqrt(self, a: float32x4_t) -> float32x4_t {
            unsafe { vsqrtq_f32(a) }
        }
        #[inline(always)]
        fn div(self, a: float32x4_t, b: float32x4_t) -> float32x4_t {
            unsafe { vdivq_f32(a, b) }
        }
        #[inline(always)]
        fn lt(self, a: float32x4_t, b: float32x4_t) -> uint32x4_t {
            unsafe { vcltq_f32(a, b) }
        }
        #[inline(always)]
        fn le(self, a: float32x4_t, b: float32x4_t) -> uint32x4_t {
            unsafe { vcleq_f32(a, b) }
        }
        #[inline(always)]
        fn gt(self, a: float32x4_t, b: float32x4_t) -> uint32x4_t {
            unsafe { vcgtq_f32(a, b) }
        }
        #[inline(always)]
        fn ge(self, a: float32x4_t, b: float32x4_t) -> uint32x4_t {
            unsafe { vcgeq_f32(a, b) }
        }
        #[inline(always)]
        fn ne(self, a: float32x4_t, b: float32x4_t) -> uint32x4_t {
            unsafe { vmvnq_u32(vceqq_f32(a, b)) }
        }
        #[inline(always)]
        fn is_nan(self, a: float32x4_t) -> uint32x4_t {
            unsafe { vmvnq_u32(vceqq_f32(a, a)) }
        }
        #[inline(always)]
        fn select(self, m: uint32x4_t, a: float32x4_t, b: float32x4_t) -> float32x4_t {
            unsafe { vbslq_f32(m, a, b) }
        }
        #[inline(always)]
        fn to_i32(self, a: float32x4_t) -> int32x4_t {
            unsafe { vcvtq_s32_f32(a) }
        }
        #[inline(always)]
        fn to_f32(self, a: int32x4_t) -> float32x4_t {
            unsafe { vcvtq_f32_s32(a) }
        }
        #[inline(always)]
        fn splat_i(self, x: i32) -> int32x4_t {
            unsafe { vdupq_n_s32(x) }
        }
        #[inline(always)]
        fn load_i(self, a: &[i32]) -> int32x4_t {
            let a = &a[..4];
            unsafe { vld1q_s32(a.as_ptr()) }
        }
        #[inline(always)]
        fn store_i(self, a: &mut [i32], v: int32x4_t) {
            let a = &mut a[..4];
            unsafe { vst1q_s32(a.as_mut_ptr(), v) }
        }
        #[inline(always)]
        fn add_i(self, a: int32x4_t, b: int32x4_t) -> int32x4_t {
            unsafe { vaddq_s32(a, b) }
        }
        #[inline(always)]
        fn mul_i(self, a: int32x4_t, b: int32x4_t) -> int32x4_t {
            unsafe { vmulq_s32(a, b) }
        }
        #[inline(always)]
        fn and_i(self, a: int32x4_t, b: int32x4_t) -> int32x4_t {
            unsafe { vandq_s32(a, b) }
        }
        #[inline(always)]
        fn shr_i(self, a: int32x4_t, n: u32) -> int32x4_t {
            // A left shift by a negative count shifts right.
            unsafe { vreinterpretq_s32_u32(vshlq_u32(vreinterpretq_u32_s32(a), vdupq_n_s32(-(n as i32)))) }
        }
        #[inline(always)]
        fn shl_i(self, a: int32x4_t, n: u32) -> int32x4_t {
            unsafe { vreinterpretq_s32_u32(vshlq_u32(vreinterpretq_u32_s32(a), vdupq_n_s32(n as i32))) }
        }
        #[inline(always)]
        fn to_bits(self, a: float32x4_t) -> int32x4_t {
            unsafe { vreinterpretq_s32_f32(a) }
        }
        #[inline(always)]
        fn bits_to_f32(self, a: int32x4_t) -> float32x4_t {
            unsafe { vreinterpretq_f32_s32(a) }
        }
        #[inline(always)]
        fn shr_each_i(self, a: int32x4_t, n: int32x4_t) -> int32x4_t {
            unsafe { vreinterpretq_s32_u32(vshlq_u32(vreinterpretq_u32_s32(a), vnegq_s32(n))) }
        }
        #[inline(always)]
        fn gt_i(self, a: int32x4_t, b: int32x4_t) -> uint32x4_t {
            unsafe { vcgtq_s32(a, b) }
        }
        #[inline(always)]
        fn count_i(self, a: int32x4_t, m: uint32x4_t) -> int32x4_t {
            // A set lane is −1.
            unsafe { vsubq_s32(a, vreinterpretq_s32_u32(m)) }
        }
        #[inline(always)]
        unsafe fn gather<const SCALE: i32>(self, base: *const u8, i: int32x4_t) -> int32x4_t {
            let mut lanes = [0i32; 4];
            vst1q_s32(lanes.as_mut_ptr(), i);
            for l in &mut lanes {
                *l = word::<SCALE>(base, *l);
            }
            vld1q_s32(lanes.as_ptr())
        }
        #[inline(always)]
        unsafe fn gather_in<const SCALE: i32>(self, base: *const u8, i: int32x4_t, m: uint32x4_t) -> int32x4_t {
            let (mut lanes, mut wanted) = ([0i32; 4], [0u32; 4]);
            vst1q_s32(lanes.as_mut_ptr(), i);
            vst1q_u32(wanted.as_mut_ptr(), m);
            for (l, &w) in lanes.iter_mut().zip(&wanted) {
                *l = if w != 0 { word::<SCALE>(base, *l) } else { 0 };
            }
            vld1q_s32(lanes.as_ptr())
        }
        #[inline(always)]
        fn lookup(self, table: &[f32; 32], _used: usize, i: int32x4_t) -> float32x4_t {
            let mut lanes = [0i32; 4];
            unsafe { vst1q_s32(lanes.as_mut_ptr(), i) };
            let values = lanes.map(|l| table[l as usize & 31]);
            unsafe { vld1q_f32(values.as_ptr()) }
        }
        #[inline(always)]
        fn bits(self, m: uint32x4_t) -> u32 {
            let lane: [u32; 4] = [1, 2, 4, 8];
            unsafe { vaddvq_u32(vandq_u32(m, vld1q_u32(lane.as_ptr()))) }
        }
        #[inline(always)]
        fn mask(self, bits: u32) -> uint32x4_t {
            let lane: [u32; 4] = [1, 2, 4, 8];
            unsafe { vtstq_u32(vdupq_n_u32(bits), vld1q_u32(lane.as_ptr())) }
        }
        #[inline(always)]
        fn and_m(self, a: uint32x4_t, b: uint32x4_t) -> uint32x4_t {
            unsafe { vandq_u32(a, b) }
        }
        #[inline(always)]
        fn or_m(self, a: uint32x4_t, b: uint32x4_t) -> uint32x4_t {
            unsafe { vorrq_u32(a, b) }
        }
    }
}
