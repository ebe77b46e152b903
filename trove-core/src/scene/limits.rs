//! The numbers and names a scene's rules are stated in: the checks (`load`, `mappings`) and
//! the messages that quote them (`error`) both read them here, so neither of those imports
//! the other and a message cannot quote a limit other than the one its check applied.

/// Largest image side accepted, in pixels.
pub const MAX_IMAGE_SIDE: u32 = 16_384;
/// Largest number of objects (and of datasets) in one scene.
pub const MAX_OBJECTS: usize = 4_096;
/// Largest number of lights in one scene: a shaded sample's cost grows with each.
pub const MAX_LIGHTS: usize = 64;
/// Largest number of samples one object may take over one piece of one ray; a scene whose
/// sampling distance could exceed it is refused at load rather than rendering for hours.
pub const MAX_SAMPLES_PER_PIECE: f64 = (1u64 << 24) as f64;
/// Largest number of samples a whole render may take, estimated at load as pixels × Σ over
/// objects of the samples one ray through the object's bounding-box diagonal takes (an
/// upper bound). 2³⁵ ≈ 3.4·10¹⁰ admits a 4096² image of a 512³ volume at half a voxel per
/// step; beyond it a scene (say a 10⁻⁶ step on a 512² image, which passes the per-piece
/// cap) would render for hours, so it is refused with the numbers instead.
pub const MAX_SAMPLES_PER_RENDER: f64 = (1u64 << 35) as f64;

/// Largest number of coefficients in a general polynomial map.
pub const MAX_POLYNOMIAL_TERMS: usize = 32;
/// Largest number of LUT domains or ramp points.
pub const MAX_TABLE_ENTRIES: usize = 65_536;

/// The interpolations a scene may name, for messages.
pub(super) const INTERPOLATIONS: &str =
    "\"nearest\", \"trilinear\", \"cubic\" or { type = \"nonlinear\", omega = [w0, w1, w2] }";
