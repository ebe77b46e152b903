//! The scheduler's per-task and per-ray lists, kept once a region is composited for the
//! next scheduler to write (as [`super::super::intersection::recycle`] keeps the
//! intersection's): memory the allocator hands out fresh is zero-filled by the kernel page
//! by page as it is first written, and a band's lists are some 40 bytes a task; kept lists
//! are written again without those faults. Every list is filled with its starting value
//! before it is used again, so nothing a region left shows in the next.

use std::sync::{Mutex, MutexGuard, PoisonError};

use super::{KnownFront, Status};

/// The most bytes of lists kept.
const KEPT_BYTES: usize = 96 << 20;

/// Lists by element type; `bytes` counts their capacity.
pub(super) struct Kept {
    known: Vec<Vec<KnownFront>>,
    status: Vec<Vec<Status>>,
    results: Vec<Vec<[f32; 4]>>,
    words: Vec<Vec<u32>>,
    bytes: usize,
}

static KEPT: Mutex<Kept> =
    Mutex::new(Kept { known: Vec::new(), status: Vec::new(), results: Vec::new(), words: Vec::new(), bytes: 0 });

fn kept() -> MutexGuard<'static, Kept> {
    // A panic while holding the lock leaves only lists behind, which are refilled anyway.
    KEPT.lock().unwrap_or_else(PoisonError::into_inner)
}

/// A list of element type `T`, as `Kept` stores it.
pub(super) trait Element: Copy + Sized + 'static {
    fn stack(kept: &mut Kept) -> &mut Vec<Vec<Self>>;
}

impl Element for KnownFront {
    fn stack(kept: &mut Kept) -> &mut Vec<Vec<Self>> {
        &mut kept.known
    }
}

impl Element for Status {
    fn stack(kept: &mut Kept) -> &mut Vec<Vec<Self>> {
        &mut kept.status
    }
}

impl Element for [f32; 4] {
    fn stack(kept: &mut Kept) -> &mut Vec<Vec<Self>> {
        &mut kept.results
    }
}

impl Element for u32 {
    fn stack(kept: &mut Kept) -> &mut Vec<Vec<Self>> {
        &mut kept.words
    }
}

fn bytes<T>(list: &Vec<T>) -> usize {
    list.capacity() * size_of::<T>()
}

/// `n` copies of `value`: in the smallest kept list with room for them where there is one
/// (cut down to about `n` if it is much longer, so that a scheduler's
/// [`heap_bytes`](super::Scheduler::heap_bytes), which memory bounds and the farm
/// simulation's inputs count, stays what its own lists need), else in a new one.
pub(super) fn filled<T: Element>(n: usize, value: T) -> Vec<T> {
    let mut kept = kept();
    let stack = T::stack(&mut kept);
    let best = stack.iter().enumerate().filter(|(_, l)| l.capacity() >= n).min_by_key(|(_, l)| l.capacity());
    let Some(i) = best.map(|(i, _)| i) else {
        drop(kept);
        return vec![value; n];
    };
    let mut list = stack.swap_remove(i);
    kept.bytes -= bytes(&list);
    drop(kept);
    list.clear();
    if list.capacity() > n + n / 8 {
        list.shrink_to(n);
    }
    list.resize(n, value);
    list
}

/// Keeps `list` for a later [`filled`], as far as there is room.
pub(super) fn keep<T: Element>(list: Vec<T>) {
    let mut kept = kept();
    let size = bytes(&list);
    if size == 0 || kept.bytes + size > KEPT_BYTES {
        return;
    }
    kept.bytes += size;
    T::stack(&mut kept).push(list);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A kept list comes back holding exactly `n` copies of the value asked for, whatever it
    /// held and however long it was (other tests may take it first: each case holds either
    /// way).
    #[test]
    fn kept_lists_come_back_refilled_whole() {
        for (len, n) in [(100, 60), (60, 60), (10, 200)] {
            keep(vec![7u32; len]);
            assert_eq!(filled(n, 0u32), vec![0; n]);
            keep(vec![Status::Done; len]);
            assert!(filled(n, Status::Pending).iter().all(|&s| s == Status::Pending));
            keep(vec![[1.0f32; 4]; len]);
            assert_eq!(filled(n, [0.0f32; 4]), vec![[0.0; 4]; n]);
            keep(vec![KnownFront { pieces: 3, alpha: 0.5 }; len]);
            let known = filled(n, KnownFront::default());
            assert!(known.len() == n && known.iter().all(|k| k.pieces == 0 && k.alpha == 0.0));
        }
    }

    /// A list much longer than asked for is cut down, so that the bytes a scheduler counts
    /// are about what it needs (other tests may keep lists meanwhile: any list it gets is
    /// within an eighth of `n`, or new).
    #[test]
    fn a_much_longer_kept_list_is_cut_down() {
        keep(vec![0u32; 1 << 20]);
        let list = filled(1000, 0u32);
        assert!(list.capacity() <= 1000 + 1000 / 8, "{}", list.capacity());
        keep(list);
    }
}
