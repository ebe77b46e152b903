//! Every channel of SPEC §1.1 loads and validates, the 7-colour-model, interpolation and
//! user channels included, so effects that use them can rely on them.

use trove_core::dataset::{ChannelName, VoxelType};
use trove_core::scene::{Scene, SceneErrorKind};
use trove_tests::{scratch, Header};

fn scene_with(channels: &str) -> String {
    let header = Header::new(8, [0.5, 0.5, 3.0], [0.5, 0.5, 0.5], 30.0);
    format!(
        r#"{header}
[[datasets]]
name = "all"
dims = [4, 3, 2]
{channels}
[[objects]]
name = "o"
dataset = "all"
colour = {{ type = "raw" }}
opacity = {{ type = "raw" }}
"#
    )
}

fn channel(name: &str, generator: &str) -> String {
    format!("[datasets.channels.{name}]\ngenerator = {generator}\n")
}

#[test]
fn all_sixteen_channels_load_with_their_types() {
    let dir = scratch("channels");
    let mut text = String::new();
    let u8c = |v: u32| format!("{{ kind = \"constant\", value = {v}, type = \"u8\" }}");
    text += &channel("voxel", "{ kind = \"ramp\", axis = \"x\", from = 0, to = 100, type = \"u16\" }");
    text += &channel("bit", "{ kind = \"chessboard\", squares = [4, 3, 2] }");
    for (i, name) in
        ["grey", "red", "green", "blue", "alpha", "red2", "green2", "blue2", "beta", "interp"].iter().enumerate()
    {
        text += &channel(name, &u8c(10 + i as u32));
    }
    text += &channel("user1", "{ kind = \"constant\", value = 1.5 }");
    text += &channel("user2", "{ kind = \"constant\", value = 7, type = \"u32\" }");
    text += &channel("user3", "{ kind = \"constant\", value = 1, type = \"bit\" }");
    text += &channel("user4", "{ kind = \"constant\", value = 300, type = \"u16\" }");
    let scene = Scene::parse(&scene_with(&text), dir.join("scene.toml")).unwrap_or_else(|e| panic!("{e}"));
    let info = &scene.datasets()[0];
    assert_eq!(info.channels().len(), 16);
    let volume = info.load().unwrap();
    let expect = |name: ChannelName, ty: VoxelType, value: f32| {
        let c = volume.channel(name).unwrap_or_else(|| panic!("{name} missing"));
        assert_eq!(c.ty(), ty, "{name}");
        assert_eq!(c.value(3 + 4 * 2 + 12), value, "{name} at voxel (3, 2, 1)");
    };
    expect(ChannelName::Voxel, VoxelType::U16, 88.0); // round(100 · 3.5/4)
    expect(ChannelName::Bit, VoxelType::Bit, 0.0); // (3 + 2 + 1) mod 2
    expect(ChannelName::Grey, VoxelType::U8, 10.0);
    expect(ChannelName::Beta, VoxelType::U8, 18.0);
    expect(ChannelName::Interp, VoxelType::U8, 19.0);
    expect(ChannelName::User(1), VoxelType::F32, 1.5);
    expect(ChannelName::User(2), VoxelType::U32, 7.0);
    expect(ChannelName::User(3), VoxelType::Bit, 1.0);
    expect(ChannelName::User(4), VoxelType::U16, 300.0);
    // Raw colour prefers red/green/blue over grey and bit.
    assert_eq!(*scene.objects()[0].colour(), trove_core::mapping::ColourMap::Raw(trove_core::mapping::RawColour::Rgb));
}

#[test]
fn colour_model_channels_must_be_bytes() {
    let dir = scratch("channels-typed");
    for name in ["red2", "green2", "blue2", "beta", "interp", "alpha"] {
        let text = scene_with(&channel(name, "{ kind = \"constant\", value = 1.5 }"));
        let err = Scene::parse(&text, dir.join("scene.toml")).unwrap_err();
        assert_eq!(err.key, Some(format!("datasets[0].channels.{name}.generator")), "{err}");
        assert!(
            matches!(err.kind, SceneErrorKind::ChannelType { got: VoxelType::F32, .. }),
            "{name} must be u8: {err}"
        );
    }
    let err = Scene::parse(
        &scene_with(&channel("bit", "{ kind = \"constant\", value = 1, type = \"u8\" }")),
        dir.join("s.toml"),
    )
    .unwrap_err();
    assert_eq!(err.key.as_deref(), Some("datasets[0].channels.bit.generator"));
    assert!(matches!(err.kind, SceneErrorKind::ChannelType { channel: ChannelName::Bit, got: VoxelType::U8 }), "{err}");
}
