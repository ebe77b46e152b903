//! TROVE side by side with VTK's fixed-point CPU ray caster (issue 10): the CT head, the same
//! head stored as f32 (as signed scans and simulation grids are once loaded; written from the
//! shared u16 file when absent), and the synthetic 256³ u8 volume of
//! `../shared/peers/make_test_volume.py`, with the camera, image size, step, threads and
//! transfer function of `scenes/peers/*.toml` on both sides.
//!
//! Runs alternate (VTK, then TROVE, `rounds` times) so that load from other jobs on a
//! shared machine falls on both; medians are reported. VTK's re-render (its frame without
//! loading) is set against TROVE's frame without loading (its whole render less the loading
//! stage: intersection, volume rendering and composition, the measure issue 19's targets
//! use), and also against the volume-rendering stage alone; VTK's load and first frame
//! against TROVE's whole render. TROVE renders in this process, round after round, as VTK
//! re-renders in its own: buffers kept from the round before are reused on both sides. Each image's error is the RMSE, in 8-bit levels, against a
//! converged TROVE image (the same scene at a quarter of its step). VTK runs through
//! `vtk_raycast.py`; without Python's `vtk` module, or without a scene's data, that part is
//! skipped with a message.
//!
//! With `--shade`, both shade (SPEC §6 on TROVE's side, `--shade on` on VTK's) with VTK's
//! defaults: its headlight as one directional light travelling from the eye to the target,
//! ambient 0.1, diffuse 0.7, specular 0.2, power 10. What still differs (VTK's quantised
//! normals, shading interpolated from the voxels', one view direction) is in the
//! benchmarks' notes; the table then also gives the PSNR between the two images.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{anyhow, bail, Context, Result};
use trove_core::render::{self, RenderOptions, Rendered};
use trove_core::scene::{DataRoot, Scene};

use crate::stats::median;

/// `trove-bench peers` options.
#[derive(clap::Args)]
pub struct Args {
    /// Alternating rounds (each: one VTK process, one TROVE render) per scene.
    #[arg(long, default_value_t = 5)]
    rounds: u32,
    /// Frames VTK re-renders per process (it reports their median).
    #[arg(long, default_value_t = 5)]
    vtk_repeat: u32,
    /// Threads on both sides.
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// The peers folder (vtk_raycast.py).
    #[arg(long, default_value = "../shared/peers")]
    peers: PathBuf,
    /// The folder of the peers scenes (cthead.toml, cthead-f32.toml, synthetic-u8.toml).
    #[arg(long, default_value = "scenes/peers")]
    scenes: PathBuf,
    /// The data root of the CT head's key (the shared data).
    #[arg(long, default_value = "../shared/data")]
    data_root: PathBuf,
    /// Where the images go.
    #[arg(long, default_value = "/tmp/trove-peers")]
    out: PathBuf,
    /// Shade on both sides (VTK's `--shade on` and its Phong defaults under a headlight).
    #[arg(long)]
    shade: bool,
}

/// VTK's shading defaults (`vtkVolumeProperty`, `../shared/peers/README.md` item 11), as a
/// TROVE `shading` table.
const VTK_SHADING: [(&str, f64); 4] = [("ambient", 0.1), ("diffuse", 0.7), ("specular", 0.2), ("shininess", 10.0)];

/// One benchmark volume: its TROVE scene and the VTK arguments that describe the same view.
struct Peer {
    name: &'static str,
    scene: &'static str,
    /// The scene's data root: the shared data (`--data-root`), or the scenes folder's `data/`,
    /// where `make_test_volume.py` writes the synthetic volume.
    shared_data: bool,
    /// `vtk_raycast.py` arguments, in parts laid end to end; `{data}` stands for the scene's
    /// data root, `{peers}` for the peers folder.
    vtk: &'static [&'static [&'static str]],
}

/// VTK's view of the CT head, and its transfer function: the same for the head as u16 and
/// as f32.
const CTHEAD_VIEW: &[&str] = &[
    "--tf",
    "{peers}/tf/cthead_tf.json",
    "--eye",
    "430",
    "-380",
    "20",
    "--look-at",
    "127.5",
    "127.5",
    "113",
    "--up",
    "0",
    "0",
    "-1",
];

const PEERS: [Peer; 3] = [
    Peer {
        name: "CT head",
        scene: "cthead.toml",
        shared_data: true,
        vtk: &[&["--nrrd", "{data}/cthead_256x256x113_uint16_le.nhdr"], CTHEAD_VIEW],
    },
    Peer {
        name: "CT head as f32",
        scene: "cthead-f32.toml",
        shared_data: false,
        vtk: &[
            &[
                "--raw",
                "{data}/cthead_f32.raw",
                "--dims",
                "256",
                "256",
                "113",
                "--dtype",
                "float32",
                "--spacing",
                "1",
                "1",
                "2",
            ],
            CTHEAD_VIEW,
        ],
    },
    Peer {
        name: "synthetic 256³ u8",
        scene: "synthetic-u8.toml",
        shared_data: false,
        vtk: &[&[
            "--raw",
            "{data}/sphere256_u8.raw",
            "--dims",
            "256",
            "256",
            "256",
            "--dtype",
            "uint8",
            "--tf",
            "{data}/sphere256_u8_tf.json",
            "--eye",
            "558.21",
            "428.99",
            "730.49",
            "--look-at",
            "127.5",
            "127.5",
            "127.5",
            "--up",
            "0",
            "1",
            "0",
        ]],
    },
];

/// Arguments both VTK runs share (the scenes' image size, field of view and step; then
/// `--shade on` or `off`).
const VTK_COMMON: [&str; 10] =
    ["--size", "512", "512", "--fov", "30", "--sample-distance", "0.5", "--interp", "linear", "--shade"];

/// One round's timings, seconds.
#[derive(Clone, Copy, Debug, Default)]
struct Round {
    vtk_rerender: Option<f64>,
    vtk_first: Option<f64>,
    trove_rendering: f64,
    /// The whole render less loading (issue 19's measure).
    trove_frame: f64,
    trove_total: f64,
}

pub fn run(args: Args) -> Result<()> {
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let vtk = vtk_available();
    if !vtk {
        println!("Python's `vtk` module is absent (pip install vtk): TROVE is timed alone.");
    }
    if let Err(e) = write_f32_head(&args) {
        println!("The CT head as f32 could not be written ({e:#}): its row is skipped.");
    }
    let pool = rayon::ThreadPoolBuilder::new().num_threads(args.threads).build()?;
    println!("{}, {} threads\n", crate::machine::describe()?, args.threads);
    println!("shading: {}\n", if args.shade { "on (both sides)" } else { "off" });
    println!(
        "| scene | VTK re-render | TROVE total − loading | VTK/TROVE on it | TROVE volume rendering | VTK/TROVE on it | VTK load + first | TROVE total | TROVE samples/s | RMSE VTK | RMSE TROVE | PSNR VTK–TROVE |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for peer in &PEERS {
        let mut path = args.scenes.join(peer.scene);
        if args.shade {
            path = match lit_copy(&path, &args.out) {
                Ok(p) => p,
                Err(e) => {
                    println!("| {} | skipped: {e:#} |", peer.name);
                    continue;
                }
            };
        }
        let scene = match Scene::load_in(&path, &DataRoot::Given(data_root(&args, peer))) {
            Ok(s) => s,
            Err(e) => {
                println!("| {} | skipped: {e} |", peer.name);
                continue;
            }
        };
        pool.install(|| bench_one(&args, peer, &scene, vtk))?;
    }
    Ok(())
}

/// Alternating rounds over one scene, then its row of the table.
fn bench_one(args: &Args, peer: &Peer, scene: &Scene, vtk: bool) -> Result<()> {
    let stem = format!("{}{}", peer.scene.trim_end_matches(".toml"), if args.shade { "-shaded" } else { "" });
    let (vtk_png, trove_png) = (args.out.join(format!("{stem}-vtk.png")), args.out.join(format!("{stem}-trove.png")));
    let mut rounds = Vec::new();
    let mut last: Option<Rendered> = None;
    for _ in 0..args.rounds.max(1) {
        let mut round = Round::default();
        if vtk {
            let (rerender, first) = run_vtk(args, peer, &vtk_png)?;
            (round.vtk_rerender, round.vtk_first) = (Some(rerender), Some(first));
        }
        let r = render::render(scene, &RenderOptions::default())?;
        let seconds = &r.stats.seconds;
        (round.trove_rendering, round.trove_total) = (seconds.volume_rendering, seconds.total);
        round.trove_frame = seconds.total - seconds.loading;
        rounds.push(round);
        last = Some(r);
    }
    let rendered = last.ok_or_else(|| anyhow!("no round ran"))?;
    rendered.image.save(&trove_png)?;
    let root = DataRoot::Given(data_root(args, peer));
    let reference = render::render(&converged(scene, &root)?, &RenderOptions::default())?.image;
    reference.save(&args.out.join(format!("{stem}-reference.png")))?;
    let rmse_vtk = if vtk { Some(rmse_levels(&read_png(&vtk_png)?, &reference.to_rgb8())?) } else { None };
    let rmse_trove = rmse_levels(&rendered.image.to_rgb8(), &reference.to_rgb8())?;
    let between = if vtk { Some(psnr(rmse_levels(&read_png(&vtk_png)?, &rendered.image.to_rgb8())?)) } else { None };
    print_row(peer.name, &rounds, rendered.stats.samples, rmse_vtk, rmse_trove, between);
    Ok(())
}

/// Peak signal-to-noise ratio, dB, of an RMSE in levels of 255.
fn psnr(rmse: f64) -> f64 {
    20.0 * (255.0 / rmse).log10()
}

/// The scene at `path` shaded as VTK shades (one directional light along the view, VTK's
/// Phong defaults on every object), written into `out`; returns its path. (Its data keys
/// are under the same data root.)
fn lit_copy(path: &Path, out: &Path) -> Result<PathBuf> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut table: toml::Table = text.parse().context("the scene's TOML")?;
    let camera = table.get("camera").and_then(|c| c.as_table()).context("the scene's camera")?;
    let point = |key: &str| -> Result<[f64; 3]> {
        let v = camera.get(key).and_then(|v| v.as_array()).with_context(|| format!("camera.{key}"))?;
        let x: Vec<f64> = v.iter().filter_map(|x| x.as_float().or_else(|| x.as_integer().map(|i| i as f64))).collect();
        x.try_into().map_err(|_| anyhow!("camera.{key} is not three numbers"))
    };
    let (eye, target) = (point("eye")?, point("target")?);
    let direction: Vec<toml::Value> = (0..3).map(|i| toml::Value::Float(target[i] - eye[i])).collect();
    let mut light = toml::Table::new();
    light.insert("type".into(), "directional".into());
    light.insert("direction".into(), toml::Value::Array(direction));
    table.insert("lights".into(), toml::Value::Array(vec![toml::Value::Table(light)]));
    let shading: toml::Table = VTK_SHADING.iter().map(|&(k, v)| (k.to_string(), toml::Value::Float(v))).collect();
    let objects = table.get_mut("objects").and_then(|o| o.as_array_mut()).context("the scene's objects")?;
    for object in objects {
        object.as_table_mut().context("an object")?.insert("shading".into(), toml::Value::Table(shading.clone()));
    }
    let name = path.file_stem().context("a scene file name")?.to_string_lossy().into_owned();
    let lit = out.join(format!("{name}-shaded.toml"));
    std::fs::write(&lit, toml::to_string(&table)?).with_context(|| format!("writing {}", lit.display()))?;
    Ok(lit)
}

fn print_row(name: &str, rounds: &[Round], samples: u64, rmse_vtk: Option<f64>, rmse_trove: f64, between: Option<f64>) {
    let vtk_rerender = median(rounds.iter().filter_map(|r| r.vtk_rerender));
    let vtk_first = median(rounds.iter().filter_map(|r| r.vtk_first));
    let rendering = median(rounds.iter().map(|r| r.trove_rendering)).unwrap_or(f64::NAN);
    let frame = median(rounds.iter().map(|r| r.trove_frame)).unwrap_or(f64::NAN);
    let total = median(rounds.iter().map(|r| r.trove_total)).unwrap_or(f64::NAN);
    let seconds = |s: Option<f64>| s.map_or("–".to_string(), |s| format!("{s:.3}"));
    // Each round's VTK and TROVE ran back to back, under the same load: the median of the
    // rounds' ratios is steadier than the ratio of the medians.
    let ratio = |trove: fn(&Round) -> f64| {
        let r = median(rounds.iter().filter_map(|r| r.vtk_rerender.map(|v| v / trove(r))));
        r.map_or("–".to_string(), |r| format!("{r:.2}"))
    };
    let (on_frame, on_rendering) = (ratio(|r| r.trove_frame), ratio(|r| r.trove_rendering));
    println!(
        "| {name} | {} | {frame:.3} | {on_frame} | {rendering:.3} | {on_rendering} | {} | {total:.3} | {:.1} M | {} | {rmse_trove:.2} | {} |",
        seconds(vtk_rerender),
        seconds(vtk_first),
        samples as f64 / rendering / 1e6,
        rmse_vtk.map_or("–".to_string(), |e| format!("{e:.2}")),
        between.map_or("–".to_string(), |p| format!("{p:.1} dB")),
    );
}

/// Where `peer`'s data files are.
/// The shared u16 CT head's voxels as little-endian f32 (exact: every u16 is an f32), in the
/// scenes folder's `data/`, unless already there; nothing where the shared head is absent.
fn write_f32_head(args: &Args) -> Result<()> {
    let (from, to) = (args.data_root.join(U16_HEAD), args.scenes.join("data").join(F32_HEAD));
    if to.exists() || !from.exists() {
        return Ok(());
    }
    let u16s = std::fs::read(&from).with_context(|| format!("reading {}", from.display()))?;
    let f32s = u16_to_f32_le(&u16s);
    std::fs::create_dir_all(args.scenes.join("data"))?;
    // Written aside and renamed, so that an interrupted run leaves no short file behind.
    let part = to.with_extension("part");
    std::fs::write(&part, f32s).with_context(|| format!("writing {}", part.display()))?;
    std::fs::rename(&part, &to).with_context(|| format!("writing {}", to.display()))?;
    Ok(())
}

/// The shared CT head, and its f32 copy under the peers scenes' `data/`.
const U16_HEAD: &str = "cthead_256x256x113_uint16_le.raw";
const F32_HEAD: &str = "cthead_f32.raw";

/// Little-endian u16 voxels as little-endian f32 ones (a trailing odd byte is ignored).
fn u16_to_f32_le(bytes: &[u8]) -> Vec<u8> {
    bytes.chunks_exact(2).flat_map(|b| f32::from(u16::from_le_bytes([b[0], b[1]])).to_le_bytes()).collect()
}

fn data_root(args: &Args, peer: &Peer) -> PathBuf {
    if peer.shared_data {
        args.data_root.clone()
    } else {
        args.scenes.join("data")
    }
}

/// Whether `python3` can import `vtk`.
fn vtk_available() -> bool {
    Command::new("python3").args(["-c", "import vtk"]).output().is_ok_and(|o| o.status.success())
}

/// One VTK process: its median re-render and its load + first frame, seconds.
fn run_vtk(args: &Args, peer: &Peer, out: &Path) -> Result<(f64, f64)> {
    let data = data_root(args, peer);
    let fill = |a: &str| a.replace("{data}", &data.to_string_lossy()).replace("{peers}", &args.peers.to_string_lossy());
    let output = Command::new("python3")
        .arg(args.peers.join("vtk_raycast.py"))
        .args(peer.vtk.iter().flat_map(|part| part.iter()).map(|a| fill(a)))
        .args(VTK_COMMON)
        .arg(if args.shade { "on" } else { "off" })
        .args(["--threads", &args.threads.to_string(), "--repeat", &args.vtk_repeat.to_string()])
        .arg("--out")
        .arg(out)
        .output()
        .context("running vtk_raycast.py")?;
    if !output.status.success() {
        bail!("vtk_raycast.py failed: {}", String::from_utf8_lossy(&output.stderr));
    }
    let stdout = String::from_utf8_lossy(&output.stdout);
    let line = stdout.lines().rev().find(|l| l.trim_start().starts_with('{')).context("no JSON line from VTK")?;
    let json: serde_json::Value = serde_json::from_str(line).context("VTK's JSON line")?;
    let field = |k: &str| json.get(k).and_then(serde_json::Value::as_f64).with_context(|| format!("VTK's `{k}`"));
    Ok((field("rerender_median_s")?, field("load_s")? + field("first_render_s")?))
}

/// `scene` at a quarter of every object's sampling distance: the converged reference. The
/// peers scenes have no opacity correction (VTK's opacity unit distance is the step), so a
/// sample's opacity a means "per original step"; at a quarter of the step each opacity point
/// of the map becomes 1 − (1 − a)^¼, which keeps the extinction per unit length at every
/// point of the ramp (between points the two differ only in second order).
fn converged(scene: &Scene, root: &DataRoot) -> Result<Scene> {
    let path = scene.path();
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut table: toml::Table = text.parse().context("the scene's TOML")?;
    let corrected = scene.render().opacity_correction;
    let objects = table.get_mut("objects").and_then(|o| o.as_array_mut()).context("the scene's objects")?;
    for (object, original) in objects.iter_mut().zip(scene.objects()) {
        let object = object.as_table_mut().context("an object")?;
        object.insert("sampling_distance".into(), toml::Value::Float(original.sampling_distance() / 4.0));
        if !corrected {
            quarter_ramp_opacity(object).with_context(|| format!("object `{}`", original.name()))?;
        }
    }
    Ok(Scene::parse_in(&toml::to_string(&table)?, path, root)?)
}

/// Replaces each point [v, a] of the object's opacity ramp by [v, 1 − (1 − a)^¼].
fn quarter_ramp_opacity(object: &mut toml::Table) -> Result<()> {
    let opacity = object.get_mut("opacity").and_then(|o| o.as_table_mut()).context("an opacity table")?;
    if opacity.get("type").and_then(|t| t.as_str()) != Some("ramp") {
        bail!("the converged reference handles ramp opacities only");
    }
    let points = opacity.get_mut("points").and_then(|p| p.as_array_mut()).context("ramp points")?;
    for point in points {
        let point = point.as_array_mut().context("a ramp point")?;
        let a = point.get(1).and_then(|a| a.as_float().or_else(|| a.as_integer().map(|i| i as f64))).context("a")?;
        point[1] = toml::Value::Float(1.0 - (1.0 - a.clamp(0.0, 1.0)).powf(0.25));
    }
    Ok(())
}

fn read_png(path: &Path) -> Result<Vec<u8>> {
    Ok(image::open(path).with_context(|| format!("reading {}", path.display()))?.to_rgb8().into_raw())
}

/// Root mean square difference of two RGB8 images, in levels of 255.
fn rmse_levels(a: &[u8], b: &[u8]) -> Result<f64> {
    if a.len() != b.len() {
        bail!("image sizes differ: {} and {} bytes", a.len(), b.len());
    }
    let sum: f64 = a.iter().zip(b).map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2)).sum();
    Ok((sum / a.len() as f64).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn u16_voxels_become_the_same_values_as_f32() {
        let u16s: Vec<u8> = [0u16, 1, 700, 3272, u16::MAX].iter().flat_map(|v| v.to_le_bytes()).collect();
        let f32s = u16_to_f32_le(&u16s);
        let back: Vec<f32> = f32s.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        assert_eq!(back, vec![0.0, 1.0, 700.0, 3272.0, 65535.0]);
    }

    #[test]
    fn rmse_of_equal_images_is_zero_and_of_one_level_off_is_one() {
        assert_eq!(rmse_levels(&[1, 2, 3], &[1, 2, 3]).unwrap(), 0.0);
        assert_eq!(rmse_levels(&[1, 2, 3], &[2, 3, 4]).unwrap(), 1.0);
        assert!(rmse_levels(&[1], &[1, 2]).is_err());
    }

    #[test]
    fn the_shaded_copy_lights_every_object_as_vtk_does_and_keeps_the_rest() {
        let dir = trove_tests::scratch("peers-shaded");
        let text = trove_tests::Header::new(4, [0.0, 1.0, 3.0], [0.0, 0.0, 1.0], 30.0).to_string()
            + "[[datasets]]\nname = \"d\"\ndims = [4, 4, 4]\n[datasets.channels.voxel]\n\
               generator = { kind = \"ramp\", axis = \"x\", from = 0.0, to = 1.0 }\n\
               [[objects]]\nname = \"o\"\ndataset = \"d\"\n\
               colour = { type = \"ramp\", points = [[0, 1, 1, 1], [1, 1, 1, 1]] }\n\
               opacity = { type = \"ramp\", points = [[0, 0], [1, 0.5]] }\n";
        let path = dir.join("scene.toml");
        std::fs::write(&path, text).unwrap();
        let lit = Scene::load(lit_copy(&path, &dir).unwrap()).unwrap();
        let plain = Scene::load(&path).unwrap();
        let [light] = lit.lights() else { panic!("one light: {:?}", lit.lights()) };
        let trove_core::scene::LightSource::Directional { direction } = light.source() else { panic!("directional") };
        let want = [0.0, -1.0, -2.0].map(|x: f64| x / 5f64.sqrt());
        assert!(direction.get().to_array().iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-12), "{direction:?}");
        let (material, _) = lit.objects()[0].lighting().expect("the object is shaded");
        let got = [material.ambient(), material.diffuse(), material.specular(), material.shininess()];
        assert_eq!(got, VTK_SHADING.map(|(_, v)| v));
        assert_eq!(lit.image(), plain.image());
        assert_eq!(lit.objects()[0].opacity(), plain.objects()[0].opacity());
    }

    #[test]
    fn the_converged_scene_quarters_every_step_and_keeps_the_rest() {
        let dir = trove_tests::scratch("peers-converged");
        let text = trove_tests::Header::new(4, [0.0, 0.0, 3.0], [0.0; 3], 30.0).to_string()
            + "[render]\nopacity_correction = false\n\n[[datasets]]\nname = \"d\"\ndims = [4, 4, 4]\n[datasets.channels.voxel]\n\
               generator = { kind = \"constant\", value = 1.0 }\n\
               [[objects]]\nname = \"o\"\ndataset = \"d\"\nsampling_distance = 0.2\n\
               colour = { type = \"constant\", red = [1.0], green = [1.0], blue = [1.0] }\n\
               opacity = { type = \"ramp\", points = [[0, 0], [1, 0.5904]] }\n";
        let path = dir.join("scene.toml");
        std::fs::write(&path, text).unwrap();
        let scene = Scene::load(&path).unwrap();
        let fine = converged(&scene, &DataRoot::Given(dir.to_path_buf())).unwrap();
        assert_eq!(fine.objects()[0].sampling_distance(), 0.05);
        // Four samples of the quartered opacity let through what one of the original did.
        let a = fine.objects()[0].opacity().map(1.0).unwrap();
        assert!(((1.0 - a).powi(4) - (1.0 - 0.5904)).abs() < 1e-12, "{a}");
        assert_eq!(fine.image(), scene.image());
    }
}
