//! [`Simd`] in plain arrays of [`LANES`] lanes, for every target: the loop's operations lane
//! by lane in ordinary Rust, which the compiler may vectorise for the target's baseline
//! (SSE2 on x86-64) but need not. Multiplies and adds are not fused (a fused one is a
//! library call where the target has no FMA instruction), and floor and ceiling are
//! computed by adding and subtracting 2²³ rather than by `f32::floor`, which is a library
//! call without SSE4.1.

use super::{word, Simd};

/// Lanes per "register": four, the width of an SSE2 or NEON register, so that where the
/// compiler vectorises an array's lanes they fill one register (eight were 7–15% slower on
/// the CT head and the synthetic volume, BENCHMARKS.md, issue 19).
pub(in crate::sampling) const LANES: usize = 4;

/// The token: always available.
#[derive(Clone, Copy, Debug)]
pub(in crate::sampling) struct Scalar;

type F = [f32; LANES];
type I = [i32; LANES];
/// A lane of ones (−1) where set, zeros where not, as a vector compare writes it: a select
/// is then three bitwise operations on a register rather than a test per lane.
type M = [i32; LANES];

#[inline(always)]
fn each(a: F, f: impl Fn(f32) -> f32) -> F {
    let mut out = a;
    for o in &mut out {
        *o = f(*o);
    }
    out
}

#[inline(always)]
fn pair(a: F, b: F, f: impl Fn(f32, f32) -> f32) -> F {
    let mut out = a;
    for (o, b) in out.iter_mut().zip(b) {
        *o = f(*o, b);
    }
    out
}

#[inline(always)]
fn pair_i(a: I, b: I, f: impl Fn(i32, i32) -> i32) -> I {
    let mut out = a;
    for (o, b) in out.iter_mut().zip(b) {
        *o = f(*o, b);
    }
    out
}

#[inline(always)]
fn test(a: F, b: F, f: impl Fn(f32, f32) -> bool) -> M {
    let mut out = [0; LANES];
    for ((o, a), b) in out.iter_mut().zip(a).zip(b) {
        *o = -i32::from(f(a, b));
    }
    out
}

/// x rounded down (`up` false) or up: exact for every f32, NaN staying NaN. |x| ≥ 2²³ is
/// an integer already; below, |x| + 2²³ − 2²³ rounds |x| to the nearest integer, and one
/// step corrects the side. Every step is a plain operation or a select, with no branch and
/// no float-to-integer conversion (Rust's saturates, which costs several instructions a
/// lane), so that the compiler vectorises a register's lanes with SSE2: the truncating
/// form this replaced was a fifth of the scalar loop's time on the CT head (BENCHMARKS.md,
/// issue 19).
#[inline(always)]
fn round(x: f32, up: bool) -> f32 {
    const BIG: f32 = 8_388_608.0;
    let magnitude = x.abs();
    let nearest = if magnitude < BIG { ((magnitude + BIG) - BIG).copysign(x) } else { x };
    let rounded =
        if up { nearest - if nearest < x { -1.0 } else { 0.0 } } else { nearest - if nearest > x { 1.0 } else { 0.0 } };
    // The result has x's sign (a ceiling of −0.5 is −0, as `f32::ceil`'s).
    rounded.copysign(x)
}

/// `x as i32` (truncated; NaN 0, saturated out of range), written so that the compiler can
/// convert a register's lanes at once: `as` compiled lane by lane here, each with its
/// checks for NaN and range, some 5% of the scalar loop. Clamped into range and NaN made 0
/// first (both lane-wise selects), the conversion is the plain truncating one, the same
/// value for every input.
#[inline(always)]
fn to_i32(x: f32) -> i32 {
    // ±2³¹ are exact f32s; the largest f32 below 2³¹ is 2³¹ − 128.
    const LOW: f32 = -2_147_483_648.0;
    let big = x >= -LOW;
    let safe = if x.is_nan() || big {
        0.0
    } else if x < LOW {
        LOW
    } else {
        x
    };
    // SAFETY: `safe` is finite and in [−2³¹, 2³¹ − 128], where truncation fits an i32.
    let v = unsafe { safe.to_int_unchecked::<i32>() };
    if big {
        i32::MAX
    } else {
        v
    }
}

impl Simd for Scalar {
    const LANES: usize = LANES;
    type F = F;
    type I = I;
    type M = M;

    fn detect() -> Option<Scalar> {
        Some(Scalar)
    }

    #[inline(always)]
    fn splat(self, x: f32) -> F {
        [x; LANES]
    }
    #[inline(always)]
    fn load(self, a: &[f32]) -> F {
        a[..LANES].try_into().expect("LANES values")
    }
    #[inline(always)]
    fn store(self, a: &mut [f32], v: F) {
        a[..LANES].copy_from_slice(&v);
    }
    #[inline(always)]
    fn add(self, a: F, b: F) -> F {
        pair(a, b, |a, b| a + b)
    }
    #[inline(always)]
    fn sub(self, a: F, b: F) -> F {
        pair(a, b, |a, b| a - b)
    }
    #[inline(always)]
    fn mul(self, a: F, b: F) -> F {
        pair(a, b, |a, b| a * b)
    }
    #[inline(always)]
    fn mul_add(self, a: F, b: F, c: F) -> F {
        self.add(self.mul(a, b), c)
    }
    #[inline(always)]
    fn neg_mul_add(self, a: F, b: F, c: F) -> F {
        self.sub(c, self.mul(a, b))
    }
    #[inline(always)]
    fn min(self, a: F, b: F) -> F {
        pair(a, b, |a, b| if a < b { a } else { b })
    }
    #[inline(always)]
    fn max(self, a: F, b: F) -> F {
        pair(a, b, |a, b| if a > b { a } else { b })
    }
    #[inline(always)]
    fn floor(self, a: F) -> F {
        each(a, |x| round(x, false))
    }
    #[inline(always)]
    fn ceil(self, a: F) -> F {
        each(a, |x| round(x, true))
    }
    #[inline(always)]
    fn abs(self, a: F) -> F {
        each(a, f32::abs)
    }
    #[inline(always)]
    fn sqrt(self, a: F) -> F {
        each(a, f32::sqrt)
    }
    #[inline(always)]
    fn div(self, a: F, b: F) -> F {
        pair(a, b, |a, b| a / b)
    }
    #[inline(always)]
    fn lt(self, a: F, b: F) -> M {
        test(a, b, |a, b| a < b)
    }
    #[inline(always)]
    fn le(self, a: F, b: F) -> M {
        test(a, b, |a, b| a <= b)
    }
    #[inline(always)]
    fn gt(self, a: F, b: F) -> M {
        test(a, b, |a, b| a > b)
    }
    #[inline(always)]
    fn ge(self, a: F, b: F) -> M {
        test(a, b, |a, b| a >= b)
    }
    #[inline(always)]
    fn ne(self, a: F, b: F) -> M {
        test(a, b, |a, b| a != b)
    }
    #[inline(always)]
    fn is_nan(self, a: F) -> M {
        test(a, a, |a, _| a.is_nan())
    }
    #[inline(always)]
    fn select(self, m: M, a: F, b: F) -> F {
        let mut out = b;
        for ((o, m), a) in out.iter_mut().zip(m).zip(a) {
            let m = m as u32;
            *o = f32::from_bits((a.to_bits() & m) | (o.to_bits() & !m));
        }
        out
    }
    #[inline(always)]
    fn to_i32(self, a: F) -> I {
        a.map(to_i32)
    }
    #[inline(always)]
    fn to_f32(self, a: I) -> F {
        a.map(|x| x as f32)
    }
    #[inline(always)]
    fn splat_i(self, x: i32) -> I {
        [x; LANES]
    }
    #[inline(always)]
    fn load_i(self, a: &[i32]) -> I {
        a[..LANES].try_into().expect("LANES values")
    }
    #[inline(always)]
    fn store_i(self, a: &mut [i32], v: I) {
        a[..LANES].copy_from_slice(&v);
    }
    #[inline(always)]
    fn add_i(self, a: I, b: I) -> I {
        pair_i(a, b, i32::wrapping_add)
    }
    #[inline(always)]
    fn mul_i(self, a: I, b: I) -> I {
        pair_i(a, b, i32::wrapping_mul)
    }
    #[inline(always)]
    fn and_i(self, a: I, b: I) -> I {
        pair_i(a, b, |a, b| a & b)
    }
    #[inline(always)]
    fn shr_i(self, a: I, n: u32) -> I {
        a.map(|x| ((x as u32) >> (n & 31)) as i32)
    }
    #[inline(always)]
    fn shl_i(self, a: I, n: u32) -> I {
        a.map(|x| ((x as u32) << (n & 31)) as i32)
    }
    #[inline(always)]
    fn to_bits(self, a: F) -> I {
        a.map(|x| x.to_bits() as i32)
    }
    #[inline(always)]
    fn bits_to_f32(self, a: I) -> F {
        a.map(|x| f32::from_bits(x as u32))
    }
    #[inline(always)]
    fn shr_each_i(self, a: I, n: I) -> I {
        pair_i(a, n, |x, n| ((x as u32) >> (n as u32 & 31)) as i32)
    }
    #[inline(always)]
    fn gt_i(self, a: I, b: I) -> M {
        let mut out = [0; LANES];
        for ((o, a), b) in out.iter_mut().zip(a).zip(b) {
            *o = -i32::from(a > b);
        }
        out
    }
    #[inline(always)]
    fn count_i(self, a: I, m: M) -> I {
        let mut out = a;
        for (o, m) in out.iter_mut().zip(m) {
            *o -= m;
        }
        out
    }
    #[inline(always)]
    unsafe fn gather<const SCALE: i32>(self, base: *const u8, i: I) -> I {
        // SAFETY: the caller's promise.
        i.map(|i| unsafe { word::<SCALE>(base, i) })
    }
    #[inline(always)]
    unsafe fn gather_in<const SCALE: i32>(self, base: *const u8, i: I, m: M) -> I {
        // SAFETY: the caller's promise, for the lanes read.
        std::array::from_fn(|l| if m[l] != 0 { unsafe { word::<SCALE>(base, i[l]) } } else { 0 })
    }
    #[inline(always)]
    fn lookup(self, table: &[f32; 32], _used: usize, i: I) -> F {
        i.map(|i| table[i as usize & 31])
    }
    #[inline(always)]
    fn bits(self, m: M) -> u32 {
        m.iter().enumerate().fold(0, |bits, (l, &m)| bits | (m as u32 >> 31) << l)
    }
    #[inline(always)]
    fn mask(self, bits: u32) -> M {
        std::array::from_fn(|l| -((bits >> l & 1) as i32))
    }
    #[inline(always)]
    fn and_m(self, a: M, b: M) -> M {
        std::array::from_fn(|l| a[l] & b[l])
    }
    #[inline(always)]
    fn or_m(self, a: M, b: M) -> M {
        std::array::from_fn(|l| a[l] | b[l])
    }
}

#[cfg(test)]
mod tests {
    use super::{round, to_i32};

    /// The branch-free floor and ceiling equal `f32::floor` and `f32::ceil` (bit for bit:
    /// −0 stays −0), on halves, near-integers, the edges of 2²³ and 2²⁴, both signs,
    /// infinities and NaN.
    #[test]
    fn floor_and_ceil_are_exact() {
        let mut xs: Vec<f32> = vec![0.0, 0.5, 1.0, 1.5, 2.5, 0.3, 0.7, 1e-30, 8_388_607.5, 8_388_608.0, 16_777_215.0];
        xs.extend([16_777_216.0, 3e9, 1e38, f32::MAX, f32::MIN_POSITIVE, f32::INFINITY, f32::EPSILON]);
        for i in 0..2000 {
            let x = i as f32 * 0.37 - 40.0;
            xs.extend([x, x.next_up(), x.next_down(), (i as f32).next_up(), (i as f32).next_down()]);
        }
        for &x in &xs.clone() {
            xs.push(-x);
        }
        for x in xs {
            assert_eq!(round(x, false).to_bits(), x.floor().to_bits(), "floor({x:e})");
            assert_eq!(round(x, true).to_bits(), x.ceil().to_bits(), "ceil({x:e})");
        }
        assert!(round(f32::NAN, false).is_nan() && round(f32::NAN, true).is_nan());
    }

    /// The lane-wise conversion is `as i32` for every input: both ends of i32's range and
    /// their neighbours, halves, infinities and NaN.
    #[test]
    fn conversion_is_as_i32() {
        let mut xs: Vec<f32> = vec![0.0, -0.0, 0.5, 0.99, 1.0, 1.5, 2_147_483_520.0, 2_147_483_648.0, 3e9, 1e38];
        xs.extend([f32::MAX, f32::INFINITY, f32::NAN, -2_147_483_648.0, f32::MIN_POSITIVE, 16_777_217.0]);
        for i in 0..3000 {
            let x = i as f32 * 0.25 - 300.0;
            xs.extend([x, x.next_up(), x.next_down()]);
        }
        for &x in &xs.clone() {
            xs.extend([-x, x.next_up(), x.next_down()]);
        }
        for x in xs {
            assert_eq!(to_i32(x), x as i32, "{x:e}");
        }
    }
}
