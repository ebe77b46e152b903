//! Object geometry: the hexahedral boxes that place datasets in the world (SPEC §2, §4.2).
pub mod hexahedron;
