//! The work units of Algorithm 2, shaped for the wire: what the intersection phase hands
//! to the volume-rendering phase, and what comes back (paper §3.3, lines 10–18).
//!
//! A [`PieceTask`] is one object over one piece of one ray: 24 bytes. It does not carry
//! the ray — whoever casts it recomputes the ray from the camera and the pixel index
//! (SPEC §4.1 is deterministic), and looks the object up in the scene it already holds.
//! A [`PieceRgba`] is what casting it yields: 16 bytes of premultiplied colour and opacity.
//! Tasks are independent of each other, so any slice of them whose objects share one
//! dataset is a batch that can be cast anywhere that dataset is resident
//! ([`BatchCaster`]); results come back in the same order, so a batch needs no ids. Their
//! compact, lossless wire forms are in [`super::wire`].
//!
//! # Why f32 results are enough
//! A piece's colour and opacity lie in [0, 1]; rounding them to f32 changes each by at most
//! 2⁻²⁴ relative. Compositing a ray's pieces multiplies and adds such values, so a pixel
//! moves by at most about (pieces on the ray) × 6·10⁻⁸ — some 10⁻⁶ for a ray through a
//! dozen pieces, four orders of magnitude below one 8-bit level (1/255 ≈ 3.9·10⁻³) and at
//! the precision of the PFM output itself (f32). `tests/tests/algorithms.rs` checks it.
//!
//! # Why the front opacity is 16 bits
//! A task also carries an opacity in front of the piece, so the cast can stop early inside
//! the piece (SPEC §4.5). The scheduler computes it by a rule every schedule agrees on (see
//! [`super::schedule`]); it is only ever a *lower bound* on the ray's true front, and a lower
//! bound may be rounded down freely: the cast then takes at most a sample more, never
//! fewer. So it is stored as a 16-bit fraction rounded down, which keeps the task at 24
//! bytes.

use std::sync::Arc;

use super::error::CastError;
use super::store::Pinned;
use crate::composite::Rgba;
use crate::dataset::Volume;
use crate::sampling::{CastOptions, ObjectCaster, PieceRequest, PieceResult};
use crate::scene::Scene;

/// One object over one piece of one ray: the unit of volume-rendering work (24 bytes).
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C)]
pub struct PieceTask {
    /// Start of the piece (world distance from the eye along the ray).
    pub t0: f64,
    /// End of the piece, > `t0`.
    pub t1: f64,
    /// Pixel index, `row · width + col`: the caster recomputes the ray from the camera.
    pub ray: u32,
    /// Index of the object in the scene (scenes hold at most 4096).
    pub object: u16,
    /// Lower bound on the ray's opacity in front of the piece as a fraction of
    /// [`PieceTask::ALPHA_ONE`], rounded down; or [`PieceTask::WHOLE`].
    pub front: u16,
}

/// What one object contributed over one piece: premultiplied colour and opacity (16 bytes).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C)]
pub struct PieceRgba {
    /// Σ c·α·(1 − A) over the piece's samples.
    pub colour: [f32; 3],
    /// Accumulated opacity A.
    pub alpha: f32,
}

/// Bytes of one task in memory (on the wire, see [`super::wire`]).
pub const TASK_BYTES: usize = std::mem::size_of::<PieceTask>();
/// Bytes of one result in memory (on the wire, see [`super::wire`]).
pub const RESULT_BYTES: usize = std::mem::size_of::<PieceRgba>();

impl PieceTask {
    /// `front` value of a piece shared by several objects: it must be cast whole, since
    /// co-located media are combined only after every object has been cast (SPEC §4.5).
    pub const WHOLE: u16 = u16::MAX;
    /// `front` value that stands for opacity 1.
    pub const ALPHA_ONE: u16 = u16::MAX - 1;

    /// A task with nothing known in front (opacity 0); `shared` marks a piece covered by
    /// several objects.
    pub fn new(ray: u32, object: u16, t0: f64, t1: f64, shared: bool) -> PieceTask {
        PieceTask { t0, t1, ray, object, front: if shared { PieceTask::WHOLE } else { 0 } }
    }

    /// Whether the piece must be cast whole (it is shared by several objects).
    pub fn is_whole(&self) -> bool {
        self.front == PieceTask::WHOLE
    }

    /// Records `alpha`, a lower bound on the ray's opacity in front of the piece, rounded
    /// down to 16 bits. Ignored for a shared piece, which is cast whole anyway.
    pub fn set_front_alpha(&mut self, alpha: f64) {
        if !self.is_whole() {
            let steps = (alpha.clamp(0.0, 1.0) * PieceTask::ALPHA_ONE as f64).floor();
            self.front = (steps as u16).min(PieceTask::ALPHA_ONE);
        }
    }

    /// The lower bound on the opacity in front (0 for a shared piece).
    pub fn front_alpha(&self) -> f64 {
        if self.is_whole() {
            0.0
        } else {
            self.front as f64 / PieceTask::ALPHA_ONE as f64
        }
    }

    /// The `stop_at` argument of `ObjectCaster::cast`: the scene's termination, or ∞ for a
    /// shared piece.
    pub fn stop_at(&self, termination: f64) -> f64 {
        if self.is_whole() {
            f64::INFINITY
        } else {
            termination
        }
    }
}

impl From<Rgba> for PieceRgba {
    fn from(c: Rgba) -> PieceRgba {
        PieceRgba { colour: c.colour.map(|v| v as f32), alpha: c.alpha as f32 }
    }
}

impl From<PieceRgba> for Rgba {
    fn from(c: PieceRgba) -> Rgba {
        Rgba { colour: c.colour.map(f64::from), alpha: f64::from(c.alpha) }
    }
}

/// The voxels a [`BatchCaster`] binds to: a dataset's [`Volume`] and, when it is pinned in
/// a [`super::VolumeStore`], the store, which keeps the macrocell classifications binding
/// works out with the resident dataset, so that the next bind over the same load and the
/// same opacity map finds them instead of classifying again (`render::store`). Made from a
/// `&Pinned`, a `&Volume` or an `&Arc<Volume>` (nothing kept: every bind classifies).
#[derive(Clone, Copy)]
pub struct BindTarget<'a> {
    volume: &'a Volume,
    store: Option<&'a Pinned>,
}

impl<'a> BindTarget<'a> {
    /// `object` bound opacity-only for shadow rays (`render::shadow`).
    pub(crate) fn opacity_only(
        self,
        object: &'a crate::scene::Object,
        opacity_correction: bool,
    ) -> Result<ObjectCaster<'a>, crate::sampling::BindError> {
        let cache = self.store.map(|p| p as &dyn crate::sampling::ClassificationCache);
        ObjectCaster::opacity_only(object, self.volume, opacity_correction, cache)
    }
}

impl<'a> From<&'a Volume> for BindTarget<'a> {
    fn from(volume: &'a Volume) -> BindTarget<'a> {
        BindTarget { volume, store: None }
    }
}

impl<'a> From<&'a Arc<Volume>> for BindTarget<'a> {
    fn from(volume: &'a Arc<Volume>) -> BindTarget<'a> {
        BindTarget { volume, store: None }
    }
}

impl<'a> From<&'a Pinned> for BindTarget<'a> {
    fn from(pinned: &'a Pinned) -> BindTarget<'a> {
        BindTarget { volume: pinned, store: Some(pinned) }
    }
}

/// Casts batches of tasks for one dataset while its volume is resident: the worker side of
/// Algorithm 2's volume-rendering phase, in every mode (local threads or farm workers).
///
/// Every object of the dataset is bound to the volume once, here, so whatever a caster
/// precomputes per object is paid once per dataset turn, not once per batch; `cast` is then
/// called from many threads at once. Tasks may come from the network, so `cast` checks each
/// one before using it and refuses a bad batch with a [`CastError`] instead of panicking.
pub struct BatchCaster<'a> {
    scene: &'a Scene,
    dataset: usize,
    /// Per object of the scene: its caster and the longest piece it can have (world
    /// units), or `None` for objects of other datasets.
    objects: Vec<Option<(ObjectCaster<'a>, f64)>>,
}

thread_local! {
    /// A batch's piece requests and their results, kept from batch to batch on each
    /// thread: for a farm batch of 4096 tasks they are some 320 and 200 KB, sizes the
    /// allocator may map and unmap for each batch (see `sampling::kernel`'s list of lines).
    static SCRATCH: std::cell::RefCell<(Vec<PieceRequest>, Vec<PieceResult>)> =
        const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
}

impl<'a> BatchCaster<'a> {
    /// Binds every object of `dataset` to `volume`, that dataset's voxels. Cells are
    /// classified when a ray first enters them ([`ObjectCaster::new`]), unless the volume
    /// is pinned in a store that keeps the object's classification or has room to: then it
    /// is used, or worked out now and kept, as [`BatchCaster::for_dataset_turn`] does (a
    /// farm worker binds per queue of batches, so a kept classification serves every
    /// queue and job while the dataset stays resident).
    pub fn new(
        scene: &'a Scene,
        dataset: usize,
        volume: impl Into<BindTarget<'a>>,
    ) -> Result<BatchCaster<'a>, CastError> {
        BatchCaster::bind(scene, dataset, volume.into(), CastOptions::default())
    }

    /// [`BatchCaster::new`] for a dataset's whole turn (Algorithm 2 binds once per
    /// dataset): every macrocell is classified for each object now
    /// ([`ObjectCaster::for_many_pieces`]), which pays back over many batches, not over one,
    /// or taken from the store that keeps the volume, where an earlier bind left it.
    pub fn for_dataset_turn(
        scene: &'a Scene,
        dataset: usize,
        volume: impl Into<BindTarget<'a>>,
    ) -> Result<BatchCaster<'a>, CastError> {
        let options = CastOptions { classify_upfront: true, ..CastOptions::default() };
        BatchCaster::bind(scene, dataset, volume.into(), options)
    }

    fn bind(
        scene: &'a Scene,
        dataset: usize,
        target: BindTarget<'a>,
        options: CastOptions,
    ) -> Result<BatchCaster<'a>, CastError> {
        if dataset >= scene.datasets().len() {
            return Err(CastError::DatasetOutOfRange { dataset, datasets: scene.datasets().len() });
        }
        let correction = scene.render().opacity_correction;
        let objects = scene
            .objects()
            .iter()
            .map(|object| {
                if object.dataset() != dataset {
                    return Ok(None);
                }
                let caster = match target.store {
                    Some(store) => ObjectCaster::with_cache(object, target.volume, correction, options, store),
                    None => ObjectCaster::with_options(object, target.volume, correction, options),
                };
                let caster = caster.map_err(|source| CastError::Bind { object: object.name().to_string(), source })?;
                Ok(Some((caster, longest_piece(object))))
            })
            .collect::<Result<_, CastError>>()?;
        Ok(BatchCaster { scene, dataset, objects })
    }

    /// The number of objects in the scene (the length of the counts
    /// [`BatchCaster::cast_counting`] adds to).
    pub fn object_count(&self) -> usize {
        self.objects.len()
    }

    /// The dataset these casters are bound to.
    pub fn dataset(&self) -> usize {
        self.dataset
    }

    /// Casts `tasks`, writing one result per task into `out`; returns the samples
    /// evaluated. The ray of each task is recomputed from the scene's camera, exactly as
    /// Algorithm 1 computes it. Refuses the whole batch, before casting anything, if one
    /// task is not a piece of an object of this dataset.
    pub fn cast(&self, tasks: &[PieceTask], out: &mut [PieceRgba]) -> Result<u64, CastError> {
        self.cast_counting(tasks, out, &mut [])
    }

    /// [`BatchCaster::cast`], adding the samples shaded for object i (SPEC §6) to
    /// `shaded[i]` where `shaded` has that entry (pass `&mut []` to count none).
    pub fn cast_counting(
        &self,
        tasks: &[PieceTask],
        out: &mut [PieceRgba],
        shaded: &mut [u64],
    ) -> Result<u64, CastError> {
        if tasks.len() != out.len() {
            return Err(CastError::LengthMismatch { tasks: tasks.len(), results: out.len() });
        }
        for (i, task) in tasks.iter().enumerate() {
            self.check(i, task)?;
        }
        let scene = self.scene;
        let (w, h) = (scene.image().width, scene.image().height);
        let termination = scene.render().termination;
        let mut samples = 0;
        SCRATCH.with_borrow_mut(|(pieces, results)| {
            // Runs of consecutive tasks of one object are cast together (several at a time).
            let mut start = 0;
            for tasks in tasks.chunk_by(|a, b| a.object == b.object) {
                let out = &mut out[start..start + tasks.len()];
                start += tasks.len();
                let Some((caster, _)) = &self.objects[tasks[0].object as usize] else {
                    unreachable!("checked above: the object belongs to this dataset")
                };
                pieces.clear();
                pieces.extend(tasks.iter().map(|task| PieceRequest {
                    ray: scene.camera().ray(task.ray % w, task.ray / w, w, h),
                    t0: task.t0,
                    t1: task.t1,
                    alpha_in: task.front_alpha(),
                    stop_at: task.stop_at(termination),
                }));
                results.clear();
                results.resize(pieces.len(), PieceResult::default());
                caster.cast_many(pieces, results);
                let mut object_shaded = 0;
                for (r, out) in results.iter().zip(out) {
                    samples += r.samples;
                    object_shaded += r.shaded;
                    *out = r.rgba.into();
                }
                if let Some(count) = shaded.get_mut(tasks[0].object as usize) {
                    *count += object_shaded;
                }
            }
        });
        Ok(samples)
    }

    /// Refuses a task that names another dataset's object, a pixel outside the image, or an
    /// interval that is not a piece of its object's box (which could otherwise ask for an
    /// unbounded number of samples).
    fn check(&self, i: usize, task: &PieceTask) -> Result<(), CastError> {
        let objects = &self.scene.objects();
        let object = task.object;
        let Some(entry) = self.objects.get(object as usize) else {
            return Err(CastError::ObjectOutOfRange { task: i, object, objects: objects.len() });
        };
        let Some((_, longest)) = entry else {
            let uses = objects[object as usize].dataset();
            return Err(CastError::WrongDataset { task: i, object, uses, batch: self.dataset });
        };
        let pixels = self.scene.image().width as u64 * self.scene.image().height as u64;
        if task.ray as u64 >= pixels {
            return Err(CastError::RayOutOfRange { task: i, ray: task.ray, pixels });
        }
        let (t0, t1) = (task.t0, task.t1);
        let reason = if !(t0.is_finite() && t1.is_finite()) {
            Some("not finite")
        } else if t0 < 0.0 || t1 < t0 {
            Some("expected 0 ≤ t0 ≤ t1")
        } else if t1 - t0 > *longest {
            Some("longer than the object's box")
        } else {
            None
        };
        match reason {
            Some(reason) => Err(CastError::BadPiece { task: i, object, t0, t1, reason }),
            None => Ok(()),
        }
    }
}

/// The longest piece an object's box can hold: its bounding box's diagonal, with room for
/// rounding in the intersection that computed the piece.
fn longest_piece(object: &crate::scene::Object) -> f64 {
    let c = object.placement().corners();
    let (lo, hi) = c.iter().fold((c[0], c[0]), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
    (hi - lo).length() * (1.0 + 1e-9) + 1e-12
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use proptest::prelude::*;

    use super::*;
    use crate::dataset::{Channel, ChannelName, Dims};

    /// Two datasets: "v" (3×4×5, voxel channel) with two objects, "rgba" (2×2×1: red,
    /// green, blue, alpha) with one raw object.
    fn scene() -> Scene {
        let text = "[image]\nwidth = 6\nheight = 5\nbackground = [0, 0, 0]\n\
            [camera]\neye = [0.5, 0.5, 4.0]\ntarget = [0.5, 0.5, 0.0]\nup = [0, 1, 0]\nfov_y = 30.0\n\
            [[datasets]]\nname = \"v\"\ndims = [3, 4, 5]\n[datasets.channels.voxel]\n\
            generator = { kind = \"ramp\", axis = \"x\", from = 0.0, to = 1.0 }\n\
            [[datasets]]\nname = \"rgba\"\ndims = [2, 2, 1]\n\
            [datasets.channels.red]\ngenerator = { kind = \"constant\", value = 200, type = \"u8\" }\n\
            [datasets.channels.green]\ngenerator = { kind = \"constant\", value = 100, type = \"u8\" }\n\
            [datasets.channels.blue]\ngenerator = { kind = \"constant\", value = 50, type = \"u8\" }\n\
            [datasets.channels.alpha]\ngenerator = { kind = \"constant\", value = 128, type = \"u8\" }\n\
            [[objects]]\nname = \"a\"\ndataset = \"v\"\ninterpolation = \"cubic\"\n\
            colour = { type = \"ramp\", points = [[0, 1, 0, 0], [1, 0, 0, 1]] }\n\
            opacity = { type = \"ramp\", points = [[0, 0.1], [1, 0.9]] }\n\
            [[objects]]\nname = \"b\"\ndataset = \"rgba\"\ncolour = { type = \"raw\" }\nopacity = { type = \"raw\" }\n\
            [[objects]]\nname = \"c\"\ndataset = \"v\"\ninterpolation = \"nearest\"\n\
            colour = { type = \"lut\", bounds = [0.5], colours = [[0, 1, 0], [1, 1, 1]] }\n\
            opacity = { type = \"constant\", coefficients = [0.3] }\n";
        Scene::parse(text, "batch.toml").unwrap()
    }

    /// A volume of `dims` holding the channels whose flags are set (voxel as f32, the
    /// colour channels as u8), filled with `fill`.
    fn volume(dims: [u64; 3], voxel: bool, rgba: bool, fill: f32) -> Volume {
        let dims = Dims::new(dims).unwrap();
        let n = dims.voxel_count() as usize;
        let mut channels = BTreeMap::new();
        if voxel {
            channels.insert(ChannelName::Voxel, Channel::from_f32(&vec![fill; n], dims).unwrap());
        }
        if rgba {
            for c in [ChannelName::Red, ChannelName::Green, ChannelName::Blue, ChannelName::Alpha] {
                channels.insert(c, Channel::from_u8(vec![fill as u8; n], dims).unwrap());
            }
        }
        Volume::new(dims, channels)
    }

    #[test]
    fn a_batch_of_another_datasets_tasks_is_refused_before_anything_is_cast() {
        let s = scene();
        let v = volume([3, 4, 5], true, false, 0.5);
        let caster = BatchCaster::new(&s, 0, &v).unwrap();
        let ok = PieceTask::new(3, 0, 3.5, 3.6, false);
        let mut out = [PieceRgba::default(); 2];
        assert_eq!(
            caster.cast(&[ok, PieceTask::new(3, 1, 3.5, 3.6, false)], &mut out),
            Err(CastError::WrongDataset { task: 1, object: 1, uses: 1, batch: 0 })
        );
        assert_eq!(out, [PieceRgba::default(); 2], "nothing cast");
        let far = PieceTask::new(3, 0, 0.0, 1e300, false);
        assert!(matches!(caster.cast(&[far], &mut out[..1]), Err(CastError::BadPiece { task: 0, .. })));
        assert!(matches!(caster.cast(&[ok], &mut out), Err(CastError::LengthMismatch { tasks: 1, results: 2 })));
        assert!(matches!(
            caster.cast(&[PieceTask::new(30, 0, 3.5, 3.6, false)], &mut out[..1]),
            Err(CastError::RayOutOfRange { ray: 30, pixels: 30, .. })
        ));
        assert!(matches!(
            caster.cast(&[PieceTask::new(3, 7, 3.5, 3.6, false)], &mut out[..1]),
            Err(CastError::ObjectOutOfRange { object: 7, objects: 3, .. })
        ));
        assert_eq!(caster.cast(&[ok], &mut out[..1]).map(|n| n > 0), Ok(true));
        // The wrong volume for a dataset is refused when binding.
        assert!(matches!(BatchCaster::new(&s, 1, &v), Err(CastError::Bind { .. })));
        assert!(matches!(BatchCaster::new(&s, 2, &v), Err(CastError::DatasetOutOfRange { dataset: 2, datasets: 2 })));
    }

    fn any_t() -> impl Strategy<Value = f64> {
        prop_oneof![
            Just(f64::NAN),
            Just(f64::INFINITY),
            Just(f64::NEG_INFINITY),
            Just(-1.0),
            Just(0.0),
            Just(1e300),
            0.0..10.0f64,
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]

        /// Whatever arrives from the network and whatever volume is resident, casting
        /// refuses or answers with plausible results; it never panics.
        #[test]
        fn random_tasks_and_volumes_never_panic(
            dataset in 0usize..3,
            dims in (1u64..6, 1u64..6, 1u64..6),
            voxel in any::<bool>(),
            rgba in any::<bool>(),
            fill in prop_oneof![Just(f32::NAN), Just(f32::INFINITY), -1e30f32..1e30],
            tasks in proptest::collection::vec((0u32..40, 0u16..5, any_t(), any_t(), any::<u16>()), 0..20),
        ) {
            let s = scene();
            let v = volume([dims.0, dims.1, dims.2], voxel, rgba, fill);
            let Ok(caster) = BatchCaster::new(&s, dataset, &v) else { return Ok(()) };
            let tasks: Vec<PieceTask> = tasks
                .into_iter()
                .map(|(ray, object, t0, t1, front)| PieceTask { t0, t1, ray, object, front })
                .collect();
            let mut out = vec![PieceRgba::default(); tasks.len()];
            if caster.cast(&tasks, &mut out).is_ok() {
                for r in &out {
                    prop_assert!((0.0..=1.0).contains(&r.alpha), "{r:?}");
                    prop_assert!(r.colour.iter().all(|c| c.is_finite()), "{r:?}");
                }
            }
        }
    }

    #[test]
    fn a_task_is_24_bytes_and_a_result_16() {
        assert_eq!(TASK_BYTES, 24);
        assert_eq!(RESULT_BYTES, 16);
    }

    #[test]
    fn front_alpha_is_a_lower_bound_within_one_step() {
        for a in [0.0, 1e-9, 0.25, 0.5, 0.998_999, 0.999, 1.0 - 1e-12, 1.0] {
            let mut t = PieceTask::new(0, 0, 0.0, 1.0, false);
            t.set_front_alpha(a);
            let back = t.front_alpha();
            assert!(back <= a && a - back <= 1.0 / PieceTask::ALPHA_ONE as f64, "{a} → {back}");
            assert!(!t.is_whole());
            assert_eq!(t.stop_at(0.99), 0.99);
        }
    }

    #[test]
    fn shared_pieces_are_cast_whole_whatever_is_in_front() {
        let mut t = PieceTask::new(0, 0, 0.0, 1.0, true);
        t.set_front_alpha(0.9);
        assert!(t.is_whole());
        assert_eq!(t.front_alpha(), 0.0);
        assert_eq!(t.stop_at(0.99), f64::INFINITY);
    }

    #[test]
    fn results_round_to_f32_within_half_an_ulp() {
        let c = Rgba { colour: [0.1, 0.2, 0.3], alpha: 0.123_456_789 };
        let back = Rgba::from(PieceRgba::from(c));
        for i in 0..3 {
            assert!((back.colour[i] - c.colour[i]).abs() <= c.colour[i] * 6e-8);
        }
        assert!((back.alpha - c.alpha).abs() <= c.alpha * 6e-8);
    }
}
