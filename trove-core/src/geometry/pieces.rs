//! Splitting one ray's object segments into pieces (SPEC §4.2): where segments overlap,
//! the union of their end points cuts the ray, and each object contributes to every piece
//! it covers. Objects sharing a piece are then composited as co-located media (§4.4).

/// The part of a ray inside one object: the first and last t ≥ 0 inside its box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    /// Index of the object in the scene.
    pub object: u32,
    /// Entry parameter (world distance from the eye).
    pub t_near: f64,
    /// Exit parameter.
    pub t_far: f64,
}

/// An interval of a ray with the objects covering it, as a range into the cover list that
/// [`split_into_pieces`] fills.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Piece {
    /// Start parameter.
    pub t0: f64,
    /// End parameter, > `t0`.
    pub t1: f64,
    /// Range of this piece's objects in the cover list.
    pub cover: (u32, u32),
}

/// What [`split_into_pieces`] and [`count_pieces`] reuse from ray to ray, so that neither
/// allocates per ray.
#[derive(Clone, Debug, Default)]
pub struct PieceScratch {
    /// Every segment's two end points: (t, segment index, whether it starts there).
    events: Vec<(f64, u32, bool)>,
    /// The segments covering the current window, in segment order.
    active: Vec<u32>,
    /// The segments of non-zero length as (t_near, index), front to back, when none
    /// overlaps another ([`PieceScratch::sort_apart`]).
    apart: Vec<(f64, u32)>,
}

impl PieceScratch {
    /// The end points of `segments` of non-zero length, sorted by t (ties keep no order
    /// that matters: every event at one t is applied before that t's window).
    fn sort_events(&mut self, segments: &[Segment]) {
        self.events.clear();
        for (i, s) in segments.iter().enumerate() {
            if long(s) {
                self.events.push((s.t_near, i as u32, true));
                self.events.push((s.t_far, i as u32, false));
            }
        }
        self.events.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
    }

    /// Whether the segments of non-zero length lie apart (touching at most): then each is
    /// one piece of its own, front to back, which is what the sweep makes of them, and
    /// `apart` lists them in that order. Sorts the segments, not their twice as many end
    /// points, and needs no sweep: rays of a scene of many objects often cross several
    /// that do not overlap (splitting into pieces was a seventh of the instructions of
    /// Table 1's core stages, BENCHMARKS.md).
    fn sort_apart(&mut self, segments: &[Segment]) -> bool {
        self.apart.clear();
        self.apart.extend(segments.iter().zip(0u32..).filter(|(s, _)| long(s)).map(|(s, i)| (s.t_near, i)));
        // Two long segments that start together overlap, and are refused below: any tie
        // order gives the same answer.
        self.apart.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        self.apart.windows(2).all(|w| segments[w[0].1 as usize].t_far <= w[1].0)
    }
}

/// Whether a segment has length: the only ones that make pieces (false for NaN end points).
#[inline]
fn long(s: &Segment) -> bool {
    s.t_far > s.t_near
}

/// Fills `pieces` (front to back) and `cover` (object indices, per piece, in segment order)
/// from one ray's segments. Pieces of zero length are dropped; the buffers are cleared
/// first so a thread can reuse them for every ray.
///
/// Segments that lie apart are their own pieces, found by sorting their starts
/// (`PieceScratch::sort_apart`). Otherwise the end points are swept once in order with
/// the set of segments covering the window kept as it changes. Either way a ray of k
/// segments costs O(k log k) plus its cover, rather than a pass over every segment per
/// piece (k = 4096 disjoint objects on one ray would cost 2k² tests per ray that way).
pub fn split_into_pieces(
    segments: &[Segment],
    scratch: &mut PieceScratch,
    pieces: &mut Vec<Piece>,
    cover: &mut Vec<u32>,
) {
    pieces.clear();
    cover.clear();
    if let Some(disjoint) = apart(segments) {
        disjoint.into_iter().flatten().for_each(|s| push_alone(s, pieces, cover));
        return;
    }
    if scratch.sort_apart(segments) {
        scratch.apart.iter().for_each(|&(_, i)| push_alone(&segments[i as usize], pieces, cover));
        return;
    }
    sweep_into_pieces(segments, scratch, pieces, cover);
}

/// Segment `s` as a piece of its own.
#[inline]
fn push_alone(s: &Segment, pieces: &mut Vec<Piece>, cover: &mut Vec<u32>) {
    cover.push(s.object);
    pieces.push(Piece { t0: s.t_near, t1: s.t_far, cover: (cover.len() as u32 - 1, cover.len() as u32) });
}

/// [`split_into_pieces`] by the sweep alone, for any segments.
fn sweep_into_pieces(segments: &[Segment], scratch: &mut PieceScratch, pieces: &mut Vec<Piece>, cover: &mut Vec<u32>) {
    pieces.clear();
    cover.clear();
    scratch.sort_events(segments);
    let PieceScratch { events, active, .. } = scratch;
    active.clear();
    sweep(events, |t0, t1, event| {
        if let Some((i, starts)) = event {
            // The active set stays in segment order, so cover lists a piece's objects in
            // scene order, as the sampler and the compositor expect.
            let at = active.partition_point(|&a| a < i);
            if starts {
                active.insert(at, i);
            } else if active.get(at) == Some(&i) {
                active.remove(at);
            }
            return;
        }
        if !active.is_empty() {
            let start = cover.len() as u32;
            cover.extend(active.iter().map(|&a| segments[a as usize].object));
            pieces.push(Piece { t0, t1, cover: (start, cover.len() as u32) });
        }
    });
}

/// The number of pieces and of (piece, object) pairs [`split_into_pieces`] would make from
/// `segments`, without storing either: O(k log k) for k segments, however many pairs.
pub fn count_pieces(segments: &[Segment], scratch: &mut PieceScratch) -> (u64, u64) {
    if let Some(disjoint) = apart(segments) {
        let n = disjoint.iter().flatten().count() as u64;
        return (n, n);
    }
    if scratch.sort_apart(segments) {
        let n = scratch.apart.len() as u64;
        return (n, n);
    }
    scratch.sort_events(segments);
    let (mut active, mut pieces, mut pairs) = (0u64, 0u64, 0u64);
    sweep(&scratch.events, |_, _, event| match event {
        Some((_, true)) => active += 1,
        Some((_, false)) => active -= 1,
        None if active > 0 => {
            pieces += 1;
            pairs += active;
        }
        None => {}
    });
    (pieces, pairs)
}

/// Most rays cross at most two objects and most pairs do not overlap: then each segment is
/// one piece of its own, front to back, which is what the sweep makes of them (a shared end
/// point cuts nothing either), without sorting. `None` for every other case, which sweeps.
fn apart(segments: &[Segment]) -> Option<[Option<&Segment>; 2]> {
    let long = |s: &&Segment| long(s);
    match segments {
        [] => Some([None, None]),
        [a] => Some([Some(a).filter(long), None]),
        [a, b] if !long(&a) || !long(&b) => Some([Some(a).filter(long).or(Some(b).filter(long)), None]),
        [a, b] if a.t_far <= b.t_near => Some([Some(a), Some(b)]),
        [a, b] if b.t_far <= a.t_near => Some([Some(b), Some(a)]),
        _ => None,
    }
}

/// Walks sorted `events`: for each distinct t (equal as f64, as `dedup` compares; the first
/// of equal values is the one kept), every event at t as `f(t, t, Some(event))`, then the
/// window up to the next distinct t as `f(t0, t1, None)`.
fn sweep(events: &[(f64, u32, bool)], mut f: impl FnMut(f64, f64, Option<(u32, bool)>)) {
    let mut i = 0;
    while i < events.len() {
        let t0 = events[i].0;
        while i < events.len() && events[i].0 == t0 {
            f(t0, t0, Some((events[i].1, events[i].2)));
            i += 1;
        }
        if let Some(&(t1, _, _)) = events.get(i) {
            f(t0, t1, None);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::numbers;

    fn split(segs: &[(u32, f64, f64)]) -> Vec<(f64, f64, Vec<u32>)> {
        let segs: Vec<Segment> =
            segs.iter().map(|&(object, t_near, t_far)| Segment { object, t_near, t_far }).collect();
        let (mut scratch, mut pieces, mut cover) = (PieceScratch::default(), vec![], vec![]);
        split_into_pieces(&segs, &mut scratch, &mut pieces, &mut cover);
        let pairs = cover.len() as u64;
        assert_eq!(count_pieces(&segs, &mut scratch), (pieces.len() as u64, pairs), "counting agrees");
        pieces.iter().map(|p| (p.t0, p.t1, cover[p.cover.0 as usize..p.cover.1 as usize].to_vec())).collect()
    }

    #[test]
    fn overlapping_segments_split_at_every_end_point() {
        let p = split(&[(0, 1.0, 3.0), (1, 2.0, 5.0), (2, 6.0, 7.0)]);
        assert_eq!(p, vec![(1.0, 2.0, vec![0]), (2.0, 3.0, vec![0, 1]), (3.0, 5.0, vec![1]), (6.0, 7.0, vec![2])]);
    }

    #[test]
    fn zero_length_segments_and_gaps_give_no_pieces() {
        assert_eq!(split(&[(0, 1.0, 1.0)]), vec![]);
        let p = split(&[(0, 1.0, 2.0), (1, 2.0, 2.0), (2, 2.0, 4.0)]);
        assert_eq!(p, vec![(1.0, 2.0, vec![0]), (2.0, 4.0, vec![2])]);
    }

    #[test]
    fn nested_segments() {
        let p = split(&[(0, 0.0, 10.0), (1, 4.0, 6.0)]);
        assert_eq!(p, vec![(0.0, 4.0, vec![0]), (4.0, 6.0, vec![0, 1]), (6.0, 10.0, vec![0])]);
    }

    /// The rule as SPEC §4.2 states it, one pass over the segments per window.
    fn by_definition(segs: &[Segment]) -> Vec<(f64, f64, Vec<u32>)> {
        let mut cuts: Vec<f64> = segs.iter().filter(|s| s.t_far > s.t_near).flat_map(|s| [s.t_near, s.t_far]).collect();
        cuts.sort_unstable_by(f64::total_cmp);
        cuts.dedup();
        cuts.windows(2)
            .map(|w| {
                let cover = segs.iter().filter(|s| s.t_far > s.t_near && s.t_near <= w[0] && s.t_far >= w[1]);
                (w[0], w[1], cover.map(|s| s.object).collect::<Vec<_>>())
            })
            .filter(|(_, _, c)| !c.is_empty())
            .collect()
    }

    /// `split_into_pieces` and `count_pieces` give what the sweep alone gives.
    fn assert_as_swept(segments: &[Segment], scratch: &mut PieceScratch) {
        let (mut fast, mut swept) = ((vec![], vec![]), (vec![], vec![]));
        split_into_pieces(segments, scratch, &mut fast.0, &mut fast.1);
        sweep_into_pieces(segments, scratch, &mut swept.0, &mut swept.1);
        assert_eq!(fast, swept, "{segments:?}");
        let counted = count_pieces(segments, scratch);
        assert_eq!(counted, (swept.0.len() as u64, swept.1.len() as u64), "{segments:?}");
    }

    #[test]
    fn one_or_two_segments_apart_make_what_the_sweep_makes() {
        let mut next = numbers(0x2545_f491_4f6c_dd1d);
        let mut scratch = PieceScratch::default();
        for _ in 0..5000 {
            // Coincident, touching, empty and overlapping segments, in either order.
            let segments: Vec<Segment> = (0..1 + next(2))
                .map(|i| {
                    let a = next(6) as f64 * 0.25 + if next(3) == 0 { 1e-17 } else { 0.0 };
                    Segment { object: i as u32 * 3, t_near: a, t_far: a + next(4) as f64 * 0.25 }
                })
                .collect();
            assert_as_swept(&segments, &mut scratch);
        }
    }

    /// Many segments, in any order, mostly apart (touching, with gaps, some empty, some a
    /// hair from touching either way), now and then overlapping or with a NaN end: the
    /// pieces and counts of the sweep, whichever path makes them.
    #[test]
    fn many_segments_apart_make_what_the_sweep_makes() {
        let mut next = numbers(0x51_7cc1_b727_220a);
        let mut scratch = PieceScratch::default();
        let (mut took_apart, mut overlapped) = (0, 0);
        for _ in 0..5000 {
            let k = 3 + next(14);
            let mut t = 0.0;
            let mut segments: Vec<Segment> = (0..k)
                .map(|i| {
                    t += [0.0, 0.25, 1e-17, 0.5][next(4) as usize];
                    let t_near = t;
                    t += [0.0, 0.25, 0.5, 0.75][next(4) as usize];
                    let t_far = t + [0.0, 0.0, 0.0, 1e-17, -1e-17][next(5) as usize];
                    Segment { object: i as u32 * 2, t_near, t_far }
                })
                .collect();
            match next(8) {
                0 => segments[next(k) as usize].t_far += 0.3,
                1 => segments[next(k) as usize].t_near = f64::NAN,
                2 => segments[next(k) as usize].t_far = f64::INFINITY,
                _ => {}
            }
            // Shuffled: the scene's order of objects is not the ray's.
            for i in (1..segments.len()).rev() {
                segments.swap(i, next(i as u64 + 1) as usize);
            }
            assert_as_swept(&segments, &mut scratch);
            if scratch.sort_apart(&segments) {
                took_apart += 1;
            } else {
                overlapped += 1;
            }
        }
        assert!(took_apart > 1000 && overlapped > 200, "both paths ran: {took_apart} apart, {overlapped} not");
    }

    #[test]
    fn the_sweep_makes_the_pieces_of_the_definition() {
        let mut next = numbers(0x9e37_79b9_7f4a_7c15);
        for _ in 0..500 {
            let k = 1 + next(12);
            // End points on a coarse grid, so that many coincide; some segments are empty.
            let segs: Vec<(u32, f64, f64)> = (0..k)
                .map(|i| {
                    let a = next(8) as f64 * 0.5;
                    (i as u32, a, a + next(5) as f64 * 0.5)
                })
                .collect();
            let segments: Vec<Segment> =
                segs.iter().map(|&(object, t_near, t_far)| Segment { object, t_near, t_far }).collect();
            assert_eq!(split(&segs), by_definition(&segments), "{segs:?}");
        }
    }
}
