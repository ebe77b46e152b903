//! The vector width of the loops that are compiled for several instruction sets and give
//! the same bits on each (the intersection's slab tests, the macrocell scan at load), as
//! opposed to the sampler's packet loop, whose instruction set ([`crate::sampling::SimdPath`])
//! changes its rounding. A leaf, so that every layer can take a width from above.

/// How wide a loop compiled more than once may run: which instructions it is compiled for,
/// narrowest first. Every width gives the same bits (the loops using it do only exact or
/// unfused IEEE operations), so the width changes the speed only.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) enum VectorWidth {
    /// The target's baseline (two f64 lanes on x86-64's SSE2).
    Baseline,
    /// x86-64 AVX2: four f64 lanes.
    Avx2,
    /// x86-64 AVX-512 F: eight f64 lanes.
    Avx512,
}

impl VectorWidth {
    /// The widest this processor runs, narrowed to at most `cap` (the sampler's configured
    /// path, so that `TROVE_SIMD=scalar` keeps the whole render on the baseline).
    pub(crate) fn detect(cap: VectorWidth) -> VectorWidth {
        #[cfg(target_arch = "x86_64")]
        {
            let best = if std::arch::is_x86_feature_detected!("avx512f") {
                VectorWidth::Avx512
            } else if std::arch::is_x86_feature_detected!("avx2") {
                VectorWidth::Avx2
            } else {
                VectorWidth::Baseline
            };
            best.min(cap)
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = cap;
            VectorWidth::Baseline
        }
    }
}
