//! Effects are opt-in (SPEC §6): a scene that asks for none renders byte for byte as it did
//! before lights and shading existed. The hashes below are of the 8-bit RGB images that
//! the binary before effects (commit e96d81e) rendered of every example scene, shrunk so
//! that its longer side is 64 pixels, with the per-ray algorithm (f64 end to end, the same
//! bytes on every SIMD path):
//!
//! ```sh
//! trove-e96d81e render SHRUNK.toml -o OUT.png --algorithm per-ray --data-root ../shared/data
//! ```
//!
//! hashed with FNV-1a over the decoded pixels. A scene with `[[lights]]` is not compared.

use trove_core::render::{render_raster, Algorithm, RenderOptions};
use trove_tests::{example_scenes, skip};

const BEFORE_EFFECTS: &[(&str, u64)] = &[
    ("ct-head.toml", 0xa59c57fbb86e606b),
    ("fig01-fifteen-objects.toml", 0xe4e068286545a0f3),
    ("fig03-channels.toml", 0x78fbefd9fcc5b5c6),
    ("fig04-colour-maps.toml", 0x888f696d4dd39e67),
    ("fig05-opacity-maps.toml", 0xaa4e771e5ccda459),
    ("fig08-transformations.toml", 0x942b8f7556e38363),
    ("fig10-opaque-translucent.toml", 0x1d5d742633574330),
    ("generated.toml", 0x5ae28baa53e25845),
    ("photo-and-volume.toml", 0xbe351c19c484a919),
];

fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3))
}

#[test]
fn unlit_example_scenes_render_byte_for_byte_as_before_effects() {
    let mut compared = 0;
    for (path, scene) in example_scenes(64) {
        let name = path.file_name().unwrap_or_default().to_string_lossy().into_owned();
        if !scene.lights().is_empty() {
            continue;
        }
        let Some(&(_, want)) = BEFORE_EFFECTS.iter().find(|(n, _)| *n == name) else {
            panic!(
                "scenes/{name} has no lights and no hash from before effects: render it with trove-e96d81e and add it"
            );
        };
        let options = RenderOptions { algorithm: Algorithm::PerRay, ..RenderOptions::default() };
        let out = render_raster(&scene, &options, false).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(fnv1a(out.image.rgb8()), want, "scenes/{name} renders other bytes than before effects");
        compared += 1;
    }
    if compared < BEFORE_EFFECTS.len() {
        skip(&format!(
            "{} of {} unlit example scenes compared (the others read absent data)",
            compared,
            BEFORE_EFFECTS.len()
        ));
    }
    assert!(compared >= 3, "only {compared} scenes compared");
}
