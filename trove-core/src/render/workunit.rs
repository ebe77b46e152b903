//! The work units of Algorithm 2, shaped for the wire: what the intersection phase hands
//! to the volume-rendering phase, and what comes back (paper §3.3, lines 10–18).
//!
//! A [`PieceTask`] is one object over one piece of one ray: 24 bytes. It does not carry
//! the ray — whoever casts it recomputes the ray from the camera and the pixel index
//! (SPEC §4.1 is deterministic), and looks the object up in the scene it already holds.
//! A [`PieceRgba`] is what casting it yields: 16 bytes of premultiplied colour and opacity.
//! Tasks are independent of each other, so any slice of them whose objects share one
//! dataset is a batch that can be cast anywhere that dataset is resident
//! ([`cast_batch`]); results come back in the same order, so a batch needs no ids.
//!
//! # Why f32 results are enough
//! A piece's colour and opacity lie in [0, 1]; rounding them to f32 changes each by at most
//! 2⁻²⁴ relative. Compositing a ray's pieces multiplies and adds such values, so a pixel
//! moves by at most about (pieces on the ray) × 6·10⁻⁸ — some 10⁻⁶ for a ray through a
//! dozen pieces, four orders of magnitude below one 8-bit level (1/255 ≈ 3.9·10⁻³) and at
//! the precision of the PFM output itself (f32). `tests/tests/algorithms.rs` checks it.
//!
//! # Why the front opacity is 16 bits
//! A task also carries what the scheduler knows of the ray's opacity in front of the piece,
//! so the cast can stop early inside the piece (SPEC §4.5). It is only ever a *lower bound*
//! (pieces in front may not be cast yet), and a lower bound may be rounded down freely: the
//! cast then takes at most a sample more, never fewer. So it is stored as a 16-bit fraction
//! rounded down, which keeps the task at 24 bytes.

use crate::composite::Rgba;
use crate::dataset::Volume;
use crate::sampling::ObjectCaster;
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

/// Bytes of one task on the wire and in memory.
pub const TASK_BYTES: usize = std::mem::size_of::<PieceTask>();
/// Bytes of one result on the wire and in memory.
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

    /// The `stop_at` argument of [`ObjectCaster::cast`]: the scene's termination, or ∞ for a
    /// shared piece.
    pub fn stop_at(&self, termination: f64) -> f64 {
        if self.is_whole() {
            f64::INFINITY
        } else {
            termination
        }
    }

    /// Little-endian wire form.
    pub fn to_bytes(&self) -> [u8; TASK_BYTES] {
        let mut b = [0u8; TASK_BYTES];
        b[0..8].copy_from_slice(&self.t0.to_le_bytes());
        b[8..16].copy_from_slice(&self.t1.to_le_bytes());
        b[16..20].copy_from_slice(&self.ray.to_le_bytes());
        b[20..22].copy_from_slice(&self.object.to_le_bytes());
        b[22..24].copy_from_slice(&self.front.to_le_bytes());
        b
    }

    /// Reads the wire form written by [`PieceTask::to_bytes`].
    pub fn from_bytes(b: &[u8; TASK_BYTES]) -> PieceTask {
        let f64_at = |i: usize| f64::from_le_bytes(b[i..i + 8].try_into().expect("8 bytes"));
        PieceTask {
            t0: f64_at(0),
            t1: f64_at(8),
            ray: u32::from_le_bytes(b[16..20].try_into().expect("4 bytes")),
            object: u16::from_le_bytes([b[20], b[21]]),
            front: u16::from_le_bytes([b[22], b[23]]),
        }
    }
}

impl PieceRgba {
    /// Little-endian wire form.
    pub fn to_bytes(&self) -> [u8; RESULT_BYTES] {
        let mut b = [0u8; RESULT_BYTES];
        for (i, v) in self.colour.iter().chain([&self.alpha]).enumerate() {
            b[i * 4..i * 4 + 4].copy_from_slice(&v.to_le_bytes());
        }
        b
    }

    /// Reads the wire form written by [`PieceRgba::to_bytes`].
    pub fn from_bytes(b: &[u8; RESULT_BYTES]) -> PieceRgba {
        let at = |i: usize| f32::from_le_bytes(b[i * 4..i * 4 + 4].try_into().expect("4 bytes"));
        PieceRgba { colour: [at(0), at(1), at(2)], alpha: at(3) }
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

/// Casts a batch of tasks whose objects all use `volume` (the dataset resident here),
/// writing one result per task into `out`; returns the samples evaluated. The ray of each
/// task is recomputed from `scene`'s camera, exactly as Algorithm 1 computes it.
pub fn cast_batch(scene: &Scene, volume: &Volume, tasks: &[PieceTask], out: &mut [PieceRgba]) -> u64 {
    assert_eq!(tasks.len(), out.len(), "one result per task");
    let (w, h) = (scene.image().width, scene.image().height);
    let (termination, correction) = (scene.render().termination, scene.render().opacity_correction);
    // Casters resolve channel readers once; a batch usually holds few distinct objects.
    let mut casters: Vec<(u16, ObjectCaster)> = Vec::new();
    let mut samples = 0;
    for (task, result) in tasks.iter().zip(out) {
        let slot = match casters.iter().position(|(o, _)| *o == task.object) {
            Some(i) => i,
            None => {
                let object = &scene.objects()[task.object as usize];
                let caster = ObjectCaster::new(object, volume, correction)
                    .unwrap_or_else(|e| panic!("object `{}`: {e}", object.name()));
                casters.push((task.object, caster));
                casters.len() - 1
            }
        };
        let ray = scene.camera().ray(task.ray % w, task.ray / w, w, h);
        let r = casters[slot].1.cast(&ray, task.t0, task.t1, task.front_alpha(), task.stop_at(termination));
        samples += r.samples;
        *result = r.rgba.into();
    }
    samples
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_task_is_24_bytes_and_a_result_16() {
        assert_eq!(TASK_BYTES, 24);
        assert_eq!(RESULT_BYTES, 16);
    }

    #[test]
    fn wire_forms_round_trip() {
        let mut t = PieceTask::new(262_143, 4095, 1.25, 3.5e-3 + 7.0, false);
        t.set_front_alpha(0.3);
        assert_eq!(PieceTask::from_bytes(&t.to_bytes()), t);
        let r = PieceRgba { colour: [0.1, 0.5, 1.0], alpha: 0.75 };
        assert_eq!(PieceRgba::from_bytes(&r.to_bytes()), r);
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
