//! Scene texts several test files render, in one place: a scene over a dataset file that
//! only the workers hold beside a generated one ([`SLAB_AND_BALL`], with its data root
//! [`slab_root`]), quick and slow generated balls, and the hostile scenes of the
//! bounded-work limits (nested boxes, many objects), so that the limit tests, the fault
//! tests and the operator tests refuse and render the same inputs; and random scenes of many
//! raw datasets ([`random_scene`]), which the farm tests render on one coordinator and on
//! several.

use std::path::{Path, PathBuf};

/// A dataset file a worker must hold (`slab.raw`, 4×4×2 u8) in front of a generated ball,
/// so that a render needs the worker's data and the scene's headers; its data is
/// [`slab_root`].
pub const SLAB_AND_BALL: &str = r#"
[image]
width = 40
height = 30
background = [0.1, 0.15, 0.2]
[camera]
eye = [0.5, 0.6, 3.2]
target = [0.5, 0.5, 0.5]
up = [0, 1, 0]
fov_y = 35.0
[[datasets]]
name = "slab"
dims = [4, 4, 2]
[datasets.channels.voxel]
raw = "slab.raw"
type = "u8"
[[datasets]]
name = "ball"
dims = [20, 20, 20]
[datasets.channels.voxel]
generator = { kind = "sphere", radius = 0.5, profile = "radial", value = 1.0, type = "f32" }
[[objects]]
name = "slab"
dataset = "slab"
colour = { type = "ramp", points = [[0, 0.2, 0.3, 0.9], [255, 1, 1, 1]] }
opacity = { type = "ramp", points = [[0, 0.05], [255, 0.5]] }
transform = { matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0.1, 0.9], [0, 0, 0, 1]] }
[[objects]]
name = "ball"
dataset = "ball"
colour = { type = "ramp", points = [[0.0, 0.9, 0.3, 0.1], [1.0, 0.2, 0.5, 1.0]] }
opacity = { type = "ramp", points = [[0.0, 0.0], [1.0, 0.4]] }
"#;

/// The folder `dir`, made if missing, holding the `slab.raw` of [`SLAB_AND_BALL`] (the
/// generated ball needs no file); returns it.
pub fn slab_root(dir: &Path) -> PathBuf {
    std::fs::create_dir_all(dir).expect("create the slab's data root");
    let voxels: Vec<u8> = (0..32u8).map(|i| i * 8).collect();
    std::fs::write(dir.join("slab.raw"), voxels).expect("write slab.raw");
    dir.to_path_buf()
}

/// `n` nested cubes over one generated 2³ dataset at `step`, the outermost filling the view.
pub fn nested_boxes(n: usize, size: u32, step: &str) -> String {
    let mut text = format!(
        "[image]\nwidth = {size}\nheight = {size}\nbackground = [0, 0, 0]\n\
         [camera]\neye = [0, 0, 4]\ntarget = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 30.0\n\
         [[datasets]]\nname = \"d\"\ndims = [2, 2, 2]\n[datasets.channels.voxel]\n\
         generator = {{ kind = \"constant\", value = 0.5 }}\n"
    );
    for i in 0..n {
        let half = 1.0 - i as f64 / (n as f64 + 1.0);
        let (s, t) = (2.0 * half, -half);
        text += &format!(
            "[[objects]]\nname = \"o{i}\"\ndataset = \"d\"\nsampling_distance = {step}\n\
             transform = {{ matrix = [[{s}, 0, 0, {t}], [0, {s}, 0, {t}], [0, 0, {s}, {t}], [0, 0, 0, 1]] }}\n\
             colour = {{ type = \"ramp\", points = [[0, 1, 1, 1], [1, 1, 1, 1]] }}\n\
             opacity = {{ type = \"ramp\", points = [[0, 0.01], [1, 0.01]] }}\n"
        );
    }
    text
}

/// `n` small cubes side by side in a row across the view, on a `size`² image.
pub fn many_objects(n: usize, size: u32) -> String {
    let mut text = nested_boxes(0, size, "0");
    for i in 0..n {
        let x = -1.0 + 2.0 * i as f64 / n as f64;
        text += &format!(
            "[[objects]]\nname = \"o{i}\"\ndataset = \"d\"\n\
             transform = {{ matrix = [[0.0004, 0, 0, {x}], [0, 0.0004, 0, 0], [0, 0, 0.0004, 0], [0, 0, 0, 1]] }}\n\
             colour = {{ type = \"ramp\", points = [[0, 1, 1, 1], [1, 1, 1, 1]] }}\n\
             opacity = {{ type = \"ramp\", points = [[0, 0.5], [1, 0.5]] }}\n"
        );
    }
    text
}

/// A ball that renders in a moment; `extra` goes into its object.
pub fn ball(size: u32, extra: &str) -> String {
    format!(
        "[image]\nwidth = {size}\nheight = {size}\nbackground = [0.1, 0.1, 0.2]\n\
         [camera]\neye = [0.5, 0.6, 3.0]\ntarget = [0.5, 0.5, 0.5]\nup = [0, 1, 0]\nfov_y = 35.0\n\
         [[datasets]]\nname = \"ball\"\ndims = [24, 24, 24]\n[datasets.channels.voxel]\n\
         generator = {{ kind = \"sphere\", radius = 0.5, profile = \"radial\", value = 1.0, type = \"f32\" }}\n\
         [[objects]]\nname = \"ball\"\ndataset = \"ball\"\n{extra}\n\
         colour = {{ type = \"ramp\", points = [[0.0, 0.9, 0.3, 0.1], [1.0, 0.2, 0.5, 1.0]] }}\n\
         opacity = {{ type = \"ramp\", points = [[0.0, 0.0], [1.0, 0.3]] }}\n"
    )
}

/// A ball slow enough to keep a worker busy for a while: cubic at a fine step.
pub fn slow_ball(size: u32) -> String {
    ball(size, "interpolation = \"cubic\"\nsampling_distance = 0.002")
}

/// A small deterministic generator (SplitMix64), so a failing scene can be rebuilt from its
/// seed.
pub struct Rng(pub u64);

impl Rng {
    /// The next 64 random bits.
    pub fn bits(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [lo, hi).
    pub fn in_range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * (self.bits() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A scene of `datasets` raw u8 datasets written under `dir` (keys `d{i}.raw`), each used
/// by one or two objects scattered so that rays cross several of them, with translucent
/// and opaque maps, so that fronts, culling and co-located pieces all occur.
pub fn random_scene(dir: &Path, datasets: usize, seed: u64) -> String {
    let mut rng = Rng(seed);
    let mut text = String::from(
        "[image]\nwidth = 40\nheight = 36\nbackground = [0.05, 0.1, 0.15]\n\
         [camera]\neye = [0.5, 0.5, 4.0]\ntarget = [0.5, 0.5, 0.5]\nup = [0, 1, 0]\nfov_y = 30.0\n",
    );
    for i in 0..datasets {
        let n = 3 + (rng.bits() % 6) as usize;
        let voxels: Vec<u8> = (0..n * n * n).map(|_| (rng.bits() % 256) as u8).collect();
        std::fs::write(dir.join(format!("d{i}.raw")), voxels).unwrap();
        text += &format!(
            "[[datasets]]\nname = \"d{i}\"\ndims = [{n}, {n}, {n}]\n[datasets.channels.voxel]\nraw = \"d{i}.raw\"\ntype = \"u8\"\n"
        );
    }
    for i in 0..datasets {
        for copy in 0..1 + (i % 2) {
            let s = rng.in_range(0.3, 0.6);
            let (x, y, z) = (rng.in_range(-0.1, 0.8), rng.in_range(-0.1, 0.8), rng.in_range(-0.5, 0.8));
            let top = if rng.bits().is_multiple_of(3) { 1.0 } else { rng.in_range(0.05, 0.5) };
            text += &format!(
                "[[objects]]\nname = \"o{i}-{copy}\"\ndataset = \"d{i}\"\n\
                 transform = {{ matrix = [[{s}, 0, 0, {x}], [0, {s}, 0, {y}], [0, 0, {s}, {z}], [0, 0, 0, 1]] }}\n\
                 colour = {{ type = \"ramp\", points = [[0, {r}, 0.2, 0.1], [255, 0.1, {g}, 0.9]] }}\n\
                 opacity = {{ type = \"ramp\", points = [[0, 0], [120, 0], [255, {top}]] }}\n",
                r = rng.in_range(0.2, 1.0),
                g = rng.in_range(0.2, 1.0),
            );
        }
    }
    text
}
