//! Distorted boxes: the hexahedron an object's dataset fills (SPEC §2, §4.2; paper §2.3.5, Fig. 7).
//!
//! A box is given by eight world corners `c[i]`, `i = x + 2y + 4z` for the unit-cube corner `(x, y, z)`, and
//! maps box coordinates `q ∈ [0,1]³` to the world by the trilinear blend
//! `W(q) = Σ c[i]·w_i(q)`, `w_i(q) = Π_a (q_a if bit a of i is set else 1 − q_a)`.
//! In monomial form `W(q) = a + b·x + c·y + d·z + e·xy + f·yz + g·zx + h·xyz` (with `q = (x, y, z)`), which
//! is what the Jacobian is computed from.
//!
//! Three numerical questions come with such a box, and each is answered here without sampling guesses:
//!
//! * **Does it fold?** ([`Hexahedron::new`]) SPEC §2 refuses a box whose Jacobian changes sign inside.
//!   `det J` is a polynomial of degree ≤ 2 in each of `x, y, z`, so it has an exact expansion in the
//!   tensor Bernstein basis of degree (2,2,2); Bernstein coefficients bound the polynomial (convex hull
//!   property), and subdividing them converges to the values. This proves the sign, where point sampling
//!   can only fail to find a counter-example.
//! * **Where is a world point in the box?** ([`Hexahedron::invert`]) Damped Newton, verified.
//! * **Where does a ray enter and leave?** ([`Hexahedron::segment`]) Exact ray/bilinear-patch
//!   intersection for the six faces (Reshetov, "Cool Patches", Ray Tracing Gems 2019), backed by ray/edge
//!   tests so that rays through edges, corners and along face planes are never lost.
use glam::{DMat3, DMat4, DVec3, DVec4};
use thiserror::Error;

/// A box counts as degenerate where `|det J|` is below this fraction of `L³` (`L` = the diagonal of the
/// corners' bounding box): a box 10⁻¹² times thinner than it is wide has no usable volume in f64.
const DEGENERATE_REL: f64 = 1e-12;
/// Subdivision depth of the Bernstein fold test: the control net converges to the values like `4^-depth`,
/// so boxes whose `det J` comes within about 10⁻⁶ of its variation of zero are refused as too close.
const FOLD_MAX_DEPTH: u32 = 10;
/// Work bound of the fold test (sub-boxes examined), so that a pathological box cannot stall the loader.
const FOLD_MAX_BOXES: usize = 200_000;
/// Corners within this fraction of `L` of an exact parallelepiped are treated as affine (brief: 1e-12).
const AFFINE_REL: f64 = 1e-12;
/// Tolerance of [`Hexahedron::contains_q`]: the box is closed, and Newton's answer is this good or better.
const CONTAINS_EPS: f64 = 1e-9;
/// Newton iteration cap for [`Hexahedron::invert`] (quadratic convergence needs about 5 from a warm start).
const NEWTON_MAX_ITERS: usize = 60;
/// Relative distance tolerance of the ray tests (times the size of the coordinates involved).
const RAY_REL_TOL: f64 = 1e-10;
/// Slack on the patch parameters `u, v ∈ [0, 1]`, so that hits on a face's border are kept.
const PATCH_EPS: f64 = 1e-9;

/// Bernstein coefficients of degree (2,2,2), indexed `[ix][iy][iz]`.
type Bern = [[[f64; 3]; 3]; 3];

/// Why [`Hexahedron::new`] refused eight corners. Messages follow the key `transform.corners`
/// (the scene loader adds file and key); box coordinates are `q ∈ [0,1]³`.
#[derive(Clone, Copy, Debug, PartialEq, Error)]
pub enum HexahedronError {
    /// A corner with a NaN or infinite coordinate.
    #[error("corner {index} is not finite ({corner:?})")]
    NonFiniteCorner {
        /// Which corner (`x + 2y + 4z`).
        index: usize,
        /// Its coordinates.
        corner: [f64; 3],
    },
    /// The corners' bounding box overflows f64.
    #[error("the corners are too far apart to be represented")]
    TooFarApart,
    /// All eight corners coincide.
    #[error("degenerate box: all eight corners are the same point")]
    SinglePoint,
    /// `det J` is zero everywhere, to rounding: the corners span no volume.
    #[error("degenerate box: the corners enclose no volume (they lie in a plane, on a line or coincide)")]
    NoVolume,
    /// `det J` is zero at corner 0, which fixes the orientation.
    #[error("degenerate box: the Jacobian determinant is zero at corner 0 (its three edges are coplanar)")]
    DegenerateAtCorner0,
    /// `det J` is zero at a point inside the box.
    #[error(
        "the hexahedron is degenerate at box coordinates {}: the Jacobian determinant is zero there \
         (edges collapse or become coplanar)",
        Q(*at)
    )]
    DegenerateAt {
        /// Where.
        at: [f64; 3],
    },
    /// `det J` changes sign: the box turns inside out.
    #[error(
        "the hexahedron folds over itself: the Jacobian determinant is {at_corner0:.3e} at corner 0 but \
         {value:.3e} at box coordinates {} (check the corner order: i = x + 2y + 4z)",
        Q(*at)
    )]
    Folds {
        /// `det J` at corner 0.
        at_corner0: f64,
        /// `det J` at `at`, of the other sign.
        value: f64,
        /// Where.
        at: [f64; 3],
    },
    /// The fold test ran out of depth without a proof either way: `det J` comes too close to 0.
    #[error(
        "the hexahedron is too close to folding over itself near box coordinates {}: the Jacobian \
         determinant comes too close to zero to prove that it keeps its sign",
        Q(*near)
    )]
    TooCloseToFolding {
        /// Centre of the sub-box where the proof stopped.
        near: [f64; 3],
    },
}

/// Box coordinates as `(0.250, 0.500, 1.000)` in messages.
pub(crate) struct Q(pub(crate) [f64; 3]);

impl std::fmt::Display for Q {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "({:.3}, {:.3}, {:.3})", self.0[0], self.0[1], self.0[2])
    }
}

/// A hexahedral object box with its precomputed data (monomial coefficients, size, orientation, affine
/// form when it is a parallelepiped). Construct it with [`Hexahedron::new`], which guarantees that the box
/// does not fold: `det J` has one strict sign on all of `[0,1]³`.
#[derive(Clone, Debug)]
pub struct Hexahedron {
    corners: [DVec3; 8],
    /// `[a, b, c, d, e, f, g, h]` of the monomial form (see the module documentation).
    mono: [DVec3; 8],
    /// Diagonal of the corners' bounding box (> 0).
    size: f64,
    bbox_min: DVec3,
    bbox_max: DVec3,
    /// +1 or −1: the sign of `det J` everywhere in the box (−1 = mirrored).
    orientation: f64,
    /// `W(½,½,½)` and `J(½,½,½)⁻¹`: the affine approximation that starts Newton.
    centre: DVec3,
    centre_inv: DMat3,
    /// For a parallelepiped: the matrix `M` (`c[i] = M·[x, y, z, 1]`) and the inverse of its linear part.
    affine: Option<(DMat4, DMat3)>,
}

/// The eight corners `c[i] = M·[x, y, z, 1]ᵀ`, `i = x + 2y + 4z` (SPEC §2, `transform = { matrix = M }`).
/// `M` is meant to be affine (last row `0 0 0 1`, checked by the scene loader); its last row is ignored.
pub fn corners_of_affine(m: &DMat4) -> [DVec3; 8] {
    std::array::from_fn(|i| {
        let p = DVec4::new((i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64, 1.0);
        (*m * p).truncate()
    })
}

impl Hexahedron {
    /// Checks and prepares a box from its eight world corners (order `i = x + 2y + 4z`).
    ///
    /// Refuses ([`HexahedronError`]): non-finite corners; a degenerate box (no volume: `|det J|` below 10⁻¹² of the bounding-box diagonal
    /// cubed, e.g. all corners in one plane); and a box that folds over itself, i.e. where `det J` changes
    /// sign or is 0 somewhere in `[0,1]³`. A mirrored box (negative `det J` throughout) is accepted.
    ///
    /// The fold test is sound, not sampled. `det J = J_x · (J_y × J_z)`; `J_x` is bilinear in `(y, z)` and
    /// constant in `x`, and likewise for the others, so `det J` has degree ≤ 2 in each variable. Its 27
    /// Bernstein coefficients of degree (2,2,2) are computed exactly (up to rounding) from the edge vectors
    /// with the Bernstein product rule. Bernstein polynomials are non-negative and sum to one, so `det J`
    /// lies between its smallest and largest coefficient: all coefficients of one sign prove that the sign
    /// never changes. Otherwise the box is split in eight (de Casteljau at ½ per axis) and the test repeats;
    /// the coefficients at a sub-box's corners are actual values of `det J`, so one of the wrong sign (or 0)
    /// proves folding. If the depth or work bound runs out undecided, `det J` comes so close to 0 that the
    /// box is refused as too close to folding: a conservative, never a wrong, acceptance.
    pub fn new(corners: [DVec3; 8]) -> Result<Hexahedron, HexahedronError> {
        if let Some(index) = corners.iter().position(|c| !c.is_finite()) {
            return Err(HexahedronError::NonFiniteCorner { index, corner: corners[index].to_array() });
        }
        let bbox_min = corners.iter().fold(DVec3::splat(f64::INFINITY), |m, c| m.min(*c));
        let bbox_max = corners.iter().fold(DVec3::splat(f64::NEG_INFINITY), |m, c| m.max(*c));
        let size = (bbox_max - bbox_min).length();
        if !size.is_finite() {
            return Err(HexahedronError::TooFarApart);
        }
        if size == 0.0 {
            return Err(HexahedronError::SinglePoint);
        }
        let tol = DEGENERATE_REL * size * size * size;
        let bern = det_bernstein(&corners);
        let orientation = check_no_fold(&bern, tol)?;

        let c = &corners;
        let mono = [
            c[0],
            c[1] - c[0],
            c[2] - c[0],
            c[4] - c[0],
            c[3] - c[1] - c[2] + c[0],
            c[6] - c[2] - c[4] + c[0],
            c[5] - c[1] - c[4] + c[0],
            c[7] - c[3] - c[5] - c[6] + c[1] + c[2] + c[4] - c[0],
        ];
        let mut hex = Hexahedron {
            corners,
            mono,
            size,
            bbox_min,
            bbox_max,
            orientation,
            centre: DVec3::ZERO,
            centre_inv: DMat3::IDENTITY,
            affine: None,
        };
        let half = DVec3::splat(0.5);
        hex.centre = hex.world(half);
        // det J(½) has the orientation's sign and |det J| > tol (proved above), so the inverse exists.
        hex.centre_inv = hex.jacobian(half).inverse();

        let (ex, ey, ez) = (c[1] - c[0], c[2] - c[0], c[4] - c[0]);
        let flat = (0..8).all(|i| {
            let (x, y, z) = ((i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64);
            (c[0] + x * ex + y * ey + z * ez - c[i]).length() <= AFFINE_REL * size
        });
        if flat {
            let m = DMat4::from_cols(ex.extend(0.0), ey.extend(0.0), ez.extend(0.0), c[0].extend(1.0));
            hex.affine = Some((m, DMat3::from_cols(ex, ey, ez).inverse()));
        }
        Ok(hex)
    }

    /// The eight world corners, index `i = x + 2y + 4z`.
    pub fn corners(&self) -> &[DVec3; 8] {
        &self.corners
    }

    /// Diagonal of the corners' bounding box: the length scale every tolerance here is relative to.
    pub fn size(&self) -> f64 {
        self.size
    }

    /// +1.0 if `det J > 0` throughout the box, −1.0 if the box is mirrored (`det J < 0` throughout).
    pub fn orientation(&self) -> f64 {
        self.orientation
    }

    /// The world point `W(q)`, evaluated as nested linear interpolations `(1−t)·a + t·b`, so that the
    /// corners (and points on edges between them) come out exactly where they were given.
    pub fn world(&self, q: DVec3) -> DVec3 {
        let c = &self.corners;
        let lerp = |a: DVec3, b: DVec3, t: f64| (1.0 - t) * a + t * b;
        let x00 = lerp(c[0], c[1], q.x);
        let x10 = lerp(c[2], c[3], q.x);
        let x01 = lerp(c[4], c[5], q.x);
        let x11 = lerp(c[6], c[7], q.x);
        lerp(lerp(x00, x10, q.y), lerp(x01, x11, q.y), q.z)
    }

    /// The Jacobian of `W` at `q`: columns `∂W/∂q_x`, `∂W/∂q_y`, `∂W/∂q_z`.
    pub fn jacobian(&self, q: DVec3) -> DMat3 {
        let [_, b, c, d, e, f, g, h] = self.mono;
        DMat3::from_cols(
            b + e * q.y + g * q.z + h * (q.y * q.z),
            c + e * q.x + f * q.z + h * (q.x * q.z),
            d + f * q.y + g * q.x + h * (q.x * q.y),
        )
    }

    /// If the eight corners form a parallelepiped (`c[i] = c0 + x·ex + y·ey + z·ez` to within 10⁻¹² of the
    /// box size), the affine matrix `M` with `c[i] = M·[x, y, z, 1]ᵀ` (columns `ex, ey, ez, c0`, last row
    /// `0 0 0 1`). The renderer then takes the fast affine path; `None` for a truly distorted box.
    pub fn as_affine(&self) -> Option<DMat4> {
        self.affine.map(|(m, _)| m)
    }

    /// Box coordinates `q` with `W(q) = p`, or `None`.
    ///
    /// Damped Newton in f64, started from `guess` (the previous sample along the ray: consecutive samples
    /// are close, so two or three steps suffice) or, without one, from the affine approximation at the box
    /// centre. Each step solves `J(q)·δ = p − W(q)` and halves `δ` until `|W − p|` decreases. It stops once
    /// the full Newton step is at most `tol_q` in every coordinate (the caller passes 10⁻⁶ voxel divided by
    /// the largest dimension), takes that last step (leaving an error of order `tol_q²`) and verifies the
    /// residual `|W(q) − p| ≤ ‖J‖·tol_q` before answering, so a returned `q` is always a genuine solution.
    /// For a parallelepiped the map is affine and inverted directly.
    ///
    /// Points outside `[0,1]³` may be returned: `W` extends beyond the box as a polynomial, and the caller
    /// tests [`Hexahedron::contains_q`]. Because that extension can have further preimages outside the box,
    /// an answer outside `[0,1]³` is double-checked with box-constrained Newton runs from the clamped answer
    /// and from the centre: inside the box `det J ≠ 0`, so the map is one-to-one there, and a preimage in the
    /// box, if there is one, is preferred. `None` means no start converged (for a point far outside the
    /// box where `J` is singular, say).
    pub fn invert(&self, p: DVec3, guess: Option<DVec3>, tol_q: f64) -> Option<DVec3> {
        if !p.is_finite() {
            return None;
        }
        if let Some((m, inv)) = &self.affine {
            let q = *inv * (p - m.w_axis.truncate());
            return q.is_finite().then_some(q);
        }
        let tol_q = if tol_q.is_finite() && tol_q > 0.0 { tol_q } else { 1e-12 };
        let start = match guess {
            Some(g) if g.is_finite() => g,
            _ => self.affine_start(p),
        };
        let first = self.newton(p, start, tol_q, false);
        if let Some(q) = first {
            if Self::contains_q(q) {
                return Some(q);
            }
        }
        let clamped = first.map(|q| q.clamp(DVec3::ZERO, DVec3::ONE));
        let centre = Some(DVec3::splat(0.5)).filter(|c| clamped != Some(*c));
        for s in [clamped, centre].into_iter().flatten() {
            if let Some(q) = self.newton(p, s, tol_q, true) {
                if Self::contains_q(q) {
                    return Some(q);
                }
            }
        }
        first
    }

    /// Whether `q ∈ [0,1]³`, closed and with a tolerance of 10⁻⁹ (boxes are closed, SPEC §4.5, and
    /// [`Hexahedron::invert`] is accurate to well within that).
    pub fn contains_q(q: DVec3) -> bool {
        q.cmpge(DVec3::splat(-CONTAINS_EPS)).all() && q.cmple(DVec3::splat(1.0 + CONTAINS_EPS)).all()
    }

    /// The ray's segment (SPEC §4.2): the first and last `t ≥ 0` at which `origin + t·dir` is in the closed
    /// box, or `None` if it never is. Never NaN; `0 ≤ t_near ≤ t_far`.
    ///
    /// The boundary of the box is the image of the cube's six faces, each a bilinear patch. Every maximal
    /// inside interval of the ray begins at `t = 0` (origin inside, decided with [`Hexahedron::invert`]) or at
    /// a boundary point and ends at one, so `t_near` and `t_far` are the extreme boundary hits (the box may be
    /// non-convex, so there can be more than two; points between the extremes may be outside, which the
    /// renderer handles per sample). Faces are intersected with Reshetov's method: the ray meets the ruling
    /// line `u = const` of a patch iff the two are coplanar, a quadratic in `u` solved in the cancellation-free
    /// form; `v` and `t` then follow from cross products. Planar faces and rays parallel to faces give a
    /// vanishing leading coefficient, which that form handles; nothing divides by a direction component
    /// (the bounding-box pre-test treats zero components separately), so `±0.0` components are harmless. Where the ray lies *in* a face (quadratic identically
    /// zero) or runs along a ruling, the face's own solutions degenerate; the ends of that contact lie on the
    /// face's edges, so the twelve edges are also tested directly (closest approach within a relative
    /// tolerance of 10⁻¹⁰). That makes rays along an edge, through a corner or in a face plane hit, as SPEC §4.5
    /// requires (boxes are closed). Patch parameters get a slack of 10⁻⁹ so that hits on face borders stay.
    pub fn segment(&self, origin: DVec3, dir: DVec3) -> Option<(f64, f64)> {
        if !origin.is_finite() || !dir.is_finite() {
            return None;
        }
        let dd = dir.length_squared();
        let scale = self.size + (origin - self.centre).length();
        let tol = RAY_REL_TOL * scale;
        if dd == 0.0 || !dd.is_finite() {
            let inside = self.point_inside(origin);
            return inside.then_some((0.0, 0.0));
        }
        if !self.ray_hits_bbox(origin, dir, tol) {
            return None;
        }
        let mut hits = Hits::new(-tol / dd.sqrt());
        let c = &self.corners;
        for axis in 0..3 {
            let (ua, va) = ((axis + 1) % 3, (axis + 2) % 3);
            for side in 0..2 {
                let idx = |u: usize, v: usize| (side << axis) | (u << ua) | (v << va);
                let (q00, q10, q01, q11) = (c[idx(0, 0)], c[idx(1, 0)], c[idx(0, 1)], c[idx(1, 1)]);
                patch_hits(origin, dir, [q00, q10, q01, q11], tol, &mut hits);
            }
        }
        for axis in 0..3 {
            for other in 0..4 {
                // The edge along `axis` whose other two bits are `other`, spread over the other axes.
                let (ua, va) = ((axis + 1) % 3, (axis + 2) % 3);
                let base = ((other & 1) << ua) | ((other >> 1) << va);
                edge_hits(origin, dir, c[base], c[base | (1 << axis)], tol, &mut hits);
            }
        }
        let inside = self.point_inside(origin);
        match (inside, hits.range()) {
            (true, Some((_, t_far))) => Some((0.0, t_far)),
            (true, None) => Some((0.0, 0.0)),
            (false, Some((t_near, t_far))) => Some((t_near, t_far)),
            (false, None) => None,
        }
    }

    /// Whether a world point is in the closed box: outside the corners' bounding box it cannot be (the
    /// trilinear weights are a convex combination), inside that, invert and check.
    fn point_inside(&self, p: DVec3) -> bool {
        let tol = RAY_REL_TOL * self.size;
        if p.cmplt(self.bbox_min - tol).any() || p.cmpgt(self.bbox_max + tol).any() {
            return false;
        }
        self.invert(p, None, 1e-12).is_some_and(Self::contains_q)
    }

    /// Slab test against the corners' bounding box (which contains the box), written so that a zero
    /// direction component never divides.
    fn ray_hits_bbox(&self, o: DVec3, d: DVec3, tol: f64) -> bool {
        let (lo, hi) = (self.bbox_min - tol, self.bbox_max + tol);
        let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
        for a in 0..3 {
            if d[a] == 0.0 {
                if o[a] < lo[a] || o[a] > hi[a] {
                    return false;
                }
            } else {
                let (ta, tb) = ((lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]);
                t0 = t0.max(ta.min(tb));
                t1 = t1.min(ta.max(tb));
            }
        }
        // A hair of slack: the exact hits are refined separately and must not be cut off here.
        t0 <= t1 * (1.0 + 1e-12) + 1e-300
    }

    /// Start for Newton without a warm start: the affine approximation of `W` at the centre.
    fn affine_start(&self, p: DVec3) -> DVec3 {
        DVec3::splat(0.5) + self.centre_inv * (p - self.centre)
    }

    /// One damped Newton run (see [`Hexahedron::invert`]); `constrained` keeps the iterates in a slightly
    /// enlarged box, where `J` is known to be regular.
    fn newton(&self, p: DVec3, start: DVec3, tol_q: f64, constrained: bool) -> Option<DVec3> {
        const LO: f64 = -1e-3;
        const HI: f64 = 1.0 + 1e-3;
        let project = |q: DVec3| {
            if constrained {
                q.clamp(DVec3::splat(LO), DVec3::splat(HI))
            } else {
                q
            }
        };
        // Residuals at or below rounding noise of the coordinates cannot be improved by further steps.
        let noise = 16.0 * f64::EPSILON * (self.size + (p - self.centre).length());
        let mut q = project(start);
        let mut r = self.world(q) - p;
        let mut rr = r.length_squared();
        for _ in 0..NEWTON_MAX_ITERS {
            let j = self.jacobian(q);
            let det = j.determinant();
            if det == 0.0 || !det.is_finite() {
                return None;
            }
            let delta = -(j.inverse() * r);
            if !delta.is_finite() {
                return None;
            }
            if delta.abs().max_element() <= tol_q || rr.sqrt() <= noise {
                let qn = q + delta;
                let rn = self.world(qn) - p;
                // Verify: the residual must be what a step of at most tol_q leaves behind.
                let jnorm = j.x_axis.length() + j.y_axis.length() + j.z_axis.length();
                let ok = rn.length() <= jnorm * tol_q + noise;
                return (ok && qn.is_finite()).then_some(qn);
            }
            let mut alpha = 1.0;
            loop {
                let qn = project(q + alpha * delta);
                let rn = self.world(qn) - p;
                let rrn = rn.length_squared();
                if rrn < rr {
                    q = qn;
                    r = rn;
                    rr = rrn;
                    break;
                }
                alpha *= 0.5;
                if alpha < 1e-12 {
                    return None;
                }
            }
        }
        None
    }
}

/// Collected ray parameters of boundary hits.
struct Hits {
    min: f64,
    max: f64,
    /// Hits down to this (slightly negative) `t` count, clamped to 0: an origin on the boundary.
    floor: f64,
}

impl Hits {
    fn new(floor: f64) -> Self {
        Hits { min: f64::INFINITY, max: f64::NEG_INFINITY, floor }
    }

    fn push(&mut self, t: f64) {
        if t.is_finite() && t >= self.floor {
            let t = t.max(0.0);
            self.min = self.min.min(t);
            self.max = self.max.max(t);
        }
    }

    fn range(&self) -> Option<(f64, f64)> {
        (self.min <= self.max).then_some((self.min, self.max))
    }
}

/// Ray / bilinear patch `P(u,v) = lerp(lerp(q00, q10, u), lerp(q01, q11, u), v)` (Reshetov 2019).
///
/// The ruling at `u` is the line `pa(u) + v·pb(u)` with `pa = lerp(q00, q10, u) − o` and
/// `pb = lerp(q01 − q00, q11 − q10, u)`. It meets the ray iff `g(u) = (pa × pb)·d = 0`, a quadratic
/// `A + B·u + C·u²` with `A = g(0)`, `C = ((q10 − q00) × (q11 − q10 − q01 + q00))·d`, `B = g(1) − A − C`.
/// Roots come from the cancellation-free formula; for each root in `[0,1]`, with `n = d × pb`,
/// `t = (pa × pb)·n / |n|²` and `v = (pa × d)·n / |n|²`. When `n ≈ 0` the ray runs along that ruling, and
/// the ruling's two ends (on the patch border) are the hits.
fn patch_hits(o: DVec3, d: DVec3, q: [DVec3; 4], tol: f64, hits: &mut Hits) {
    let [q00, q10, q01, q11] = q;
    let e00 = q01 - q00;
    let e11 = q11 - q10;
    let p00 = q00 - o;
    let p10 = q10 - o;
    let a = p00.cross(e00).dot(d);
    let c = (q10 - q00).cross(e11 - e00).dot(d);
    let b = p10.cross(e11).dot(d) - a - c;

    let mut roots = [f64::NAN; 2];
    if c == 0.0 {
        if b != 0.0 {
            roots[0] = -a / b;
        }
    } else {
        let mut disc = b * b - 4.0 * a * c;
        // A tangent ray may come out marginally negative; keep it as a double root.
        if disc < 0.0 && disc >= -1e-12 * (b * b + (4.0 * a * c).abs()) {
            disc = 0.0;
        }
        if disc >= 0.0 {
            let s = -0.5 * (b + disc.sqrt().copysign(b));
            if s != 0.0 {
                roots = [a / s, s / c];
            } else {
                // b = 0 and disc = 0, so a·c = 0 with c ≠ 0: a = 0, double root at 0.
                roots[0] = 0.0;
            }
        }
    }
    let dd = d.length_squared();
    for u in roots {
        if !(-PATCH_EPS..=1.0 + PATCH_EPS).contains(&u) {
            continue; // also rejects NaN
        }
        let pa = p00.lerp(p10, u);
        let pb = e00.lerp(e11, u);
        let n = d.cross(pb);
        let nn = n.length_squared();
        if nn > 1e-24 * dd * pb.length_squared() {
            let t = pa.cross(pb).dot(n) / nn;
            let v = pa.cross(d).dot(n) / nn;
            if (-PATCH_EPS..=1.0 + PATCH_EPS).contains(&v) {
                // Verify (guards against an ill-conditioned root of a nearly degenerate quadratic).
                if (t * d - pa - v * pb).length() <= 1e3 * tol {
                    hits.push(t);
                }
            }
        } else {
            // The ray runs along the ruling: its two ends are the contact's ends.
            for end in [pa, pa + pb] {
                let t = end.dot(d) / dd;
                if (t * d - end).length() <= tol {
                    hits.push(t);
                }
            }
        }
    }
}

/// Ray / straight edge `[a, b]`: the closest approach, kept if within `tol`; an edge parallel to the ray
/// contributes both ends if the ray runs along it.
///
/// With `n = d × e` (`e = b − a`), the distance between the two lines is `|(a − o)·n| / |n|`; comparing
/// squares rejects almost every edge without a division or square root. For a close edge, writing
/// `a − o = t·d − s·e + k·n` and crossing with `e` and `d` gives `t = ((a−o) × e)·n / |n|²` and
/// `s = ((a−o) × d)·n / |n|²`; `s` is clamped to the edge and the end point re-checked.
fn edge_hits(o: DVec3, d: DVec3, a: DVec3, b: DVec3, tol: f64, hits: &mut Hits) {
    let e = b - a;
    let w = a - o;
    let (dd, ee) = (d.length_squared(), e.length_squared());
    let n = d.cross(e);
    let nn = n.length_squared();
    if ee == 0.0 || nn <= 1e-20 * dd * ee {
        // Parallel: the ray runs along the edge iff both ends are on it.
        for p in [a, b] {
            let t = (p - o).dot(d) / dd;
            if (o + t * d - p).length() <= tol {
                hits.push(t);
            }
        }
        return;
    }
    let sep = w.dot(n);
    if sep * sep > tol * tol * nn {
        return;
    }
    let s = (w.cross(d).dot(n) / nn).clamp(0.0, 1.0);
    let p = a + s * e;
    let t = (p - o).dot(d) / dd;
    if (o + t * d - p).length() <= tol {
        hits.push(t);
    }
}

/// Bernstein product weight for degrees (1, 1): `C(1,i)·C(1,j)/C(2,i+j)`.
fn prod_w(i: usize, j: usize) -> f64 {
    if i + j == 1 {
        0.5
    } else {
        1.0
    }
}

/// The 27 Bernstein coefficients of degree (2,2,2) of `det J = J_x · (J_y × J_z)`.
///
/// `J_x` is bilinear in `(y, z)` with Bernstein (= corner) coefficients the four x-edge vectors
/// `c[1+2j+4k] − c[2j+4k]`; likewise `J_y` in `(x, z)` and `J_z` in `(x, y)`. Products of Bernstein
/// polynomials of degrees `m` and `n` have coefficients `Σ_{i+j=k} C(m,i)C(n,j)/C(m+n,k)·a_i·b_j`, per
/// axis; applying that twice gives the coefficients exactly (in exact arithmetic).
#[allow(clippy::needless_range_loop)] // the indices are the Bernstein degrees of the product rule
fn det_bernstein(c: &[DVec3; 8]) -> Bern {
    let at = |x: usize, y: usize, z: usize| c[x + 2 * y + 4 * z];
    let jx = |j: usize, k: usize| at(1, j, k) - at(0, j, k);
    let jy = |i: usize, k: usize| at(i, 1, k) - at(i, 0, k);
    let jz = |i: usize, j: usize| at(i, j, 1) - at(i, j, 0);
    // J_y × J_z: degree (2, 1, 1); x from both factors, y from J_z, z from J_y.
    let mut cross = [[[DVec3::ZERO; 2]; 2]; 3];
    for i1 in 0..2 {
        for i2 in 0..2 {
            for j in 0..2 {
                for k in 0..2 {
                    cross[i1 + i2][j][k] += prod_w(i1, i2) * jy(i1, k).cross(jz(i2, j));
                }
            }
        }
    }
    let mut out = [[[0.0; 3]; 3]; 3];
    for (i, plane) in cross.iter().enumerate() {
        for j1 in 0..2 {
            for (j2, row) in plane.iter().enumerate() {
                for k1 in 0..2 {
                    for (k2, v) in row.iter().enumerate() {
                        out[i][j1 + j2][k1 + k2] += prod_w(j1, j2) * prod_w(k1, k2) * jx(j1, k1).dot(*v);
                    }
                }
            }
        }
    }
    out
}

/// Splits degree-2 Bernstein coefficients along `axis` at ½ (de Casteljau): (lower half, upper half).
fn split(b: &Bern, axis: usize) -> (Bern, Bern) {
    let (mut lo, mut hi) = (*b, *b);
    for m in 0..3 {
        for n in 0..3 {
            let at = |k: usize| match axis {
                0 => [k, m, n],
                1 => [m, k, n],
                _ => [m, n, k],
            };
            let get = |k: usize| {
                let [i, j, l] = at(k);
                b[i][j][l]
            };
            let (b0, b1, b2) = (get(0), get(1), get(2));
            let mid = 0.25 * (b0 + 2.0 * b1 + b2);
            let set = |arr: &mut Bern, k: usize, v: f64| {
                let [i, j, l] = at(k);
                arr[i][j][l] = v;
            };
            set(&mut lo, 1, 0.5 * (b0 + b1));
            set(&mut lo, 2, mid);
            set(&mut hi, 0, mid);
            set(&mut hi, 1, 0.5 * (b1 + b2));
        }
    }
    (lo, hi)
}

/// The sign of `det J` on `[0,1]³` (+1 or −1), or the reason the box is refused. See [`Hexahedron::new`].
fn check_no_fold(bern: &Bern, tol: f64) -> Result<f64, HexahedronError> {
    let max_abs = bern.iter().flatten().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    if max_abs <= tol {
        return Err(HexahedronError::NoVolume);
    }
    let first = bern[0][0][0];
    if first.abs() <= tol {
        return Err(HexahedronError::DegenerateAtCorner0);
    }
    let sign = first.signum();
    let mut stack = vec![(*bern, DVec3::ZERO, 1.0f64, 0u32)];
    let mut examined = 0usize;
    while let Some((b, lo, h, depth)) = stack.pop() {
        examined += 1;
        if b.iter().flatten().flatten().all(|&v| sign * v > tol) {
            continue;
        }
        for (ix, iy, iz) in (0..8).map(|i| (2 * (i & 1), (i >> 1) & 1, (i >> 2) & 1)) {
            let (iy, iz) = (2 * iy, 2 * iz);
            let v = b[ix][iy][iz];
            if sign * v <= tol {
                let at = (lo + 0.5 * h * DVec3::new(ix as f64, iy as f64, iz as f64)).to_array();
                return Err(if v.abs() <= tol {
                    HexahedronError::DegenerateAt { at }
                } else {
                    HexahedronError::Folds { at_corner0: first, value: v, at }
                });
            }
        }
        if depth >= FOLD_MAX_DEPTH || examined >= FOLD_MAX_BOXES {
            return Err(HexahedronError::TooCloseToFolding { near: (lo + DVec3::splat(0.5 * h)).to_array() });
        }
        let h2 = 0.5 * h;
        let (x0, x1) = split(&b, 0);
        for (xb, xs) in [(x0, 0.0), (x1, 1.0)] {
            let (y0, y1) = split(&xb, 1);
            for (yb, ys) in [(y0, 0.0), (y1, 1.0)] {
                let (z0, z1) = split(&yb, 2);
                for (zb, zs) in [(z0, 0.0), (z1, 1.0)] {
                    stack.push((zb, lo + h2 * DVec3::new(xs, ys, zs), h2, depth + 1));
                }
            }
        }
    }
    Ok(sign)
}

#[cfg(test)]
mod tests;
