//! The simulation's two kinds of resource: a pool of cores shared by jobs that each use up to
//! a number of them (a worker's rayon pool, the coordinator's blocking threads), and a link
//! that carries one message at a time (a network interface in one direction).

use std::collections::VecDeque;

/// Jobs sharing `capacity` cores, oldest first: each takes up to its `cap` cores from what
/// the older ones left, and keeps them until it finishes (rayon's work stealing spreads a
/// job's chunks over every idle thread, and older jobs' chunks were queued first). Work is
/// in core-seconds.
#[derive(Debug)]
pub(crate) struct Pool<T> {
    capacity: f64,
    jobs: VecDeque<PoolJob<T>>,
    /// Time up to which `remaining` is accounted.
    last: f64,
    /// Changes on every addition and completion, so a completion event computed before a
    /// change is recognised as stale.
    pub version: u64,
    /// Core-seconds spent so far.
    pub busy: f64,
}

#[derive(Debug)]
struct PoolJob<T> {
    tag: T,
    work: f64,
    remaining: f64,
    cap: f64,
}

impl<T> Pool<T> {
    /// An idle pool of `capacity` cores.
    pub(crate) fn new(capacity: f64) -> Pool<T> {
        Pool { capacity, jobs: VecDeque::new(), last: 0.0, version: 0, busy: 0.0 }
    }

    /// The cores each job runs on now, oldest first.
    fn rates(&self) -> impl Iterator<Item = f64> + '_ {
        let mut left = self.capacity;
        self.jobs.iter().map(move |j| {
            let r = j.cap.min(left).max(0.0);
            left -= r;
            r
        })
    }

    /// Accounts the work done up to `now`.
    fn advance(&mut self, now: f64) {
        let dt = now - self.last;
        if dt > 0.0 {
            let rates: Vec<f64> = self.rates().collect();
            for (job, r) in self.jobs.iter_mut().zip(rates) {
                let done = (r * dt).min(job.remaining);
                job.remaining -= done;
                self.busy += done;
            }
        }
        self.last = self.last.max(now);
    }

    /// Starts a job of `work` core-seconds that can use up to `cap` cores.
    pub(crate) fn add(&mut self, now: f64, tag: T, work: f64, cap: f64) {
        self.advance(now);
        let work = work.max(0.0);
        self.jobs.push_back(PoolJob { tag, work, remaining: work, cap: cap.max(1e-9) });
        self.version += 1;
    }

    /// When the next job finishes, if any runs.
    pub(crate) fn next_completion(&self) -> Option<f64> {
        self.jobs
            .iter()
            .zip(self.rates())
            .filter(|(_, r)| *r > 0.0)
            .map(|(j, r)| self.last + j.remaining / r)
            .min_by(f64::total_cmp)
    }

    /// Removes and returns the jobs finished by `now`, oldest first.
    pub(crate) fn take_finished(&mut self, now: f64) -> Vec<T> {
        self.advance(now);
        let mut finished = Vec::new();
        let mut kept = VecDeque::with_capacity(self.jobs.len());
        for job in self.jobs.drain(..) {
            // Rounding leaves crumbs of a few ulps of the work on a job that is done.
            if job.remaining <= 1e-12 + 1e-9 * job.work {
                self.busy += job.remaining;
                finished.push(job.tag);
            } else {
                kept.push_back(job);
            }
        }
        self.jobs = kept;
        if !finished.is_empty() {
            self.version += 1;
        }
        finished
    }

    /// Cores of the pool.
    pub(crate) fn capacity(&self) -> f64 {
        self.capacity
    }

    /// Jobs not finished.
    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        self.jobs.len()
    }
}

/// One direction of a network interface: messages leave one after the other at its
/// bandwidth, each also costing the sending stack a fixed time.
#[derive(Clone, Debug, Default)]
pub(crate) struct Link {
    /// When the link is next free.
    free: f64,
    /// Seconds spent sending.
    pub busy: f64,
}

impl Link {
    /// Reserves the link for `seconds` from `now` or when it is next free; returns when the
    /// message started and when it has left.
    pub(crate) fn reserve(&mut self, now: f64, seconds: f64) -> (f64, f64) {
        let start = self.free.max(now);
        self.free = start + seconds;
        self.busy += seconds;
        (start, self.free)
    }
}

/// A message over two links (the sender's interface out, the receiver's in) with a one-way
/// `latency` between them, cut through: the receiving side starts `latency` after the
/// sending side, and neither finishes before the other could. Returns the arrival time.
pub(crate) fn transfer(now: f64, seconds: f64, out: &mut Link, into: &mut Link, latency: f64) -> f64 {
    let (start, left) = out.reserve(now, seconds);
    let (_, end) = into.reserve(start + latency, seconds);
    let arrival = end.max(left + latency);
    into.free = into.free.max(arrival);
    arrival
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run_to_end(pool: &mut Pool<&'static str>) -> Vec<(&'static str, f64)> {
        let mut out = Vec::new();
        while let Some(t) = pool.next_completion() {
            out.extend(pool.take_finished(t).into_iter().map(|tag| (tag, t)));
        }
        out
    }

    #[test]
    fn older_jobs_take_their_cores_first_and_the_rest_goes_to_younger_ones() {
        let mut pool = Pool::new(4.0);
        pool.add(0.0, "a", 6.0, 3.0); // 3 cores: done at 2
        pool.add(0.0, "b", 4.0, 4.0); // 1 core until 2, then 4: 2 left at 2, done at 2.5
        let done = run_to_end(&mut pool);
        assert_eq!(done.len(), 2);
        assert_eq!(done[0].0, "a");
        assert!((done[0].1 - 2.0).abs() < 1e-12);
        assert_eq!(done[1].0, "b");
        assert!((done[1].1 - 2.5).abs() < 1e-12);
        assert!((pool.busy - 10.0).abs() < 1e-9);
        assert_eq!(pool.len(), 0);
    }

    #[test]
    fn a_job_added_later_starts_when_it_is_added() {
        let mut pool = Pool::new(2.0);
        pool.add(0.0, "a", 2.0, 1.0);
        pool.add(1.0, "b", 1.0, 1.0);
        let done = run_to_end(&mut pool);
        assert!((done[0].1 - 2.0).abs() < 1e-12 && (done[1].1 - 2.0).abs() < 1e-12, "{done:?}");
    }

    #[test]
    fn a_link_sends_one_message_at_a_time_and_cut_through_adds_latency_once() {
        let (mut out, mut into) = (Link::default(), Link::default());
        assert!((transfer(0.0, 1.0, &mut out, &mut into, 0.5) - 1.5).abs() < 1e-12);
        // The second message waits for the first to leave.
        assert!((transfer(0.0, 1.0, &mut out, &mut into, 0.5) - 2.5).abs() < 1e-12);
        assert!((out.busy - 2.0).abs() < 1e-12);
    }
}
