//! (partial)
pub mod geometry;
pub mod interp;
