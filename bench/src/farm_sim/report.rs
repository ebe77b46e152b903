//! The sweeps and their tables: the inputs, the workloads, speedup and efficiency of the
//! design as it is over workers × datasets, and what lifts the coordinator's limit.

use anyhow::Result;

use super::inputs::Inputs;
use super::placement::Placement;
use super::scene::SceneSpec;
use super::sim::{simulate, Dispatch, FarmConfig, Outcome};
use super::workload::{extract, Workload};
use super::Args;

/// Workers at which the target is judged (the issue: efficiency ≥ 0.8 at 64 workers on a
/// scene of at least 256 datasets).
const TARGET_WORKERS: usize = 64;
const TARGET_EFFICIENCY: f64 = 0.8;

/// A farm to simulate: the machines, how the coordinator works, and where the data is.
#[derive(Clone, Debug)]
pub(crate) struct Farm {
    pub config: FarmConfig,
    pub placement: Placement,
    /// Scales the event loop's cost per task handed out (1: `next_batch` as it is).
    pub dispatch_scale: f64,
    /// Whether the coordinator's work costs nothing (a bound: what placement, waves, bands
    /// and the network allow).
    pub free_coordinator: bool,
}

impl Farm {
    /// The design as it is, with `workers` workers.
    pub(crate) fn as_is(args: &Args, workers: usize) -> Farm {
        Farm {
            config: FarmConfig {
                workers,
                worker_threads: args.worker_threads,
                coordinator_cores: args.coordinator_cores,
                loops: 1,
                coordinators: 1,
                spread_bands: false,
                batch_tasks: 4096,
                bands_in_flight: 2,
                dispatch: Dispatch::Scan,
                bvh: false,
            },
            placement: Placement::round_robin(1),
            dispatch_scale: 1.0,
            free_coordinator: false,
        }
    }

    /// The same farm with one worker that holds every dataset: the speedup's baseline.
    fn single(&self) -> Farm {
        let mut one = self.clone();
        one.config.workers = 1;
        one.placement = Placement::round_robin(1);
        one
    }

    pub(crate) fn simulate(&self, work: &Workload, inputs: &Inputs) -> Outcome {
        let samples: Vec<u64> = work.per_dataset().iter().map(|p| p.1).collect();
        let holders = self.placement.holders(self.config.workers, &samples);
        let mut inputs = inputs.clone();
        inputs.dispatch_per_task *= self.dispatch_scale;
        if self.free_coordinator {
            inputs = inputs.without_coordinator();
        }
        simulate(work, &inputs, &self.config, &holders)
    }
}

/// A farm's outcome and its speedup and efficiency over the same farm with one worker.
pub(crate) struct Scaled {
    pub outcome: Outcome,
    pub speedup: f64,
    pub efficiency: f64,
}

pub(crate) fn scaled(farm: &Farm, work: &Workload, inputs: &Inputs) -> Scaled {
    let one = farm.single().simulate(work, inputs).seconds;
    let outcome = farm.simulate(work, inputs);
    let speedup = one / outcome.seconds;
    Scaled { speedup, efficiency: speedup / farm.config.workers as f64, outcome }
}

/// What limits a job: the busiest resource, and for the event loop the parts that fill it.
pub(crate) fn bottleneck(o: &Outcome) -> String {
    let candidates = [
        ("coordinator event loop", o.loop_busy),
        ("coordinator blocking threads", o.pool_busy),
        ("coordinator link", o.link_busy),
        ("workers", o.worker_max),
    ];
    let (name, busy) = candidates.iter().copied().fold(("", 0.0), |a, b| if b.1 > a.1 { b } else { a });
    if busy < 0.7 {
        if o.no_band_cast > 0.15 {
            return format!(
                "band pipeline: no band being cast {:.0}% of the time (busiest: {name} {:.0}%)",
                100.0 * o.no_band_cast,
                100.0 * busy
            );
        }
        return format!("nothing saturated (busiest: {name} {:.0}%): waves and latency", 100.0 * busy);
    }
    match name {
        "coordinator event loop" => {
            let s = &o.spent;
            let t = s.total().max(1e-12);
            let mut parts = [
                ("dispatch", s.dispatch),
                ("scan", s.scan),
                ("record", s.record),
                ("progress", s.progress),
                ("open", s.open),
                ("events", s.events),
            ];
            parts.sort_by(|a, b| b.1.total_cmp(&a.1));
            let top: Vec<String> = parts.iter().take(2).map(|(n, v)| format!("{n} {:.0}%", 100.0 * v / t)).collect();
            format!("event loop {:.0}% busy ({})", 100.0 * busy, top.join(", "))
        }
        "workers" if o.worker_mean < 0.85 * o.worker_max => {
            format!("workers, uneven: busiest {:.0}%, mean {:.0}%", 100.0 * o.worker_max, 100.0 * o.worker_mean)
        }
        _ => format!("{name} {:.0}% busy", 100.0 * busy),
    }
}

/// Runs every table.
pub(crate) fn run(args: &Args, inputs: &Inputs) -> Result<()> {
    print_inputs(inputs);
    let mut workloads = Vec::new();
    for &d in &args.datasets {
        let spec = SceneSpec {
            datasets: d,
            depth: args.depth,
            dims: args.dims,
            width: args.size,
            height: args.size,
            step_voxels: 1.0,
            seed: args.seed,
        };
        workloads.push(extract(&spec, args.band_pixels, args.sampled_rows, 2 * (args.dims as u64).pow(3))?);
    }
    print_workloads(&workloads, inputs, args);
    print_sweep("The design as it is", &workloads, inputs, args, |_| {});
    let lifted = workloads.iter().filter(|w| w.datasets >= 256).collect::<Vec<_>>();
    for w in &lifted {
        print_lifts(w, inputs, args);
    }
    print_sweep("With every lift", &workloads, inputs, args, |f| LIFTS.iter().for_each(|(_, lift)| lift(f)));
    Ok(())
}

/// One change to the farm, applied on top of the ones before it.
type Lift = (&'static str, fn(&mut Farm));

/// The changes that lift the coordinator's limit, in the order the table applies them.
/// Those marked "projected" model code that does not exist yet.
pub(crate) const LIFTS: [Lift; 7] = [
    ("holders kept per job: no registry scan per event", |f| f.config.dispatch = Dispatch::Indexed),
    ("intersection through a BVH (projected)", |f| f.config.bvh = true),
    ("8 bands in flight, spread over the image", |f| {
        f.config.bands_in_flight = 8;
        f.config.spread_bands = true
    }),
    ("an event loop per band in flight, 32 coordinator cores", |f| {
        f.config.loops = 8;
        f.config.coordinator_cores = 32
    }),
    ("every dataset on 2 workers, the busiest quarter on 2 more", |f| {
        f.placement.replicas = 2;
        f.placement.hot_fraction = 0.25;
        f.placement.hot_extra = 2
    }),
    ("next_batch 4× cheaper (projected: fronts kept per ray)", |f| f.dispatch_scale = 0.25),
    ("2 coordinators, each a tile of the image", |f| f.config.coordinators = 2),
];

fn print_inputs(inputs: &Inputs) {
    println!("## Inputs\n\n| input | value | unit | source |\n|---|---:|---|---|");
    for p in inputs.provenance() {
        println!("| {} | {:.3} | {} | {} |", p.name, p.value, p.unit, p.how);
    }
}

fn print_workloads(workloads: &[Workload], inputs: &Inputs, args: &Args) {
    println!(
        "\n## Workloads ({0}×{0} pixels, bands of {1} pixels, datasets {2}³ u16, {3} datasets per ray on average)\n",
        args.size, args.band_pixels, args.dims, args.depth
    );
    println!("| datasets | bands | tasks | samples / task | datasets per band | waves per dataset and band | casting (core-s) | event loop, per-task work (s) |");
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|");
    for w in workloads {
        let cast = w.tasks() as f64 * inputs.cast_per_task + w.samples() as f64 * inputs.cast_per_sample;
        let lanes: usize = w.bands.iter().map(|b| b.lanes.len()).sum();
        let waves: usize = w.bands.iter().flat_map(|b| &b.lanes).map(|l| l.waves.len()).sum();
        println!(
            "| {} | {} | {} | {:.0} | {:.1} | {:.2} | {:.0} | {:.1} |",
            w.datasets,
            w.bands.len(),
            w.tasks(),
            w.samples() as f64 / w.tasks() as f64,
            lanes as f64 / w.bands.len() as f64,
            waves as f64 / lanes.max(1) as f64,
            cast,
            w.tasks() as f64 * (inputs.dispatch_per_task + inputs.record_per_task)
        );
    }
}

fn print_sweep(title: &str, workloads: &[Workload], inputs: &Inputs, args: &Args, change: impl Fn(&mut Farm)) {
    println!("\n## {title}\n");
    println!("| datasets | workers | time (s) | speedup | efficiency | bottleneck |");
    println!("|---:|---:|---:|---:|---:|---|");
    for w in workloads {
        for &n in &args.workers {
            let mut farm = Farm::as_is(args, n);
            change(&mut farm);
            let r = scaled(&farm, w, inputs);
            println!(
                "| {} | {n} | {:.2} | {:.1} | {:.2} | {} |",
                w.datasets,
                r.outcome.seconds,
                r.speedup,
                r.efficiency,
                bottleneck(&r.outcome)
            );
        }
    }
}

fn print_lifts(work: &Workload, inputs: &Inputs, args: &Args) {
    let n = TARGET_WORKERS;
    println!("\n## What lifts the limit: {} datasets, {n} workers, each change on top of those above\n", work.datasets);
    println!("| change | time (s) | efficiency | busiest loop | loop seconds: dispatch / scan / record / other | bottleneck |");
    println!("|---|---:|---:|---:|---|---|");
    let mut farm = Farm::as_is(args, n);
    let mut reached = None;
    let row = |name: &str, farm: &Farm| {
        let r = scaled(farm, work, inputs);
        let s = &r.outcome.spent;
        println!(
            "| {name} | {:.2} | {:.2} | {:.0}% | {:.1} / {:.1} / {:.1} / {:.1} | {} |",
            r.outcome.seconds,
            r.efficiency,
            100.0 * r.outcome.loop_busy,
            s.dispatch,
            s.scan,
            s.record,
            s.events + s.open + s.progress,
            bottleneck(&r.outcome)
        );
        r.efficiency
    };
    let as_is = row("as it is", &farm);
    for (name, lift) in LIFTS {
        lift(&mut farm);
        let e = row(name, &farm);
        if e >= TARGET_EFFICIENCY && reached.is_none() {
            reached = Some((name, e));
        }
    }
    farm.free_coordinator = true;
    let bound = row("(bound: the same with a coordinator that costs nothing)", &farm);
    println!(
        "\nTarget, efficiency ≥ {TARGET_EFFICIENCY} at {n} workers on {} datasets: as it is {as_is:.2}; {}; \
         with a free coordinator the same placement, bands and network allow {bound:.2}.",
        work.datasets,
        match reached {
            Some((name, e)) => format!("reached ({e:.2}) once \"{name}\" is added"),
            None => "not reached by the changes above".to_string(),
        }
    );
}

#[cfg(test)]
mod tests {
    use super::super::sim::LoopSpent;
    use super::*;

    fn outcome(loop_busy: f64, pool_busy: f64, worker_mean: f64, worker_max: f64) -> Outcome {
        Outcome {
            seconds: 1.0,
            loop_busy,
            spent: LoopSpent { dispatch: 0.6, scan: 0.3, record: 0.1, ..LoopSpent::default() },
            pool_busy,
            intersect: 0.0,
            composite: 0.0,
            link_busy: 0.1,
            no_band_cast: 0.0,
            worker_mean,
            worker_max,
            cast: 0.0,
            load: 0.0,
            batches: 1,
        }
    }

    #[test]
    fn the_bottleneck_is_the_busiest_resource_with_its_parts() {
        assert_eq!(bottleneck(&outcome(0.95, 0.2, 0.3, 0.4)), "event loop 95% busy (dispatch 60%, scan 30%)");
        assert_eq!(bottleneck(&outcome(0.3, 0.9, 0.3, 0.4)), "coordinator blocking threads 90% busy");
        assert_eq!(bottleneck(&outcome(0.3, 0.2, 0.5, 0.9)), "workers, uneven: busiest 90%, mean 50%");
        assert_eq!(bottleneck(&outcome(0.3, 0.2, 0.85, 0.9)), "workers 90% busy");
        assert!(bottleneck(&outcome(0.3, 0.2, 0.3, 0.4)).starts_with("nothing saturated"));
    }
}
