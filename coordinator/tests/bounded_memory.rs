//! `trove render` writes a PNG in the memory its file needs, not in the 24 bytes a pixel of
//! the library's f64 [`trove_core::render::Image`]: the command line renders into the
//! compact `Raster` (3 bytes a pixel), band by band (issue 21's bound on local mode).
//!
//! The real binary renders a 2048² image under a data-segment limit (`ulimit -d`, which
//! counts the heap and every private writable mapping, not address space merely reserved)
//! of 64 MiB: less than the f64 image alone (96 MiB), twice what the raster render takes
//! (about 30 MiB with two threads). Rendering into an f64 image and quantising at the end,
//! as local mode did before, aborts on a failed allocation here.

#![cfg(target_os = "linux")]

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use trove_tests::process::Server;
use trove_tests::scratch;

const SIDE: u32 = 2048;

/// Every ray meets one thin slab of a 2³ ramp: one piece and two samples a pixel, so the
/// image, not casting, is what the render holds.
fn slab_scene() -> String {
    format!(
        "[image]\nwidth = {SIDE}\nheight = {SIDE}\nbackground = [0.05, 0.06, 0.1]\n\n\
         [camera]\neye = [0.0, 0.0, 4.0]\ntarget = [0.0, 0.0, 0.0]\nup = [0.0, 1.0, 0.0]\nfov_y = 40.0\n\n\
         [[datasets]]\nname = \"ramp\"\ndims = [2, 2, 2]\n\
         [datasets.channels.voxel]\ngenerator = {{ kind = \"ramp\", axis = \"x\", from = 0.0, to = 1.0 }}\n\n\
         [[objects]]\nname = \"slab\"\ndataset = \"ramp\"\n\
         colour = {{ type = \"ramp\", points = [[0.0, 0.1, 0.3, 0.9], [1.0, 1.0, 0.8, 0.2]] }}\n\
         opacity = {{ type = \"constant\", coefficients = [0.5] }}\n\
         transform = {{ matrix = [[8, 0, 0, -4], [0, 8, 0, -4], [0, 0, 0.5, -0.25], [0, 0, 0, 1]] }}\n"
    )
}

#[test]
fn a_png_render_holds_its_bytes_not_an_f64_image() {
    let dir = scratch("bounded-memory");
    let scene = dir.join("slab.toml");
    std::fs::write(&scene, slab_scene()).unwrap();
    let png = dir.join("slab.png");
    let f64_image_kib = SIDE as u64 * SIDE as u64 * 24 / 1024;
    let limit_kib = 64 * 1024;
    assert!(limit_kib < f64_image_kib, "the limit must refuse an f64 image");
    // Two threads (stacks count against the limit), two malloc arenas, bands of 4 MiB of
    // pieces, and no backtrace: an allocation failing while one is printed can hang.
    let trove = Path::new(env!("CARGO_BIN_EXE_trove"));
    let child = Command::new("sh")
        .arg("-c")
        .arg(format!("ulimit -d {limit_kib} && exec \"$0\" \"$@\""))
        .arg(trove)
        .args(["render", "--band-memory", "4194304", "-o"])
        .arg(&png)
        .arg(&scene)
        .env("RAYON_NUM_THREADS", "2")
        .env("MALLOC_ARENA_MAX", "2")
        .env("RUST_BACKTRACE", "0")
        .env_remove("RUST_LOG")
        .env_remove("TROVE_DATA")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run trove under sh");
    let mut child = Server(child);
    let status = child.exit_within(Duration::from_secs(120));
    let mut err = String::new();
    std::io::Read::read_to_string(child.0.stderr.as_mut().unwrap(), &mut err).unwrap();
    assert!(status.success(), "trove render within {limit_kib} KiB of data: {status:?}\n{err}");
    let image = image::open(&png).expect("a readable PNG").to_rgb8();
    assert_eq!(image.dimensions(), (SIDE, SIDE));
    let centre = image.get_pixel(SIDE / 2, SIDE / 2).0;
    assert!(centre[0] > 40 && centre[2] > 40, "the slab covers the centre: {centre:?}");
    std::fs::remove_dir_all(&dir).ok();
}
