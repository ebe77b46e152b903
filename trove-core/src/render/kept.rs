//! Lists kept once a band is done, for the next band or render in this process to write:
//! memory the allocator hands out fresh is zero-filled by the kernel page by page as it is
//! first written (a coordinator spent about a tenth of its time in those page faults), and
//! a band's intersections and scheduler hold some 100 bytes a task. Kept memory is written
//! again without the faults. The one pool of both: the intersection's lists (its sub-bands'
//! and a region's, [`super::intersection::recycle`]) and the scheduler's per-task and
//! per-ray lists ([`super::Scheduler::into_intersections`]).
//!
//! A list handed out is empty, or refilled whole ([`filled`]), so nothing a band left
//! shows, except from [`for_overwrite`], whose caller writes every item before it reads
//! one (and so skips a fill that would be overwritten at once). One much longer than asked
//! for is cut down to about the size needed, so that the bytes its holder counts
//! (`Scheduler::heap_bytes`, which memory bounds and the farm simulation's inputs read)
//! stay what it needs. At most [`KEPT_BYTES`] are kept.

use std::any::{Any, TypeId};
use std::sync::{Mutex, MutexGuard, PoisonError};

/// The most bytes of lists kept: a 512² band of the CT head's or Table 1's scene holds
/// some 20–30 MB of them, a farm band of 2¹⁶ pixels a few.
const KEPT_BYTES: usize = 96 << 20;

/// A kept `Vec<T>`, its type and capacity noted.
struct List {
    of: TypeId,
    capacity: usize,
    bytes: usize,
    list: Box<dyn Any + Send>,
}

struct Kept {
    lists: Vec<List>,
    bytes: usize,
}

static KEPT: Mutex<Kept> = Mutex::new(Kept { lists: Vec::new(), bytes: 0 });

fn kept() -> MutexGuard<'static, Kept> {
    // A panic while holding the lock leaves only lists behind, which are emptied anyway.
    KEPT.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Takes out the smallest kept `Vec<T>` with room for `n`, as it was kept. Where none has room,
/// the largest of those without is dropped instead (freed, as a list too small to serve
/// is replaced), so that lists of sizes no band asks for again do not pile up in the pool.
fn take<T: Send + 'static>(n: usize) -> Option<Vec<T>> {
    let mut kept = kept();
    let of = TypeId::of::<Vec<T>>();
    let (mut fit, mut short): (Option<usize>, Option<usize>) = (None, None);
    for (i, l) in kept.lists.iter().enumerate().filter(|(_, l)| l.of == of) {
        let (better, slot) = if l.capacity >= n {
            (fit.is_none_or(|b| l.capacity < kept.lists[b].capacity), &mut fit)
        } else {
            (short.is_none_or(|b| l.capacity > kept.lists[b].capacity), &mut short)
        };
        if better {
            *slot = Some(i);
        }
    }
    let Some(i) = fit else {
        if let Some(i) = short {
            let dropped = kept.lists.swap_remove(i);
            kept.bytes -= dropped.bytes;
        }
        return None;
    };
    let list = kept.lists.swap_remove(i);
    kept.bytes -= list.bytes;
    drop(kept);
    Some(*list.list.downcast::<Vec<T>>().expect("kept under its own type"))
}

/// The smallest kept `Vec<T>` with room for `n`, at most `n` long (its first items as it
/// was kept), cut down to about `n` if it is much longer.
fn take_room<T: Send + 'static>(n: usize) -> Option<Vec<T>> {
    let mut list = take::<T>(n)?;
    list.truncate(n);
    if list.capacity() > n + n / 8 {
        list.shrink_to(n);
    }
    Some(list)
}

/// An empty list with room for `n` items, kept ([`take_room`]) or new: for lists written to
/// `n` items.
pub(super) fn with_room<T: Send + 'static>(n: usize) -> Vec<T> {
    let mut list = take_room(n).unwrap_or_else(|| Vec::with_capacity(n));
    list.clear();
    list
}

/// `n` copies of `value`, in a kept list ([`take_room`]) or a new one.
pub(super) fn filled<T: Clone + Send + 'static>(n: usize, value: T) -> Vec<T> {
    match take_room(n) {
        Some(mut list) => {
            list.clear();
            list.resize(n, value);
            list
        }
        // A new list of zeros is the kernel's zero pages until written.
        None => vec![value; n],
    }
}

/// `n` items for a caller that writes every one before it reads it: a kept list's old
/// items as they are (any bits are a valid `T`: it is `Copy` and was written before), the
/// rest `T::default()`. Saves [`filled`]'s pass over memory that is written again at once
/// (the plan's keys and queue, the scheduler's results: 24 bytes a task, filled and then
/// written; the fills were about 1% of a coordinator's CPU, BENCHMARKS.md).
pub(super) fn for_overwrite<T: Copy + Default + Send + 'static>(n: usize) -> Vec<T> {
    match take_room(n) {
        Some(mut list) => {
            list.resize(n, T::default());
            list
        }
        None => vec![T::default(); n],
    }
}

/// An empty list to grow by pushing, of about `hint` items or more: the smallest kept one
/// with room for `hint` (not cut down: it may grow into it), else a new one that has no
/// room yet (a band whose rays meet nothing then holds nothing).
pub(super) fn growing<T: Send + 'static>(hint: usize) -> Vec<T> {
    let mut list = take::<T>(hint).unwrap_or_default();
    list.clear();
    list
}

/// Keeps `list` for a later [`with_room`], [`filled`], [`for_overwrite`] or [`growing`], as
/// far as there is room.
pub(super) fn keep<T: Send + 'static>(list: Vec<T>) {
    let (capacity, bytes) = (list.capacity(), list.capacity() * size_of::<T>());
    let mut kept = kept();
    if bytes == 0 || kept.bytes + bytes > KEPT_BYTES {
        return;
    }
    kept.bytes += bytes;
    kept.lists.push(List { of: TypeId::of::<Vec<T>>(), capacity, bytes, list: Box::new(list) });
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
            keep(vec![true; len]);
            assert!(filled(n, false).iter().all(|&s| !s));
            keep(vec![[1.0f32; 4]; len]);
            assert_eq!(filled(n, [0.0f32; 4]), vec![[0.0; 4]; n]);
            keep(vec![(3u32, 0.5f64); len]);
            let known = filled(n, (0u32, 0.0f64));
            assert!(known.len() == n && known.iter().all(|&(p, a)| p == 0 && a == 0.0));
            // Lists to write or grow come back empty.
            keep(vec![9u64; len]);
            assert!(with_room::<u64>(n).is_empty() && growing::<u64>(n).is_empty());
        }
    }

    /// A list to overwrite comes back `n` long: a kept list's items where it had them, the
    /// default after (a type of this test's own, so that only this test's lists are seen).
    #[test]
    fn a_list_to_overwrite_keeps_its_items_and_is_as_long_as_asked() {
        #[derive(Clone, Copy, Default, PartialEq, Debug)]
        struct Mine(u32);
        let mut grown = Vec::with_capacity(200);
        grown.extend([Mine(7); 50]);
        keep(grown);
        assert_eq!(for_overwrite::<Mine>(120), [vec![Mine(7); 50], vec![Mine(0); 70]].concat());
        keep(vec![Mine(7); 100]);
        assert_eq!(for_overwrite::<Mine>(60), vec![Mine(7); 60]);
        // Nothing kept has room: a new list.
        keep(vec![Mine(7); 10]);
        assert_eq!(for_overwrite::<Mine>(30), vec![Mine(0); 30]);
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
        keep(Vec::<u16>::with_capacity(1 << 20));
        assert!(with_room::<u16>(1000).capacity() <= 1000 + 1000 / 8);
    }

    /// A list of a size no one asks for again does not stay: a request that no kept list
    /// can serve frees the largest that falls short.
    #[test]
    fn a_list_too_small_to_serve_is_dropped_not_kept() {
        // A type of this test's own, so that no other test's lists mix in.
        #[derive(Clone, Copy)]
        struct Mine(#[allow(dead_code)] u64);
        keep(Vec::<Mine>::with_capacity(10));
        keep(Vec::<Mine>::with_capacity(20));
        // Nothing holds 100: the list of 20 is dropped, the list of 10 stays.
        assert_eq!(with_room::<Mine>(100).capacity(), 100);
        let ten = growing::<Mine>(5);
        assert_eq!(ten.capacity(), 10, "the list of 10 was kept");
        assert_eq!(with_room::<Mine>(15).capacity(), 15, "the list of 20 was dropped");
    }
}
