//! The compact wire forms of a batch of [`PieceTask`]s and of its [`PieceRgba`] results:
//! what a farm sends to a worker and gets back. Lossless — a decoded task or result is
//! bit for bit the one encoded, which is what keeps farm images equal to local ones.
//!
//! # Why not the 24 and 16 bytes of the in-memory forms
//! The farm's traffic is per piece, and most of a piece's bytes are predictable: a
//! batch's tasks come in ray order, so the pixel index is a small step from the previous
//! task's; scenes have few objects; and pieces of air yield exactly zero. So a task is
//! written as a varint step of its ray, a varint object index, its 16-bit front and its
//! two f64 bounds (typically 20 bytes), and the results as a presence bitmap over the
//! batch followed by the non-zero results only (16 bytes each, 1 bit for a zero one).
//! Decoding is strict: any byte string that is not exactly such an encoding is refused
//! with a [`WireError`], never a panic (a worker's input comes from the network).

use thiserror::Error;

use super::workunit::{PieceRgba, PieceTask, RESULT_BYTES};

/// Why bytes are not a batch's wire form.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum WireError {
    /// The bytes end inside an item.
    #[error("the bytes end inside item {item} (of {expected})")]
    Truncated {
        /// Index of the item being read.
        item: usize,
        /// Items announced.
        expected: usize,
    },
    /// A varint is longer than its type allows, or a value does not fit its field.
    #[error("item {item}: `{field}` is out of range")]
    OutOfRange {
        /// Index of the item being read.
        item: usize,
        /// The field.
        field: &'static str,
    },
    /// Bytes remain after the announced items.
    #[error("{0} bytes remain after the last item")]
    Trailing(usize),
    /// More items are announced than the bytes could possibly hold.
    #[error("{count} items announced in {bytes} bytes")]
    CountTooLarge {
        /// Items announced.
        count: u64,
        /// Bytes given.
        bytes: usize,
    },
}

/// Writes `tasks` in their wire form.
pub fn encode_tasks(tasks: &[PieceTask]) -> Vec<u8> {
    let mut out = Vec::with_capacity(tasks.len() * 20 + 5);
    put_varint(&mut out, tasks.len() as u64);
    let mut ray = 0u32;
    for t in tasks {
        put_task(&mut out, &mut ray, t);
    }
    out
}

/// The most bytes one task takes on the wire: a ray step of up to 33 bits (5 bytes), an
/// object of 16 bits (3), the front (2) and the bounds (16).
const MAX_TASK_BYTES: usize = 5 + 3 + 2 + 16;

/// Room left before the tasks for the count, which is known only at the end: a varint of
/// up to 64 bits.
const COUNT_ROOM: usize = 10;

/// Appends task `t` (after a task of ray `ray`, which it updates) in [`encode_tasks`]' form.
///
/// The task's widest form is zeroed in place at the end of `out`, its fields written over
/// it, and the rest cut back: every byte is stored once where it stays. Building it in a
/// buffer on the stack and copying that (as this did) loaded sixteen bytes that had just
/// been stored as a 2-, an 8- and an 8-byte piece, which the processor cannot forward from
/// its store buffer: a stall on every task, a quarter of `next_batch_encoded`'s time
/// (BENCHMARKS.md, issue 21). A copy of the task's own length instead of a fixed size
/// would be a call to memcpy (2% of the coordinator's CPU, measured earlier).
#[inline]
fn put_task(out: &mut Vec<u8>, ray: &mut u32, t: &PieceTask) {
    let len = out.len();
    out.resize(len + MAX_TASK_BYTES, 0);
    let buf = &mut out[len..];
    let mut n = put_varint_into(buf, 0, zigzag(t.ray as i64 - *ray as i64));
    *ray = t.ray;
    n = put_varint_into(buf, n, t.object as u64);
    buf[n..n + 2].copy_from_slice(&t.front.to_le_bytes());
    buf[n + 2..n + 10].copy_from_slice(&t.t0.to_le_bytes());
    buf[n + 10..n + 18].copy_from_slice(&t.t1.to_le_bytes());
    out.truncate(len + n + 18);
}

/// Tasks written one at a time, as they are decided, into [`encode_tasks`]' form: the
/// bytes are those `encode_tasks` makes of the same tasks, with no list of tasks between.
pub struct TaskWriter {
    out: Vec<u8>,
    count: u64,
    ray: u32,
}

impl TaskWriter {
    /// A writer with room for `tasks` tasks.
    pub fn with_capacity(tasks: usize) -> TaskWriter {
        let mut out = Vec::with_capacity(COUNT_ROOM + tasks * MAX_TASK_BYTES);
        out.resize(COUNT_ROOM, 0);
        TaskWriter { out, count: 0, ray: 0 }
    }

    /// Appends `task`.
    #[inline]
    pub fn push(&mut self, task: &PieceTask) {
        put_task(&mut self.out, &mut self.ray, task);
        self.count += 1;
    }

    /// Makes room for `tasks` more tasks.
    pub fn reserve(&mut self, tasks: usize) {
        self.out.reserve(tasks * MAX_TASK_BYTES);
    }

    /// Tasks written so far.
    pub fn len(&self) -> usize {
        self.count as usize
    }

    /// Whether no task is written.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Forgets every task written, keeping the buffer.
    pub fn clear(&mut self) {
        self.out.truncate(COUNT_ROOM);
        (self.count, self.ray) = (0, 0);
    }

    /// The buffer, and where the encoding starts in it: `buf[start..]` is what
    /// [`encode_tasks`] makes of the tasks written (the count goes just before them).
    pub fn finish(mut self) -> (Vec<u8>, usize) {
        let mut count = [0u8; COUNT_ROOM];
        let n = put_varint_into(&mut count, 0, self.count);
        let start = COUNT_ROOM - n;
        self.out[start..COUNT_ROOM].copy_from_slice(&count[..n]);
        (self.out, start)
    }
}

/// Reads tasks written by [`encode_tasks`]. Whether each task makes sense for a scene
/// (object index, bounds) is [`super::BatchCaster`]'s to check.
pub fn decode_tasks(bytes: &[u8]) -> Result<Vec<PieceTask>, WireError> {
    let mut r = Reader { bytes, at: 0, item: 0, expected: 0 };
    // A task takes at least 1 + 1 + 2 + 16 bytes.
    let count = r.count(20)?;
    let mut tasks = Vec::with_capacity(count);
    let mut ray = 0u32;
    for item in 0..count {
        r.item = item;
        let step = unzigzag(r.varint()?);
        ray = (ray as i64)
            .checked_add(step)
            .and_then(|r| u32::try_from(r).ok())
            .ok_or(WireError::OutOfRange { item, field: "ray" })?;
        let object = u16::try_from(r.varint()?).map_err(|_| WireError::OutOfRange { item, field: "object" })?;
        let front = u16::from_le_bytes(r.array()?);
        let t0 = f64::from_le_bytes(r.array()?);
        let t1 = f64::from_le_bytes(r.array()?);
        tasks.push(PieceTask { t0, t1, ray, object, front });
    }
    r.finish()?;
    Ok(tasks)
}

/// Writes `results` in their wire form.
pub fn encode_results(results: &[PieceRgba]) -> Vec<u8> {
    let mut out = Vec::with_capacity(results.len().div_ceil(8) + 5);
    put_varint(&mut out, results.len() as u64);
    for group in results.chunks(8) {
        let mask = group.iter().enumerate().fold(0u8, |m, (i, r)| if is_zero(r) { m } else { m | 1 << i });
        out.push(mask);
        for r in group.iter().filter(|r| !is_zero(r)) {
            for v in r.colour.iter().chain([&r.alpha]) {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    out
}

/// Reads results written by [`encode_results`].
pub fn decode_results(bytes: &[u8]) -> Result<Vec<PieceRgba>, WireError> {
    let mut r = Reader { bytes, at: 0, item: 0, expected: 0 };
    // Eight results take at least their mask byte.
    let count = r.count_with(|bytes| bytes.saturating_mul(8))?;
    let mut results = Vec::with_capacity(count);
    while results.len() < count {
        r.item = results.len();
        let mask = r.array::<1>()?[0];
        let group = (count - results.len()).min(8);
        if (mask as u16) >> group != 0 {
            return Err(WireError::OutOfRange { item: results.len(), field: "mask" });
        }
        for i in 0..group {
            if mask & 1 << i == 0 {
                results.push(PieceRgba::default());
            } else {
                r.item = results.len();
                let b: [u8; RESULT_BYTES] = r.array()?;
                let at = |k: usize| f32::from_le_bytes([b[k * 4], b[k * 4 + 1], b[k * 4 + 2], b[k * 4 + 3]]);
                results.push(PieceRgba { colour: [at(0), at(1), at(2)], alpha: at(3) });
            }
        }
    }
    r.finish()?;
    Ok(results)
}

/// Exactly zero in every bit (a `-0.0` is sent as it is, so decoding is bit-exact).
fn is_zero(r: &PieceRgba) -> bool {
    r.colour.iter().chain([&r.alpha]).all(|v| v.to_bits() == 0)
}

fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

fn unzigzag(v: u64) -> i64 {
    (v >> 1) as i64 ^ -((v & 1) as i64)
}

/// [`put_varint`] into `buf` at `at`; returns where it ends.
#[inline]
fn put_varint_into(buf: &mut [u8], mut at: usize, mut v: u64) -> usize {
    while v >= 0x80 {
        buf[at] = v as u8 | 0x80;
        v >>= 7;
        at += 1;
    }
    buf[at] = v as u8;
    at + 1
}

/// LEB128: seven bits a byte, low first.
fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push(v as u8 | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
    item: usize,
    expected: usize,
}

impl Reader<'_> {
    fn truncated(&self) -> WireError {
        WireError::Truncated { item: self.item, expected: self.expected }
    }

    fn varint(&mut self) -> Result<u64, WireError> {
        let mut v = 0u64;
        for shift in (0..64).step_by(7) {
            let byte = *self.bytes.get(self.at).ok_or_else(|| self.truncated())?;
            self.at += 1;
            let bits = (byte & 0x7f) as u64;
            if shift == 63 && bits > 1 {
                break;
            }
            v |= bits << shift;
            if byte & 0x80 == 0 {
                return Ok(v);
            }
        }
        Err(WireError::OutOfRange { item: self.item, field: "varint" })
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], WireError> {
        let end = self.at.checked_add(N).filter(|&e| e <= self.bytes.len()).ok_or_else(|| self.truncated())?;
        let a = self.bytes[self.at..end].try_into().map_err(|_| self.truncated())?;
        self.at = end;
        Ok(a)
    }

    /// The leading item count, refused when `min_bytes` per item could not fit.
    fn count(&mut self, min_bytes: usize) -> Result<usize, WireError> {
        self.count_with(|bytes| bytes / min_bytes)
    }

    fn count_with(&mut self, most: impl Fn(usize) -> usize) -> Result<usize, WireError> {
        let count = self.varint()?;
        let bytes = self.bytes.len();
        match usize::try_from(count) {
            Ok(c) if c <= most(bytes) => {
                self.expected = c;
                Ok(c)
            }
            _ => Err(WireError::CountTooLarge { count, bytes }),
        }
    }

    fn finish(&self) -> Result<(), WireError> {
        match self.bytes.len() - self.at {
            0 => Ok(()),
            n => Err(WireError::Trailing(n)),
        }
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    fn task() -> impl Strategy<Value = PieceTask> {
        (any::<u32>(), any::<u16>(), any::<u16>(), any::<f64>(), any::<f64>())
            .prop_map(|(ray, object, front, t0, t1)| PieceTask { t0, t1, ray, object, front })
    }

    fn result() -> impl Strategy<Value = PieceRgba> {
        let v = prop_oneof![Just(0.0f32), Just(-0.0f32), any::<f32>()];
        (v.clone(), v.clone(), v.clone(), v).prop_map(|(r, g, b, a)| PieceRgba { colour: [r, g, b], alpha: a })
    }

    /// Bit patterns, so NaNs and signed zeros compare exactly.
    fn task_bits(t: &PieceTask) -> (u64, u64, u32, u16, u16) {
        (t.t0.to_bits(), t.t1.to_bits(), t.ray, t.object, t.front)
    }

    fn result_bits(r: &PieceRgba) -> [u32; 4] {
        [r.colour[0].to_bits(), r.colour[1].to_bits(), r.colour[2].to_bits(), r.alpha.to_bits()]
    }

    proptest! {
        #[test]
        fn tasks_round_trip_bit_for_bit(tasks in prop::collection::vec(task(), 0..200)) {
            let back = decode_tasks(&encode_tasks(&tasks)).unwrap();
            prop_assert_eq!(back.iter().map(task_bits).collect::<Vec<_>>(), tasks.iter().map(task_bits).collect::<Vec<_>>());
        }

        #[test]
        fn tasks_written_one_at_a_time_are_the_bytes_of_encode_tasks(
            tasks in prop::collection::vec(task(), 0..200),
            first in prop::collection::vec(task(), 0..5),
        ) {
            let mut writer = TaskWriter::with_capacity(1);
            // A writer cleared after some tasks starts again from nothing.
            for t in &first {
                writer.push(t);
            }
            writer.clear();
            for t in &tasks {
                writer.push(t);
            }
            prop_assert_eq!(writer.len(), tasks.len());
            let (buf, start) = writer.finish();
            prop_assert_eq!(&buf[start..], &encode_tasks(&tasks)[..]);
        }

        #[test]
        fn results_round_trip_bit_for_bit(results in prop::collection::vec(result(), 0..200)) {
            let back = decode_results(&encode_results(&results)).unwrap();
            prop_assert_eq!(back.iter().map(result_bits).collect::<Vec<_>>(), results.iter().map(result_bits).collect::<Vec<_>>());
        }

        #[test]
        fn any_bytes_decode_or_are_refused_without_panicking(bytes in prop::collection::vec(any::<u8>(), 0..300)) {
            let _ = decode_tasks(&bytes);
            let _ = decode_results(&bytes);
        }

        #[test]
        fn a_cut_or_extended_encoding_is_refused(tasks in prop::collection::vec(task(), 1..50), cut in 1usize..20) {
            let bytes = encode_tasks(&tasks);
            prop_assert!(decode_tasks(&bytes[..bytes.len() - cut.min(bytes.len())]).is_err());
            let mut longer = bytes.clone();
            longer.push(0);
            prop_assert_eq!(decode_tasks(&longer), Err(WireError::Trailing(1)));
        }
    }

    #[test]
    fn tasks_in_ray_order_take_20_bytes_and_zero_results_one_bit() {
        let tasks: Vec<PieceTask> = (0..1000).map(|i| PieceTask::new(i, 3, 1.0, 2.0, false)).collect();
        assert_eq!(encode_tasks(&tasks).len(), 2 + 1000 * 20);
        let mut results = vec![PieceRgba::default(); 1000];
        results[7] = PieceRgba { colour: [0.5, 0.25, 0.0], alpha: 0.5 };
        assert_eq!(encode_results(&results).len(), 2 + 125 + 16);
    }

    #[test]
    fn a_huge_count_is_refused_before_allocating() {
        let mut bytes = Vec::new();
        put_varint(&mut bytes, u64::MAX);
        assert!(matches!(decode_tasks(&bytes), Err(WireError::CountTooLarge { .. })));
        assert!(matches!(decode_results(&bytes), Err(WireError::CountTooLarge { .. })));
    }
}
