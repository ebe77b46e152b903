//! What the simulation is fed: the cost of each step of the farm, in seconds per unit of
//! work. Most are measured on this machine by running `trove-core`'s own code
//! ([`super::measure`]); a few are not measurable without the farm's network stack and are
//! stated as assumptions. The defaults ([`Inputs::recorded`]) are one such measurement,
//! written down so that the simulation gives the same numbers on every run; `farm-sim
//! --measure` measures again and uses what it finds.

/// Costs of every step of a farm job. Core-seconds unless marked otherwise.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Inputs {
    // --- workers -------------------------------------------------------------------------
    /// Casting: per sample evaluated (interpolate, classify, composite).
    pub cast_per_sample: f64,
    /// Casting: per task (recompute the ray, check the task, walk set-up).
    pub cast_per_task: f64,
    /// Binding a dataset's objects before casting (`BatchCaster::new`), per voxel; paid
    /// whenever a worker's stream for that dataset starts again after running dry.
    pub bind_per_voxel: f64,
    /// Loading a dataset, per byte (one core).
    pub load_per_byte: f64,
    /// Parsing and validating the job's scene when a stream opens, per object.
    pub parse_per_object: f64,

    // --- coordinator, blocking threads --------------------------------------------------
    /// Intersection, per ray and object tested (every ray meets every object).
    pub intersect_per_ray_object: f64,
    /// Intersection, per task made (pieces split, tasks written).
    pub intersect_per_task: f64,
    /// `Scheduler::new` after a band's intersection (waves and dataset order), per task;
    /// it runs on one thread.
    pub plan_per_task: f64,
    /// Composition, per ray (background, quantisation) and per piece laid.
    pub composite_per_ray: f64,
    pub composite_per_piece: f64,
    /// Encoding the final PNG, per pixel, on one thread.
    pub png_per_pixel: f64,

    // --- coordinator, the job's event loop (one thread) ---------------------------------
    /// Handing out a task: `Scheduler::next_batch` (its culling bound and front) and
    /// `encode_tasks`.
    pub dispatch_per_task: f64,
    /// Taking a result back: `decode_results` and `Scheduler::record`.
    pub record_per_task: f64,
    /// `Registry::holders`, per registered worker (clock read, key lookup, id copy); the
    /// driver calls it for every unfinished dataset of every band being cast, on every
    /// event, and once more per batch sent.
    pub holders_per_worker: f64,
    /// `pick_worker`'s work per holder (a handle: lock, lookup, clones; filters; minimum).
    pub pick_per_holder: f64,
    /// `update_progress` after each answer, per worker that has answered in the job.
    pub progress_per_worker: f64,
    /// Opening a stream (once per worker and dataset): the scene's text and the headers of
    /// its files copied into the `open` message, per byte.
    pub open_per_byte: f64,
    /// Fixed cost of an event on the loop (channel receive, `select!`, match, status
    /// update). Assumed.
    pub per_event: f64,
    /// Fixed cost of a batch sent (stream map, queue send, bookkeeping). Assumed.
    pub per_send: f64,

    // --- network --------------------------------------------------------------------------
    /// Each machine's link, one direction, bytes per second.
    pub link_bytes_per_s: f64,
    /// One-way latency between two machines, seconds.
    pub latency: f64,
    /// Per message: framing bytes (gRPC, HTTP/2, protobuf) beyond the payload.
    pub message_overhead_bytes: f64,
    /// Per message: CPU time of each end's network stack, charged to its link. Assumed.
    pub per_message: f64,
}

/// Where an input comes from, for the printed table.
pub(crate) struct Provenance {
    pub name: &'static str,
    pub value: f64,
    pub unit: &'static str,
    pub how: &'static str,
}

impl Inputs {
    /// The measured defaults: see `BENCHMARKS.md` ("Farm simulation") for the run.
    pub(crate) fn recorded() -> Inputs {
        Inputs {
            cast_per_sample: 125.699e-9,
            cast_per_task: 217.259e-9,
            bind_per_voxel: 0.004e-9,
            load_per_byte: 0.542e-9,
            parse_per_object: 98954.863e-9,
            intersect_per_ray_object: 28.494e-9,
            intersect_per_task: 108.468e-9,
            plan_per_task: 46.558e-9,
            composite_per_ray: 0.0,
            composite_per_piece: 11.67e-9,
            png_per_pixel: 6.549e-9,
            dispatch_per_task: 147.138e-9,
            record_per_task: 12.204e-9,
            holders_per_worker: 56.176e-9,
            pick_per_holder: 287.396e-9,
            progress_per_worker: 47.42e-9,
            open_per_byte: 0.123e-9,
            per_event: 2e-6,
            per_send: 1e-6,
            link_bytes_per_s: 10e9 / 8.0,
            latency: 50e-6,
            message_overhead_bytes: 64.0,
            per_message: 2e-6,
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
        for cost in [
            &mut self.intersect_per_ray_object,
            &mut self.intersect_per_task,
            &mut self.plan_per_task,
            &mut self.composite_per_ray,
            &mut self.composite_per_piece,
            &mut self.png_per_pixel,
            &mut self.dispatch_per_task,
            &mut self.record_per_task,
            &mut self.holders_per_worker,
            &mut self.pick_per_holder,
            &mut self.progress_per_worker,
            &mut self.open_per_byte,
            &mut self.per_event,
            &mut self.per_send,
        ] {
            *cost = 0.0;
        }
        self
    }

    /// Seconds a message of `payload` bytes occupies a link.
    pub(crate) fn wire_seconds(&self, payload: f64) -> f64 {
        (payload + self.message_overhead_bytes) / self.link_bytes_per_s + self.per_message
    }

    /// Every input with its unit and how it was obtained, for the printed table.
    pub(crate) fn provenance(&self) -> Vec<Provenance> {
        let m = "measured";
        let p = |name, value, unit, how| Provenance { name, value, unit, how };
        vec![
            p("cast per sample", self.cast_per_sample * 1e9, "core-ns", m),
            p("cast per task", self.cast_per_task * 1e9, "core-ns", m),
            p("bind per voxel", self.bind_per_voxel * 1e9, "core-ns", m),
            p("load per byte", self.load_per_byte * 1e9, "core-ns", m),
            p("scene parse per object", self.parse_per_object * 1e9, "core-ns", m),
            p("intersect per ray·object", self.intersect_per_ray_object * 1e9, "core-ns", m),
            p("intersect per task", self.intersect_per_task * 1e9, "core-ns", m),
            p("plan per task", self.plan_per_task * 1e9, "ns (1 thread)", m),
            p("composite per ray", self.composite_per_ray * 1e9, "core-ns", m),
            p("composite per piece", self.composite_per_piece * 1e9, "core-ns", m),
            p("PNG per pixel", self.png_per_pixel * 1e9, "ns (1 thread)", m),
            p("dispatch per task", self.dispatch_per_task * 1e9, "ns (event loop)", m),
            p("record per task", self.record_per_task * 1e9, "ns (event loop)", m),
            p("holders per worker", self.holders_per_worker * 1e9, "ns (event loop)", "measured on a replica"),
            p("pick per holder", self.pick_per_holder * 1e9, "ns (event loop)", "measured on a replica"),
            p("progress per worker", self.progress_per_worker * 1e9, "ns (event loop)", "measured on a replica"),
            p("open per scene byte", self.open_per_byte * 1e9, "ns (event loop)", "measured on a replica"),
            p("per event", self.per_event * 1e9, "ns (event loop)", "assumed"),
            p("per batch sent", self.per_send * 1e9, "ns (event loop)", "assumed"),
            p("link", self.link_bytes_per_s * 8e-9, "Gbit/s", "parameter"),
            p("latency (one way)", self.latency * 1e6, "µs", "parameter"),
            p("framing per message", self.message_overhead_bytes, "bytes", "assumed"),
            p("stack per message", self.per_message * 1e9, "ns per end", "assumed"),
        ]
    }
}
