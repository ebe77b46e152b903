//! The sampler's own tests: the jump logic of empty-space skipping on its own (every sample
//! it passes over is based in an empty cell), and whole casts compared bit for bit across
//! the ways an object can be bound (specialised or general loop, skipping on or off), over
//! datasets of every stored type, every interpolation, map kind, extents, dataset borders
//! and distorted boxes.

use std::collections::BTreeMap;
use std::sync::Arc;

use glam::{DMat4, DVec3};
use proptest::prelude::*;

use super::skip::{cell_of, Jumps, Skipper};
use super::*;
use crate::dataset::macrocell::{Level, Macrocells};
use crate::dataset::{Channel, Dims, Endian, VoxelBytes, VoxelType};
use crate::geometry::hexahedron::Hexahedron;
use crate::geometry::{Extent, LineSamples, Placement, Shape};
use crate::interp::{Cubic, Identity, Interp, Interpolation, Linear, Nearest};
use crate::mapping::{Lut, Polynomial, Ramp, RawColour};

#[test]
fn opacity_correction_is_exact_at_the_ends_and_precise_for_tiny_values() {
    assert_eq!(corrected_opacity(0.0, 3.0), 0.0);
    assert_eq!(corrected_opacity(1.0, 0.25), 1.0);
    assert_eq!(corrected_opacity(1.0, 0.0), 0.0);
    assert_eq!(corrected_opacity(0.3, 1.0), 0.3);
    let a = corrected_opacity(0.5, 2.0);
    assert!((a - 0.75).abs() < 1e-15);
    // 1 − (1 − 1e-12)^1e-3 ≈ 1e-15: the naive formula loses every digit here.
    let tiny = corrected_opacity(1e-12, 1e-3);
    assert!((tiny / 1e-15 - 1.0).abs() < 1e-9, "{tiny}");
}

/// A sparse field: zero except in blocks of 3³ voxels (not aligned with macrocells) that a
/// hash of the block picks, about 1 in `rarity`, holding values 1..=200.
fn sparse(dims: Dims, seed: u64, rarity: u64) -> Vec<f32> {
    let [nx, ny, nz] = dims.as_array().map(|n| n as u64);
    let hash = |a: u64, b: u64, c: u64| {
        ((a * 73_856_093) ^ (b * 19_349_663) ^ (c * 83_492_791) ^ seed).wrapping_mul(0x9E37_79B9_7F4A_7C15)
    };
    let mut v = Vec::with_capacity((nx * ny * nz) as usize);
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let block = hash(i / 3, j / 3, k / 3);
                let voxel = hash(i, j, k);
                v.push(if (block >> 33) % rarity == 0 { ((voxel >> 20) % 200 + 1) as f32 } else { 0.0 });
            }
        }
    }
    v
}

fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    return std::is_x86_feature_detected!("avx2");
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// The channel `values` stored as `ty` (bit: non-zero → 1).
fn channel(ty: VoxelType, endian: Endian, values: &[f32], dims: Dims) -> Channel {
    let bytes: Vec<u8> = match ty {
        VoxelType::Bit => {
            let mut b = vec![0u8; values.len().div_ceil(8)];
            for (i, v) in values.iter().enumerate() {
                if *v != 0.0 {
                    b[i >> 3] |= 1 << (i & 7);
                }
            }
            b
        }
        VoxelType::U8 => values.iter().map(|&v| v as u8).collect(),
        VoxelType::U16 => values
            .iter()
            .flat_map(|&v| if endian == Endian::Little { (v as u16).to_le_bytes() } else { (v as u16).to_be_bytes() })
            .collect(),
        VoxelType::U32 => values
            .iter()
            .flat_map(|&v| if endian == Endian::Little { (v as u32).to_le_bytes() } else { (v as u32).to_be_bytes() })
            .collect(),
        VoxelType::F32 => values
            .iter()
            .flat_map(|&v| if endian == Endian::Little { v.to_le_bytes() } else { v.to_be_bytes() })
            .collect(),
    };
    Channel::new(ty, endian, VoxelBytes::Owned(Arc::new(bytes)), dims).unwrap()
}

fn volume(dims: Dims, channels: Vec<(ChannelName, Channel)>) -> Volume {
    Volume::new(dims, channels.into_iter().collect::<BTreeMap<_, _>>())
}

/// The unit box scaled to `size` and moved by `at`.
fn affine(size: f64, at: DVec3) -> Shape {
    let m = DMat4::from_translation(at) * DMat4::from_scale(DVec3::splat(size));
    Shape::Affine { world_from_box: m, box_from_world: m.inverse() }
}

fn object(
    colour: ColourMap,
    opacity: OpacityMap,
    interpolation: Interpolation,
    shape: Shape,
    extent: Extent,
    dims: Dims,
) -> Object {
    Object::for_tests(colour, opacity, interpolation, 0.0, Placement::new(shape, extent, dims))
}

/// `o` with another interpolation and sampling distance.
fn respecified(o: &Object, interpolation: Interpolation, sampling_distance: f64) -> Object {
    Object::for_tests(o.colour().clone(), o.opacity().clone(), interpolation, sampling_distance, o.placement().clone())
}

/// Opacity 0 below 0.5, rising after: voxels of value 0 are empty space.
fn opacity_ramp() -> OpacityMap {
    OpacityMap::Ramp(Ramp::new(vec![(0.5, [0.0]), (150.0, [0.4]), (200.0, [0.9])]))
}

fn colour_ramp() -> ColourMap {
    ColourMap::Ramp(Ramp::new(vec![(0.0, [0.1, 0.2, 0.3]), (100.0, [0.9, 0.5, 0.1]), (200.0, [1.0, 1.0, 1.0])]))
}

/// A deterministic spread of rays into a box around the origin of side `size` placed at
/// `at`: diagonal ones, ones parallel to faces, and ones through cell corners and faces
/// (integer coordinates, where snapping decides the cell).
fn rays(size: f64, at: DVec3, count: usize) -> Vec<Ray> {
    let mut out = Vec::new();
    let c = at + DVec3::splat(size / 2.0);
    for i in 0..count {
        let f = i as f64 / count as f64;
        let a = f * std::f64::consts::TAU * 7.0;
        let dir = DVec3::new(a.cos(), (a * 1.3).sin(), 0.4 + f).normalize();
        out.push(Ray { origin: c - dir * size * 2.0 + DVec3::new(0.1 * a.sin(), 0.07 * a.cos(), 0.0) * size, dir });
    }
    for axis in 0..3 {
        for i in 0..count / 4 + 1 {
            // Along an axis, in planes on and between voxel and cell boundaries.
            let mut o = at + DVec3::splat(size * (i as f64 + 0.5) / (count / 4 + 1) as f64);
            o[axis] = at[axis] - size;
            let mut dir = DVec3::ZERO;
            dir[axis] = 1.0;
            out.push(Ray { origin: o, dir });
            let mut grid = at + DVec3::splat(size * 0.25);
            grid[axis] = at[axis] - size;
            out.push(Ray { origin: grid, dir });
        }
    }
    out
}

/// [`casts_agree_on`] on every SIMD path this processor has; returns what the first
/// (widest) path gave.
fn casts_agree(object: &Object, volume: &Volume, correction: bool, rays: &[Ray]) -> (u64, u64) {
    let paths = SimdPath::available();
    let counts: Vec<(u64, u64)> =
        paths.iter().map(|&path| casts_agree_on(object, volume, correction, rays, path)).collect();
    // The f64 loops count the same samples whichever path the packets took.
    assert!(counts.windows(2).all(|w| w[0] == w[1]), "{paths:?}: {counts:?}");
    counts[0]
}

/// Casts every piece of every ray with each binding, its vector loops on `path`, and
/// requires identical results; then casts them many at a time and requires the same, or
/// where pieces are cast in f32 lanes, the same to f32's rounding. Returns (samples with
/// skipping, samples without).
fn casts_agree_on(object: &Object, volume: &Volume, correction: bool, rays: &[Ray], path: SimdPath) -> (u64, u64) {
    let bind = |specialise, skip_empty_space, classify_upfront| {
        let options = CastOptions { specialise, skip_empty_space, classify_upfront };
        ObjectCaster::on_path(object, volume, correction, options, path).unwrap()
    };
    let casters = [
        bind(true, true, false),
        bind(true, false, false),
        bind(false, true, false),
        bind(false, false, false),
        bind(true, true, true),
        bind(false, true, true),
    ];
    let (mut skipped, mut all) = (0, 0);
    let mut requests = Vec::new();
    for ray in rays {
        let Some((t0, t1)) = object.placement().segment(ray) else { continue };
        if t1 <= t0 {
            continue;
        }
        // Whole pieces, and a piece cut in two as a shared segment would be.
        for (a, b, stop) in [(t0, t1, 0.99), ((t0 + t1) / 2.0, t1, f64::INFINITY), (t0, (t0 + t1) / 3.0, 0.5)] {
            let results = casters.each_ref().map(|c| c.cast(ray, a, b, 0.0, stop));
            for (i, r) in results.iter().enumerate() {
                assert_eq!(r.rgba, results[3].rgba, "binding {i} differs from the general loop without skipping");
            }
            skipped += results[0].samples;
            all += results[3].samples;
            assert_eq!(results[0].samples, results[2].samples);
            assert_eq!(results[1].samples, results[3].samples);
            // Cells classified at bind skip exactly the samples classified on entry do.
            assert_eq!(results[4].samples, results[0].samples);
            assert_eq!(results[5].samples, results[2].samples);
            for alpha_in in [0.0, 0.3, 0.97] {
                requests.push(PieceRequest { ray: *ray, t0: a, t1: b, alpha_in, stop_at: stop });
            }
        }
    }
    // Many pieces at once give each piece's result: the same, or where they are cast many at
    // a time in f32 lanes (on `path`), the same up to f32's rounding ([`agree_to_f32`]).
    for caster in &casters {
        let mut many = vec![PieceResult::default(); requests.len()];
        caster.cast_many(&requests, &mut many);
        for (r, many) in requests.iter().zip(&many) {
            let one = caster.cast(&r.ray, r.t0, r.t1, r.alpha_in, r.stop_at);
            assert!(caster.packet_path().is_none_or(|p| p == path), "{:?} on {path}", caster.packet_path());
            if caster.casts_packets() {
                agree_to_f32(many, &one);
            } else {
                assert_eq!(*many, one, "cast_many differs from cast");
            }
        }
    }
    (skipped, all)
}

/// A piece cast in f32 lanes against the same piece cast in f64: colour and opacity within
/// 1e-5 (sums of a few hundred samples, each off by about 1e-7), and the samples looked at
/// the same but for one whose f32 position rounds into the next macrocell (which, being
/// empty there, contributes nothing either way).
fn agree_to_f32(f32: &PieceResult, f64: &PieceResult) {
    // `f64::max` passes NaN over: a non-finite result is caught here, not in the difference.
    let finite = |r: &PieceResult| r.rgba.colour.iter().chain([&r.rgba.alpha]).all(|c| c.is_finite());
    assert!(finite(f32) && finite(f64), "non-finite results: {f32:?} against {f64:?}");
    let difference = f32
        .rgba
        .colour
        .iter()
        .zip(&f64.rgba.colour)
        .fold((f32.rgba.alpha - f64.rgba.alpha).abs(), |d, (a, b)| d.max((a - b).abs()));
    assert!(difference <= 1e-5, "f32 lanes differ from the f64 loop by {difference}: {f32:?} against {f64:?}");
    assert!(
        f32.samples.abs_diff(f64.samples) <= 1,
        "f32 lanes looked at {} samples, the f64 loop {}",
        f32.samples,
        f64.samples
    );
}

#[test]
fn every_stored_type_interpolation_and_map_casts_alike_on_every_path() {
    let dims = Dims::new([13, 11, 9]).unwrap();
    let values = sparse(dims, 7, 9);
    let types = [
        (VoxelType::Bit, Endian::Little),
        (VoxelType::U8, Endian::Little),
        (VoxelType::U16, Endian::Little),
        (VoxelType::U16, Endian::Big),
        (VoxelType::U32, Endian::Little),
        (VoxelType::F32, Endian::Little),
        (VoxelType::F32, Endian::Big),
    ];
    let interps = [
        Interpolation::Nearest,
        Interpolation::Trilinear,
        Interpolation::Nonlinear { omega: [0.0, 0.0, 1.0] },
        Interpolation::Nonlinear { omega: [-0.1, 1.5, -0.3] },
        Interpolation::Cubic,
    ];
    let colours = || {
        vec![
            colour_ramp(),
            ColourMap::Lut(Lut::new(vec![0.5, 120.0], vec![[0.0, 0.0, 1.0], [0.3, 0.6, 0.2], [1.0, 0.9, 0.8]])),
            ColourMap::Polynomial([
                Polynomial(vec![0.1, 0.004]),
                Polynomial(vec![0.2]),
                Polynomial(vec![0.9, -0.002, 1e-5]),
            ]),
        ]
    };
    let opacities = || {
        vec![
            opacity_ramp(),
            OpacityMap::Lut(Lut::new(vec![0.5, 60.0], vec![0.0, 0.05, 0.3])),
            OpacityMap::Polynomial(Polynomial(vec![-0.05, 0.004])),
            OpacityMap::Polynomial(Polynomial(vec![0.01, 0.0, 1e-5])),
        ]
    };
    let (size, at) = (1.0, DVec3::new(-0.5, -0.5, -0.5));
    let rays = rays(size, at, 24);
    let (mut specialised, mut avx2, mut packets) = (0, 0, 0);
    for (ty, endian) in types {
        let vol = volume(dims, vec![(ChannelName::Voxel, channel(ty, endian, &values, dims))]);
        for interp in interps {
            for colour in colours() {
                for opacity in opacities() {
                    for correction in [false, true] {
                        let o = object(colour.clone(), opacity.clone(), interp, affine(size, at), Extent::FULL, dims);
                        casts_agree(&o, &vol, correction, &rays);
                        let caster = ObjectCaster::new(&o, &vol, correction).unwrap();
                        specialised += usize::from(caster.is_specialised());
                        avx2 += usize::from(caster.uses_avx2());
                        packets += usize::from(caster.casts_packets());
                    }
                }
            }
        }
    }
    // u8, u16 le and f32 le have specialised loops for nearest and trilinear with every map
    // pair, and for nonlinear and cubic with piecewise maps: (2·12 + 3·4)·3 types·2.
    assert_eq!(specialised, (2 * 12 + 3 * 4) * 3 * 2);
    // Trilinear over u8 and u16 le with LUT or ramp colour and opacity runs in AVX2 where the
    // processor has it, so the comparisons above held its lanes against the general loop.
    let eligible = 2 * 4 * 2;
    assert_eq!(avx2, if has_avx2() { eligible } else { 0 });
    // They, and the same over f32 le (whose opacity maps here are zero somewhere, so the
    // channel's range is known from its macrocells), cast many pieces at a time in f32
    // lanes on every path, held above against casting them one by one.
    assert_eq!(packets, 3 * 4 * 2);
}

#[test]
fn f32_voxels_cast_in_packets_alike_with_negative_fractional_and_non_finite_values() {
    // Signed data and simulation grids load as f32: values below zero and between integers,
    // and voxels that are NaN or infinite, which leave out every sample blending them (SPEC
    // §4.5) in the packet loop as in the f64 loops.
    let dims = Dims::new([29, 23, 17]).unwrap();
    let mut values: Vec<f32> = sparse(dims, 5, 5)
        .iter()
        .enumerate()
        .map(|(i, &v)| if v == 0.0 { -50.0 } else { v * 1.37 - 40.0 + (i % 7) as f32 * 0.125 })
        .collect();
    let mut non_finite = 0;
    for (i, v) in values.iter_mut().enumerate() {
        if *v > 20.0 && i % 41 == 0 {
            *v = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY][non_finite % 3];
            non_finite += 1;
        }
    }
    assert!(non_finite >= 20, "{non_finite} non-finite voxels among the data");
    let (size, at) = (1.0, DVec3::new(-0.5, -0.5, -0.5));
    let rays = rays(size, at, 160);
    let signed_ramp = OpacityMap::Ramp(Ramp::new(vec![(-30.0, [0.0]), (-10.0, [0.2]), (100.0, [0.5]), (250.0, [0.9])]));
    let signed_lut = OpacityMap::Lut(Lut::new(vec![-20.0, 0.5, 60.25], vec![0.0, 0.05, 0.1, 0.3]));
    let colour_lut =
        ColourMap::Lut(Lut::new(vec![-5.0, 120.0], vec![[0.0, 0.0, 1.0], [0.3, 0.6, 0.2], [1.0, 0.9, 0.8]]));
    let cases =
        [(colour_ramp(), opacity_ramp(), false), (colour_ramp(), signed_ramp, true), (colour_lut, signed_lut, true)];
    let f32_volume = |values: &[f32]| {
        volume(dims, vec![(ChannelName::Voxel, channel(VoxelType::F32, Endian::Little, values, dims))])
    };
    for (colour, opacity, correction) in cases {
        let vol = f32_volume(&values);
        let o = object(colour, opacity, Interpolation::Trilinear, affine(size, at), Extent::FULL, dims);
        assert!(ObjectCaster::new(&o, &vol, correction).unwrap().casts_packets());
        casts_agree(&o, &vol, correction, &rays);
        // A finite value beyond 10³⁰ could overflow f32 differences: such a channel keeps
        // the f64 loops (which the same comparisons then hold to themselves).
        let mut huge = values.clone();
        huge[1000] = 3e35;
        let vol = f32_volume(&huge);
        assert!(!ObjectCaster::new(&o, &vol, correction).unwrap().casts_packets());
        casts_agree(&o, &vol, correction, &rays);
    }
    // An opacity map that is nowhere zero has no empty-space classification: the channel's
    // range comes from its macrocells alone, and the packets hold the f64 loops as above.
    let everywhere = OpacityMap::Ramp(Ramp::new(vec![(-60.0, [0.01]), (250.0, [0.5])]));
    let vol = f32_volume(&values);
    let o = object(colour_ramp(), everywhere, Interpolation::Trilinear, affine(size, at), Extent::FULL, dims);
    assert!(ObjectCaster::new(&o, &vol, true).unwrap().casts_packets());
    casts_agree(&o, &vol, true, &rays);
}

#[test]
fn a_constant_opacity_with_a_piecewise_colour_casts_in_packets_alike() {
    // Floors and photographs one voxel deep: a constant opacity (opaque, translucent, above
    // 1, below 0) with a LUT or ramp colour joins the colour's map as a map of one segment.
    let dims = Dims::new([21, 17, 13]).unwrap();
    let values = sparse(dims, 3, 2);
    let (size, at) = (1.0, DVec3::new(-0.5, -0.5, -0.5));
    let rays = rays(size, at, 60);
    let lut = || ColourMap::Lut(Lut::new(vec![0.5, 120.0], vec![[0.0, 0.0, 1.0], [0.3, 0.6, 0.2], [1.0, 0.9, 0.8]]));
    for ty in [VoxelType::U8, VoxelType::U16, VoxelType::F32] {
        let vol = volume(dims, vec![(ChannelName::Voxel, channel(ty, Endian::Little, &values, dims))]);
        for (colour, c) in [(colour_ramp(), 1.0), (lut(), 0.3), (colour_ramp(), 1.7), (lut(), -0.2)] {
            let opacity = OpacityMap::Polynomial(Polynomial(vec![c]));
            for correction in [false, true] {
                let o = object(
                    colour.clone(),
                    opacity.clone(),
                    Interpolation::Trilinear,
                    affine(size, at),
                    Extent::FULL,
                    dims,
                );
                let caster = ObjectCaster::new(&o, &vol, correction).unwrap();
                assert!(caster.is_specialised());
                // (An opacity of at most 0 is a transparent object, whose pieces are never
                // cast at all.)
                assert!(caster.casts_packets(), "{ty:?}, opacity {c}");
                casts_agree(&o, &vol, correction, &rays);
            }
        }
    }
}

#[test]
fn many_pieces_at_once_skip_alike_in_volumes_of_many_cells() {
    // Hundreds of macrocells (so their bits span many words), sparse data (so lanes jump
    // often and at different times), u8 and u16 under the vector loops' maps.
    let dims = Dims::new([45, 38, 29]).unwrap();
    let values = sparse(dims, 11, 40);
    let (size, at) = (1.0, DVec3::new(-0.5, -0.5, -0.5));
    let rays = rays(size, at, 160);
    // LUTs of 16 break points: 17 segments, one more than two registers' permutes hold.
    let breaks: Vec<f64> = (1..=16).map(|i| 12.0 * i as f64).collect();
    let opacity_lut = OpacityMap::Lut(Lut::new(breaks.clone(), (0..17).map(|i| (i / 3) as f64 * 0.03).collect()));
    let colour_lut =
        ColourMap::Lut(Lut::new(breaks, (0..17).map(|i| [i as f64 / 16.0, 0.5, 1.0 - i as f64 / 20.0]).collect()));
    let cases = [
        (VoxelType::U8, false, colour_ramp(), opacity_ramp()),
        (VoxelType::U16, true, colour_ramp(), opacity_ramp()),
        (VoxelType::U8, false, colour_lut, opacity_lut),
    ];
    for (ty, correction, colour, opacity) in cases {
        let vol = volume(dims, vec![(ChannelName::Voxel, channel(ty, Endian::Little, &values, dims))]);
        let o = object(colour, opacity, Interpolation::Trilinear, affine(size, at), Extent::FULL, dims);
        assert!(ObjectCaster::new(&o, &vol, correction).unwrap().casts_packets());
        let (skipped, all) = casts_agree(&o, &vol, correction, &rays);
        assert!(skipped < all / 2, "{ty:?}: most samples lie in empty cells ({skipped} of {all} looked at)");
    }
}

/// A smooth field over `dims`: a ball of values rising to 200 towards (0.4, 0.55, 0.5) of
/// the grid, rippled, 0 outside it (so that macrocells there are empty).
fn smooth_ball(dims: Dims) -> Vec<f32> {
    let [nx, ny, nz] = dims.as_array().map(|n| n as f64);
    let mut v = Vec::new();
    for k in 0..nz as u64 {
        for j in 0..ny as u64 {
            for i in 0..nx as u64 {
                let p = DVec3::new(i as f64 / nx, j as f64 / ny, k as f64 / nz);
                let r = (p - DVec3::new(0.4, 0.55, 0.5)).length() / 0.42;
                let ripple = 1.0 + 0.15 * (11.0 * p.x).sin() * (7.0 * p.y).cos();
                v.push(if r < 1.0 { (200.0 * (1.0 - r * r) * ripple).round().min(255.0) as f32 } else { 0.0 });
            }
        }
    }
    v
}

/// Lit objects (SPEC §6) cast many pieces at once in the lit packet loop, which holds the
/// f64 one-piece loop (the generic line loop, shading each contributing sample) to 1e-5
/// per piece on every path: u8 and u16, with and without opacity correction, a LUT and a
/// ramp, a box turned and scaled unevenly (so that normals need the inverse transpose), a
/// directional light and point lights outside and inside the box; a whole and a fractional
/// shininess; and more directional lights than lanes keep H for.
#[test]
fn lit_pieces_cast_in_packets_hold_the_f64_lit_loop_on_every_path() {
    use crate::scene::{Light, LightSource, Shading, UnitVector};
    let dims = Dims::new([27, 22, 19]).unwrap();
    let (size, at) = (1.0, DVec3::new(-0.5, -0.5, -0.5));
    let centre = at + DVec3::splat(size / 2.0);
    let m = DMat4::from_translation(centre)
        * DMat4::from_axis_angle(DVec3::new(0.3, 1.0, -0.4).normalize(), 0.6)
        * DMat4::from_scale(DVec3::new(0.95, 0.7, 0.8) * size)
        * DMat4::from_translation(DVec3::splat(-0.5));
    let shape = Shape::Affine { world_from_box: m, box_from_world: m.inverse() };
    let material = Shading::new(0.15, 0.7, 0.4, 12.0).unwrap();
    let fractional = Shading::new(0.1, 0.6, 0.5, 7.3).unwrap();
    let directional = |d: [f64; 3], e: f64| {
        Light::new(LightSource::Directional { direction: UnitVector::new(DVec3::from(d)).unwrap() }, [1.0; 3], e)
            .unwrap()
    };
    let many: Vec<Light> = (0..6).map(|i| directional([(i as f64).sin(), -0.5, -1.0 + 0.2 * i as f64], 0.3)).collect();
    let lights = [
        Light::new(
            LightSource::Directional { direction: UnitVector::new(DVec3::new(-0.3, -0.5, -1.0)).unwrap() },
            [1.0, 0.9, 0.8],
            1.0,
        )
        .unwrap(),
        Light::new(LightSource::Point { position: centre + DVec3::new(2.0, 1.5, 2.5) }, [1.0; 3], 0.6).unwrap(),
        Light::new(LightSource::Point { position: centre + DVec3::new(0.1, -0.05, 0.02) }, [0.3, 0.5, 1.0], 0.8)
            .unwrap(),
    ];
    let breaks: Vec<f64> = (1..=6).map(|i| 30.0 * i as f64).collect();
    let opacity_lut = OpacityMap::Lut(Lut::new(breaks.clone(), (0..7).map(|i| (i / 2) as f64 * 0.08).collect()));
    let colour_lut =
        ColourMap::Lut(Lut::new(breaks, (0..7).map(|i| [i as f64 / 6.0, 0.5, 1.0 - i as f64 / 8.0]).collect()));
    // f32 voxels at the ball's scale, and scaled far down and up (with the maps' points):
    // their gradients' squares would vanish or overflow in f32 but for the rescaling.
    let scaled_ramps = |k: f64| {
        let colour = ColourMap::Ramp(Ramp::new(vec![
            (0.0, [0.1, 0.2, 0.3]),
            (100.0 * k, [0.9, 0.5, 0.1]),
            (200.0 * k, [1.0, 1.0, 1.0]),
        ]));
        let opacity = OpacityMap::Ramp(Ramp::new(vec![(0.5 * k, [0.0]), (150.0 * k, [0.4]), (200.0 * k, [0.9])]));
        (colour, opacity)
    };
    let (tiny_colour, tiny_opacity) = scaled_ramps(1e-20);
    let (huge_colour, huge_opacity) = scaled_ramps(1e20);
    let cases = [
        (VoxelType::U8, false, colour_ramp(), opacity_ramp(), material, &lights[..], 1.0),
        (VoxelType::U16, true, colour_ramp(), opacity_ramp(), fractional, &lights[..], 1.0),
        (VoxelType::U8, true, colour_lut, opacity_lut, material, &many[..], 1.0),
        (VoxelType::F32, true, colour_ramp(), opacity_ramp(), material, &lights[..], 1.0),
        (VoxelType::F32, false, tiny_colour, tiny_opacity, fractional, &lights[..], 1e-20),
        (VoxelType::F32, true, huge_colour, huge_opacity, material, &many[..], 1e20),
    ];
    let rays = rays(size, at, 120);
    for (ty, correction, colour, opacity, material, lights, scale) in cases {
        let values: Vec<f32> = smooth_ball(dims).iter().map(|&v| (f64::from(v) * scale) as f32).collect();
        let vol = volume(dims, vec![(ChannelName::Voxel, channel(ty, Endian::Little, &values, dims))]);
        let unlit = object(colour, opacity, Interpolation::Trilinear, shape.clone(), Extent::FULL, dims);
        let lit = respecified(&unlit, Interpolation::Trilinear, 0.0).lit_for_tests(material, lights);
        let mut shaded = 0;
        for path in SimdPath::available() {
            let options = CastOptions::default();
            let caster = ObjectCaster::on_path(&lit, &vol, correction, options, path).unwrap();
            assert!(caster.is_shaded() && caster.packet_path() == Some(path), "{ty:?} on {path}");
            assert!(!caster.uses_avx2(), "the AVX2 lines are unlit");
            let plain = ObjectCaster::on_path(&unlit, &vol, correction, options, path).unwrap();
            let mut requests = Vec::new();
            for ray in &rays {
                let Some((t0, t1)) = lit.placement().segment(ray) else { continue };
                for (a, b, stop) in [(t0, t1, 0.99), ((t0 + t1) / 2.0, t1, f64::INFINITY), (t0, (t0 + t1) / 3.0, 0.5)] {
                    for alpha_in in [0.0, 0.3] {
                        requests.push(PieceRequest { ray: *ray, t0: a, t1: b, alpha_in, stop_at: stop });
                    }
                }
            }
            let mut many = vec![PieceResult::default(); requests.len()];
            caster.cast_many(&requests, &mut many);
            let mut unlit_many = vec![PieceResult::default(); requests.len()];
            plain.cast_many(&requests, &mut unlit_many);
            let mut changed = 0.0f64;
            for ((r, many), unlit) in requests.iter().zip(&many).zip(&unlit_many) {
                let one = caster.cast(&r.ray, r.t0, r.t1, r.alpha_in, r.stop_at);
                agree_to_f32(many, &one);
                assert!(many.shaded.abs_diff(one.shaded) <= 1, "{path}: shaded {} against {}", many.shaded, one.shaded);
                shaded += many.shaded;
                changed = changed.max((many.rgba.colour[0] - unlit.rgba.colour[0]).abs());
            }
            // The lights change the pieces: a loop that did not shade would fail above.
            assert!(changed > 0.05, "{ty:?} on {path}: lighting changed at most {changed}");
        }
        assert!(shaded > 1000, "{ty:?}: {shaded} samples shaded");
    }
}

/// Where the packet loop cannot shade as the f64 loop does, a lit object keeps the f64
/// loops: a distorted box (its normals' matrix changes from sample to sample), and a point
/// light too far out for f32 lanes.
#[test]
fn lit_objects_the_packet_loop_cannot_shade_keep_the_f64_loops() {
    use crate::scene::{Light, LightSource, Shading};
    let dims = Dims::new([12, 10, 9]).unwrap();
    let vol =
        volume(dims, vec![(ChannelName::Voxel, channel(VoxelType::U8, Endian::Little, &smooth_ball(dims), dims))]);
    let material = Shading::DEFAULT;
    let near = [Light::new(LightSource::Point { position: DVec3::new(2.0, 2.0, 2.0) }, [1.0; 3], 1.0).unwrap()];
    let far = [Light::new(LightSource::Point { position: DVec3::new(1e19, 0.0, 0.0) }, [1.0; 3], 1.0).unwrap()];
    let mut corners: [DVec3; 8] =
        std::array::from_fn(|i| DVec3::new((i & 1) as f64, (i >> 1 & 1) as f64, (i >> 2 & 1) as f64));
    corners[7] += DVec3::new(0.3, 0.25, 0.2);
    let distorted = Shape::Distorted { hex: Box::new(Hexahedron::new(corners).unwrap()), straight: true };
    for (shape, lights, packets) in
        [(affine(1.0, DVec3::ZERO), &near, true), (distorted, &near, false), (affine(1.0, DVec3::ZERO), &far, false)]
    {
        let o = object(colour_ramp(), opacity_ramp(), Interpolation::Trilinear, shape, Extent::FULL, dims)
            .lit_for_tests(material, lights);
        let caster = ObjectCaster::new(&o, &vol, true).unwrap();
        assert!(caster.is_shaded());
        assert_eq!(caster.casts_packets(), packets, "{:?}", o.placement().shape());
        assert!(caster.is_specialised());
    }
}

#[test]
fn raw_colour_and_alpha_cast_alike_and_skip_transparent_pixels() {
    // A photograph as a volume one voxel deep: alpha 0 outside a disc.
    let dims = Dims::new([40, 30, 1]).unwrap();
    let [nx, ny, _] = dims.as_array();
    let (mut r, mut g, mut b, mut a) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for j in 0..ny {
        for i in 0..nx {
            let inside = (i as f64 - 20.0).hypot(j as f64 - 15.0) < 9.0;
            r.push((i * 6) as u8);
            g.push((j * 8) as u8);
            b.push(200);
            a.push(if inside { 180 } else { 0 });
        }
    }
    let vol = volume(
        dims,
        vec![
            (ChannelName::Red, Channel::from_u8(r, dims).unwrap()),
            (ChannelName::Green, Channel::from_u8(g, dims).unwrap()),
            (ChannelName::Blue, Channel::from_u8(b, dims).unwrap()),
            (ChannelName::Alpha, Channel::from_u8(a, dims).unwrap()),
        ],
    );
    let (size, at) = (1.0, DVec3::new(-0.5, -0.5, -0.5));
    for interp in [Interpolation::Nearest, Interpolation::Trilinear, Interpolation::Cubic] {
        for opacity in [OpacityMap::Raw, OpacityMap::Polynomial(Polynomial(vec![0.3]))] {
            let o = object(ColourMap::Raw(RawColour::Rgb), opacity, interp, affine(size, at), Extent::FULL, dims);
            let (skipped, all) = casts_agree(&o, &vol, true, &rays(size, at, 40));
            let caster = ObjectCaster::new(&o, &vol, true).unwrap();
            if matches!(o.opacity(), OpacityMap::Raw) {
                assert!(caster.skips_empty_space() && skipped < all, "{interp:?}: {skipped} of {all}");
            } else {
                assert!(!caster.skips_empty_space(), "a constant opacity above 0 never skips");
            }
            assert_eq!(caster.is_specialised(), interp != Interpolation::Cubic);
        }
    }
}

#[test]
fn a_map_that_is_non_zero_everywhere_turns_skipping_off() {
    let dims = Dims::new([8, 8, 8]).unwrap();
    let vol = volume(dims, vec![(ChannelName::Voxel, Channel::from_f32(&sparse(dims, 1, 5), dims).unwrap())]);
    let everywhere = [
        OpacityMap::Ramp(Ramp::new(vec![(0.0, [0.01]), (100.0, [0.5])])),
        OpacityMap::Lut(Lut::new(vec![10.0], vec![0.2, 0.1])),
        OpacityMap::Polynomial(Polynomial(vec![0.3])),
        // Quadratic: not monotone, so no zero set is claimed (it would be empty anyway).
        OpacityMap::Polynomial(Polynomial(vec![0.1, 0.0, 1.0])),
    ];
    for opacity in everywhere {
        let o = object(colour_ramp(), opacity, Interpolation::Trilinear, affine(1.0, DVec3::ZERO), Extent::FULL, dims);
        assert!(!ObjectCaster::new(&o, &vol, true).unwrap().skips_empty_space(), "{:?}", o.opacity());
    }
    let zero_below_half =
        object(colour_ramp(), opacity_ramp(), Interpolation::Trilinear, affine(1.0, DVec3::ZERO), Extent::FULL, dims);
    assert!(ObjectCaster::new(&zero_below_half, &vol, true).unwrap().skips_empty_space());
    // A constant 0 opacity casts nothing at all, skipping or not.
    let clear = object(
        colour_ramp(),
        OpacityMap::Polynomial(Polynomial(vec![0.0])),
        Interpolation::Trilinear,
        affine(1.0, DVec3::ZERO),
        Extent::FULL,
        dims,
    );
    let ray = Ray { origin: DVec3::new(0.5, 0.5, -1.0), dir: DVec3::Z };
    assert_eq!(ObjectCaster::new(&clear, &vol, true).unwrap().cast(&ray, 1.0, 2.0, 0.0, 1.0), PieceResult::default());
}

/// Every sample a jump passes over is based in an empty cell: checked sample by sample on
/// lines through `object`'s box.
fn jumps_pass_only_empty_samples<I: Interp>(interp: &I, object: &Object, volume: &Volume, rays: &[Ray]) -> (u64, u64) {
    let cells = volume.macrocells(ChannelName::Voxel).unwrap();
    let skipper = || {
        Skipper::new(cells, ChannelName::Voxel, object.opacity().zero_set(), true).expect("the map is zero somewhere")
    };
    // Walking cell by cell (cells classified on entry) and leaping over cubes of empty cells
    // (cells classified, and their distances worked out, at bind).
    let (mut passed, mut looked) = (0, 0);
    for skipper in [skipper(), skipper().classified(interp)] {
        let (p, l) = passes_only_empty_samples(interp, object, &skipper, rays);
        passed += p;
        looked += l;
    }
    (passed, looked)
}

fn passes_only_empty_samples<I: Interp>(
    interp: &I,
    object: &Object,
    skipper: &Skipper<'_>,
    rays: &[Ray],
) -> (u64, u64) {
    let (mut passed, mut looked) = (0, 0);
    for ray in rays {
        let Some((t0, t1)) = object.placement().segment(ray) else { continue };
        let Some(line) = object.placement().walk(ray, t0, t1, object.sampling_distance()).line() else { continue };
        let base_cell = |j: u64| cell_of(interp.base(&interp.locate(line.point(j))));
        let empty = |j: u64| skipper.is_empty(interp, Level::Fine, base_cell(j));
        let jumps = Jumps::new(interp, &line);
        let mut k = 0;
        while k < line.len() {
            looked += 1;
            if empty(k) {
                let next = jumps.skip(interp, skipper, k, base_cell(k));
                assert!(next > k);
                for j in k + 1..next.min(line.len()) {
                    assert!(empty(j), "sample {j} of {} jumped over from {k} is based in a non-empty cell", line.len());
                    passed += 1;
                }
                k = next;
            } else {
                k += 1;
            }
        }
    }
    (passed, looked)
}

fn jump_case(dims: [u64; 3], extent: Extent, rarity: u64, seed: u64) {
    let dims = Dims::new(dims).unwrap();
    let vol = volume(dims, vec![(ChannelName::Voxel, Channel::from_f32(&sparse(dims, seed, rarity), dims).unwrap())]);
    let (size, at) = (2.0, DVec3::new(-1.0, -0.5, -1.5));
    let rays = rays(size, at, 30);
    let mut passed = 0;
    for interp in [Interpolation::Nearest, Interpolation::Trilinear, Interpolation::Cubic] {
        let o = object(colour_ramp(), opacity_ramp(), interp, affine(size, at), extent, dims);
        passed += match interp {
            Interpolation::Nearest => jumps_pass_only_empty_samples(&Nearest::new(dims), &o, &vol, &rays).0,
            Interpolation::Cubic => jumps_pass_only_empty_samples(&Cubic::new(dims), &o, &vol, &rays).0,
            _ => jumps_pass_only_empty_samples(&Linear::new(dims, Identity), &o, &vol, &rays).0,
        };
        let (skipped, all) = casts_agree(&o, &vol, true, &rays);
        assert!(skipped <= all);
    }
    assert!(passed > 0, "the case must exercise jumps");
}

#[test]
fn cells_classified_at_bind_are_those_classified_on_entry() {
    // Bind packs every cell's answer into words of 64 bits, then leaps read them: axes here
    // that are neither multiples of a cell nor of 64 cells, at both levels.
    for (dims, seed) in [([99u64, 91, 79], 6u64), ([13, 9, 17], 7)] {
        let dims = Dims::new(dims).unwrap();
        let vol = volume(dims, vec![(ChannelName::Voxel, Channel::from_f32(&sparse(dims, seed, 17), dims).unwrap())]);
        let cells = vol.macrocells(ChannelName::Voxel).unwrap();
        for interp in [Interpolation::Trilinear, Interpolation::Cubic] {
            let o = object(colour_ramp(), opacity_ramp(), interp, affine(1.0, DVec3::ZERO), Extent::FULL, dims);
            let on_entry = Skipper::new(cells, ChannelName::Voxel, o.opacity().zero_set(), false).unwrap();
            let at_bind = Skipper::new(cells, ChannelName::Voxel, o.opacity().zero_set(), false).unwrap();
            let (mut empty, mut not) = (0, 0);
            let mut check = |classify: &dyn Fn(Level, [u32; 3]) -> bool, entry: &dyn Fn(Level, [u32; 3]) -> bool| {
                for level in [Level::Fine, Level::Coarse] {
                    let [nx, ny, nz] = cells.cells(level);
                    for c in (0..nz).flat_map(|z| (0..ny).flat_map(move |y| (0..nx).map(move |x| [x, y, z]))) {
                        let e = entry(level, c);
                        assert_eq!(classify(level, c), e, "{interp:?}, {level:?} cell {c:?} of {dims:?}");
                        if e {
                            empty += 1;
                        } else {
                            not += 1;
                        }
                    }
                }
            };
            match interp {
                Interpolation::Cubic => {
                    let i = Cubic::new(dims);
                    let at_bind = at_bind.classified(&i);
                    check(&|l, c| at_bind.is_empty(&i, l, c), &|l, c| on_entry.is_empty(&i, l, c));
                }
                _ => {
                    let i = Linear::new(dims, Identity);
                    let at_bind = at_bind.classified(&i);
                    check(&|l, c| at_bind.is_empty(&i, l, c), &|l, c| on_entry.is_empty(&i, l, c));
                }
            }
            assert!(empty > 0 && not > 0, "{interp:?}: {empty} empty, {not} not");
        }
    }
}

#[test]
fn jumps_pass_only_empty_samples_at_dataset_borders() {
    // Axes that are not multiples of the cell (a last cell of one voxel: 13 = 3·4 + 1), a
    // single-voxel axis, and data only in the outermost voxels.
    jump_case([13, 9, 17], Extent::FULL, 7, 3);
    jump_case([41, 1, 6], Extent::FULL, 5, 4);
    let dims = Dims::new([21, 14, 10]).unwrap();
    let [nx, ny, nz] = dims.as_array().map(|n| n as usize);
    let mut v = vec![0.0f32; nx * ny * nz];
    for k in 0..nz {
        for j in 0..ny {
            v[dims.index(nx - 1, j, k)] = 180.0;
            v[dims.index(0, j, k)] = if (j + k) % 3 == 0 { 90.0 } else { 0.0 };
        }
    }
    let vol = volume(dims, vec![(ChannelName::Voxel, Channel::from_f32(&v, dims).unwrap())]);
    let (size, at) = (1.0, DVec3::ZERO);
    for interp in [Interpolation::Nearest, Interpolation::Trilinear, Interpolation::Cubic] {
        let o = object(colour_ramp(), opacity_ramp(), interp, affine(size, at), Extent::FULL, dims);
        let (skipped, all) = casts_agree(&o, &vol, false, &rays(size, at, 30));
        assert!(skipped < all, "{interp:?}: the empty middle must be skipped");
        // The border layers are seen: some ray is not clear.
        let ray = Ray { origin: DVec3::new(-1.0, 0.5, 0.5), dir: DVec3::X };
        let (t0, t1) = o.placement().segment(&ray).unwrap();
        assert!(ObjectCaster::new(&o, &vol, false).unwrap().cast(&ray, t0, t1, 0.0, 1.0).rgba.alpha > 0.0);
    }
}

#[test]
fn jumps_pass_only_empty_samples_in_extent_sub_boxes() {
    // The extent stretches part of the dataset over the box; cells outside it are never
    // sampled, cells at its faces are read by samples just inside.
    let extent = Extent { min: DVec3::new(0.2, 0.05, 0.5), max: DVec3::new(0.7, 0.9, 0.95) };
    jump_case([24, 20, 16], extent, 6, 5);
    // Data only just outside the extent: interpolation at its faces still reads it.
    let dims = Dims::new([16, 16, 16]).unwrap();
    let mut v = vec![0.0f32; 16 * 16 * 16];
    for k in 0..16 {
        for j in 0..16 {
            v[dims.index(3, j, k)] = 200.0; // NVC x of voxel 3 = 3.5/16 ≈ 0.22
        }
    }
    let vol = volume(dims, vec![(ChannelName::Voxel, Channel::from_f32(&v, dims).unwrap())]);
    let extent = Extent { min: DVec3::new(0.25, 0.0, 0.0), max: DVec3::new(0.75, 1.0, 1.0) };
    let o = object(colour_ramp(), opacity_ramp(), Interpolation::Trilinear, affine(1.0, DVec3::ZERO), extent, dims);
    // Steps of 0.08 voxel, so that the first samples lie between the face (VC 3.5) and VC 4,
    // in the cell [3, 4] whose lower corner is voxel 3.
    let o = respecified(&o, Interpolation::Trilinear, 0.01);
    let (size, at) = (1.0, DVec3::ZERO);
    let (skipped, all) = casts_agree(&o, &vol, true, &rays(size, at, 30));
    assert!(skipped < all);
    let ray = Ray { origin: DVec3::new(-1.0, 0.5, 0.5), dir: DVec3::X };
    let (t0, t1) = o.placement().segment(&ray).unwrap();
    let r = ObjectCaster::new(&o, &vol, true).unwrap().cast(&ray, t0, t1, 0.0, 1.0);
    assert!(r.rgba.alpha > 0.0, "voxel 3, outside the extent, is read by samples at its face");
}

#[test]
fn distorted_boxes_skip_sample_by_sample_and_cast_alike() {
    let dims = Dims::new([18, 14, 12]).unwrap();
    let vol = volume(dims, vec![(ChannelName::Voxel, Channel::from_f32(&sparse(dims, 11, 8), dims).unwrap())]);
    let mut corners: [DVec3; 8] =
        std::array::from_fn(|i| DVec3::new((i & 1) as f64, (i >> 1 & 1) as f64, (i >> 2 & 1) as f64));
    corners[7] += DVec3::new(0.3, 0.25, 0.2);
    corners[2] += DVec3::new(-0.15, 0.1, 0.0);
    let hex = Hexahedron::new(corners).unwrap();
    for straight in [false, true] {
        let shape = Shape::Distorted { hex: Box::new(hex.clone()), straight };
        let o = object(colour_ramp(), opacity_ramp(), Interpolation::Trilinear, shape, Extent::FULL, dims);
        let ray = Ray { origin: DVec3::new(0.5, 0.5, -2.0), dir: DVec3::Z };
        let (t0, t1) = o.placement().segment(&ray).unwrap();
        // Exact inversion has no straight line to jump along; the straight mode has one.
        assert_eq!(o.placement().walk(&ray, t0, t1, 0.0).line().is_some(), straight);
        let (skipped, all) = casts_agree(&o, &vol, true, &rays(1.3, DVec3::ZERO, 30));
        assert!(skipped < all, "straight = {straight}: {skipped} of {all}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Random sparse volumes, extents and lines, at sample steps from far below a voxel
    /// to several voxels.
    #[test]
    fn jumps_never_pass_a_sample_of_a_non_empty_cell(
        dims in prop::array::uniform3(1u64..30),
        seed in 0u64..1000,
        rarity in 2u64..40,
        lo in prop::array::uniform3(0.0f64..0.45),
        width in prop::array::uniform3(0.3f64..0.55),
        origin in prop::array::uniform3(-3.0f64..3.0),
        target in prop::array::uniform3(0.0f64..1.0),
        step in prop::sample::select(vec![0.0, 0.002, 0.013, 0.05, 0.31]),
    ) {
        let dims = Dims::new(dims).unwrap();
        let vol = volume(dims, vec![(ChannelName::Voxel, Channel::from_f32(&sparse(dims, seed, rarity), dims).unwrap())]);
        let extent = Extent { min: DVec3::from(lo), max: DVec3::from(lo) + DVec3::from(width) };
        let o = object(colour_ramp(), opacity_ramp(), Interpolation::Trilinear, affine(1.0, DVec3::ZERO), extent, dims);
        let o = respecified(&o, Interpolation::Trilinear, step);
        let origin = DVec3::from(origin);
        let ray = Ray { origin, dir: (DVec3::from(target) - origin).normalize() };
        jumps_pass_only_empty_samples(&Linear::new(dims, Identity), &o, &vol, &[ray]);
        let o = respecified(&o, Interpolation::Nearest, step);
        jumps_pass_only_empty_samples(&Nearest::new(dims), &o, &vol, &[ray]);
        casts_agree(&o, &vol, true, &[ray]);
    }
}

#[test]
fn lines_through_integer_planes_jump_exactly() {
    // Rays along voxel and cell faces (coordinates exactly integral, where the snapping
    // rule moves samples across cell bounds) and along cell edges and corners.
    let dims = Dims::new([16, 16, 16]).unwrap();
    let vol = volume(dims, vec![(ChannelName::Voxel, Channel::from_f32(&sparse(dims, 5, 6), dims).unwrap())]);
    let o = object(
        colour_ramp(),
        opacity_ramp(),
        Interpolation::Trilinear,
        affine(16.0, DVec3::splat(-0.5)),
        Extent::FULL,
        dims,
    );
    // With this box, world = VC: voxel i at world i.
    let mut rays = Vec::new();
    for a in [0.0, 1.0, 3.0, 4.0, 3.5, 7.999_999_999_9, 8.0, 12.0] {
        for b in [0.0, 4.0, 5.0, 3.999_999_999_99] {
            rays.push(Ray { origin: DVec3::new(-3.0, a, b), dir: DVec3::X });
            rays.push(Ray { origin: DVec3::new(a, -3.0, b), dir: DVec3::Y });
            rays.push(Ray { origin: DVec3::new(-3.0, a - 3.0, b), dir: DVec3::new(1.0, 1.0, 0.0).normalize() });
            rays.push(Ray { origin: DVec3::new(-4.0, a - 4.0, b - 4.0), dir: DVec3::ONE.normalize() });
        }
    }
    let (passed, _) = jumps_pass_only_empty_samples(&Linear::new(dims, Identity), &o, &vol, &rays);
    assert!(passed > 0);
    casts_agree(&o, &vol, false, &rays);
}

#[test]
fn macrocell_ranges_are_counted_in_both_byte_lengths() {
    let dims = Dims::new([20, 9, 5]).unwrap();
    let vol = volume(
        dims,
        vec![
            (ChannelName::Voxel, Channel::from_f32(&sparse(dims, 1, 3), dims).unwrap()),
            (ChannelName::Alpha, Channel::from_u8(vec![1; 900], dims).unwrap()),
            (ChannelName::Red, Channel::from_u8(vec![1; 900], dims).unwrap()),
        ],
    );
    // voxel and alpha have ranges; red does not.
    assert_eq!(vol.byte_len(), 900 * 4 + 900 + 900 + 2 * Macrocells::byte_len(dims));
    assert!(vol.macrocells(ChannelName::Red).is_none());
}

#[test]
fn a_line_of_samples_is_the_walk_it_came_from() {
    let dims = Dims::new([10, 10, 10]).unwrap();
    let o =
        object(colour_ramp(), opacity_ramp(), Interpolation::Trilinear, affine(1.0, DVec3::ZERO), Extent::FULL, dims);
    let ray = Ray { origin: DVec3::new(0.3, 0.4, -1.0), dir: DVec3::new(0.1, 0.05, 1.0).normalize() };
    let (t0, t1) = o.placement().segment(&ray).unwrap();
    let walk = o.placement().walk(&ray, t0, t1, 0.0);
    let line: LineSamples = walk.line().unwrap();
    let points: Vec<[f64; 3]> = o.placement().walk(&ray, t0, t1, 0.0).map(|(vc, _)| vc.unwrap()).collect();
    assert_eq!(points.len() as u64, line.len());
    for (k, p) in points.iter().enumerate() {
        assert_eq!(*p, line.point(k as u64));
    }
}

#[test]
fn values_near_a_lut_bound_are_classified_as_the_f64_loop_classifies_them() {
    // f32 positions are off the f64 ones by about 1e-7 of their coordinates, so a value
    // within that much (times the gradient) of a bound where the map jumps could fall on
    // the bound's other side in f32; about one sample in a thousand here, over long rays
    // through a steep field and sixteen bounds. Opacities are faint, so that every sample
    // counts, and a sample classified across a bound would change its piece by ~1e-3.
    let dims = Dims::new([240, 7, 6]).unwrap();
    let values: Vec<f32> = (0..dims.voxel_count() as usize)
        .map(|i| ((i % 240) * 37 + (i / 240 % 7) * 11 + (i / (240 * 7)) * 5) as f32 % 250.0)
        .collect();
    let vol = volume(dims, vec![(ChannelName::Voxel, channel(VoxelType::U8, Endian::Little, &values, dims))]);
    let bounds: Vec<f64> = (1..=16).map(|i| 14.5 * i as f64 + 0.25).collect();
    let opacity = OpacityMap::Lut(Lut::new(bounds.clone(), (0..17).map(|i| 0.001 + 0.0004 * i as f64).collect()));
    let colour =
        ColourMap::Lut(Lut::new(bounds, (0..17).map(|i| [i as f64 / 16.0, 1.0 - i as f64 / 16.0, 0.5]).collect()));
    let (size, at) = (1.0, DVec3::new(-0.5, -0.5, -0.5));
    let o = object(colour, opacity, Interpolation::Trilinear, affine(size, at), Extent::FULL, dims);
    let o = respecified(&o, Interpolation::Trilinear, 1.0 / 600.0);
    let rays: Vec<Ray> = (0..60)
        .map(|i| {
            let t = i as f64 / 60.0;
            Ray {
                origin: DVec3::new(-1.0, -0.4 + 0.8 * t, 0.3 - 0.5 * t),
                dir: DVec3::new(1.0, 0.05 - 0.1 * t, 0.02 + 0.03 * t),
            }
        })
        .collect();
    casts_agree(&o, &vol, false, &rays);
    assert!(ObjectCaster::new(&o, &vol, false).unwrap().casts_packets());
}

#[test]
fn binding_on_a_path_the_processor_lacks_is_refused() {
    let dims = Dims::new([9, 8, 7]).unwrap();
    let values = sparse(dims, 3, 4);
    let vol = volume(dims, vec![(ChannelName::Voxel, channel(VoxelType::U8, Endian::Little, &values, dims))]);
    let (size, at) = (1.0, DVec3::new(-0.5, -0.5, -0.5));
    let o = object(colour_ramp(), opacity_ramp(), Interpolation::Trilinear, affine(size, at), Extent::FULL, dims);
    for path in SimdPath::ALL {
        match ObjectCaster::on_path(&o, &vol, false, CastOptions::default(), path) {
            Ok(caster) => {
                assert!(path.is_available());
                assert_eq!(caster.packet_path(), Some(path));
                assert_eq!(caster.uses_avx2(), matches!(path, SimdPath::Avx2 | SimdPath::Avx512));
            }
            Err(BindError::Simd(SimdError::Unavailable { path: refused, .. })) => {
                assert!(!path.is_available() && refused == path);
            }
            Err(e) => panic!("{path}: {e}"),
        }
    }
}
