//! The scenes the simulation renders: `datasets` cubes scattered through a slab in front of
//! the camera, one object per dataset, sizes drawn so that a ray crosses `depth` cubes on
//! average. Positions and sizes come from a seeded generator, so a scene is the same on
//! every run; overlapping cubes split each other's segments into pieces, which is what
//! gives datasets several waves per band, as in real scenes.
//!
//! The datasets are generated (`marschner_lobb`), so a scene needs no files: the workload
//! is taken from its intersection alone (which never reads a voxel), and the calibration
//! casts real voxels of the same family at a small size. The opacity map is non-zero at
//! every value, so empty-space skipping never applies and every sample position the
//! intersection counts is a sample a worker casts.

use std::fmt::Write as _;

use anyhow::{Context, Result};
use trove_core::scene::Scene;
use trove_tests::Header;

/// A small, seeded generator (SplitMix64): the simulation must not depend on anything but
/// its seed, and it needs no more than uniform numbers.
#[derive(Clone, Debug)]
pub(crate) struct Rng(u64);

impl Rng {
    /// A generator started from `seed`.
    pub(crate) fn new(seed: u64) -> Rng {
        Rng(seed)
    }

    /// The next 64 random bits.
    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [lo, hi).
    pub(crate) fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// What a generated scene looks like.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct SceneSpec {
    /// Datasets, one object (a cube) each.
    pub datasets: usize,
    /// Mean number of cubes a ray through the view crosses.
    pub depth: f64,
    /// Voxels per axis of every dataset.
    pub dims: u32,
    /// Image width and height.
    pub width: u32,
    pub height: u32,
    /// Sampling distance in voxels (SPEC's `sampling_distance` is in world units; it is
    /// converted per object). 1 is SPEC's default step.
    pub step_voxels: f64,
    /// Seed of the layout.
    pub seed: u64,
}

/// Half the side of the square of the z = 0 plane that the camera sees.
const VIEW_HALF: f64 = 1.0;
/// The camera's distance from the z = 0 plane.
const EYE_Z: f64 = 8.0;

impl SceneSpec {
    /// The scene as TOML text, its datasets generated.
    pub(crate) fn toml(&self) -> String {
        self.text(false)
    }

    /// The scene as TOML text with every dataset read from `d{i}.raw` beside the scene file,
    /// `dims`³ u16 (as `crate::table1::write_dataset` writes CT-like heads): what a farm's
    /// real scenes hold, for timing the worker's caster. The maps span those values (0 to
    /// about 3000) as the generated scene's span its, and stay non-zero everywhere.
    pub(crate) fn toml_raw(&self) -> String {
        self.text(true)
    }

    fn text(&self, raw: bool) -> String {
        let fov = 2.0 * (VIEW_HALF / EYE_Z).atan().to_degrees();
        let header = Header::new(self.width, [0.0, 0.0, EYE_Z], [0.0, 0.0, 0.0], fov).size(self.width, self.height);
        let mut text = format!("{header}[render]\ntermination = 0.999\n\n");
        // Mean area of a cube's face: depth × the view's area / datasets, for sides drawn
        // uniformly in [0.6, 1.4] × the mean side (E[u²] = 1 + 0.8²/12).
        let mean_side = (self.depth * (2.0 * VIEW_HALF).powi(2) / self.datasets as f64 / (1.0 + 0.64 / 12.0)).sqrt();
        let mut rng = Rng::new(self.seed);
        let n = self.dims;
        for i in 0..self.datasets {
            let side = mean_side * rng.uniform(0.6, 1.4);
            let centre =
                [rng.uniform(-VIEW_HALF, VIEW_HALF), rng.uniform(-VIEW_HALF, VIEW_HALF), rng.uniform(-1.0, 1.0)];
            let [x, y, z] = centre.map(|c| c - side / 2.0);
            let step = self.step_voxels * side / n as f64;
            let (voxels, v) = if raw {
                (format!("raw = \"d{i}.raw\"\ntype = \"u16\""), 3333.0)
            } else {
                ("generator = { kind = \"marschner_lobb\" }".to_string(), 1.0)
            };
            let (c0, c1, o0, o1) = (0.2 * v, 0.8 * v, 0.3 * v, 0.9 * v);
            let _ = write!(
                text,
                "[[datasets]]\nname = \"d{i}\"\ndims = [{n}, {n}, {n}]\n\
                 [datasets.channels.voxel]\n{voxels}\n\
                 [[objects]]\nname = \"o{i}\"\ndataset = \"d{i}\"\nsampling_distance = {step:?}\n\
                 colour = {{ type = \"ramp\", points = [[{c0:?}, 0.2, 0.3, 0.9], [{c1:?}, 1.0, 0.9, 0.6]] }}\n\
                 opacity = {{ type = \"ramp\", points = [[{o0:?}, 0.001], [{o1:?}, 0.02]] }}\n\
                 transform = {{ matrix = [[{side:?}, 0, 0, {x:?}], [0, {side:?}, 0, {y:?}], [0, 0, {side:?}, {z:?}], [0, 0, 0, 1]] }}\n\n"
            );
        }
        text
    }

    /// The scene, parsed and validated by `trove-core` (no voxel is generated until a
    /// dataset is loaded).
    pub(crate) fn build(&self) -> Result<Scene> {
        Scene::parse(&self.toml(), "farm-sim.toml").context("building the simulated scene")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_generator_is_seeded_and_uniform() {
        let (mut a, mut b) = (Rng::new(7), Rng::new(7));
        let xs: Vec<f64> = (0..10_000).map(|_| a.uniform(2.0, 4.0)).collect();
        assert!(xs.iter().zip((0..10_000).map(|_| b.uniform(2.0, 4.0))).all(|(x, y)| *x == y));
        assert!(xs.iter().all(|x| (2.0..4.0).contains(x)));
        let mean = xs.iter().sum::<f64>() / xs.len() as f64;
        assert!((mean - 3.0).abs() < 0.02, "mean {mean}");
        assert_ne!(Rng::new(8).next_u64(), Rng::new(7).next_u64());
    }

    #[test]
    fn a_scene_has_one_cube_per_dataset_and_is_the_same_for_a_seed() {
        let spec = SceneSpec { datasets: 12, depth: 3.0, dims: 32, width: 16, height: 16, step_voxels: 1.0, seed: 3 };
        let scene = spec.build().unwrap();
        assert_eq!(scene.datasets().len(), 12);
        assert_eq!(scene.objects().len(), 12);
        assert_eq!(spec.toml(), spec.toml());
        assert_ne!(spec.toml(), SceneSpec { seed: 4, ..spec.clone() }.toml());
    }
}
