//! Object-level geometry: camera rays (SPEC §4.1), object placement and ray segments
//! (§2, §4.2), and the split of overlapping segments into pieces. Nothing here reads a
//! voxel: the intersection phase needs only dims and placements (paper §3.3).

mod camera;
pub mod hexahedron;
mod pieces;
mod placement;
mod slab;

pub(crate) use camera::PixelRays;
pub(crate) use camera::PixelRect;
pub use camera::{Camera, CameraError, CameraField, Ray};
pub use pieces::{count_pieces, split_into_pieces, Piece, PieceScratch, Segment};
pub use placement::{
    sample_count, BoxOrigin, Extent, GradientToWorld, InversionPrecisionError, LineSamples, Placement, SampleWalk,
    Shape, VcLine, WorldPoints,
};
pub(crate) use slab::{Crossing, Crossings, RowDirections};
