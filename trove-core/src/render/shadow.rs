//! Shadows (SPEC §6), grouped by dataset so that Algorithm 2 and the farm keep loading each
//! dataset once per pass.
//!
//! S, the transmittance from a sample towards a light, is a product over objects of
//! (1 − A), each object's A along the shadow ray depending on that object alone. The
//! product splits in two:
//! * the **lit object's own factor**, cast exactly along each sample's shadow ray through
//!   the object's own volume while its pieces are cast (`sampling::shade`'s `Shadows`):
//!   that is what tells a surface facing the light from one facing away, at the scale of
//!   the surface, where any lattice would blur it;
//! * the **other objects' factors**, on a lattice over the lit object's box ([`ShadowPlan`]):
//!   for each (shadowing light, lit object) a lattice with [`POINTS_PER_VOXEL`] points per
//!   voxel of the finest other object along each side, and for each other object the
//!   factor (1 − A) along the shadow ray from every lattice point, cast while that object's
//!   dataset is resident ([`ShadowPlan::factors`]). A sample takes the trilinear blend of
//!   the lattice ([`crate::scene::Transmittance`]). A second round computes the points of
//!   the cells where the first round's lattice bends, three times finer
//!   ([`ShadowPlan::refinement`], `scene::transmittance`): a shadow edge is where blending
//!   fails.
//!
//! So the shadow pass is one more visit of each dataset per round, before the image's own
//! pass: locally ([`attach`]) each dataset is loaded once a round, and on a farm each worker
//! computes the factors of the objects of the datasets it holds, and the coordinator
//! multiplies them ([`ShadowPlan::combine`], in object order, so that every mode gets the
//! same f32 values) and hands the lattices to the workers with the scene. Its cost and its
//! error against SPEC §6's definition are in `docs/shadows.md`.

use std::borrow::Cow;
use std::sync::Arc;
use std::time::Instant;

use glam::DVec3;
use rayon::prelude::*;

use super::error::CastError;
use super::workunit::BindTarget;
use super::{RenderError, VolumeStore};
use crate::geometry::{Placement, Ray};
use crate::sampling::{self, ObjectCaster, PieceRequest, PieceResult, SHADOW_STOP};
use crate::scene::transmittance::{fine_point, Refinement};
use crate::scene::{Scene, Transmittance};

/// Lattice points per voxel of the finest other object, along each side of a lit object's
/// box (docs/shadows.md measures what finer lattices change).
pub const POINTS_PER_VOXEL: f64 = 1.0;

/// The most points in one lattice (16 MiB of f32).
pub const MAX_POINTS: u64 = 1 << 22;

/// The world lengths of a box's three sides (the longest of the four parallel edges).
fn edges(p: &Placement) -> [f64; 3] {
    let c = p.corners();
    // Corner index x + 2y + 4z: the edges along axis a join i and i + 2^a.
    std::array::from_fn(|a| {
        let step = 1 << a;
        (0..8).filter(|i| i & step == 0).map(|i| (c[i + step] - c[i]).length()).fold(0.0, f64::max)
    })
}

/// The world size of an object's smallest voxel side (its box's shortest side over its
/// voxels along that side).
fn finest_voxel(p: &Placement) -> f64 {
    let dims = p.dims().as_array();
    let c = p.corners();
    (0..3)
        .flat_map(|a| {
            let step = 1 << a;
            (0..8).filter(move |i| i & step == 0).map(move |i| (c[i + step] - c[i]).length() / f64::from(dims[a]))
        })
        .fold(f64::INFINITY, f64::min)
}

/// Shadow rays cast at a time by [`ShadowPlan::factors`].
const CHUNK: usize = 4096;

/// One lattice to compute: the transmittance towards `light` over `receiver`'s box, at its
/// own points or, in a refinement pass ([`ShadowPlan::refinement`]), at the fine points of
/// its refined cells.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Lattice {
    /// Index of the light in the scene.
    pub light: usize,
    /// Index of the lit object.
    pub receiver: usize,
    /// Points per side.
    pub dims: [u32; 3],
    /// In a refinement pass, the refinement of the lattice's coarse values
    /// (`Transmittance::refinement`), whose fine points are the points to compute.
    pub refinement: Option<Arc<Refinement>>,
}

impl Lattice {
    /// Points to compute.
    pub fn len(&self) -> usize {
        match &self.refinement {
            None => self.dims.iter().map(|&n| n as usize).product(),
            Some(r) => r.points().len(),
        }
    }

    /// Whether it has no points to compute (a refinement of a lattice with no refined cell).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Box coordinates of point `n` (x fastest).
    fn box_point(&self, n: usize) -> DVec3 {
        if let Some(r) = &self.refinement {
            return fine_point(self.dims, r.points()[n]);
        }
        let [nx, ny, nz] = self.dims.map(|d| d as usize);
        let (i, j, k) = (n % nx, (n / nx) % ny, n / (nx * ny));
        DVec3::new(i as f64 / (nx - 1) as f64, j as f64 / (ny - 1) as f64, k as f64 / (nz - 1) as f64)
    }
}

/// What one object contributes to one lattice: (1 − A) at each of its points.
#[derive(Clone, Debug, PartialEq)]
pub struct Factors {
    /// Index into [`ShadowPlan::lattices`].
    pub lattice: usize,
    /// The object whose opacity they are.
    pub occluder: usize,
    /// One per lattice point, each in [0, 1].
    pub values: Vec<f32>,
}

/// Every lattice a scene's shadows need: one per (light with shadows, shaded object lit by
/// it), in (object, light) order; and whether the lattices are refined where they bend, in
/// a second pass ([`ShadowPlan::refinement`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ShadowPlan {
    lattices: Vec<Lattice>,
    refine: bool,
}

impl ShadowPlan {
    /// The lattices of `scene` (none without shadows), [`POINTS_PER_VOXEL`] points per
    /// voxel of the finest other object along each side of a lit object's box, refined
    /// where they bend.
    pub fn of(scene: &Scene) -> ShadowPlan {
        ShadowPlan { refine: true, ..ShadowPlan::with_density(scene, POINTS_PER_VOXEL, MAX_POINTS) }
    }

    /// [`ShadowPlan::of`] with `per_voxel` lattice points per voxel of the finest other
    /// object (the shadows' sharpest detail is that object's voxel, seen from the lit one),
    /// at least two a side, at most [`Transmittance::MAX_SIDE`], and at most `max_points`
    /// in all (a lattice over that is coarsened evenly along every side); not refined (tests
    /// hold the plan against such uniform lattices).
    pub fn with_density(scene: &Scene, per_voxel: f64, max_points: u64) -> ShadowPlan {
        let objects = scene.objects();
        let voxel: Vec<f64> = objects.iter().map(|o| finest_voxel(o.placement())).collect();
        ShadowPlan::with_lattices(scene, |receiver| {
            let finest = (0..objects.len()).filter(|&o| o != receiver).map(|o| voxel[o]).fold(f64::INFINITY, f64::min);
            let edges = edges(objects[receiver].placement());
            let side = |edge: f64, scale: f64| {
                // Lengths carry rounding (a turned box's sides differ in their last bits),
                // so a ratio within 10⁻⁹ of a whole number is taken as that number: the
                // lattice of a turned scene is the same lattice, turned.
                let n = (edge * per_voxel * scale / finest * (1.0 - 1e-9)).ceil() + 1.0;
                if n.is_finite() {
                    n.clamp(2.0, f64::from(Transmittance::MAX_SIDE)) as u32
                } else {
                    2
                }
            };
            let dims = edges.map(|e| side(e, 1.0));
            let points: f64 = dims.iter().map(|&n| f64::from(n)).product();
            if points <= max_points as f64 {
                return dims;
            }
            let scale = (max_points as f64 / points).cbrt();
            edges.map(|e| side(e, scale))
        })
    }

    /// The plan with lit object `receiver`'s lattice `dims_of(receiver)` points a side (tests
    /// compare the plan's lattices with finer ones).
    pub(crate) fn with_lattices(scene: &Scene, dims_of: impl Fn(usize) -> [u32; 3]) -> ShadowPlan {
        let mut lattices = Vec::new();
        for (receiver, o) in scene.objects().iter().enumerate() {
            if !(o.needs_shadow_maps() && sampling::shades(o)) {
                continue;
            }
            let dims = dims_of(receiver);
            for (light, l) in scene.lights().iter().enumerate() {
                if l.shadows() {
                    lattices.push(Lattice { light, receiver, dims, refinement: None });
                }
            }
        }
        ShadowPlan { lattices, refine: false }
    }

    /// Whether a second pass refines the lattices where they bend.
    pub fn refines(&self) -> bool {
        self.refine
    }

    /// The second pass of a refining plan: the same lattices, in the same order, each with
    /// the fine points of its coarse values, read from `scene`'s attached maps (the first
    /// pass's, [`ShadowPlan::combine`]); a lattice that got no map (nothing shades it) or
    /// that bends nowhere has no points.
    pub fn refinement(&self, scene: &Scene) -> ShadowPlan {
        let lattices = self
            .lattices
            .iter()
            .map(|l| {
                let map = scene.objects()[l.receiver].shadow_maps().and_then(|m| m[l.light].as_ref());
                let refinement = map.map_or_else(Refinement::default, Transmittance::refinement);
                Lattice { refinement: Some(refinement.into()), ..l.clone() }
            })
            .collect();
        ShadowPlan { lattices, refine: false }
    }

    /// The lattices.
    pub fn lattices(&self) -> &[Lattice] {
        &self.lattices
    }

    /// Whether there is nothing to compute.
    pub fn is_empty(&self) -> bool {
        self.lattices.iter().all(Lattice::is_empty)
    }

    /// Whether object `o` shades some lattice with points (it is not the only receiver).
    pub fn has_work_for(&self, o: usize) -> bool {
        self.lattices.iter().any(|l| l.receiver != o && !l.is_empty())
    }

    /// The datasets, in order of first use, of which some object shades some lattice: the
    /// ones the shadow pass visits.
    pub fn datasets_with_work(&self, scene: &Scene) -> Vec<usize> {
        let objects = scene.objects();
        scene
            .used_datasets()
            .into_iter()
            .filter(|&d| (0..objects.len()).any(|o| objects[o].dataset() == d && self.has_work_for(o)))
            .collect()
    }

    /// Object `occluder`'s factors on every lattice but its own, cast by `caster` (the object
    /// bound opacity-only, [`opacity_caster`]); lattices it does not shade anywhere (every
    /// factor 1) are left out. Shadow rays are cast `CHUNK` at a time on rayon's threads.
    pub fn factors(&self, scene: &Scene, occluder: usize, caster: &ObjectCaster<'_>) -> Vec<Factors> {
        let object = &scene.objects()[occluder];
        let reach_of = Ball::around(object.placement());
        let mut out = Vec::new();
        for (index, lattice) in self.lattices.iter().enumerate() {
            if lattice.receiver == occluder || lattice.is_empty() {
                continue;
            }
            let light = scene.lights()[lattice.light];
            let receiver = scene.objects()[lattice.receiver].placement();
            let len = lattice.len();
            let values: Vec<f32> = (0..len.div_ceil(CHUNK))
                .into_par_iter()
                .flat_map_iter(|c| {
                    let chunk = c * CHUNK..((c + 1) * CHUNK).min(len);
                    let mut requests = Vec::with_capacity(chunk.len());
                    let mut slots = vec![None; chunk.len()];
                    for (slot, n) in chunk.enumerate() {
                        let x = receiver.world_of_box(lattice.box_point(n));
                        let Some((l, reach)) = light.towards(x) else { continue };
                        // Most shadow rays pass far from a given object: a ball around its
                        // box turns them away before the box itself is tested.
                        if reach_of.misses(x, l, reach) {
                            continue;
                        }
                        let ray = Ray { origin: x, dir: l };
                        if let Some((t0, t1)) = object.placement().segment(&ray) {
                            let t1 = t1.min(reach);
                            if t1 > t0 {
                                slots[slot] = Some(requests.len());
                                requests.push(PieceRequest { ray, t0, t1, alpha_in: 0.0, stop_at: SHADOW_STOP });
                            }
                        }
                    }
                    let mut results = vec![PieceResult::default(); requests.len()];
                    caster.cast_many(&requests, &mut results);
                    slots
                        .into_iter()
                        .map(|s| s.map_or(1.0, |r| (1.0 - results[r].rgba.alpha).clamp(0.0, 1.0) as f32))
                        .collect::<Vec<f32>>()
                })
                .collect();
            if values.iter().any(|&v| v < 1.0) {
                out.push(Factors { lattice: index, occluder, values });
            }
        }
        out
    }

    /// Per lattice, the product of its occluders' factors in object order (in f32, so that
    /// every mode that multiplies the same factors gets the same values); `None` where no
    /// occluder shades it.
    fn products(&self, mut factors: Vec<Factors>) -> Result<Vec<Option<Vec<f32>>>, ShadowError> {
        factors.sort_by_key(|f| (f.lattice, f.occluder));
        let mut factors = factors.into_iter().peekable();
        let mut products = Vec::with_capacity(self.lattices.len());
        for (index, lattice) in self.lattices.iter().enumerate() {
            let mut product: Option<Vec<f32>> = None;
            while let Some(f) = factors.next_if(|f| f.lattice <= index) {
                if f.lattice < index || f.values.len() != lattice.len() || f.occluder == lattice.receiver {
                    return Err(ShadowError::Factors { lattice: f.lattice, occluder: f.occluder });
                }
                match &mut product {
                    None => product = Some(f.values),
                    Some(p) => p.iter_mut().zip(&f.values).for_each(|(p, f)| *p *= f),
                }
            }
            products.push(product);
        }
        if let Some(f) = factors.next() {
            return Err(ShadowError::Factors { lattice: f.lattice, occluder: f.occluder });
        }
        Ok(products)
    }

    /// The lattices from every occluder's factors (`ShadowPlan::products`), as
    /// [`Scene::with_shadow_maps`] takes them: per object, per light; not refined yet.
    pub fn combine(
        &self,
        scene: &Scene,
        factors: Vec<Factors>,
    ) -> Result<Vec<Option<Vec<Option<Transmittance>>>>, ShadowError> {
        let mut maps: Vec<Option<Vec<Option<Transmittance>>>> =
            scene.objects().iter().map(|o| o.needs_shadow_maps().then(|| vec![None; scene.lights().len()])).collect();
        for ((index, lattice), product) in self.lattices.iter().enumerate().zip(self.products(factors)?) {
            if let Some(values) = product {
                let t = Transmittance::new(lattice.dims, values)
                    .map_err(|_| ShadowError::Factors { lattice: index, occluder: lattice.receiver })?;
                if let Some(m) = &mut maps[lattice.receiver] {
                    m[lattice.light] = Some(t);
                }
            }
        }
        Ok(maps)
    }

    /// `scene`'s maps (the first pass's, attached) with their refined cells, from the factors
    /// of this refinement pass ([`ShadowPlan::refinement`]) multiplied as
    /// [`ShadowPlan::combine`] multiplies; fine points no occluder shades are 1.
    pub fn refine(
        &self,
        scene: &Scene,
        factors: Vec<Factors>,
    ) -> Result<Vec<Option<Vec<Option<Transmittance>>>>, ShadowError> {
        let mut maps: Vec<Option<Vec<Option<Transmittance>>>> =
            scene.objects().iter().map(|o| o.shadow_maps().map(<[_]>::to_vec)).collect();
        for ((index, lattice), product) in self.lattices.iter().enumerate().zip(self.products(factors)?) {
            let bad = ShadowError::Factors { lattice: index, occluder: lattice.receiver };
            if lattice.is_empty() {
                if product.is_some() {
                    return Err(bad);
                }
                continue;
            }
            let slot = maps[lattice.receiver].as_mut().and_then(|m| m[lattice.light].as_mut()).ok_or(bad.clone())?;
            let refinement = lattice.refinement.as_deref().ok_or(bad.clone())?;
            let fine = product.unwrap_or_else(|| vec![1.0; lattice.len()]);
            *slot = slot.clone().with_fine(refinement, fine).map_err(|_| bad)?;
        }
        Ok(maps)
    }
}

/// A ball holding a box (it holds the box's corners, whose hull holds the box).
struct Ball {
    centre: DVec3,
    /// Its radius, widened so that rounding never turns away a ray that meets the box.
    radius: f64,
}

impl Ball {
    fn around(p: &Placement) -> Ball {
        let c = p.corners();
        let centre = c.iter().fold(DVec3::ZERO, |a, &x| a + x) / 8.0;
        let radius = c.iter().map(|&x| (x - centre).length()).fold(0.0, f64::max);
        Ball { centre, radius: radius * (1.0 + 1e-6) + 1e-9 * centre.abs().max_element() }
    }

    /// Whether the ray from `x` along unit `l`, for t in [0, `reach`], stays out of the ball
    /// (so out of the box: no segment, no factor).
    #[inline]
    fn misses(&self, x: DVec3, l: DVec3, reach: f64) -> bool {
        let w = self.centre - x;
        let t = w.dot(l);
        let r = self.radius;
        t < -r || t - r > reach || (w.length_squared() - t * t) > r * r
    }
}

/// Factors that do not fit the plan (a farm worker's answer for another scene).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ShadowError {
    /// Factors for a lattice that does not exist, of the wrong size, out of range, or of a
    /// lattice's own receiver.
    #[error("shadow factors of object {occluder} do not fit lattice {lattice} of the scene's plan")]
    Factors {
        /// The lattice named.
        lattice: usize,
        /// The object named.
        occluder: usize,
    },
}

/// `object` bound to `target` opacity-only, as the shadow pass casts it: unlit whatever its
/// lighting (its colour is not used), its classification kept with the volume when the
/// target is a store's.
pub fn opacity_caster<'a>(
    scene: &'a Scene,
    object: usize,
    target: impl Into<BindTarget<'a>>,
) -> Result<ObjectCaster<'a>, CastError> {
    let o = &scene.objects()[object];
    let target = target.into();
    target
        .opacity_only(o, scene.render().opacity_correction)
        .map_err(|source| CastError::Bind { object: o.name().to_string(), source })
}

/// The factors that the objects of dataset `d` contribute to `plan`'s lattices, the dataset
/// loaded from `store` only where one of them has some to give: the shadow pass's visit of
/// one dataset, locally ([`attach`]) and on a farm worker alike.
pub fn dataset_factors(
    scene: &Scene,
    plan: &ShadowPlan,
    d: usize,
    store: &VolumeStore,
) -> Result<Vec<Factors>, RenderError> {
    let objects: Vec<usize> =
        (0..scene.objects().len()).filter(|&o| scene.objects()[o].dataset() == d && plan.has_work_for(o)).collect();
    let mut factors = Vec::new();
    if objects.is_empty() {
        return Ok(factors);
    }
    let volume = store.get(&scene.datasets()[d])?;
    for o in objects {
        let caster = opacity_caster(scene, o, &volume)?;
        factors.extend(plan.factors(scene, o, &caster));
    }
    Ok(factors)
}

/// `scene` with its shadow maps computed and attached ([`Scene::with_shadow_maps`]), each
/// dataset loaded once from `store` for it; `scene` itself, not a copy, where it casts no
/// shadows or has its maps already (by the caller, or a farm's coordinator). Returns the
/// seconds spent.
pub fn attach<'a>(scene: &'a Scene, store: &VolumeStore) -> Result<(Cow<'a, Scene>, f64), RenderError> {
    if scene.objects().iter().all(|o| !o.needs_shadow_maps() || o.shadow_maps().is_some()) {
        return Ok((Cow::Borrowed(scene), 0.0));
    }
    attach_planned(scene, &ShadowPlan::of(scene), store)
}

/// [`attach`] with the lattices of `plan`.
pub(crate) fn attach_planned<'a>(
    scene: &'a Scene,
    plan: &ShadowPlan,
    store: &VolumeStore,
) -> Result<(Cow<'a, Scene>, f64), RenderError> {
    let started = Instant::now();
    if plan.is_empty() {
        return Ok((Cow::Borrowed(scene), 0.0));
    }
    let mut factors = Vec::new();
    for d in plan.datasets_with_work(scene) {
        factors.extend(dataset_factors(scene, plan, d, store)?);
    }
    let maps = plan.combine(scene, factors).expect("factors computed from this plan fit it");
    let mut attached = scene.with_shadow_maps(maps);
    if plan.refines() {
        let fine = plan.refinement(&attached);
        if !fine.is_empty() {
            let mut factors = Vec::new();
            for d in fine.datasets_with_work(&attached) {
                factors.extend(dataset_factors(&attached, &fine, d, store)?);
            }
            let maps = fine.refine(&attached, factors).expect("factors computed from this refinement fit it");
            attached = scene.with_shadow_maps(maps);
        }
    }
    Ok((Cow::Owned(attached), started.elapsed().as_secs_f64()))
}
