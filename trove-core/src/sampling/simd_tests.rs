//! Issue 19: every SIMD path this processor has renders the example scenes (and the peers'
//! benchmark scenes) within 1/255 of the f64 loops (and the paths that fuse multiply-adds
//! bit for bit alike), a path it lacks is refused, and `TROVE_SIMD` forces a path. The per-piece agreement (1e-5) on every path is in
//! [`super::tests`].

use std::path::{Path, PathBuf};
use std::process::Command;

use super::*;
use crate::geometry::{split_into_pieces, PieceScratch, Segment};
use crate::render::Image;
use crate::scene::{DataRoot, Scene, SceneError, SceneErrorKind};

/// The repository's example scenes and the peers' scenes, with their data roots.
fn scenes() -> Vec<(PathBuf, PathBuf)> {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let data = repo.join("../shared/data");
    let mut files: Vec<(PathBuf, PathBuf)> = std::fs::read_dir(repo.join("scenes"))
        .expect("scenes/ exists")
        .map(|e| e.expect("dir entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .map(|p| (p, data.clone()))
        .collect();
    files.sort();
    files.push((repo.join("scenes/peers/cthead.toml"), data));
    files.push((repo.join("scenes/peers/synthetic-u8.toml"), repo.join("scenes/peers/data")));
    files.push((repo.join("scenes/peers/cthead-f32.toml"), repo.join("scenes/peers/data")));
    files
}

/// `scene` with the other objects' shares of its shadows computed (SPEC §6): the same for
/// every path compared, which then differ only in how they cast.
fn with_shadow_maps(scene: Scene) -> Scene {
    crate::render::shadow::attach(&scene, &crate::render::VolumeStore::new(None)).expect("shadow pass").0.into_owned()
}

/// `scene`, every pixel's pieces cast with each object bound on `path`, many at a time
/// ([`ObjectCaster::cast_many`]: in f32 lanes where the object's loop has them) or, with
/// `one_by_one`, piece by piece in f64 ([`ObjectCaster::cast`]), then composited front to
/// back. Pieces are cast whole (no early termination), so that the two differ only by how
/// each piece was cast. Also returns how many objects cast packets, and how many of those
/// are lit.
fn render(scene: &Scene, path: SimdPath, one_by_one: bool) -> (Image, usize, usize) {
    let (w, h) = (scene.image().width, scene.image().height);
    let volumes: Vec<_> = scene.datasets().iter().map(|d| d.load().expect("load")).collect();
    let correction = scene.render().opacity_correction;
    let casters: Vec<ObjectCaster<'_>> = scene
        .objects()
        .iter()
        .map(|o| ObjectCaster::on_path(o, &volumes[o.dataset()], correction, CastOptions::default(), path).unwrap())
        .collect();
    let packets = casters.iter().filter(|c| c.casts_packets()).count();
    let lit = casters.iter().filter(|c| c.casts_packets() && c.is_shaded()).count();
    // Per object, the pieces it casts; per pixel, its pieces' (object, request) lists.
    let mut requests: Vec<Vec<PieceRequest>> = vec![Vec::new(); casters.len()];
    let mut pixels: Vec<Vec<Vec<(usize, usize)>>> = Vec::new();
    let (mut segments, mut scratch, mut pieces, mut cover) =
        (Vec::new(), PieceScratch::default(), Vec::new(), Vec::new());
    for row in 0..h {
        for col in 0..w {
            let ray = scene.camera().ray(col, row, w, h);
            segments.clear();
            for (i, o) in scene.objects().iter().enumerate() {
                if let Some((t_near, t_far)) = o.placement().segment(&ray) {
                    if t_far > t_near {
                        segments.push(Segment { object: i as u32, t_near, t_far });
                    }
                }
            }
            split_into_pieces(&segments, &mut scratch, &mut pieces, &mut cover);
            let mut pixel = Vec::new();
            for piece in &pieces {
                let objects = &cover[piece.cover.0 as usize..piece.cover.1 as usize];
                let mut parts = Vec::new();
                for &o in objects {
                    let o = o as usize;
                    parts.push((o, requests[o].len()));
                    requests[o].push(PieceRequest {
                        ray,
                        t0: piece.t0,
                        t1: piece.t1,
                        alpha_in: 0.0,
                        stop_at: f64::INFINITY,
                    });
                }
                pixel.push(parts);
            }
            pixels.push(pixel);
        }
    }
    let results: Vec<Vec<PieceResult>> = casters
        .iter()
        .zip(&requests)
        .map(|(caster, requests)| {
            let mut out = vec![PieceResult::default(); requests.len()];
            if one_by_one {
                for (out, r) in out.iter_mut().zip(requests) {
                    *out = caster.cast(&r.ray, r.t0, r.t1, r.alpha_in, r.stop_at);
                }
            } else {
                caster.cast_many(requests, &mut out);
            }
            out
        })
        .collect();
    let image = pixels
        .iter()
        .map(|pixel| {
            let mut acc = Rgba::CLEAR;
            for parts in pixel {
                acc.over(Rgba::colocated(parts.iter().map(|&(o, i)| results[o][i].rgba)));
            }
            acc.with_background(scene.image().background)
        })
        .collect();
    (Image::new(w, h, image), packets, lit)
}

#[test]
fn every_available_path_renders_every_example_scene_within_a_level_of_the_f64_loops() {
    let required = std::env::var_os("TROVE_REQUIRE_DATA").is_some();
    let (mut scenes_checked, mut packet_objects, mut skipped) = (0, 0, 0);
    for (file, data) in scenes() {
        let scene = match Scene::load_in(&file, &DataRoot::Given(data.clone())) {
            Ok(scene) => scene,
            // The synthetic volume and the f32 head are made by scripts (their scenes'
            // comments say how).
            Err(SceneError { kind: SceneErrorKind::DataNotFound { .. }, .. })
                if !required || file.ends_with("synthetic-u8.toml") || file.ends_with("cthead-f32.toml") =>
            {
                eprintln!("SKIPPED {}: its data is absent under {}", file.display(), data.display());
                skipped += 1;
                continue;
            }
            Err(e) => panic!("{}: {e}", file.display()),
        };
        let (width, height) = (scene.image().width, scene.image().height);
        let scale = 40.0 / width.max(height) as f64;
        let side = |s: u32| ((s as f64 * scale).round() as u32).max(1);
        let scene = scene.with_image_size(side(width), side(height)).unwrap();
        let scene = with_shadow_maps(scene);
        let (reference, _, _) = render(&scene, SimdPath::Scalar, true);
        // The paths with fused multiply-adds run the same operations lane by lane, whatever
        // their width: the same bits (so farm workers on AVX2 and on AVX-512 agree).
        let mut fused: Option<(SimdPath, Image)> = None;
        for path in SimdPath::available() {
            let (image, packets, _) = render(&scene, path, false);
            let difference = image.max_abs_difference(&reference);
            assert!(
                difference <= 1.0 / 255.0,
                "{} on {path}: {difference} from the f64 loops ({packets} objects in packets)",
                file.display()
            );
            packet_objects += packets;
            if path != SimdPath::Scalar {
                match &fused {
                    Some((first, first_image)) => assert!(
                        image.pixels() == first_image.pixels(),
                        "{}: {path} differs from {first} by {}",
                        file.display(),
                        image.max_abs_difference(first_image)
                    ),
                    None => fused = Some((path, image)),
                }
            }
        }
        scenes_checked += 1;
    }
    eprintln!("{scenes_checked} scenes, {packet_objects} (object, path) pairs cast in packets");
    // The scenes whose objects take the packet loop read real data: a fresh clone without
    // ../shared/data checks what it has and says what it skipped (CI, with the data, fails).
    if packet_objects == 0 && skipped > 0 && !required {
        eprintln!("SKIPPED the packet loop's part: no scene with data to cast in packets");
        return;
    }
    assert!(scenes_checked > 0 && packet_objects > 0, "no scene exercised the packet loop");
}

/// The shaded example scenes (SPEC §6), at a size where their surfaces span many pixels:
/// their lit objects that the packet loop can cast (trilinear over u8, u16 or f32 (Fig. 4's
/// generated volumes), affine boxes) cast in the lit packet loop on every path, within 1/255
/// of the f64 loops.
#[test]
fn every_path_renders_the_shaded_scenes_lit_in_packets_within_a_level_of_the_f64_loops() {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let data = DataRoot::Given(repo.join("../shared/data"));
    let required = std::env::var_os("TROVE_REQUIRE_DATA").is_some();
    for (name, lit_packets) in [("fig01-shaded", true), ("fig04-shaded", true), ("fig10-shaded", true)] {
        let file = repo.join("scenes").join(format!("{name}.toml"));
        let scene = match Scene::load_in(&file, &data) {
            Ok(scene) => scene,
            Err(SceneError { kind: SceneErrorKind::DataNotFound { .. }, .. }) if !required => {
                eprintln!("SKIPPED {name}: its data is absent");
                continue;
            }
            Err(e) => panic!("{name}: {e}"),
        };
        assert!(!scene.lights().is_empty(), "{name} is lit");
        let (width, height) = (scene.image().width, scene.image().height);
        let scale = 120.0 / width.max(height) as f64;
        let scene = scene
            .with_image_size(
                ((width as f64 * scale).round() as u32).max(1),
                ((height as f64 * scale).round() as u32).max(1),
            )
            .unwrap();
        let scene = with_shadow_maps(scene);
        let (reference, _, _) = render(&scene, SimdPath::Scalar, true);
        for path in SimdPath::available() {
            let (image, _, lit) = render(&scene, path, false);
            assert_eq!(lit > 0, lit_packets, "{name} on {path}: {lit} lit objects cast in packets");
            let difference = image.max_abs_difference(&reference);
            assert!(
                difference <= 1.0 / 255.0,
                "{name} on {path}: {difference} from the f64 loops ({lit} lit in packets)"
            );
            eprintln!("{name} on {path}: {lit} lit objects in packets, {difference:.2e} from the f64 loops");
        }
    }
}

#[test]
fn a_path_the_processor_lacks_is_refused_and_an_unknown_name_too() {
    let available = SimdPath::available();
    assert_eq!(available.last(), Some(&SimdPath::Scalar), "scalar runs everywhere, last");
    assert_eq!(SimdPath::best(), available[0]);
    for path in SimdPath::ALL {
        assert_eq!(path.checked().is_ok(), available.contains(&path));
        assert_eq!(path.name().parse::<SimdPath>(), Ok(path));
        if !available.contains(&path) {
            let e = path.checked().unwrap_err();
            let message = e.to_string();
            assert!(matches!(e, SimdError::Unavailable { path: p, .. } if p == path), "{e:?}");
            assert!(message.contains(path.name()) && message.contains(path.needs()), "{message}");
        }
    }
    // Every x86-64 processor lacks NEON and every AArch64 one AVX2: some path is refused here.
    assert!(available.len() < SimdPath::ALL.len());
    assert!(matches!("sse9".parse::<SimdPath>(), Err(SimdError::Unknown { .. })));
    assert_eq!(" AVX2 ".parse::<SimdPath>(), Ok(SimdPath::Avx2));
}

/// Where the child process of [`trove_simd_forces_a_path_and_refuses_one_the_processor_lacks`]
/// finds what `SimdPath::configured` must answer.
const EXPECTS: &str = "TROVE_SIMD_TEST_EXPECTS";

#[test]
fn trove_simd_forces_a_path_and_refuses_one_the_processor_lacks() {
    // `TROVE_SIMD` is read once per process, so each value is tried in a child process
    // running this test alone, which checks the answer.
    if let Ok(expected) = std::env::var(EXPECTS) {
        let got = match SimdPath::configured() {
            Ok(path) => path.name().to_string(),
            Err(e) => format!("error: {e}"),
        };
        assert!(got.starts_with(&expected), "TROVE_SIMD={:?}: {got}, expected {expected}", std::env::var("TROVE_SIMD"));
        return;
    }
    let best = SimdPath::best().name();
    let lacking = SimdPath::ALL.into_iter().find(|p| !p.is_available()).expect("some path is lacking");
    let refused = format!("error: SIMD path `{lacking}` is refused: this processor lacks {}", lacking.needs());
    let cases = [
        ("scalar", "scalar".to_string()),
        (best, best.to_string()),
        ("", best.to_string()),
        (lacking.name(), refused),
        ("sse9", "error: `sse9` is not a SIMD path".to_string()),
    ];
    let me = std::env::current_exe().expect("the test binary");
    for (value, expects) in cases {
        let out = Command::new(&me)
            .args(["--exact", "sampling::simd_tests::trove_simd_forces_a_path_and_refuses_one_the_processor_lacks"])
            .env("TROVE_SIMD", value)
            .env(EXPECTS, &expects)
            .output()
            .expect("run the test binary");
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "TROVE_SIMD={value:?}: {stdout}{}", String::from_utf8_lossy(&out.stderr));
        assert!(stdout.contains("1 passed"), "TROVE_SIMD={value:?}: the child ran no test: {stdout}");
    }
}

/// `gather_in` on `s`: the wanted lanes' words as `gather` reads them, 0 in the others,
/// for several masks (none, one lane, every other lane, all).
fn gathers_in_the_wanted_lanes_only<S: simd::Simd>(s: S) {
    let bytes: Vec<u8> = (0..64u32).map(|i| (i * 37 + 11) as u8).collect();
    let index: Vec<i32> = (0..S::LANES as i32).map(|l| (l * 7) % 50).collect();
    let mut all = [0i32; 16];
    // SAFETY: at scale 1 a lane's four bytes start at its index, at most 49, and end
    // inside the 64 bytes.
    s.store_i(&mut all, unsafe { s.gather::<1>(bytes.as_ptr(), s.load_i(&index)) });
    let full = ((1u64 << S::LANES) - 1) as u32;
    for wanted in [0, 1, 0x5555_5555 & full, full] {
        let mut got = [0i32; 16];
        // SAFETY: as above.
        s.store_i(&mut got, unsafe { s.gather_in::<1>(bytes.as_ptr(), s.load_i(&index), s.mask(wanted)) });
        for l in 0..S::LANES {
            let expected = if wanted >> l & 1 == 1 { all[l] } else { 0 };
            assert_eq!(got[l], expected, "lane {l} of {wanted:#x}");
        }
    }
}

#[test]
fn a_masked_gather_reads_the_wanted_lanes_on_every_path_the_processor_has() {
    use simd::Simd;
    gathers_in_the_wanted_lanes_only(simd::scalar::Scalar);
    #[cfg(target_arch = "x86_64")]
    if let Some(s) = simd::avx2::Avx2::detect() {
        gathers_in_the_wanted_lanes_only(s);
    }
    #[cfg(target_arch = "x86_64")]
    if let Some(s) = simd::avx512::Avx512::detect() {
        gathers_in_the_wanted_lanes_only(s);
    }
    #[cfg(target_arch = "aarch64")]
    if let Some(s) = simd::neon::Neon::detect() {
        gathers_in_the_wanted_lanes_only(s);
    }
}
