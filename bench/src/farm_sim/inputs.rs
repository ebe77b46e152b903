//! What the simulation is fed: the cost of each step of the farm. The coordinator's come
//! from `trove-bench coordinator --record` (the real coordinator, its CPU per piece by
//! stage, each stage placed on the job's event loop, a band's thread or the other
//! threads); the workers'
//! from the worker's own caster timed on this processor (`super::measure`), recorded in
//! `bench/recorded/worker.json` or measured at start with `--measure`. Only the network is
//! a parameter or an assumption.

use super::recorded::{At, CoordinatorRecord, RunsOn, WorkerRecord};

/// One coordinator stage's cost in the model: seconds per unit of `at` (per piece for
/// intersection and composition, per task for sending and answering, per pixel at the end).
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Cost {
    pub name: String,
    pub runs_on: RunsOn,
    pub at: At,
    pub seconds: f64,
}

/// Costs of every step of a farm job. Core-seconds unless marked otherwise.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Inputs {
    // --- workers -------------------------------------------------------------------------
    /// Casting: per sample evaluated (interpolate, classify, composite).
    pub cast_per_sample: f64,
    /// Casting: per task (recompute the ray, check the task, set up the walk).
    pub cast_per_task: f64,
    /// A worker's first bind of a dataset's objects (`BatchCaster::new` through its
    /// store, which classifies the cells and keeps them), per voxel, once per dataset.
    pub bind_per_voxel: f64,
    /// Binding again when a stream starts after running dry (the store kept the cells), per
    /// voxel.
    pub rebind_per_voxel: f64,
    /// Loading a dataset, per byte (one core).
    pub load_per_byte: f64,
    /// Parsing and validating the job's scene when a stream opens, per object.
    pub parse_per_object: f64,

    // --- coordinator ---------------------------------------------------------------------
    /// Its stages, as recorded.
    pub stages: Vec<Cost>,

    // --- network --------------------------------------------------------------------------
    /// Each machine's link, one direction, bytes per second.
    pub link_bytes_per_s: f64,
    /// One-way latency between two machines, seconds.
    pub latency: f64,
    /// Per message: framing bytes (gRPC, HTTP/2, protobuf) beyond the payload. Assumed.
    pub message_overhead_bytes: f64,
}

/// Bytes per task on the wire, coordinator to worker and back (`render/wire.rs`: at most 24
/// out and 16 back, the bound).
pub(crate) const TASK_BYTES_OUT: f64 = 24.0;
pub(crate) const TASK_BYTES_BACK: f64 = 16.0;

impl Inputs {
    /// The inputs from the two records, with a 10 Gbit/s link and 50 µs one way.
    pub(crate) fn from_records(coordinator: &CoordinatorRecord, worker: &WorkerRecord) -> Inputs {
        Inputs {
            cast_per_sample: worker.cast_per_sample,
            cast_per_task: worker.cast_per_task,
            bind_per_voxel: worker.bind_per_voxel,
            rebind_per_voxel: worker.rebind_per_voxel,
            load_per_byte: worker.load_per_byte,
            parse_per_object: worker.parse_per_object,
            stages: coordinator_costs(coordinator),
            link_bytes_per_s: 10e9 / 8.0,
            latency: 50e-6,
            message_overhead_bytes: 64.0,
        }
    }

    /// The same with the network's parameters replaced.
    pub(crate) fn with_link(mut self, gbit_per_s: f64, latency_us: f64) -> Inputs {
        self.link_bytes_per_s = gbit_per_s * 1e9 / 8.0;
        self.latency = latency_us * 1e-6;
        self
    }

    /// The same with every cost of the coordinator's own work set to zero (its network
    /// links stay): a bound on what the rest of the farm allows.
    pub(crate) fn without_coordinator(mut self) -> Inputs {
        self.stages.iter_mut().for_each(|c| c.seconds = 0.0);
        self
    }

    /// Seconds per unit of the stages paid at `at` that run on `runs_on`.
    pub(crate) fn cost(&self, at: At, runs_on: RunsOn) -> f64 {
        self.stages.iter().filter(|c| c.at == at && c.runs_on == runs_on).map(|c| c.seconds).sum()
    }

    /// Seconds a message of `payload` bytes occupies a link.
    pub(crate) fn wire_seconds(&self, payload: f64) -> f64 {
        (payload + self.message_overhead_bytes) / self.link_bytes_per_s
    }
}

/// Each recorded stage's cost per unit of its step, over all the recorded scenes (pieces
/// weigh: a stage's CPU over every scene's pieces): per piece as recorded for intersection
/// and composition, per task sent for sending and answering (over the tasks the scenes sent
/// per piece), per pixel at the end (over their pieces per pixel).
pub(crate) fn coordinator_costs(record: &CoordinatorRecord) -> Vec<Cost> {
    let pieces: f64 = record.scenes.iter().map(|s| s.pieces as f64).sum();
    let tasks: f64 = record.scenes.iter().map(|s| s.tasks_sent as f64).sum();
    let pixels: f64 = record.scenes.iter().map(|s| s.pixels as f64).sum();
    let mut costs: Vec<Cost> = Vec::new();
    for scene in &record.scenes {
        for st in &scene.stages {
            let seconds = st.cpu_ns_per_piece * 1e-9 * scene.pieces as f64 / pieces;
            match costs.iter_mut().find(|c| c.name == st.name) {
                Some(c) => c.seconds += seconds,
                None => costs.push(Cost { name: st.name.clone(), runs_on: st.runs_on, at: st.at, seconds }),
            }
        }
    }
    for c in &mut costs {
        c.seconds *= match c.at {
            At::Intersect | At::Composite => 1.0,
            At::Send | At::Answer => pieces / tasks.max(1.0),
            At::Finish => pieces / pixels.max(1.0),
        };
    }
    costs
}

#[cfg(test)]
mod tests {
    use super::super::recorded::tests::sample;
    use super::*;

    #[test]
    fn recorded_costs_per_piece_become_costs_per_unit_of_their_step() {
        // The sample: 2000 pieces, 1000 tasks, 1000 pixels.
        let costs = coordinator_costs(&sample());
        let of = |name: &str| costs.iter().find(|c| c.name == name).unwrap().seconds * 1e9;
        assert!((of("intersection") - 40.0).abs() < 1e-9, "per piece");
        assert!((of("dispatch") - 40.0).abs() < 1e-9, "20 ns a piece, half a task a piece: 40 ns a task");
        assert!((of("image_encoding") - 10.0).abs() < 1e-9, "5 ns a piece, 2 pieces a pixel: 10 ns a pixel");
    }
}
