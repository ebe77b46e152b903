//! [`Simd`] in AVX-512 registers: sixteen f32 lanes, masks in mask registers, a 32-entry
//! table lookup in one two-register permute.

#[cfg(target_arch = "x86_64")]
pub(in crate::sampling) use imp::Avx512;

/// Where AVX-512 cannot be: no token is ever made.
#[cfg(not(target_arch = "x86_64"))]
#[derive(Clone, Copy, Debug)]
pub(in crate::sampling) enum Avx512 {}

#[cfg(not(target_arch = "x86_64"))]
impl Avx512 {
    pub(in crate::sampling) fn detect() -> Option<Avx512> {
        None
    }
}

#[cfg(target_arch = "x86_64")]
mod imp {
    use std::arch::x86_64::*;

    use super::super::Simd;

    /// The token: the processor has AVX-512 F, DQ and VL, AVX2 and FMA.
    #[derive(Clone, Copy, Debug)]
    pub(in crate::sampling) struct Avx512(());

    // SAFETY (every `unsafe` block below): an `Avx512` exists only where `detect` found the
    // instructions, and loads and stores stay inside the slices they are given.
    impl Simd for Avx512 {
        const LANES: usize = 16;
        type F = __m512;
        type I = __m512i;
        type M = __mmask16;

        fn detect() -> Option<Avx512> {
            let has = std::is_x86_feature_detected!("avx512f")
                && std::is_x86_feature_detected!("avx512dq")
                && std::is_x86_feature_detected!("avx512vl")
                && std::is_x86_feature_detected!("avx2")
                && std::is_x86_feature_detected!("fma");
            has.then_some(Avx512(()))
        }

        #[inline(always)]
        fn splat(self, x: f32) -> __m512 {
            unsafe { _mm512_set1_ps(x) }
        }
        #[inline(always)]
        fn load(self, a: &[f32]) -> __m512 {
            let a = &a[..16];
            unsafe { _mm512_loadu_ps(a.as_ptr()) }
        }
        #[inline(always)]
        fn store(self, a: &mut [f32], v: __m512) {
            let a = &mut a[..16];
            unsafe { _mm512_storeu_ps(a.as_mut_ptr(), v) }
        }
        #[inline(always)]
        fn add(self, a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_add_ps(a, b) }
        }
        #[inline(always)]
        fn sub(self, a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_sub_ps(a, b) }
        }
        #[inline(always)]
        fn mul(self, a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_mul_ps(a, b) }
        }
        #[inline(always)]
        fn mul_add(self, a: __m512, b: __m512, c: __m512) -> __m512 {
            unsafe { _mm512_fmadd_ps(a, b, c) }
        }
        #[inline(always)]
        fn neg_mul_add(self, a: __m512, b: __m512, c: __m512) -> __m512 {
            unsafe { _mm512_fnmadd_ps(a, b, c) }
        }
        #[inline(always)]
        fn min(self, a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_min_ps(a, b) }
        }
        #[inline(always)]
        fn max(self, a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_max_ps(a, b) }
        }
        #[inline(always)]
        fn floor(self, a: __m512) -> __m512 {
            unsafe { _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC }>(a) }
        }
        #[inline(always)]
        fn ceil(self, a: __m512) -> __m512 {
            unsafe { _mm512_roundscale_ps::<{ _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC }>(a) }
        }
        #[inline(always)]
        fn abs(self, a: __m512) -> __m512 {
            unsafe { _mm512_andnot_ps(_mm512_set1_ps(-0.0), a) }
        }
        #[inline(always)]
        fn sqrt(self, a: __m512) -> __m512 {
            unsafe { _mm512_sqrt_ps(a) }
        }
        #[inline(always)]
        fn div(self, a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_div_ps(a, b) }
        }
        #[inline(always)]
        fn lt(self, a: __m512, b: __m512) -> __mmask16 {
            unsafe { _mm512_cmp_ps_mask::<_CMP_LT_OQ>(a, b) }
        }
        #[inline(always)]
        fn le(self, a: __m512, b: __m512) -> __mmask16 {
            unsafe { _mm512_cmp_ps_mask::<_CMP_LE_OQ>(a, b) }
        }
        #[inline(always)]
        fn gt(self, a: __m512, b: __m512) -> __mmask16 {
            unsafe { _mm512_cmp_ps_mask::<_CMP_GT_OQ>(a, b) }
        }
        #[inline(always)]
        fn ge(self, a: __m512, b: __m512) -> __mmask16 {
            unsafe { _mm512_cmp_ps_mask::<_CMP_GE_OQ>(a, b) }
        }
        #[inline(always)]
        fn ne(self, a: __m512, b: __m512) -> __mmask16 {
            unsafe { _mm512_cmp_ps_mask::<_CMP_NEQ_UQ>(a, b) }
        }
        #[inline(always)]
        fn is_nan(self, a: __m512) -> __mmask16 {
            unsafe { _mm512_cmp_ps_mask::<_CMP_UNORD_Q>(a, a) }
        }
        #[inline(always)]
        fn select(self, m: __mmask16, a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_mask_blend_ps(m, b, a) }
        }
        #[inline(always)]
        fn to_i32(self, a: __m512) -> __m512i {
            unsafe { _mm512_cvttps_epi32(a) }
        }
        #[inline(always)]
        fn to_f32(self, a: __m512i) -> __m512 {
            unsafe { _mm512_cvtepi32_ps(a) }
        }
        #[inline(always)]
        fn splat_i(self, x: i32) -> __m512i {
            unsafe { _mm512_set1_epi32(x) }
        }
        #[inline(always)]
        fn load_i(self, a: &[i32]) -> __m512i {
            let a = &a[..16];
            unsafe { _mm512_loadu_si512(a.as_ptr().cast()) }
        }
        #[inline(always)]
        fn store_i(self, a: &mut [i32], v: __m512i) {
            let a = &mut a[..16];
            unsafe { _mm512_storeu_si512(a.as_mut_ptr().cast(), v) }
        }
        #[inline(always)]
        fn add_i(self, a: __m512i, b: __m512i) -> __m512i {
            unsafe { _mm512_add_epi32(a, b) }
        }
        #[inline(always)]
        fn mul_i(self, a: __m512i, b: __m512i) -> __m512i {
            unsafe { _mm512_mullo_epi32(a, b) }
        }
        #[inline(always)]
        fn and_i(self, a: __m512i, b: __m512i) -> __m512i {
            unsafe { _mm512_and_si512(a, b) }
        }
        #[inline(always)]
        fn shr_i(self, a: __m512i, n: u32) -> __m512i {
            unsafe { _mm512_srl_epi32(a, _mm_cvtsi32_si128(n as i32)) }
        }
        #[inline(always)]
        fn shl_i(self, a: __m512i, n: u32) -> __m512i {
            unsafe { _mm512_sll_epi32(a, _mm_cvtsi32_si128(n as i32)) }
        }
        #[inline(always)]
        fn to_bits(self, a: __m512) -> __m512i {
            unsafe { _mm512_castps_si512(a) }
        }
        #[inline(always)]
        fn bits_to_f32(self, a: __m512i) -> __m512 {
            unsafe { _mm512_castsi512_ps(a) }
        }
        #[inline(always)]
        fn shr_each_i(self, a: __m512i, n: __m512i) -> __m512i {
            unsafe { _mm512_srlv_epi32(a, n) }
        }
        #[inline(always)]
        fn gt_i(self, a: __m512i, b: __m512i) -> __mmask16 {
            unsafe { _mm512_cmpgt_epi32_mask(a, b) }
        }
        #[inline(always)]
        fn count_i(self, a: __m512i, m: __mmask16) -> __m512i {
            unsafe { _mm512_mask_add_epi32(a, m, a, _mm512_set1_epi32(1)) }
        }
        #[inline(always)]
        unsafe fn gather<const SCALE: i32>(self, base: *const u8, i: __m512i) -> __m512i {
            _mm512_i32gather_epi32::<SCALE>(i, base.cast())
        }
        #[inline(always)]
        unsafe fn gather_in<const SCALE: i32>(self, base: *const u8, i: __m512i, m: __mmask16) -> __m512i {
            _mm512_mask_i32gather_epi32::<SCALE>(_mm512_setzero_si512(), m, i, base.cast())
        }
        #[inline(always)]
        fn lookup(self, table: &[f32; 32], _used: usize, i: __m512i) -> __m512 {
            unsafe {
                _mm512_permutex2var_ps(_mm512_loadu_ps(table.as_ptr()), i, _mm512_loadu_ps(table.as_ptr().add(16)))
            }
        }
        #[inline(always)]
        fn bits(self, m: __mmask16) -> u32 {
            u32::from(m)
        }
        #[inline(always)]
        fn mask(self, bits: u32) -> __mmask16 {
            bits as __mmask16
        }
        #[inline(always)]
        fn and_m(self, a: __mmask16, b: __mmask16) -> __mmask16 {
            a & b
        }
        #[inline(always)]
        fn or_m(self, a: __mmask16, b: __mmask16) -> __mmask16 {
            a | b
        }
    }
}
