//! What a benchmark ran on, for the line above its table: the processor's model and the
//! SIMD path the sampler took (`TROVE_SIMD` forces one; BENCHMARKS.md records both).

use anyhow::Result;
use trove_core::SimdPath;

/// "processor: …, SIMD path: avx2 (this processor can run: avx512, avx2, scalar)"; an error
/// where `TROVE_SIMD` names a path this processor lacks, so that a forced run never
/// measures another path than the one asked for.
pub fn describe() -> Result<String> {
    let path = SimdPath::configured()?;
    let available = SimdPath::available().iter().map(|p| p.name()).collect::<Vec<_>>().join(", ");
    Ok(format!("processor: {}, SIMD path: {path} (this processor can run: {available})", processor()))
}

/// The processor's model name (Linux's `/proc/cpuinfo`), or the architecture elsewhere.
fn processor() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|info| {
            info.lines()
                .find(|l| l.starts_with("model name") || l.starts_with("Model"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, name)| name.trim().to_string())
        })
        .unwrap_or_else(|| std::env::consts::ARCH.to_string())
}
