//! Which workers hold which datasets: what an operator decides when sharding the data over
//! worker groups (`deploy/README.md`). The coordinator can only send a dataset's batches to
//! its holders, so placement bounds how evenly the work can spread.
//!
//! * **Round robin** (what an operator does knowing only file sizes, which are equal here):
//!   replica j of dataset i lives on worker (i + j·⌊W/r⌋) mod W, so a dataset's replicas sit
//!   on different workers and every worker holds about D·r/W datasets. Dataset indices follow
//!   the scene file, whose cubes are scattered at random, so neighbouring cubes (which share
//!   bands) land on different workers. When there are fewer datasets than workers, r is
//!   raised to ⌈W/D⌉ so that no worker holds nothing.
//! * **Hot replicas**: the given fraction of datasets that carry the most samples (what an
//!   operator sees in the per-worker counts of past jobs) get `extra` more replicas each,
//!   on the workers whose expected share of samples is smallest.

/// How datasets are spread over workers.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Placement {
    /// Replicas of every dataset (raised to ⌈workers / datasets⌉ when that is larger).
    pub replicas: usize,
    /// Fraction of datasets, the heaviest by samples, that get more replicas.
    pub hot_fraction: f64,
    /// Replicas added to each hot dataset.
    pub hot_extra: usize,
}

impl Placement {
    /// One copy of each dataset, round robin.
    pub(crate) fn round_robin(replicas: usize) -> Placement {
        Placement { replicas, hot_fraction: 0.0, hot_extra: 0 }
    }

    /// The holders of each dataset, given each dataset's samples (its expected work).
    pub(crate) fn holders(&self, workers: usize, samples: &[u64]) -> Vec<Vec<usize>> {
        let datasets = samples.len();
        let r = self.replicas.max(workers.div_ceil(datasets.max(1))).clamp(1, workers);
        let stride = (workers / r).max(1);
        let mut holders: Vec<Vec<usize>> = (0..datasets)
            .map(|i| {
                let mut h: Vec<usize> = Vec::with_capacity(r);
                for j in 0..r {
                    let mut w = (i + j * stride) % workers;
                    while h.contains(&w) {
                        w = (w + 1) % workers;
                    }
                    h.push(w);
                }
                h
            })
            .collect();
        self.add_hot(&mut holders, workers, samples);
        holders
    }

    fn add_hot(&self, holders: &mut [Vec<usize>], workers: usize, samples: &[u64]) {
        let hot = (self.hot_fraction * samples.len() as f64).round() as usize;
        if hot == 0 || self.hot_extra == 0 {
            return;
        }
        // Expected samples per worker, each dataset's split evenly over its holders.
        let mut load = vec![0.0; workers];
        for (h, &s) in holders.iter().zip(samples) {
            h.iter().for_each(|&w| load[w] += s as f64 / h.len() as f64);
        }
        let mut by_weight: Vec<usize> = (0..samples.len()).collect();
        by_weight.sort_by(|&a, &b| samples[b].cmp(&samples[a]).then(a.cmp(&b)));
        for &d in by_weight.iter().take(hot) {
            for _ in 0..self.hot_extra {
                let Some(w) = (0..workers)
                    .filter(|w| !holders[d].contains(w))
                    .min_by(|&a, &b| load[a].total_cmp(&load[b]).then(a.cmp(&b)))
                else {
                    break;
                };
                let share = samples[d] as f64;
                let before = holders[d].len() as f64;
                holders[d].iter().for_each(|&h| load[h] += share / (before + 1.0) - share / before);
                load[w] += share / (before + 1.0);
                holders[d].push(w);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_robin_spreads_replicas_over_different_workers() {
        let holders = Placement::round_robin(2).holders(64, &[1; 256]);
        let mut held = vec![0; 64];
        for h in &holders {
            assert_eq!(h.len(), 2);
            assert_ne!(h[0], h[1]);
            h.iter().for_each(|&w| held[w] += 1);
        }
        assert!(held.iter().all(|&n| n == 8), "{held:?}");
    }

    #[test]
    fn fewer_datasets_than_workers_still_give_every_worker_a_dataset() {
        let holders = Placement::round_robin(1).holders(256, &[1; 16]);
        let mut held = vec![0; 256];
        holders.iter().flatten().for_each(|&w| held[w] += 1);
        assert!(held.iter().all(|&n| n == 1));
    }

    #[test]
    fn hot_datasets_get_replicas_on_the_least_loaded_workers() {
        let mut samples = vec![10; 8];
        samples[3] = 1000;
        let placement = Placement { replicas: 1, hot_fraction: 0.125, hot_extra: 2 };
        let holders = placement.holders(8, &samples);
        assert_eq!(holders[3].len(), 3);
        assert!(holders.iter().enumerate().all(|(d, h)| d == 3 || h.len() == 1));
        assert!(!holders[3][1..].contains(&holders[3][0]));
    }
}
