//! [`Simd`] in AVX2 registers with FMA: eight f32 lanes, masks as lanes of ones, and the
//! table lookup as one in-register permute per eight entries used.

#[cfg(target_arch = "x86_64")]
pub(in crate::sampling) use imp::Avx2;

/// Where AVX2 cannot be: no token is ever made.
#[cfg(not(target_arch = "x86_64"))]
#[derive(Clone, Copy, Debug)]
pub(in crate::sampling) enum Avx2 {}

#[cfg(not(target_arch = "x86_64"))]
impl Avx2 {
    pub(in crate::sampling) fn detect() -> Option<Avx2> {
        None
    }
}

#[cfg(target_arch = "x86_64")]
mod imp {
    use std::arch::x86_64::*;

    use super::super::Simd;

    /// The token: the processor has AVX2 and FMA.
    #[derive(Clone, Copy, Debug)]
    pub(in crate::sampling) struct Avx2(());

    // SAFETY (every `unsafe` block below): an `Avx2` exists only where `detect` found the
    // instructions, and loads and stores stay inside the slices they are given.
    impl Simd for Avx2 {
        const LANES: usize = 8;
        type F = __m256;
        type I = __m256i;
        type M = __m256;

        fn detect() -> Option<Avx2> {
            let has = std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma");
            has.then_some(Avx2(()))
        }

        #[inline(always)]
        fn splat(self, x: f32) -> __m256 {
            unsafe { _mm256_set1_ps(x) }
        }
        #[inline(always)]
        fn load(self, a: &[f32]) -> __m256 {
            let a = &a[..8];
            unsafe { _mm256_loadu_ps(a.as_ptr()) }
        }
        #[inline(always)]
        fn store(self, a: &mut [f32], v: __m256) {
            let a = &mut a[..8];
            unsafe { _mm256_storeu_ps(a.as_mut_ptr(), v) }
        }
        #[inline(always)]
        fn add(self, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_add_ps(a, b) }
        }
        #[inline(always)]
        fn sub(self, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_sub_ps(a, b) }
        }
        #[inline(always)]
        fn mul(self, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_mul_ps(a, b) }
        }
        #[inline(always)]
        fn mul_add(self, a: __m256, b: __m256, c: __m256) -> __m256 {
            unsafe { _mm256_fmadd_ps(a, b, c) }
        }
        #[inline(always)]
        fn neg_mul_add(self, a: __m256, b: __m256, c: __m256) -> __m256 {
            unsafe { _mm256_fnmadd_ps(a, b, c) }
        }
        #[inline(always)]
        fn min(self, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_min_ps(a, b) }
        }
        #[inline(always)]
        fn max(self, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_max_ps(a, b) }
        }
        #[inline(always)]
        fn floor(self, a: __m256) -> __m256 {
            unsafe { _mm256_round_ps::<{ _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC }>(a) }
        }
        #[inline(always)]
        fn ceil(self, a: __m256) -> __m256 {
            unsafe { _mm256_round_ps::<{ _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC }>(a) }
        }
        #[inline(always)]
        fn abs(self, a: __m256) -> __m256 {
            unsafe { _mm256_andnot_ps(_mm256_set1_ps(-0.0), a) }
        }
        #[inline(always)]
        fn sqrt(self, a: __m256) -> __m256 {
            unsafe { _mm256_sqrt_ps(a) }
        }
        #[inline(always)]
        fn div(self, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_div_ps(a, b) }
        }
        #[inline(always)]
        fn lt(self, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_cmp_ps::<_CMP_LT_OQ>(a, b) }
        }
        #[inline(always)]
        fn le(self, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_cmp_ps::<_CMP_LE_OQ>(a, b) }
        }
        #[inline(always)]
        fn gt(self, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_cmp_ps::<_CMP_GT_OQ>(a, b) }
        }
        #[inline(always)]
        fn ge(self, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_cmp_ps::<_CMP_GE_OQ>(a, b) }
        }
        #[inline(always)]
        fn ne(self, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_cmp_ps::<_CMP_NEQ_UQ>(a, b) }
        }
        #[inline(always)]
        fn is_nan(self, a: __m256) -> __m256 {
            unsafe { _mm256_cmp_ps::<_CMP_UNORD_Q>(a, a) }
        }
        #[inline(always)]
        fn select(self, m: __m256, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_blendv_ps(b, a, m) }
        }
        #[inline(always)]
        fn to_i32(self, a: __m256) -> __m256i {
            unsafe { _mm256_cvttps_epi32(a) }
        }
        #[inline(always)]
        fn to_f32(self, a: __m256i) -> __m256 {
            unsafe { _mm256_cvtepi32_ps(a) }
        }
        #[inline(always)]
        fn splat_i(self, x: i32) -> __m256i {
            unsafe { _mm256_set1_epi32(x) }
        }
        #[inline(always)]
        fn load_i(self, a: &[i32]) -> __m256i {
            let a = &a[..8];
            unsafe { _mm256_loadu_si256(a.as_ptr().cast()) }
        }
        #[inline(always)]
        fn store_i(self, a: &mut [i32], v: __m256i) {
            let a = &mut a[..8];
            unsafe { _mm256_storeu_si256(a.as_mut_ptr().cast(), v) }
        }
        #[inline(always)]
        fn add_i(self, a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_add_epi32(a, b) }
        }
        #[inline(always)]
        fn mul_i(self, a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_mullo_epi32(a, b) }
        }
        #[inline(always)]
        fn and_i(self, a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_and_si256(a, b) }
        }
        #[inline(always)]
        fn shr_i(self, a: __m256i, n: u32) -> __m256i {
            unsafe { _mm256_srl_epi32(a, _mm_cvtsi32_si128(n as i32)) }
        }
        #[inline(always)]
        fn shl_i(self, a: __m256i, n: u32) -> __m256i {
            unsafe { _mm256_sll_epi32(a, _mm_cvtsi32_si128(n as i32)) }
        }
        #[inline(always)]
        fn to_bits(self, a: __m256) -> __m256i {
            unsafe { _mm256_castps_si256(a) }
        }
        #[inline(always)]
        fn bits_to_f32(self, a: __m256i) -> __m256 {
            unsafe { _mm256_castsi256_ps(a) }
        }
        #[inline(always)]
        fn shr_each_i(self, a: __m256i, n: __m256i) -> __m256i {
            unsafe { _mm256_srlv_epi32(a, n) }
        }
        #[inline(always)]
        fn gt_i(self, a: __m256i, b: __m256i) -> __m256 {
            unsafe { _mm256_castsi256_ps(_mm256_cmpgt_epi32(a, b)) }
        }
        #[inline(always)]
        fn count_i(self, a: __m256i, m: __m256) -> __m256i {
            // A set lane is −1.
            unsafe { _mm256_sub_epi32(a, _mm256_castps_si256(m)) }
        }
        #[inline(always)]
        unsafe fn gather<const SCALE: i32>(self, base: *const u8, i: __m256i) -> __m256i {
            _mm256_i32gather_epi32::<SCALE>(base.cast(), i)
        }
        #[inline(always)]
        unsafe fn gather_in<const SCALE: i32>(self, base: *const u8, i: __m256i, m: __m256) -> __m256i {
            _mm256_mask_i32gather_epi32::<SCALE>(_mm256_setzero_si256(), base.cast(), i, _mm256_castps_si256(m))
        }
        #[inline(always)]
        fn lookup(self, table: &[f32; 32], used: usize, i: __m256i) -> __m256 {
            // Eight entries per permute; a lane takes the permute of its block of eight.
            unsafe {
                let mut out = _mm256_permutevar8x32_ps(_mm256_loadu_ps(table.as_ptr()), i);
                for block in 1..used.div_ceil(8).min(4) {
                    let part = _mm256_permutevar8x32_ps(_mm256_loadu_ps(table.as_ptr().add(8 * block)), i);
                    let inside = _mm256_cmpgt_epi32(i, _mm256_set1_epi32(8 * block as i32 - 1));
                    out = _mm256_blendv_ps(out, part, _mm256_castsi256_ps(inside));
                }
                out
            }
        }
        #[inline(always)]
        fn bits(self, m: __m256) -> u32 {
            unsafe { _mm256_movemask_ps(m) as u32 }
        }
        #[inline(always)]
        fn mask(self, bits: u32) -> __m256 {
            unsafe {
                let lane = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
                let set = _mm256_and_si256(_mm256_set1_epi32(bits as i32), lane);
                _mm256_castsi256_ps(_mm256_cmpeq_epi32(set, lane))
            }
        }
        #[inline(always)]
        fn and_m(self, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_and_ps(a, b) }
        }
        #[inline(always)]
        fn or_m(self, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_or_ps(a, b) }
        }
    }
}
