//! The dispatch policy of Algorithm 2's drivers, in one place: how many batches a caster may
//! have in flight, which of a dataset's holders casts the next batch, how many bands of the
//! image are admitted at once and in what order. The farm's coordinator and `trove-bench
//! farm-sim` both call it, so the simulation cannot drift from the code it models; it knows
//! no clocks, sockets or threads, so its unit tests are exact.
//!
//! Several coordinators may share a worker, each counting only its own batches on it. The
//! worker therefore has the last word ([`admits`]: it holds at most its own maximum, beyond
//! which a job over its fair share is refused as busy), and a coordinator counts a worker
//! that refused it as full until that worker answers one of its batches ([`Load::refused`]).

/// Batches a worker of `threads` threads may have in flight at once: enough that its
/// threads stay busy while answers travel (two per thread), few enough that culling, which
/// needs answers in front, still saves work.
pub fn capacity(threads: u32) -> u64 {
    (2 * threads as u64).max(4)
}

/// What the policy needs to know of one candidate caster of a batch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Load {
    /// Batches it has in flight, over every job it serves.
    pub in_flight: u64,
    /// Its threads.
    pub threads: u32,
    /// It refused a batch as busy (other coordinators fill it) and has not answered one since:
    /// it has no room, whatever `in_flight` says.
    pub refused: bool,
}

impl Load {
    /// Whether it has room for another batch.
    pub fn has_room(&self) -> bool {
        self.room() > 0
    }

    /// How many more batches it has room for.
    pub fn room(&self) -> u64 {
        if self.refused {
            return 0;
        }
        capacity(self.threads).saturating_sub(self.in_flight)
    }
}

/// Whether a worker that holds at most `max` batches at once (queued or being cast), holding
/// `total` now over every coordinator and job it serves, takes one more of a job that holds
/// `held` of them, while `jobs` other jobs hold at least one each: while it has room it takes
/// any batch; when full, it still takes one of a job below its fair share (`max` over the
/// jobs holding batches, this one counted, at least one), and refuses the rest as busy. So
/// a job never waits for a worker that other jobs — on this coordinator or another — keep
/// full: it is always admitted up to its share, and the others are refused until their
/// answers bring them down to theirs. What a worker holds stays below twice `max` (plus one
/// per job). With one coordinator, which never has more than [`capacity`] batches out on a
/// worker, and `max` at least that, nothing is ever refused.
pub fn admits(max: u64, total: u64, held: u64, jobs: u64) -> bool {
    if total < max {
        return true;
    }
    let sharing = jobs + 1;
    held < (max / sharing).max(1)
}

/// The index of the candidate that casts the next batch: of those with room, the one with
/// the fewest batches in flight relative to its capacity (a worker of 16 threads with 8
/// batches out is as busy as one of 8 threads with 4); ties go to the earlier candidate, so
/// a caller that lists holders in a fixed order gets a deterministic choice. `None` when
/// every candidate is full (the batch waits for an answer).
pub fn least_loaded(candidates: impl IntoIterator<Item = Load>) -> Option<usize> {
    let mut best: Option<(usize, Load)> = None;
    for (i, c) in candidates.into_iter().enumerate() {
        if !c.has_room() {
            continue;
        }
        // c is less loaded than b when c.in_flight / cap(c) < b.in_flight / cap(b).
        let less = |b: &Load| {
            let (mine, theirs) =
                (c.in_flight as u128 * capacity(b.threads) as u128, b.in_flight as u128 * capacity(c.threads) as u128);
            mine < theirs
        };
        if best.as_ref().is_none_or(|(_, b)| less(b)) {
            best = Some((i, c));
        }
    }
    best.map(|(i, _)| i)
}

/// How many more batches of one dataset a driver asks its bands for: as many as the
/// dataset's holders have room for (`room`, summed over them), and one per holder more so
/// that an answer finds the next batch waiting, less the batches in stock and those already
/// asked for; and the share asked of each of the `bands` that may have some (earliest
/// started first), so that several bands' threads make them at once. `None` when nothing
/// is to be asked. The farm's driver and `farm-sim` both ask by it.
pub fn batches_to_ask(room: usize, holders: usize, stock: usize, asked: usize, bands: usize) -> Option<(usize, usize)> {
    let want = (room + holders).saturating_sub(stock + asked);
    if want == 0 || bands == 0 {
        return None;
    }
    Some((want, want.div_ceil(bands).max(1)))
}

/// How much of an image a driver works on at once.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Admission {
    /// Bands whose pieces are held at once, at most.
    pub max_bands: usize,
    /// Bytes of band bookkeeping (tasks, results, fronts: [`crate::render::Scheduler::heap_bytes`])
    /// held at once, at most; one band is always admitted, however large.
    pub memory_bound: u64,
}

impl Admission {
    /// Whether another band, expected to take `next` bytes, may start while `bands` bands
    /// holding `held` bytes are in flight.
    pub fn admits(&self, bands: usize, held: u64, next: u64) -> bool {
        bands == 0 || (bands < self.max_bands && held.saturating_add(next) <= self.memory_bound)
    }
}

/// The order in which a driver starts `bands` bands of rows: the bit-reversed
/// (van der Corput) order, so that the bands in flight at any time are spread over the
/// image, and so over more of its datasets, instead of being neighbours that meet the same
/// few. Every band appears once.
pub fn band_order(bands: usize) -> Vec<usize> {
    if bands <= 1 {
        return (0..bands).collect();
    }
    let bits = usize::BITS - (bands - 1).leading_zeros();
    (0..1usize << bits).map(|i| i.reverse_bits() >> (usize::BITS - bits)).filter(|&b| b < bands).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn load(in_flight: u64, threads: u32) -> Load {
        Load { in_flight, threads, refused: false }
    }

    #[test]
    fn capacity_is_two_batches_per_thread_and_at_least_four() {
        assert_eq!(capacity(1), 4);
        assert_eq!(capacity(2), 4);
        assert_eq!(capacity(3), 6);
        assert_eq!(capacity(16), 32);
    }

    #[test]
    fn the_least_loaded_candidate_with_room_is_chosen() {
        assert_eq!(least_loaded([load(3, 2), load(1, 2), load(2, 2)]), Some(1));
        // Full candidates are passed over even when they are first.
        assert_eq!(least_loaded([load(4, 2), load(3, 2)]), Some(1));
        assert_eq!(least_loaded([load(4, 2), load(4, 1)]), None);
        assert_eq!(least_loaded(std::iter::empty()), None);
    }

    #[test]
    fn load_is_relative_to_capacity_and_ties_go_to_the_first() {
        // 8 of 32 is a quarter; 2 of 4 is a half.
        assert_eq!(least_loaded([load(2, 2), load(8, 16)]), Some(1));
        // 2 of 4 and 16 of 32 are both half: the first wins.
        assert_eq!(least_loaded([load(16, 16), load(2, 2)]), Some(0));
        assert_eq!(least_loaded([load(0, 2), load(0, 8)]), Some(0));
    }

    #[test]
    fn a_worker_that_refused_a_batch_has_no_room_until_it_answers() {
        let refused = Load { refused: true, ..load(0, 8) };
        assert_eq!(refused.room(), 0);
        assert!(!refused.has_room());
        // Its replica takes the batch even though it is busier by the count.
        assert_eq!(least_loaded([refused, load(5, 2)]), None);
        assert_eq!(least_loaded([refused, load(3, 2)]), Some(1));
        assert_eq!(load(3, 2).room(), 1);
        assert_eq!(load(9, 2).room(), 0, "over capacity, no room and no underflow");
    }

    #[test]
    fn a_full_worker_admits_a_job_below_its_share_and_refuses_the_rest() {
        // Room: anything goes.
        assert!(admits(8, 7, 7, 0));
        // Full, one other job holding everything: a new job gets up to half.
        assert!(admits(8, 8, 0, 1));
        assert!(admits(8, 11, 3, 1));
        assert!(!admits(8, 12, 4, 1), "at its share");
        assert!(!admits(8, 8, 8, 0), "the job alone, at the maximum");
        // Three jobs sharing 8: shares of 2 (8 / 3 rounded down).
        assert!(admits(8, 9, 1, 2));
        assert!(!admits(8, 9, 2, 2));
        // More jobs than the maximum: each still gets one.
        assert!(admits(4, 6, 0, 9));
        assert!(!admits(4, 6, 1, 9));
    }

    #[test]
    fn two_jobs_filling_one_worker_end_with_equal_shares_and_neither_starves() {
        // Job 0 fills an 8-batch worker alone; job 1 arrives. Each step: whoever has a batch
        // ready offers it (both always do); every other step the worker answers one batch of
        // the job holding most. Neither is ever left without a batch on the worker.
        let max = 8;
        let mut held = [8u64, 0];
        for step in 0..200 {
            for j in 0..2 {
                let total = held[0] + held[1];
                let others = held.iter().enumerate().filter(|&(k, &h)| k != j && h > 0).count() as u64;
                if admits(max, total, held[j], others) {
                    held[j] += 1;
                }
            }
            assert!(held[0] + held[1] <= 2 * max + 2, "step {step}: {held:?}");
            assert!(held[1] > 0 && held[0] > 0, "step {step}: {held:?}");
            if step % 2 == 1 {
                let j = if held[0] >= held[1] { 0 } else { 1 };
                held[j] -= 1;
            }
        }
        // The last step answered one: equal halves of the worker, less that one.
        assert!(held[0].abs_diff(held[1]) <= 1 && held[0] + held[1] == max - 1, "{held:?}");
    }

    #[test]
    fn a_replica_with_room_takes_the_batch_a_full_holder_cannot() {
        // A dataset held by three workers: the busy one is skipped, the idle one chosen.
        let holders = [load(4, 2), load(1, 2), load(0, 2)];
        assert_eq!(least_loaded(holders), Some(2));
    }

    #[test]
    fn a_worker_joining_mid_job_gets_the_next_batches() {
        // Two workers at 3 of 4; a new one registers with nothing in flight: it gets batches
        // until it is as loaded as the others.
        let mut holders = vec![load(3, 2), load(3, 2)];
        assert_eq!(least_loaded(holders.iter().copied()), Some(0));
        holders.push(load(0, 2));
        for expected_in_flight in 0..3 {
            let pick = least_loaded(holders.iter().copied()).unwrap();
            assert_eq!(pick, 2, "after {expected_in_flight} batches");
            holders[pick].in_flight += 1;
        }
        assert_eq!(least_loaded(holders.iter().copied()), Some(0));
    }

    #[test]
    fn bands_are_asked_for_the_room_and_one_per_holder_less_what_is_stocked_or_asked_in_shares() {
        // Two holders with 3 batches of room between them: 5 wanted, over two bands 3 each.
        assert_eq!(batches_to_ask(3, 2, 0, 0, 2), Some((5, 3)));
        assert_eq!(batches_to_ask(3, 2, 2, 1, 2), Some((2, 1)));
        assert_eq!(batches_to_ask(3, 2, 4, 1, 2), None, "stock and asks cover the room");
        assert_eq!(batches_to_ask(0, 1, 0, 0, 3), Some((1, 1)), "full holders still get one waiting");
        assert_eq!(batches_to_ask(8, 2, 0, 0, 0), None, "no band to ask");
    }

    #[test]
    fn admission_holds_one_band_always_and_more_within_the_bounds() {
        let a = Admission { max_bands: 3, memory_bound: 100 };
        assert!(a.admits(0, 0, 1000), "the first band, however large");
        assert!(a.admits(1, 40, 60));
        assert!(!a.admits(1, 40, 61), "over the memory bound");
        assert!(!a.admits(3, 0, 0), "over the band count");
        assert!(!a.admits(2, u64::MAX, 1), "no overflow");
    }

    #[test]
    fn band_order_visits_every_band_once_spread_over_the_image() {
        for n in 0..70 {
            let order = band_order(n);
            let mut sorted = order.clone();
            sorted.sort_unstable();
            assert_eq!(sorted, (0..n).collect::<Vec<_>>(), "{n} bands");
        }
        assert_eq!(band_order(8), [0, 4, 2, 6, 1, 5, 3, 7]);
        assert_eq!(band_order(5), [0, 4, 2, 1, 3]);
        // The first bands started are far apart: the first two are half the image apart.
        let order = band_order(64);
        assert_eq!(order[1] - order[0], 32);
    }
}
