//! Lighting as one more axis of the sampler's specialisation (SPEC §6): a loop is compiled
//! for [`NoShade`], which computes nothing and whose loop is the unlit one, or for
//! [`Shaded`], which shades every sample that contributes. Whether an object is shaded is
//! decided once, when it is bound ([`super::bind`]); no loop tests it per sample.
//!
//! A shaded sample's normal is the gradient of the object's own interpolation function over
//! the channel its opacity map reads, by central differences one voxel either side along
//! each VC axis (points outside the dataset clamped as interpolation clamps them), taken to
//! world space by the inverse transpose of the VC → world Jacobian at the sample
//! ([`GradientToWorld`]) and turned to face the viewer. Blinn–Phong then gives the colour
//! that replaces the mapped one; opacity is unchanged.
//!
//! The f32 packet loop ([`super::packet`]) has the same axis, as a constant parameter of its
//! loop: [`LaneShading`] is `Shaded`'s computation in f32 lanes, for the objects that loop
//! casts (trilinear, u8 or u16 voxels, a small joint map) in an affine box, whose normals
//! all go to world space through one constant matrix. A distorted box's Jacobian changes
//! from sample to sample; such an object keeps the f64 loops.

use std::sync::Arc;

use glam::DVec3;

use super::kernel::VoxelSource;
use super::packed::pow;
use super::simd::Simd;
use super::ObjectCaster;
use crate::geometry::{GradientToWorld, Placement, Ray};
use crate::interp::Interp;
use crate::scene::{Light, LightSource, Shading, Transmittance};

/// What a loop does to a contributing sample's colour.
pub(super) trait Shade: Send + Sync {
    /// Whether the loop shades at all: a constant, so the unlit loop keeps no trace of it.
    const ON: bool;

    /// The colour of the sample at VC point `vc` and world point `x`, seen along `view` (the
    /// unit vector from the sample towards the eye), whose mapped colour is `c`.
    fn shade<I: Interp>(&self, interp: &I, vc: [f64; 3], x: DVec3, view: DVec3, c: [f64; 3]) -> [f64; 3];
}

/// No lighting: the colour is the mapped one (SPEC §4).
pub(super) struct NoShade;

impl Shade for NoShade {
    const ON: bool = false;

    #[inline(always)]
    fn shade<I: Interp>(&self, _: &I, _: [f64; 3], _: DVec3, _: DVec3, c: [f64; 3]) -> [f64; 3] {
        c
    }
}

/// A light as a sample uses it.
#[derive(Clone, Copy, Debug)]
enum LightAt {
    /// A directional light: L, the unit vector towards it, the same everywhere.
    Towards { l: DVec3, radiance: DVec3 },
    /// A point light at a world position.
    At { position: DVec3, radiance: DVec3 },
}

/// A shadow ray's cast stops once its opacity reaches this: S is then below 2⁻²⁰, which
/// no 8-bit image can show (SPEC §6 allows approximations within 2/255).
pub const SHADOW_STOP: f64 = 1.0 - 1.0 / (1u64 << 20) as f64;

/// S of SPEC §6 for a shaded object under lights that cast shadows: the product over every
/// object of (1 − A) along the shadow ray. This object's own factor is cast exactly, sample
/// by sample, through its own volume (`own`, the object bound unlit): it is what decides
/// whether a surface faces its light, at the scale of the surface itself, where any
/// lattice would blur it. The other objects' factors come from the lattice over this
/// object's box that `render::shadow` computed dataset by dataset ([`Transmittance`]).
pub(super) struct Shadows<'a> {
    /// The object bound unlit: its opacity along a shadow ray.
    pub own: ObjectCaster<'a>,
    pub placement: &'a Placement,
    /// Per light: `None` where it casts no shadows; else the transmittance through the
    /// other objects (`None` inside where none comes between).
    pub per_light: Vec<Option<Option<Transmittance>>>,
}

impl Shadows<'_> {
    /// S for light `i`, seen from world point `x` (VC point `vc` of this object) along `l`
    /// (unit, towards the light) up to `reach` (∞ for a directional light).
    #[inline]
    fn transmittance(&self, i: usize, x: DVec3, vc: [f64; 3], l: DVec3, reach: f64) -> f64 {
        let others = match &self.per_light[i] {
            None => return 1.0,
            Some(None) => 1.0,
            Some(Some(t)) => t.at(self.placement.box_of_vc(DVec3::from(vc))),
        };
        if others <= 0.0 {
            return 0.0;
        }
        let ray = Ray { origin: x, dir: l };
        let own = match self.placement.segment(&ray) {
            Some((t0, t1)) if t1.min(reach) > t0 => {
                1.0 - self.own.cast(&ray, t0, t1.min(reach), 0.0, SHADOW_STOP).rgba.alpha
            }
            _ => 1.0,
        };
        own * others
    }
}

/// Blinn–Phong with the gradient of `field` (SPEC §6).
pub(super) struct Shaded<'a, F> {
    /// The channel the opacity map reads, through the object's interpolation.
    field: F,
    material: Shading,
    lights: Vec<LightAt>,
    to_world: GradientToWorld<'a>,
    /// Where some light casts shadows: how S is found.
    shadows: Option<Arc<Shadows<'a>>>,
}

impl<'a, F: VoxelSource> Shaded<'a, F> {
    /// Shading of `field` with `material` under `lights`, normals taken to world space by
    /// `to_world`.
    pub(super) fn new(field: F, material: Shading, lights: &[Light], to_world: GradientToWorld<'a>) -> Self {
        let lights = lights
            .iter()
            .map(|l| {
                let radiance = DVec3::from(l.radiance());
                match l.source() {
                    LightSource::Directional { direction } => LightAt::Towards { l: -direction.get(), radiance },
                    LightSource::Point { position } => LightAt::At { position, radiance },
                }
            })
            .collect();
        Shaded { field, material, lights, to_world, shadows: None }
    }

    /// The same shading with S (SPEC §6) from `shadows` for the lights that cast them.
    pub(super) fn with_shadows(self, shadows: Option<Arc<Shadows<'a>>>) -> Self {
        Shaded { shadows, ..self }
    }

    /// I at VC point `p`.
    #[inline(always)]
    fn value<I: Interp>(&self, interp: &I, p: [f64; 3]) -> f64 {
        self.field.value(interp, &interp.locate(p))
    }

    /// The VC gradient of I at `p` by central differences over one voxel.
    #[inline]
    fn gradient<I: Interp>(&self, interp: &I, p: [f64; 3]) -> DVec3 {
        let mut g = [0.0; 3];
        for (axis, g) in g.iter_mut().enumerate() {
            let (mut hi, mut lo) = (p, p);
            hi[axis] += 1.0;
            lo[axis] -= 1.0;
            *g = (self.value(interp, hi) - self.value(interp, lo)) / 2.0;
        }
        DVec3::from(g)
    }
}

impl<F: VoxelSource> Shade for Shaded<'_, F> {
    const ON: bool = true;

    #[inline]
    fn shade<I: Interp>(&self, interp: &I, vc: [f64; 3], x: DVec3, view: DVec3, c: [f64; 3]) -> [f64; 3] {
        let g = self.to_world.apply(DVec3::from(vc), self.gradient(interp, vc));
        let len = g.length();
        // No surface to light (or a gradient that is not a number): the sample keeps its colour.
        if !(len > 0.0 && len.is_finite()) {
            return c;
        }
        let n = -g / len;
        let n = if n.dot(view) < 0.0 { -n } else { n };
        let m = &self.material;
        let (mut diffuse, mut specular) = (DVec3::ZERO, DVec3::ZERO);
        for (i, light) in self.lights.iter().enumerate() {
            let (l, radiance, reach) = match *light {
                LightAt::Towards { l, radiance } => (l, radiance, f64::INFINITY),
                // A sample at the light's own position is not lit by it (L is undefined).
                LightAt::At { position, radiance } => {
                    let d = position - x;
                    (d.normalize_or_zero(), radiance, d.length())
                }
            };
            let n_dot_l = n.dot(l);
            // Only where N·L > 0: max(0, N·L) is 0 elsewhere, and so is the specular term
            // (and S, which scales both, is not needed).
            if n_dot_l > 0.0 {
                let s = match &self.shadows {
                    Some(shadows) => shadows.transmittance(i, x, vc, l, reach),
                    None => 1.0,
                };
                diffuse += m.diffuse() * n_dot_l * s * radiance;
                // L + V ≠ 0 here: N·V ≥ 0 and N·L > 0 rule out L = −V.
                let h = (l + view).normalize();
                specular += m.specular() * n.dot(h).max(0.0).powf(m.shininess()) * s * radiance;
            }
        }
        let lit = DVec3::from(c) * (DVec3::splat(m.ambient()) + diffuse) + specular;
        lit.to_array()
    }
}

/// A light as a lane uses it: [`LightAt`] in f32. A directional light's H depends on the
/// ray only (V is the same along it): the first [`HALF_VECTORS`] are worked out once per
/// piece, in f64, and `slot` says which ([`LaneShading::half_vector`]).
#[derive(Clone, Copy, Debug)]
enum LaneLight {
    Towards { l: [f32; 3], radiance: [f32; 3], slot: Option<usize> },
    At { position: [f32; 3], radiance: [f32; 3] },
}

/// Directional lights whose H a lane keeps per piece; further ones compute it per sample.
pub(super) const HALF_VECTORS: usize = 4;

/// [`Shaded`] for the f32 packet loop: an affine box's normal matrix, the material and the
/// lights, rounded to f32, and the same operations on a register of samples at a time
/// ([`LaneShading::shade`]).
#[derive(Clone, Debug)]
pub(super) struct LaneShading {
    /// The box's [`GradientToWorld::Affine`] matrix row by row, scaled by a power of two (so
    /// exactly) to put its largest entry in [1, 2): a normal does not depend on the
    /// gradient's scale, and so scaled the world gradient of u8 or u16 values, and its
    /// square, stay far inside f32's range whatever the box's size in the world.
    to_world: [[f32; 3]; 3],
    ambient: f32,
    diffuse: f32,
    specular: f32,
    shininess: f32,
    /// The shininess where it is a whole number up to 64, and the least base whose power
    /// that is stays a normal f32: the power is then a few multiplications
    /// ([`LaneShading::power`]).
    whole_shininess: Option<(u32, f32)>,
    lights: Vec<LaneLight>,
    /// L of the directional lights whose H lanes keep, in slot order.
    towards: Vec<DVec3>,
    /// Divide each world gradient by its largest component before its length is taken
    /// ([`LaneShading::rescaled`]): f32 voxels' gradients can be of any size, where their
    /// squares would overflow or vanish; u8 and u16 ones cannot.
    rescale: bool,
}

/// For a whole-number shininess n up to 64, n and the least f32 x at or above which xⁿ
/// (and so every power of x up to n) is a normal f32, with a factor of two to spare for
/// the roundings on the way (0 for n = 0: x⁰ = 1); `None` for any other shininess.
fn whole_power(shininess: f64) -> Option<(u32, f32)> {
    if !(shininess.fract() == 0.0 && (0.0..=64.0).contains(&shininess)) {
        return None;
    }
    let n = shininess as u32;
    if n == 0 {
        return Some((0, 0.0));
    }
    let least = (2.0 * f64::from(f32::MIN_POSITIVE)).powf(1.0 / f64::from(n));
    // Rounded up, so that every f32 at or above it keeps the bound.
    let floor = least as f32;
    Some((n, if f64::from(floor) < least { floor.next_up() } else { floor }))
}

/// Bound on a lit colour and on light positions: far inside f32's range, so that no lane,
/// live or idle, overflows to a value that would turn a sum into NaN.
const LANE_LIMIT: f64 = 1e18;

impl LaneShading {
    /// `material` under `lights` for an object whose normals go to world space by
    /// `to_world`; `None` for a distorted box (its Jacobian is not one matrix) and where a
    /// number could leave f32's range: those objects keep the f64 loops.
    pub(super) fn new(material: Shading, lights: &[Light], to_world: GradientToWorld<'_>) -> Option<LaneShading> {
        let GradientToWorld::Affine(m) = to_world else { return None };
        let largest = m.to_cols_array().iter().fold(0.0f64, |a, x| a.max(x.abs()));
        if !(largest > 0.0 && largest.is_finite()) {
            return None;
        }
        let scale = 2f64.powi(-(largest.log2().floor() as i32));
        let to_world = std::array::from_fn(|r| std::array::from_fn(|c| (m.col(c)[r] * scale) as f32));
        // A lit colour is at most ambient + Σ (diffuse + specular)·E per channel (c ≤ 1,
        // N·L ≤ 1, (N·H)^shininess ≤ 1).
        let mut brightest = material.ambient();
        let mut lane_lights = Vec::with_capacity(lights.len());
        let mut towards = Vec::new();
        for light in lights {
            let radiance = light.radiance();
            brightest += (material.diffuse() + material.specular()) * radiance.iter().fold(0.0f64, |a, &e| a.max(e));
            let radiance = radiance.map(|e| e as f32);
            lane_lights.push(match light.source() {
                LightSource::Directional { direction } => {
                    let slot = (towards.len() < HALF_VECTORS).then_some(towards.len());
                    if slot.is_some() {
                        towards.push(-direction.get());
                    }
                    LaneLight::Towards { l: (-direction.get()).to_array().map(|x| x as f32), radiance, slot }
                }
                LightSource::Point { position } => {
                    if position.abs().max_element() >= LANE_LIMIT {
                        return None;
                    }
                    LaneLight::At { position: position.to_array().map(|x| x as f32), radiance }
                }
            });
        }
        if !(brightest < LANE_LIMIT && material.shininess() < LANE_LIMIT) {
            return None;
        }
        Some(LaneShading {
            to_world,
            ambient: material.ambient() as f32,
            diffuse: material.diffuse() as f32,
            specular: material.specular() as f32,
            shininess: material.shininess() as f32,
            whole_shininess: whole_power(material.shininess()),
            lights: lane_lights,
            towards,
            rescale: false,
        })
    }

    /// The same shading for gradients of any finite size (f32 voxels'): each world gradient
    /// is divided by its largest component (the normal is the same direction) before its
    /// length is taken, so that no square overflows or vanishes where the f64 loop's does not.
    pub(super) fn rescaled(self) -> LaneShading {
        LaneShading { rescale: true, ..self }
    }

    /// How many directional lights have their H kept per piece ([`LaneShading::half_vector`]).
    pub(super) fn half_vectors(&self) -> usize {
        self.towards.len()
    }

    /// H = normalise(L + V) of the directional light in `slot`, for a ray whose unit vector
    /// towards the eye is `view`, as `Shaded::shade` computes it (in f64; NaN where L = −V,
    /// where N·L > 0 cannot hold and H is not used).
    pub(super) fn half_vector(&self, slot: usize, view: DVec3) -> [f32; 3] {
        (self.towards[slot] + view).normalize().to_array().map(|x| x as f32)
    }

    /// xˢ for x ≥ 0 and the shininess s: by repeated squaring where s is a whole number
    /// (exact to a few roundings, and 0⁰ = 1 as `powf` has it), else [`pow`]. Below the
    /// floor that [`whole_power`] sets, where xˢ is under twice f32's smallest normal, it is
    /// 0 (as `pow` is near 0 there): no product is subnormal, which x86 computes slowly.
    #[inline(always)]
    fn power<S: Simd>(&self, s: S, x: S::F) -> S::F {
        let Some((mut n, floor)) = self.whole_shininess else { return pow(s, x, self.shininess) };
        let x = s.select(s.ge(x, s.splat(floor)), x, s.splat(0.0));
        let (mut result, mut base) = (s.splat(1.0), x);
        while n > 0 {
            if n & 1 == 1 {
                result = s.mul(result, base);
            }
            n >>= 1;
            if n > 0 {
                base = s.mul(base, base);
            }
        }
        result
    }

    /// The colours `c` of a register of samples lit (SPEC §6), [`Shaded::shade`]'s
    /// operations in f32 lanes: `g` is their VC gradient ([`super::packed::Grid::gradient`]),
    /// `x` their world points, `view` the unit vectors from them towards the eye, `half(j)`
    /// the H kept per piece of the directional light in slot `j`
    /// ([`LaneShading::half_vector`]), read only where a light uses it. Lanes
    /// whose world gradient is zero or not finite keep `c`; every lane's result is finite
    /// (idle lanes' included, which the loop weighs by +0).
    #[inline(always)]
    pub(super) fn shade<S: Simd>(
        &self,
        s: S,
        g: [S::F; 3],
        x: [S::F; 3],
        view: [S::F; 3],
        half: impl Fn(usize) -> [S::F; 3],
        c: [S::F; 3],
    ) -> [S::F; 3] {
        let (zero, one) = (s.splat(0.0), s.splat(1.0));
        let dot = |a: [S::F; 3], b: [S::F; 3]| s.mul_add(a[2], b[2], s.mul_add(a[1], b[1], s.mul(a[0], b[0])));
        let m = &self.to_world;
        let mut world = [zero; 3];
        for (r, w) in world.iter_mut().enumerate() {
            *w = dot([s.splat(m[r][0]), s.splat(m[r][1]), s.splat(m[r][2])], g);
        }
        if self.rescale {
            // Largest |component| first: a zero gradient gives 0·∞ = NaN below, which is not
            // lit, as a non-finite one is not.
            let big = s.max(s.abs(world[0]), s.max(s.abs(world[1]), s.abs(world[2])));
            let inv = s.div(one, big);
            for w in &mut world {
                *w = s.mul(*w, inv);
            }
        }
        let len = s.sqrt(dot(world, world));
        // No surface to light (or a gradient that is not a number): false for NaN.
        let lit = s.and_m(s.gt(len, zero), s.lt(len, s.splat(f32::INFINITY)));
        let minus_inv = s.div(s.splat(-1.0), len);
        let mut n = [zero; 3];
        for (n, &w) in n.iter_mut().zip(&world) {
            *n = s.mul(w, minus_inv);
        }
        let back = s.lt(dot(n, view), zero);
        for n in &mut n {
            *n = s.select(back, s.sub(zero, *n), *n);
        }
        let (mut diffuse, mut specular) = ([zero; 3], [zero; 3]);
        for light in &self.lights {
            let (l, radiance, kept) = match *light {
                LaneLight::Towards { l, radiance, slot } => {
                    ([s.splat(l[0]), s.splat(l[1]), s.splat(l[2])], radiance, slot.map(&half))
                }
                LaneLight::At { position, radiance } => {
                    let mut d = [zero; 3];
                    for (a, d) in d.iter_mut().enumerate() {
                        *d = s.sub(s.splat(position[a]), x[a]);
                    }
                    // At the light's own position d = 0, so L is NaN (0·∞) and N·L > 0 fails:
                    // not lit by it, as the f64 loop's L = 0 gives.
                    let inv = s.div(one, s.sqrt(dot(d, d)));
                    ([s.mul(d[0], inv), s.mul(d[1], inv), s.mul(d[2], inv)], radiance, None)
                }
            };
            let n_dot_l = dot(n, l);
            // Only where N·L > 0: elsewhere neither term counts.
            let on = s.gt(n_dot_l, zero);
            let n_dot_h = match kept {
                Some(h) => dot(n, h),
                None => {
                    let mut half = [zero; 3];
                    for (a, h) in half.iter_mut().enumerate() {
                        *h = s.add(l[a], view[a]);
                    }
                    s.mul(dot(n, half), s.div(one, s.sqrt(dot(half, half))))
                }
            };
            let n_dot_h = s.max(n_dot_h, zero);
            let kd = s.select(on, s.mul(s.splat(self.diffuse), n_dot_l), zero);
            let ks = s.select(on, s.mul(s.splat(self.specular), self.power(s, n_dot_h)), zero);
            for i in 0..3 {
                let e = s.splat(radiance[i]);
                diffuse[i] = s.mul_add(kd, e, diffuse[i]);
                specular[i] = s.mul_add(ks, e, specular[i]);
            }
        }
        let ambient = s.splat(self.ambient);
        let mut out = c;
        for (i, out) in out.iter_mut().enumerate() {
            *out = s.select(lit, s.mul_add(c[i], s.add(ambient, diffuse[i]), specular[i]), c[i]);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;
    use std::sync::Arc;

    use glam::{DMat3, DMat4, DVec3};

    use super::*;
    use crate::dataset::{Channel, ChannelName, Dims, Endian, F32LeVoxels, Volume, VoxelBytes, VoxelType};
    use crate::geometry::hexahedron::Hexahedron;
    use crate::geometry::{Extent, Placement, Shape};
    use crate::interp::{Cubic, Identity, Linear, Nearest};
    use crate::sampling::kernel::Read;

    /// A dataset of `dims` whose f32 `voxel` channel holds f(i, j, k).
    fn field_volume(dims: [u64; 3], f: impl Fn(f64, f64, f64) -> f64) -> Volume {
        let d = Dims::new(dims).unwrap();
        let mut bytes = Vec::new();
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    bytes.extend((f(i as f64, j as f64, k as f64) as f32).to_le_bytes());
                }
            }
        }
        let ch = Channel::new(VoxelType::F32, Endian::Little, VoxelBytes::Owned(Arc::new(bytes)), d).unwrap();
        Volume::new(d, BTreeMap::from([(ChannelName::Voxel, ch)]))
    }

    /// Points spread through the interior, where neither trilinear's nor the cubic's stencil
    /// one voxel either side is clamped; some on voxel and cell boundaries.
    fn interior_points(dims: [u64; 3]) -> Vec<[f64; 3]> {
        let mut out = vec![[2.0, 2.0, 2.0], [3.5, 4.0, 2.25]];
        for i in 0..40 {
            let f = i as f64 / 40.0;
            out.push(std::array::from_fn(|a| {
                let span = dims[a] as f64 - 5.0;
                2.0 + span * ((f * (a as f64 + 1.7) * 3.1).sin() * 0.5 + 0.5)
            }));
        }
        out
    }

    #[test]
    fn the_gradient_of_a_linear_field_is_exact_under_trilinear_cubic_and_nearest() {
        let dims = [12, 10, 9];
        let (a, b, c) = (3.0, -5.0, 7.0);
        let volume = field_volume(dims, |i, j, k| a * i + b * j + c * k + 100.0);
        let voxels = F32LeVoxels::of(volume.channel(ChannelName::Voxel).unwrap().reader()).unwrap();
        let shaded = Shaded::new(Read(voxels), Shading::DEFAULT, &[], GradientToWorld::Affine(DMat3::IDENTITY));
        let d = Dims::new(dims).unwrap();
        let want = DVec3::new(a, b, c);
        for p in interior_points(dims) {
            let linear = shaded.gradient(&Linear::new(d, Identity), p);
            let cubic = shaded.gradient(&Cubic::new(d), p);
            assert!((linear - want).abs().max_element() < 1e-9, "trilinear at {p:?}: {linear}");
            assert!((cubic - want).abs().max_element() < 1e-9, "cubic at {p:?}: {cubic}");
            // Nearest: p ± 1 reads the neighbours of p's voxel, one voxel either side.
            let nearest = shaded.gradient(&Nearest::new(d), p);
            assert!((nearest - want).abs().max_element() < 1e-9, "nearest at {p:?}: {nearest}");
        }
        // A field that is not linear has a gradient that these differences do not hit
        // exactly, so the test can tell.
        let curved = field_volume(dims, |i, j, k| i * i + j * k);
        let voxels = F32LeVoxels::of(curved.channel(ChannelName::Voxel).unwrap().reader()).unwrap();
        let shaded = Shaded::new(Read(voxels), Shading::DEFAULT, &[], GradientToWorld::Affine(DMat3::IDENTITY));
        let g = shaded.gradient(&Linear::new(d, Identity), [4.5, 4.0, 4.0]);
        assert!((g - DVec3::new(9.0, 4.0, 4.0)).abs().max_element() < 1e-9, "{g}");
    }

    /// A truly distorted box (no parallelepiped) well away from folding.
    fn distorted() -> Hexahedron {
        let mut c: [DVec3; 8] = std::array::from_fn(|i| {
            DVec3::new((i & 1) as f64 * 2.0, ((i >> 1) & 1) as f64 * 1.5, ((i >> 2) & 1) as f64)
        });
        c[7] += DVec3::new(0.3, -0.2, 0.25);
        c[2] += DVec3::new(-0.2, 0.1, 0.05);
        c[4] += DVec3::new(0.1, 0.15, -0.1);
        Hexahedron::new(c).unwrap()
    }

    /// World → VC by inverting the placement's map.
    fn vc_of_world(p: &Placement, x: DVec3) -> DVec3 {
        let Shape::Distorted { hex, .. } = p.shape() else { panic!("distorted") };
        p.vc_of_box(hex.invert(x, None, 1e-14).expect("inside"))
    }

    #[test]
    fn gradients_reach_world_space_through_the_jacobian_at_the_sample() {
        // f(VC) = g·VC: its world gradient is what finite differences of f(VC(world)) give.
        let g = DVec3::new(0.7, -1.3, 2.1);
        let extent = Extent { min: DVec3::new(0.1, 0.0, 0.2), max: DVec3::new(0.9, 1.0, 0.7) };
        let dims = Dims::new([8, 6, 5]).unwrap();
        let distorted = Placement::new(Shape::Distorted { hex: Box::new(distorted()), straight: false }, extent, dims);
        let m = DMat4::from_rotation_y(0.4) * DMat4::from_scale(DVec3::new(2.0, 0.5, 1.5));
        let affine = Placement::new(Shape::Affine { world_from_box: m, box_from_world: m.inverse() }, extent, dims);
        for q in [DVec3::splat(0.5), DVec3::new(0.2, 0.8, 0.3), DVec3::new(0.9, 0.1, 0.75)] {
            for p in [&distorted, &affine] {
                let (x, vc) = match p.shape() {
                    Shape::Distorted { hex, .. } => (hex.world(q), p.vc_of_box(q)),
                    Shape::Affine { world_from_box, .. } => (world_from_box.transform_point3(q), p.vc_of_box(q)),
                };
                let vc_of = |x: DVec3| match p.shape() {
                    Shape::Distorted { .. } => vc_of_world(p, x),
                    Shape::Affine { box_from_world, .. } => p.vc_of_box(box_from_world.transform_point3(x)),
                };
                let h = 1e-5;
                let numeric = DVec3::from(std::array::from_fn::<f64, 3, _>(|a| {
                    let e = DVec3::from(std::array::from_fn::<f64, 3, _>(|b| if a == b { h } else { 0.0 }));
                    (g.dot(vc_of(x + e)) - g.dot(vc_of(x - e))) / (2.0 * h)
                }));
                let exact = p.gradient_to_world().apply(vc, g);
                assert!((exact - numeric).length() < 1e-6 * numeric.length(), "at q {q}: {exact} vs {numeric}");
            }
        }
    }

    /// [`LaneShading::power`] of `xs` with shininess `e`, a register at a time.
    fn powers<S: Simd>(s: S, e: f64, xs: &[f32]) -> Vec<f32> {
        let material = Shading::new(0.1, 0.6, 0.3, e).unwrap();
        let lanes = LaneShading::new(material, &[], GradientToWorld::Affine(DMat3::IDENTITY)).unwrap();
        let mut out = Vec::new();
        for chunk in xs.chunks(S::LANES) {
            let (mut x, mut y) = ([0.0f32; 16], [0.0f32; 16]);
            x[..chunk.len()].copy_from_slice(chunk);
            s.store(&mut y, lanes.power(s, s.load(&x)));
            out.extend_from_slice(&y[..chunk.len()]);
        }
        out
    }

    /// The lanes' specular power holds `powf` on every path this processor has: by repeated
    /// squaring for whole shininesses (0 and 1 among them), through `pow` otherwise (for
    /// normal x and 0). For a whole shininess the result is 0 or a normal f32 (no product on
    /// the way is subnormal), and 0 only where `powf` gives under twice the smallest normal.
    #[test]
    fn lane_powers_hold_powf_and_never_go_subnormal() {
        #[cfg(target_arch = "aarch64")]
        use super::super::simd::neon::Neon;
        use super::super::simd::scalar::Scalar;
        use super::super::simd::SimdPath;
        #[cfg(target_arch = "x86_64")]
        use super::super::simd::{avx2::Avx2, avx512::Avx512};
        let mut xs: Vec<f32> = vec![0.0, 1e-45, 1e-40, f32::MIN_POSITIVE, 1e-30, 1e-12, 1e-6, 1e-3, 0.05, 0.2];
        xs.extend((0..=1000).map(|i| i as f32 / 1000.0));
        xs.extend([1.0 - f32::EPSILON, 1.0, 1.0 + f32::EPSILON]);
        for e in [0.0, 1.0, 2.0, 3.0, 7.0, 10.0, 12.0, 24.0, 40.0, 63.0, 64.0, 0.5, 7.3] {
            let mut xs = xs.clone();
            if let Some((_, floor)) = whole_power(e) {
                xs.extend([floor.next_down(), floor, floor.next_up()]);
            }
            for path in SimdPath::available() {
                let got = match path {
                    #[cfg(target_arch = "x86_64")]
                    SimdPath::Avx512 => powers(Avx512::detect().unwrap(), e, &xs),
                    #[cfg(target_arch = "x86_64")]
                    SimdPath::Avx2 => powers(Avx2::detect().unwrap(), e, &xs),
                    #[cfg(target_arch = "aarch64")]
                    SimdPath::Neon => powers(Neon::detect().unwrap(), e, &xs),
                    SimdPath::Scalar => powers(Scalar, e, &xs),
                    #[allow(unreachable_patterns)]
                    other => unreachable!("{other} is not available on this architecture"),
                };
                for (&x, &y) in xs.iter().zip(&got) {
                    if whole_power(e).is_none() && x != 0.0 && !x.is_normal() {
                        continue; // `pow` takes a subnormal x as 0, as it documents
                    }
                    let want = f64::from(x).powf(e);
                    let error = (f64::from(y) - want).abs();
                    assert!(error <= 8e-6 * want || error <= 4e-38, "{path}: {x:e}^{e}: {y:e} against {want:e}");
                    if whole_power(e).is_some() {
                        assert!(y == 0.0 || y.is_normal(), "{path}: {x:e}^{e} = {y:e} is subnormal");
                        assert!(y != 0.0 || want < 2.0 * f64::from(f32::MIN_POSITIVE), "{path}: {x:e}^{e} = 0");
                    }
                }
            }
        }
        assert_eq!(whole_power(12.0).map(|(n, _)| n), Some(12));
        assert_eq!(whole_power(64.5), None);
        assert_eq!(whole_power(65.0), None);
    }

    #[test]
    fn blinn_phong_is_as_the_spec_writes_it() {
        // A field rising along −z in VC (so N = +z), lit from +x+z: N·L = cos 45°.
        let volume = field_volume([5, 5, 5], |_, _, k| -2.0 * k);
        let voxels = F32LeVoxels::of(volume.channel(ChannelName::Voxel).unwrap().reader()).unwrap();
        let material = Shading::new(0.1, 0.6, 0.3, 8.0).unwrap();
        let towards = DVec3::new(1.0, 0.0, 1.0).normalize();
        let direction = crate::scene::UnitVector::new(-towards).unwrap();
        let lights = [
            Light::new(LightSource::Directional { direction }, [1.0, 0.5, 0.25], 2.0).unwrap(),
            // Behind the surface: N·L < 0, no diffuse and no specular.
            Light::new(LightSource::Point { position: DVec3::new(2.0, 2.0, -50.0) }, [1.0; 3], 1.0).unwrap(),
        ];
        let shaded = Shaded::new(Read(voxels), material, &lights, GradientToWorld::Affine(DMat3::IDENTITY));
        let interp = Linear::new(Dims::new([5, 5, 5]).unwrap(), Identity);
        let view = DVec3::Z;
        let c = [0.5, 0.4, 0.2];
        let got = shaded.shade(&interp, [2.0, 2.0, 2.0], DVec3::new(2.0, 2.0, 2.0), view, c);
        let e = [2.0, 1.0, 0.5];
        let n_dot_l = std::f64::consts::FRAC_1_SQRT_2;
        let h = (towards + view).normalize();
        let spec = 0.3 * h.z.powf(8.0);
        for i in 0..3 {
            let want = c[i] * (0.1 + 0.6 * n_dot_l * e[i]) + spec * e[i];
            assert!((got[i] - want).abs() < 1e-12, "channel {i}: {} vs {want}", got[i]);
        }
        // Seen from behind, the normal turns to face the viewer: lit by the point light only.
        let back = shaded.shade(&interp, [2.0, 2.0, 2.0], DVec3::new(2.0, 2.0, 2.0), -view, c);
        let to_light = (DVec3::new(2.0, 2.0, -50.0) - DVec3::new(2.0, 2.0, 2.0)).normalize();
        let n_dot_l = -to_light.z;
        let want = c[0] * (0.1 + 0.6 * n_dot_l) + 0.3 * (-(to_light - view).normalize().z).powf(8.0);
        assert!((back[0] - want).abs() < 1e-12, "{} vs {want}", back[0]);
        // A flat field has no normal: the sample keeps its colour.
        let flat = field_volume([5, 5, 5], |_, _, _| 3.0);
        let voxels = F32LeVoxels::of(flat.channel(ChannelName::Voxel).unwrap().reader()).unwrap();
        let shaded = Shaded::new(Read(voxels), material, &lights, GradientToWorld::Affine(DMat3::IDENTITY));
        assert_eq!(shaded.shade(&interp, [2.0, 2.0, 2.0], DVec3::ZERO, view, c), c);
    }
}
