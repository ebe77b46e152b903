//! Interpolation functions (SPEC §3.3).
pub mod cubic;
