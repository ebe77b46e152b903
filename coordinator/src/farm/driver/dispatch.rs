//! A job's side of dispatch: the holders of each of its datasets (looked up in the registry
//! once, then again only when the registry changes or on the driver's tick), the `Cast`
//! streams it opened, and its batches in flight. Which holder casts a batch is
//! [`trove_core::render::dispatch::least_loaded`]'s choice; this module only keeps what that
//! choice and the answers need.
//!
//! A worker that refused a batch as busy (it serves other coordinators too, and this job
//! has its share of it) has no room for this job ([`Load::refused`]) until it answers one of
//! the job's batches, its stream is lost, or the driver's tick; the refused batch goes back
//! to the stock as it was, its attempt unspent ([`Dispatch::refused`]).
//!
//! A (worker, dataset) pair whose stream was lost *rests* ([`Rest`]): for a while when the
//! stream broke, went silent or the worker was busy, after which a worker still alive (its
//! heartbeats kept coming) serves the job again; for the rest of the job when the worker
//! answered with something the job cannot use. A dataset whose holders all rest for a while
//! is not orphaned: the job waits for them.

use std::collections::{HashMap, HashSet};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use prost::bytes::Bytes;
use trove_core::render::dispatch::{least_loaded, Load};

use super::super::registry::{Registry, WorkerHandle};
use super::StreamKey;

/// A batch handed to a worker and not answered yet.
pub(super) struct InFlight {
    pub band: usize,
    /// The scheduler's id of the batch.
    pub id: u64,
    pub dataset: usize,
    pub attempt: u32,
    pub stream: StreamKey,
    pub tasks: u64,
    /// The tasks as sent, kept (shared, not copied) to send again if the worker refuses them
    /// as busy.
    pub encoded: Bytes,
    pub sent: Instant,
}

/// How long a (worker, dataset) pair is not used after its stream was lost.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Rest {
    /// Until then; the worker serves the job again if it is still alive.
    Until(Instant),
    /// For the rest of the job.
    Job,
}

/// Why an answer is not taken.
#[derive(Debug, PartialEq, Eq)]
pub(super) enum Refused {
    /// No such batch is in flight: it was given up (and perhaps sent elsewhere), or never sent.
    Unknown,
    /// The answer came on another stream than the batch went out on.
    WrongStream,
    /// The answer names another attempt of the batch.
    WrongAttempt { sent: u32, answered: u32 },
}

/// The job's holders, streams and batches in flight.
pub(super) struct Dispatch {
    /// Per dataset: the keys of its files (empty for generated datasets).
    keys: Vec<Vec<String>>,
    /// Per dataset: its alive holders, in the registry's (id) order.
    holders: Vec<Vec<WorkerHandle>>,
    generation: u64,
    /// (worker, dataset) pairs this job does not use now (their stream broke, the worker was
    /// busy or answered wrongly), and until when.
    resting: HashMap<StreamKey, Rest>,
    in_flight: HashMap<u64, InFlight>,
    /// Workers that refused one of this job's batches as busy and have not answered one
    /// since: no room for this job.
    busy: HashSet<String>,
    next_wire: u64,
}

impl Dispatch {
    pub fn new(keys: Vec<Vec<String>>) -> Dispatch {
        let holders = vec![Vec::new(); keys.len()];
        Dispatch {
            keys,
            holders,
            generation: u64::MAX,
            resting: HashMap::new(),
            in_flight: HashMap::new(),
            busy: HashSet::new(),
            next_wire: 1,
        }
    }

    /// Looks the holders of every dataset up again if the registry changed since, or if
    /// `always` (the tick: heartbeats age without the registry changing).
    pub fn refresh(&mut self, registry: &Registry, always: bool) {
        let generation = registry.generation();
        if !always && generation == self.generation {
            return;
        }
        self.generation = generation;
        if always {
            // A refusal's answer or the last batch in flight may have crossed it: at the
            // latest on the tick, a busy worker is asked again.
            self.busy.clear();
        }
        let now = Instant::now();
        self.resting.retain(|_, rest| !matches!(rest, Rest::Until(t) if *t <= now));
        for (d, keys) in self.keys.iter().enumerate() {
            self.holders[d] = registry
                .holders(keys)
                .into_iter()
                .filter(|w| !self.resting.contains_key(&(w.clone(), d)))
                .filter_map(|w| registry.handle(&w))
                .collect();
        }
    }

    /// Whether dataset `d` has no holder left for this job: none usable, and none resting
    /// for a while.
    pub fn is_orphaned(&self, d: usize) -> bool {
        self.holders[d].is_empty() && !self.resting.iter().any(|((_, rd), rest)| *rd == d && *rest != Rest::Job)
    }

    /// The holder of dataset `d` that casts its next batch, if one of those `usable` admits
    /// has room.
    pub fn pick(&self, d: usize, usable: impl Fn(&WorkerHandle) -> bool) -> Option<&WorkerHandle> {
        let holders: Vec<&WorkerHandle> = self.holders[d].iter().filter(|w| usable(w)).collect();
        least_loaded(holders.iter().map(|w| self.load(w))).map(|i| holders[i])
    }

    /// What the policy knows of `worker` for this job.
    fn load(&self, worker: &WorkerHandle) -> Load {
        Load {
            in_flight: worker.in_flight.load(Ordering::Relaxed),
            threads: worker.threads,
            refused: self.busy.contains(&worker.id),
        }
    }

    /// The batches dataset `d`'s holders have room for now, over every job they serve, and
    /// how many holders it has.
    pub fn room(&self, d: usize) -> (usize, usize) {
        let holders = &self.holders[d];
        let room = holders.iter().map(|w| self.load(w).room() as usize).sum();
        (room, holders.len())
    }

    /// A fresh wire id for a batch.
    pub fn next_wire(&mut self) -> u64 {
        let wire = self.next_wire;
        self.next_wire += 1;
        wire
    }

    /// Notes batch `wire` as sent to `worker`.
    pub fn sent(&mut self, wire: u64, worker: &WorkerHandle, batch: InFlight) {
        worker.in_flight.fetch_add(1, Ordering::Relaxed);
        self.in_flight.insert(wire, batch);
    }

    /// Takes the answer to batch `wire` (attempt `attempt`) arriving on `stream`, with the
    /// worker's counters updated; a refused answer leaves the batch in flight.
    pub fn answered(
        &mut self,
        wire: u64,
        attempt: u32,
        stream: &StreamKey,
        worker: Option<&WorkerHandle>,
    ) -> Result<InFlight, Refused> {
        let batch = self.take(wire, stream, Some(attempt))?;
        if let Some(w) = worker {
            w.in_flight.fetch_sub(1, Ordering::Relaxed);
            w.done.fetch_add(1, Ordering::Relaxed);
        }
        // It answered: it has room for this job again as far as its count says.
        self.busy.remove(&stream.0);
        Ok(batch)
    }

    /// Takes back batch `wire`, which the worker of `stream` refused as busy: no longer in
    /// flight (the worker's count given back), and the worker has no room for this job
    /// until it answers one of its batches. The caller sends the batch again, attempt
    /// unchanged.
    pub fn refused(
        &mut self,
        wire: u64,
        stream: &StreamKey,
        worker: Option<&WorkerHandle>,
    ) -> Result<InFlight, Refused> {
        let batch = self.take(wire, stream, None)?;
        if let Some(w) = worker {
            w.in_flight.fetch_sub(1, Ordering::Relaxed);
        }
        self.busy.insert(stream.0.clone());
        Ok(batch)
    }

    /// Takes batch `wire` out of flight if it was sent on `stream` (and, given `attempt`,
    /// as that attempt); otherwise leaves it in flight and says why.
    fn take(&mut self, wire: u64, stream: &StreamKey, attempt: Option<u32>) -> Result<InFlight, Refused> {
        let batch = self.in_flight.get(&wire).ok_or(Refused::Unknown)?;
        if batch.stream != *stream {
            return Err(Refused::WrongStream);
        }
        if let Some(attempt) = attempt.filter(|&a| a != batch.attempt) {
            return Err(Refused::WrongAttempt { sent: batch.attempt, answered: attempt });
        }
        Ok(self.in_flight.remove(&wire).expect("looked up above"))
    }

    /// Stops using `stream` for this job, for `rest`; returns its batches in flight, with the
    /// worker's count given back, for the caller to hand to their schedulers again.
    pub fn lose(&mut self, stream: &StreamKey, worker: Option<&WorkerHandle>, rest: Rest) -> Vec<InFlight> {
        let wires: Vec<u64> = self.in_flight.iter().filter(|(_, b)| b.stream == *stream).map(|(&w, _)| w).collect();
        let lost: Vec<InFlight> = wires.into_iter().filter_map(|w| self.in_flight.remove(&w)).collect();
        if let Some(w) = worker {
            w.in_flight.fetch_sub(lost.len() as u64, Ordering::Relaxed);
        }
        // A pair that is out for the job stays out.
        self.busy.remove(&stream.0);
        let kept = self.resting.get(stream).copied();
        self.resting.insert(stream.clone(), if kept == Some(Rest::Job) { Rest::Job } else { rest });
        if let Some(holders) = self.holders.get_mut(stream.1) {
            holders.retain(|w| w.id != stream.0);
        }
        lost
    }

    /// The streams with a batch older than `deadline`.
    pub fn overdue(&self, deadline: Duration) -> HashSet<StreamKey> {
        self.in_flight.values().filter(|b| b.sent.elapsed() > deadline).map(|b| b.stream.clone()).collect()
    }
}

#[cfg(test)]
mod tests {
    use trove_proto::v1 as pb;

    use super::*;

    #[tokio::test]
    async fn a_lost_pair_rests_then_serves_the_job_again_and_one_out_for_the_job_stays_out() {
        // Heartbeats every 10 ms: a worker counts as lost 50 ms after its last one.
        let registry = Registry::new(Duration::from_millis(10));
        let request = pb::RegisterRequest {
            address: "127.0.0.1:9".into(),
            threads: 1,
            worker_id: "w-test".into(),
            ..Default::default()
        };
        let id = registry.register(request).unwrap();
        // One generated dataset: every worker holds it.
        let mut dispatch = Dispatch::new(vec![Vec::new()]);
        dispatch.refresh(&registry, true);
        assert!(dispatch.pick(0, |_| true).is_some());
        let pair = (id.clone(), 0);
        let lost = dispatch.lose(&pair, None, Rest::Until(Instant::now() + Duration::from_millis(20)));
        assert!(lost.is_empty());
        assert!(dispatch.pick(0, |_| true).is_none(), "a resting pair is not picked");
        assert!(!dispatch.is_orphaned(0), "a dataset whose holder rests waits for it");
        tokio::time::sleep(Duration::from_millis(30)).await;
        assert!(registry.heartbeat_from(&id));
        dispatch.refresh(&registry, true);
        assert!(dispatch.pick(0, |_| true).is_some(), "an alive worker serves the job again after its rest");
        dispatch.lose(&pair, None, Rest::Job);
        dispatch.lose(&pair, None, Rest::Until(Instant::now()));
        dispatch.refresh(&registry, true);
        assert!(dispatch.pick(0, |_| true).is_none());
        assert!(dispatch.is_orphaned(0), "a pair out for the job stays out, and its dataset is orphaned");
    }
}
