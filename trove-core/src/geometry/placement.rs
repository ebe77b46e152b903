//! Where an object sits (paper §2.3.5, SPEC §2): its box in the world, the extent
//! sub-box of its dataset that fills it, and the map from world points to volume
//! coordinates (VC) that sampling needs.

use glam::{DMat3, DMat4, DVec3};
use thiserror::Error;

use super::hexahedron::{Hexahedron, Q};
use super::Ray;
use crate::dataset::Dims;

/// The NVC sub-box of a dataset that fills the object's box (clips and stretches).
/// Invariant: 0 ≤ min < max ≤ 1 per axis, checked by the scene validator.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Extent {
    /// Lower NVC corner.
    pub min: DVec3,
    /// Upper NVC corner.
    pub max: DVec3,
}

impl Extent {
    /// The whole dataset.
    pub const FULL: Extent = Extent { min: DVec3::ZERO, max: DVec3::ONE };
}

/// A distorted box that does not fold but comes so close to folding that f64 cannot invert
/// its world map to the SPEC §4.2 tolerance somewhere (see
/// [`Placement::check_inversion_precision`]).
#[derive(Clone, Copy, Debug, PartialEq, Error)]
#[error(
    "the box is too close to folding near box coordinates {}: its map cannot be inverted there to better \
     than about {attainable_voxels:.1e} voxel in f64 (1e-6 is required); move the corners further from folding",
    Q(*near)
)]
pub struct InversionPrecisionError {
    /// Box coordinates of the worst-conditioned grid point.
    pub near: [f64; 3],
    /// The precision attainable there, in voxels.
    pub attainable_voxels: f64,
}

/// The shape of an object's box.
// One per object and read on every ray: keeping the matrices inline avoids a pointer chase
// in the intersection loop, which matters more than the enum's size.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug)]
pub enum Shape {
    /// A parallelepiped (from a matrix, or eight corners that form one).
    Affine {
        /// Box coordinates q ∈ \[0,1\]³ → world.
        world_from_box: DMat4,
        /// World → box coordinates.
        box_from_world: DMat4,
    },
    /// A distorted hexahedron: trilinear corner blend, inverted per sample.
    Distorted {
        /// The validated (non-folding) hexahedron.
        hex: Box<Hexahedron>,
        /// Sample along the straight VC line between the mapped end points (the paper's
        /// fast approximation, §3.1) instead of inverting the map at every sample.
        straight: bool,
    },
}

/// An object's placement: shape, extent and the dataset dims that fix VC.
#[derive(Clone, Debug)]
pub struct Placement {
    shape: Shape,
    extent: Extent,
    /// The dataset's dims, which fix VC.
    dims: Dims,
    /// VC = vc_scale * q + vc_offset (per axis).
    vc_scale: DVec3,
    vc_offset: DVec3,
    /// World → VC, for affine shapes.
    vc_from_world: DMat4,
    /// Tolerance on box coordinates for the exact inversion: 1e-6 voxel.
    tol_q: f64,
}

/// Relative slack (64 ulps of the largest box coordinate involved) within which a ray that
/// runs along a face plane counts as lying in it, so that rounding in the world → box
/// transform cannot push a ray in a face plane out of the closed box (SPEC §4.5). The slack
/// applies only to axes the ray is parallel to within that rounding: on every other axis the
/// entry and exit are exact, so no chord is lengthened by it (a fixed 1e-12·|o| slack made
/// chords 5e-11 too long at unit scale and 1e-6 too long with the camera 10⁶ away).
const BOX_SLACK: f64 = 64.0 * f64::EPSILON;

/// Points per axis, minus one, of the grid on which a distorted box's conditioning is
/// estimated ([`Placement::check_inversion_precision`]).
const CONDITION_GRID: usize = 8;

impl Placement {
    /// A placement; the shape and extent were validated by the scene loader.
    pub fn new(shape: Shape, extent: Extent, dims: Dims) -> Placement {
        let n = DVec3::new(dims.axis(0) as f64, dims.axis(1) as f64, dims.axis(2) as f64);
        let vc_scale = (extent.max - extent.min) * n;
        let vc_offset = extent.min * n - DVec3::splat(0.5);
        let box_to_vc = DMat4::from_cols(
            DVec3::new(vc_scale.x, 0.0, 0.0).extend(0.0),
            DVec3::new(0.0, vc_scale.y, 0.0).extend(0.0),
            DVec3::new(0.0, 0.0, vc_scale.z).extend(0.0),
            vc_offset.extend(1.0),
        );
        let vc_from_world = match &shape {
            Shape::Affine { box_from_world, .. } => box_to_vc * *box_from_world,
            Shape::Distorted { .. } => DMat4::NAN,
        };
        let tol_q = 1e-6 / vc_scale.max_element();
        Placement { shape, extent, dims, vc_scale, vc_offset, vc_from_world, tol_q }
    }

    /// Chooses straight-line sampling (true) or exact inversion for a distorted box; affine
    /// boxes are unaffected.
    pub fn set_straight(&mut self, straight_line: bool) {
        if let Shape::Distorted { straight, .. } = &mut self.shape {
            *straight = straight_line;
        }
    }

    /// The shape.
    pub fn shape(&self) -> &Shape {
        &self.shape
    }

    /// The extent.
    pub fn extent(&self) -> Extent {
        self.extent
    }

    /// The dims of the dataset this placement maps into.
    pub fn dims(&self) -> Dims {
        self.dims
    }

    /// The eight world corners, index x + 2y + 4z.
    pub fn corners(&self) -> [DVec3; 8] {
        match &self.shape {
            Shape::Affine { world_from_box, .. } => super::hexahedron::corners_of_affine(world_from_box),
            Shape::Distorted { hex, .. } => *hex.corners(),
        }
    }

    /// VC of box coordinates q.
    #[inline]
    pub fn vc_of_box(&self, q: DVec3) -> DVec3 {
        self.vc_scale * q + self.vc_offset
    }

    /// Box coordinates of VC point `vc` ([`Placement::vc_of_box`]'s inverse).
    #[inline]
    pub fn box_of_vc(&self, vc: DVec3) -> DVec3 {
        (vc - self.vc_offset) / self.vc_scale
    }

    /// The world point at box coordinates `q` (the unit cube maps onto the hexahedron).
    pub fn world_of_box(&self, q: DVec3) -> DVec3 {
        match &self.shape {
            Shape::Affine { world_from_box, .. } => world_from_box.transform_point3(q),
            Shape::Distorted { hex, .. } => hex.world(q),
        }
    }

    /// For a distorted box, whether f64 can invert its world map to the SPEC §4.2 tolerance
    /// (10⁻⁶ voxel) everywhere in it; the error says where it cannot. Affine boxes always can.
    ///
    /// A box that does not fold (which [`Hexahedron::new`] proves) can still come so close
    /// to folding that its Jacobian is nearly singular somewhere: the world point W(q) is
    /// only known to about ε·(coordinate size), so q is only known to about that times
    /// ‖J⁻¹‖, however well Newton converges. Where that exceeds the tolerance the sampled
    /// voxels would be wrong by more than the SPEC allows, so the scene is refused at load
    /// instead of rendering a wrong image. ‖J⁻¹‖ is estimated on a grid of 9³ points,
    /// corners and faces included (the polynomial det J is smallest on the boundary unless
    /// the box bends inward, and the grid then still brackets it to a fraction of its
    /// variation); the factor 4 was measured on boxes approaching a fold at a corner.
    pub fn check_inversion_precision(&self) -> Result<(), InversionPrecisionError> {
        let Shape::Distorted { hex, .. } = &self.shape else { return Ok(()) };
        let scale = hex.size() + hex.corners().iter().map(|c| c.abs().max_element()).fold(0.0, f64::max);
        let mut worst = (0.0f64, DVec3::ZERO);
        for i in 0..=CONDITION_GRID {
            for j in 0..=CONDITION_GRID {
                for k in 0..=CONDITION_GRID {
                    let q = DVec3::new(i as f64, j as f64, k as f64) / CONDITION_GRID as f64;
                    let inv = hex.jacobian(q).inverse();
                    let norm =
                        (inv.x_axis.length_squared() + inv.y_axis.length_squared() + inv.z_axis.length_squared())
                            .sqrt();
                    let norm = if norm.is_finite() { norm } else { f64::INFINITY };
                    if norm > worst.0 {
                        worst = (norm, q);
                    }
                }
            }
        }
        let attainable_q = 4.0 * f64::EPSILON * scale * worst.0;
        if attainable_q <= self.tol_q {
            return Ok(());
        }
        Err(InversionPrecisionError { near: worst.1.to_array(), attainable_voxels: attainable_q / self.tol_q * 1e-6 })
    }

    /// The first and last t ≥ 0 at which the ray is inside the closed box (SPEC §4.2).
    pub fn segment(&self, ray: &Ray) -> Option<(f64, f64)> {
        match &self.shape {
            Shape::Affine { box_from_world, .. } => {
                let linear = DMat3::from_mat4(*box_from_world);
                BoxOrigin::new(ray.origin, box_from_world.transform_point3(ray.origin), linear).segment(ray)
            }
            Shape::Distorted { hex, .. } => hex.segment(ray.origin, ray.dir),
        }
    }

    /// What [`Placement::segment`] works out from a ray's origin alone, for an affine box:
    /// every ray of a pinhole camera starts at the eye, so the intersection phase does this
    /// once per object instead of once per ray. `None` for a distorted box.
    pub fn box_origin(&self, origin: DVec3) -> Option<BoxOrigin> {
        match &self.shape {
            Shape::Affine { box_from_world, .. } => {
                let linear = DMat3::from_mat4(*box_from_world);
                Some(BoxOrigin::new(origin, box_from_world.transform_point3(origin), linear))
            }
            Shape::Distorted { .. } => None,
        }
    }

    /// [`Placement::segment`], with the origin's part taken from `from` when the ray starts
    /// where `from` was worked out: the same operations on the same values, so the same
    /// segment to the bit.
    pub fn segment_from(&self, from: Option<&BoxOrigin>, ray: &Ray) -> Option<(f64, f64)> {
        match (&self.shape, from) {
            (Shape::Affine { .. }, Some(o)) if o.starts(ray) => o.segment(ray),
            _ => self.segment(ray),
        }
    }

    /// The world length of one VC step along the ray direction (for sampling-distance
    /// sanity checks): the norm of d(VC)/dt for affine boxes.
    pub fn vc_per_world(&self, dir: DVec3) -> f64 {
        self.vc_from_world.transform_vector3(dir).length()
    }

    /// What turns a VC gradient into a world one at a VC point (SPEC §6): the inverse
    /// transpose of the VC → world Jacobian there.
    pub fn gradient_to_world(&self) -> GradientToWorld<'_> {
        match &self.shape {
            // World → VC is linear plus an offset, so its Jacobian M is constant and the VC →
            // world Jacobian's inverse transpose is Mᵀ.
            Shape::Affine { .. } => GradientToWorld::Affine(DMat3::from_mat4(self.vc_from_world).transpose()),
            Shape::Distorted { hex, .. } => {
                GradientToWorld::Distorted { hex, vc_scale: self.vc_scale, vc_offset: self.vc_offset }
            }
        }
    }

    /// The samples of this object over the piece [t0, t1] of `ray` (SPEC §4.2–4.3):
    /// `sampling_distance` 0 means one voxel per step.
    pub fn walk(&self, ray: &Ray, t0: f64, t1: f64, sampling_distance: f64) -> SampleWalk<'_> {
        let len = t1 - t0;
        let (state, vc_len) = match &self.shape {
            Shape::Affine { .. } => {
                let vc0 = self.vc_from_world.transform_point3(ray.at(t0));
                let vc1 = self.vc_from_world.transform_point3(ray.at(t1));
                (WalkState::Line { vc0, delta: vc1 - vc0 }, (vc1 - vc0).length())
            }
            Shape::Distorted { hex, straight } => {
                let q0 = hex.invert(ray.at(t0), None, self.tol_q);
                let q1 = hex.invert(ray.at(t1), q0, self.tol_q);
                match (q0, q1) {
                    (Some(q0), Some(q1)) => {
                        let (vc0, vc1) = (self.vc_of_box(q0), self.vc_of_box(q1));
                        let state = if *straight {
                            WalkState::Line { vc0, delta: vc1 - vc0 }
                        } else {
                            WalkState::Exact { hex, prev_q: q0, prev_vc: vc0 }
                        };
                        (state, (vc1 - vc0).length())
                    }
                    _ => (WalkState::Failed, 0.0),
                }
            }
        };
        let n = sample_count(len, sampling_distance, vc_len);
        SampleWalk { placement: self, ray: *ray, t0, dt: len / n as f64, n, k: 0, state }
    }
}

/// The inverse transpose of an object's VC → world Jacobian, which takes a gradient of a
/// field over VC to the world gradient of the same field ([`Placement::gradient_to_world`]).
#[derive(Clone, Copy, Debug)]
pub enum GradientToWorld<'a> {
    /// An affine box: the constant matrix (world → VC Jacobian, transposed).
    Affine(DMat3),
    /// A distorted box: world = W(q), VC = scale·q + offset, so the VC → world Jacobian at a
    /// point is J_W(q)·diag(scale)⁻¹, whose inverse transpose is J_W(q)⁻ᵀ·diag(scale).
    Distorted {
        /// The box's map W.
        hex: &'a Hexahedron,
        /// VC per unit of q, per axis.
        vc_scale: DVec3,
        /// VC at q = 0.
        vc_offset: DVec3,
    },
}

impl GradientToWorld<'_> {
    /// The world gradient at VC point `vc` of a field whose VC gradient there is `g`.
    /// Non-finite only where the map is singular (which a validated box is not inside).
    #[inline]
    pub fn apply(&self, vc: DVec3, g: DVec3) -> DVec3 {
        match self {
            GradientToWorld::Affine(m) => *m * g,
            GradientToWorld::Distorted { hex, vc_scale, vc_offset } => {
                let q = (vc - *vc_offset) / *vc_scale;
                hex.jacobian(q).inverse().transpose() * (*vc_scale * g)
            }
        }
    }
}

/// The number of samples over a piece (SPEC §4.2): round(L/Δ), or round(VC length) when Δ
/// is 0, at least 1, with `round` half away from zero. The argument is snapped to the
/// nearest half-integer within the SPEC §4.5 tolerance so rounding noise cannot flip n.
#[inline]
pub fn sample_count(world_len: f64, sampling_distance: f64, vc_len: f64) -> u64 {
    let x = if sampling_distance > 0.0 { world_len / sampling_distance } else { vc_len };
    let half = round_half_away(x * 2.0) / 2.0;
    let x = if (x - half).abs() <= 1e-9 * x.abs().max(1.0) { half } else { x };
    (round_half_away(x) as u64).max(1)
}

/// `x.round()` (half away from zero) to the bit, without a call: x86-64's baseline has no
/// rounding instruction, so `f64::round` is a call into libm, and [`sample_count`] makes two
/// for every piece a worker casts (and every task the coordinator culls). At and above 2⁵²
/// every f64 is an integer, and the infinities round to themselves, as a NaN does to a NaN;
/// below, the truncation `(x as i64) as f64` and the fraction `x − t` are exact.
#[inline]
fn round_half_away(x: f64) -> f64 {
    const INTEGRAL: f64 = 4_503_599_627_370_496.0; // 2⁵²
    if x.is_nan() || x.abs() >= INTEGRAL {
        return x;
    }
    let t = (x as i64) as f64;
    let r = if (x - t).abs() >= 0.5 { t + 1f64.copysign(x) } else { t };
    // A zero keeps x's sign, as `f64::round`'s does.
    r.copysign(x)
}

/// A ray origin in an affine box's coordinates, with what the slab test derives from it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoxOrigin {
    world: DVec3,
    o: DVec3,
    slack: f64,
    o_len: f64,
    /// The box-from-world map of directions, kept beside the origin so that a ray's slab
    /// test reads these 136 bytes rather than the whole object.
    linear: DMat3,
}

impl BoxOrigin {
    pub(crate) fn new(world: DVec3, o: DVec3, linear: DMat3) -> BoxOrigin {
        BoxOrigin { world, o, slack: BOX_SLACK * (1.0 + o.abs().max_element()), o_len: o.length(), linear }
    }

    /// The box-from-world map of directions.
    #[inline]
    pub(crate) fn linear(&self) -> &DMat3 {
        &self.linear
    }

    /// The ray origin in box coordinates.
    #[inline]
    pub(crate) fn box_point(&self) -> DVec3 {
        self.o
    }

    /// The rounding slack of the slab test at this origin.
    #[inline]
    pub(crate) fn slack(&self) -> f64 {
        self.slack
    }

    /// |origin| in box coordinates.
    #[inline]
    pub(crate) fn o_len(&self) -> f64 {
        self.o_len
    }

    /// Whether `ray` starts where this was worked out.
    #[inline]
    pub fn starts(&self, ray: &Ray) -> bool {
        self.world == ray.origin
    }

    /// [`Placement::segment`] of a ray that [`BoxOrigin::starts`] here: the same operations
    /// on the same values (the direction mapped as `DMat4::transform_vector3` maps it — the
    /// same products, added in an order IEEE addition does not see), so the same segment to
    /// the bit.
    #[inline]
    pub fn segment(&self, ray: &Ray) -> Option<(f64, f64)> {
        slab_segment(self, self.linear.mul_vec3(ray.dir))
    }
}

/// The slab test against the closed unit box in box coordinates. An axis along which the
/// ray moves less than the rounding slack over every t at which it could be in the box
/// (`reach` bounds those t) is treated as parallel: the ray is inside that slab for all t
/// or for none, decided on its origin with the slack. A zero direction component (+0.0 or
/// −0.0) takes that branch, so it never divides and never makes NaN. Other axes give the
/// exact crossing parameters.
fn slab_segment(origin: &BoxOrigin, d: DVec3) -> Option<(f64, f64)> {
    let (o, slack) = (origin.o, origin.slack);
    // |o + t·d| ≤ √3 inside the box, so t ≤ (|o| + √3)/|d| there: `reach`. Its square root
    // and division are paid only for an axis the cheap bound below cannot decide — a ray
    // nearly parallel to a face — which is rare; every other ray skips them.
    let (ad, num) = (d.abs(), origin.o_len + 2.0);
    // |d| ≤ ‖d‖₁, so |d_a|·reach ≥ |d_a|·num/‖d‖₁ up to a few roundings: above the slack by
    // the margin, the exact test below would find the axis not parallel too.
    let l1_slack = slack * (ad.x + ad.y + ad.z) * (1.0 + 1e-6);
    let mut reach = None;
    let (mut t_near, mut t_far) = (0.0f64, f64::INFINITY);
    // The smallest |d_a| over the crossing axes: the rounding tolerance of a crossing
    // parameter, max_a slack/|d_a|, is slack over it (division rounds monotonically), so it
    // costs one division, taken only for a ray that grazes an edge.
    let mut min_crossing = f64::INFINITY;
    for a in 0..3 {
        let parallel =
            d[a] == 0.0 || (ad[a] * num <= l1_slack && ad[a] * *reach.get_or_insert_with(|| num / d.length()) <= slack);
        if parallel {
            if o[a] < -slack || o[a] > 1.0 + slack {
                return None;
            }
            continue;
        }
        let (ta, tb) = ((0.0 - o[a]) / d[a], (1.0 - o[a]) / d[a]);
        t_near = t_near.max(ta.min(tb));
        t_far = t_far.min(ta.max(tb));
        min_crossing = min_crossing.min(ad[a]);
    }
    // A ray that only touches an edge or a corner meets the closed box in one point, and
    // rounding may put the entry a hair after the exit: keep that point (a zero-length
    // segment, which the renderer then drops) rather than report a miss.
    if t_near > t_far && t_near - t_far <= slack / min_crossing {
        t_far = t_near;
    }
    (t_near <= t_far && t_far.is_finite()).then_some((t_near, t_far))
}

/// The samples of a walk along a straight VC line (affine boxes, and distorted boxes in the
/// paper's straight mode): sample k sits at `vc0 + delta·(k + ½)/n` (SPEC §4.2) and every
/// sample has the same ℓ. Each coordinate is monotone in k (every rounding step is), which
/// empty-space skipping relies on to jump over whole runs of samples.
#[derive(Clone, Copy, Debug)]
pub struct LineSamples {
    vc0: DVec3,
    delta: DVec3,
    n: u64,
    /// 1/n, so a sample's position costs a multiplication, not a division.
    inv_n: f64,
}

impl LineSamples {
    /// The number of samples.
    #[inline]
    pub fn len(&self) -> u64 {
        self.n
    }

    /// Whether there is none (never: n ≥ 1).
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// The VC point of sample k: vc0 + δ·((k + ½)·(1/n)), within an ulp or two of
    /// (k + ½)/n of the way along.
    #[inline(always)]
    pub fn point(&self, k: u64) -> [f64; 3] {
        (self.vc0 + self.delta * ((k as f64 + 0.5) * self.inv_n)).to_array()
    }

    /// What [`LineSamples::point`] computes from: VC at the start, the change over the
    /// piece, and 1/n (for samplers that compute several points at once, the same way).
    #[inline]
    pub(crate) fn parts(&self) -> ([f64; 3], [f64; 3], f64) {
        (self.vc0.to_array(), self.delta.to_array(), self.inv_n)
    }

    /// ℓ, the VC length of each sample's sub-interval.
    #[inline]
    pub fn ell(&self) -> f64 {
        self.delta.length() / self.n as f64
    }

    /// VC at the piece's start.
    pub fn start(&self) -> [f64; 3] {
        self.vc0.to_array()
    }

    /// VC change over the whole piece.
    pub fn delta(&self) -> [f64; 3] {
        self.delta.to_array()
    }
}

enum WalkState<'a> {
    /// Sample the straight VC line vc0 + s·delta, s ∈ [0, 1].
    Line { vc0: DVec3, delta: DVec3 },
    /// Invert the world map exactly at each sample and sub-interval boundary.
    Exact { hex: &'a Hexahedron, prev_q: DVec3, prev_vc: DVec3 },
    /// The end points could not be inverted: the piece contributes nothing.
    Failed,
}

/// The samples of one object over one piece, front to back: each is the VC point (or
/// `None` where it maps outside a non-convex box) and ℓ, the VC length of its
/// sub-interval, which opacity correction needs (SPEC §4.3).
pub struct SampleWalk<'a> {
    placement: &'a Placement,
    ray: Ray,
    t0: f64,
    dt: f64,
    n: u64,
    k: u64,
    state: WalkState<'a>,
}

impl SampleWalk<'_> {
    /// The number of samples this walk yields.
    pub fn len(&self) -> u64 {
        self.n
    }

    /// Whether the walk yields nothing (never: n ≥ 1; provided for clippy's sake).
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// The walk as a straight line of samples, when it is one (and has not started).
    pub fn line(&self) -> Option<LineSamples> {
        match self.state {
            WalkState::Line { vc0, delta } if self.k == 0 => {
                Some(LineSamples { vc0, delta, n: self.n, inv_n: 1.0 / self.n as f64 })
            }
            _ => None,
        }
    }

    /// Where the walk's samples are in the world (what lighting needs besides their VC
    /// points).
    pub fn world_points(&self) -> WorldPoints {
        WorldPoints { ray: self.ray, t0: self.t0, dt: self.dt }
    }

    /// The ray the walk samples.
    pub fn ray(&self) -> &Ray {
        &self.ray
    }

    /// Whether every sample of the walk lies outside the box (its end points could not be
    /// inverted): the piece contributes nothing.
    pub fn is_failed(&self) -> bool {
        matches!(self.state, WalkState::Failed)
    }
}

/// The world points of a walk's samples ([`SampleWalk::world_points`]).
#[derive(Clone, Copy, Debug)]
pub struct WorldPoints {
    ray: Ray,
    t0: f64,
    dt: f64,
}

impl WorldPoints {
    /// Sample k's world point, at t0 + (k + ½)·L/n along the ray (SPEC §4.2).
    #[inline]
    pub fn at(&self, k: u64) -> DVec3 {
        self.ray.at(self.t0 + (k as f64 + 0.5) * self.dt)
    }

    /// [`WorldPoints::at`] as `first + step·k` (for samplers that compute several points at
    /// once), and the ray's unit direction.
    pub(crate) fn parts(&self) -> (DVec3, DVec3, DVec3) {
        (self.ray.at(self.t0 + 0.5 * self.dt), self.dt * self.ray.dir, self.ray.dir)
    }
}

/// One sample: VC point (None when outside the box) and ℓ in voxels.
pub type VcLine = (Option<[f64; 3]>, f64);

impl Iterator for SampleWalk<'_> {
    type Item = VcLine;

    #[inline]
    fn next(&mut self) -> Option<VcLine> {
        if self.k >= self.n {
            return None;
        }
        let k = self.k as f64;
        self.k += 1;
        let n = self.n as f64;
        match &mut self.state {
            WalkState::Line { vc0, delta } => {
                // As `LineSamples::point`.
                let vc = *vc0 + *delta * ((k + 0.5) * (1.0 / n));
                Some((Some(vc.to_array()), delta.length() / n))
            }
            WalkState::Exact { hex, prev_q, prev_vc } => {
                let p = self.placement;
                let t_mid = self.t0 + (k + 0.5) * self.dt;
                let t_end = self.t0 + (k + 1.0) * self.dt;
                let q_mid = hex.invert(self.ray.at(t_mid), Some(*prev_q), p.tol_q);
                let q_end = hex.invert(self.ray.at(t_end), q_mid.or(Some(*prev_q)), p.tol_q);
                let item = match (q_mid, q_end) {
                    (Some(qm), Some(qe)) => {
                        let vc_end = p.vc_of_box(qe);
                        let ell = (vc_end - *prev_vc).length();
                        *prev_q = qe;
                        *prev_vc = vc_end;
                        let inside = Hexahedron::contains_q(qm);
                        (inside.then(|| p.vc_of_box(qm).to_array()), ell)
                    }
                    // Newton failed: never guess; this sample contributes nothing.
                    _ => (None, 0.0),
                };
                Some(item)
            }
            WalkState::Failed => Some((None, 0.0)),
        }
    }
}

#[cfg(test)]
mod tests {

    use proptest::prelude::*;

    /// The slab test as first written — `reach` and every axis's tolerance computed
    /// outright — which [`slab_segment`] must equal to the bit.
    fn slab_segment_outright(origin: &BoxOrigin, d: DVec3) -> Option<(f64, f64)> {
        let (o, slack) = (origin.o, origin.slack);
        let reach = (origin.o_len + 2.0) / d.length();
        let (mut t_near, mut t_far) = (0.0f64, f64::INFINITY);
        let mut t_tol = 0.0f64;
        for a in 0..3 {
            if d[a] == 0.0 || d[a].abs() * reach <= slack {
                if o[a] < -slack || o[a] > 1.0 + slack {
                    return None;
                }
                continue;
            }
            let (ta, tb) = ((0.0 - o[a]) / d[a], (1.0 - o[a]) / d[a]);
            t_near = t_near.max(ta.min(tb));
            t_far = t_far.min(ta.max(tb));
            t_tol = t_tol.max(slack / d[a].abs());
        }
        if t_near > t_far && t_near - t_far <= t_tol {
            t_far = t_near;
        }
        (t_near <= t_far && t_far.is_finite()).then_some((t_near, t_far))
    }

    /// A direction component: ordinary, tiny (nearly parallel to a face), or zero.
    fn component() -> impl Strategy<Value = f64> {
        prop_oneof![-3.0f64..3.0, (-1e-9f64..1e-9), (-1e-14f64..1e-14), Just(0.0), Just(-0.0)]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(20_000))]
        #[test]
        fn the_cheap_slab_test_equals_the_outright_one_to_the_bit(
            o in prop::array::uniform3(-3.0f64..4.0), d in prop::array::uniform3(component()),
            edge in 0usize..4,
        ) {
            // Some origins exactly on a face or an edge, where the tolerances decide.
            let mut o = DVec3::from_array(o);
            if edge < 3 {
                o[edge] = if o[edge] < 0.5 { 0.0 } else { 1.0 };
            }
            let origin = BoxOrigin::new(DVec3::ZERO, o, DMat3::IDENTITY);
            let d = DVec3::from_array(d);
            let (fast, outright) = (slab_segment(&origin, d), slab_segment_outright(&origin, d));
            prop_assert_eq!(fast.map(|(a, b)| (a.to_bits(), b.to_bits())), outright.map(|(a, b)| (a.to_bits(), b.to_bits())));
        }
    }
    use super::*;

    fn unit_box(dims: [u64; 3]) -> Placement {
        Placement::new(
            Shape::Affine { world_from_box: DMat4::IDENTITY, box_from_world: DMat4::IDENTITY },
            Extent::FULL,
            Dims::new(dims).unwrap(),
        )
    }

    #[test]
    fn rays_parallel_to_faces_with_signed_zeros_do_not_miss_or_nan() {
        let p = unit_box([4, 4, 4]);
        for dz in [0.0, -0.0] {
            for dy in [0.0, -0.0] {
                // Along +x, in the face plane y = 0 and z = 1 (an edge), and through the interior.
                for (oy, oz) in [(0.0, 1.0), (0.5, 0.5), (1.0, 0.0), (0.0, 0.0)] {
                    let ray = Ray { origin: DVec3::new(-1.0, oy, oz), dir: DVec3::new(1.0, dy, dz) };
                    let (a, b) = p.segment(&ray).expect("closed box: no miss");
                    assert!((a - 1.0).abs() < 1e-9 && (b - 2.0).abs() < 1e-9, "{a} {b}");
                }
                let outside = Ray { origin: DVec3::new(-1.0, 1.5, 0.5), dir: DVec3::new(1.0, dy, dz) };
                assert_eq!(p.segment(&outside), None);
            }
        }
    }

    #[test]
    fn a_ray_through_a_corner_touches_the_box_and_the_camera_may_be_inside() {
        let p = unit_box([2, 2, 2]);
        let d = DVec3::new(1.0, 1.0, 1.0).normalize();
        let (a, b) = p.segment(&Ray { origin: DVec3::splat(-1.0), dir: d }).unwrap();
        assert!((a - 3f64.sqrt()).abs() < 1e-9 && (b - 2.0 * 3f64.sqrt()).abs() < 1e-9);
        let (a, b) = p.segment(&Ray { origin: DVec3::splat(0.5), dir: DVec3::X }).unwrap();
        assert_eq!(a, 0.0);
        assert!((b - 0.5).abs() < 1e-9);
        // Touching only the corner point gives a zero-length segment, dropped later.
        let corner = Ray { origin: DVec3::new(2.0, 0.0, 0.0), dir: DVec3::new(-1.0, -1.0, 0.0).normalize() };
        if let Some((a, b)) = p.segment(&corner) {
            assert!(b - a < 1e-9);
        }
    }

    #[test]
    fn samples_sit_at_midpoints_with_one_voxel_steps() {
        let p = unit_box([4, 1, 1]);
        let ray = Ray { origin: DVec3::new(-1.0, 0.5, 0.5), dir: DVec3::X };
        let (a, b) = p.segment(&ray).unwrap();
        let s: Vec<_> = p.walk(&ray, a, b, 0.0).collect();
        assert_eq!(s.len(), 4);
        for (k, (vc, ell)) in s.iter().enumerate() {
            let vc = vc.unwrap();
            assert!((vc[0] - k as f64).abs() < 1e-9, "{vc:?}");
            assert!((ell - 1.0).abs() < 1e-9);
        }
        // An explicit sampling distance: round(1.0 / 0.3) = 3 samples.
        assert_eq!(p.walk(&ray, a, b, 0.3).len(), 3);
    }

    #[test]
    fn sample_count_rounds_half_away_from_zero_despite_noise() {
        assert_eq!(sample_count(2.5, 1.0, 0.0), 3);
        assert_eq!(sample_count(2.5 - 1e-13, 1.0, 0.0), 3);
        assert_eq!(sample_count(2.4, 1.0, 0.0), 2);
        assert_eq!(sample_count(0.1, 1.0, 0.0), 1);
        assert_eq!(sample_count(1.0, 0.0, 3.5), 4);
    }

    #[test]
    fn rounding_without_a_call_is_f64_round_to_the_bit() {
        let two52 = 4_503_599_627_370_496.0f64;
        let mut cases = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.5,
            2.5,
            -2.5,
            0.49999999999999994,
            -0.49999999999999994,
            two52 - 0.5,
            two52 - 1.5,
            two52,
            two52 + 1.0,
            1e300,
            f64::MAX,
            f64::MIN_POSITIVE,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        // Every half step and its neighbours up to 2000.
        for k in 0..4000 {
            let h = k as f64 / 2.0;
            cases.extend([h, -h, f64::from_bits(h.to_bits() + 1), f64::from_bits(h.to_bits().saturating_sub(1))]);
        }
        for x in cases {
            if x.is_nan() {
                assert!(round_half_away(x).is_nan());
            } else {
                assert_eq!(round_half_away(x).to_bits(), x.round().to_bits(), "{x:e}");
            }
        }
    }

    proptest! {
        #[test]
        fn rounding_without_a_call_matches_on_any_bits(bits in any::<u64>()) {
            let x = f64::from_bits(bits);
            if x.is_nan() {
                // A NaN's payload is not specified (libm quiets a signalling one): NaN is all.
                prop_assert!(round_half_away(x).is_nan());
            } else {
                prop_assert_eq!(round_half_away(x).to_bits(), x.round().to_bits(), "{:e}", x);
            }
        }

        #[test]
        fn rounding_without_a_call_matches_on_sample_counts(x in -1e7f64..1e7f64) {
            prop_assert_eq!(round_half_away(x).to_bits(), x.round().to_bits(), "{:e}", x);
        }
    }
}
