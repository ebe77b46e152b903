//! The sweeps and their tables: the inputs, the workloads, speedup and efficiency of the
//! coordinator as it is over workers × datasets, and which coordinator layout (cores per
//! coordinator, coordinators, tiles or whole jobs) reaches the targets.

use std::collections::HashMap;

use anyhow::Result;

use super::inputs::Inputs;
use super::placement::Placement;
use super::recorded::{At, CoordinatorRecord, RunsOn, WorkerRecord};
use super::scene::SceneSpec;
use super::sim::{simulate, FarmConfig, Outcome, Split};
use super::workload::{extract, Workload};
use super::Args;

/// The targets: (datasets, workers, efficiency at least).
pub(crate) const TARGETS: [(usize, usize, f64); 4] =
    [(256, 64, 0.8), (1024, 64, 0.8), (256, 256, 0.6), (1024, 256, 0.6)];

/// A farm to simulate: the machines, the coordinators, and where the data is.
#[derive(Clone, Debug)]
pub(crate) struct Farm {
    pub config: FarmConfig,
    pub placement: Placement,
    /// Whether the coordinator's work costs nothing (a bound: what placement, waves, bands
    /// and the network allow).
    pub free_coordinator: bool,
}

impl Farm {
    /// The farm the options describe, with `workers` workers.
    pub(crate) fn new(args: &Args, workers: usize) -> Farm {
        Farm {
            config: FarmConfig {
                workers,
                worker_threads: args.worker_threads,
                coordinator_cores: args.coordinator_cores,
                coordinators: args.coordinators,
                split: if args.split_jobs { Split::Jobs } else { Split::Tiles },
                batch_tasks: trove_coordinator::farm::driver::DEFAULT_BATCH_TASKS as u64,
                max_bands: args.max_bands,
                memory_bound: args.band_memory_mib << 20,
            },
            placement: Placement::round_robin(1),
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
        if self.free_coordinator {
            return simulate(work, &inputs.clone().without_coordinator(), &self.config, &holders);
        }
        simulate(work, inputs, &self.config, &holders)
    }
}

/// A farm's outcome and its speedup and efficiency over the same farm with one worker.
pub(crate) struct Scaled {
    pub outcome: Outcome,
    pub speedup: f64,
    pub efficiency: f64,
}

/// Simulates `farm` and its one-worker baseline (kept in `baselines` by layout, scene and
/// whether the coordinator is free, since many farms share one).
pub(crate) fn scaled(farm: &Farm, work: &Workload, inputs: &Inputs, baselines: &mut HashMap<String, f64>) -> Scaled {
    let c = &farm.config;
    let key = format!(
        "{} {} {:?} {} {} {}",
        c.coordinator_cores, c.coordinators, c.split, work.datasets, c.worker_threads, farm.free_coordinator
    );
    let one = *baselines.entry(key).or_insert_with(|| farm.single().simulate(work, inputs).seconds);
    let outcome = farm.simulate(work, inputs);
    let speedup = one / outcome.seconds;
    Scaled { speedup, efficiency: speedup / farm.config.workers as f64, outcome }
}

/// What limits a run: the busiest resource, and for the event loop and the bands' threads
/// the parts that fill them. The bands' threads wait for a core when the cores are full, so
/// they are named only when the cores are not.
pub(crate) fn bottleneck(o: &Outcome) -> String {
    let candidates = [
        ("coordinator event loop", o.loop_busy),
        ("coordinator's other cores", o.pool_busy),
        ("bands' threads", if o.pool_busy < 0.9 { o.band_busy } else { 0.0 }),
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
            let t = (o.loop_send + o.loop_answer + o.loop_other).max(1e-12);
            format!(
                "event loop {:.0}% busy (sending {:.0}%, answers {:.0}%)",
                100.0 * busy,
                100.0 * o.loop_send / t,
                100.0 * o.loop_answer / t
            )
        }
        "bands' threads" => {
            let t = (o.band_send + o.band_answer + o.band_other).max(1e-12);
            format!(
                "bands' threads {:.0}% busy, {:.1} bands held (handing out {:.0}%, answers {:.0}%)",
                100.0 * busy,
                o.bands_held,
                100.0 * o.band_send / t,
                100.0 * o.band_answer / t
            )
        }
        "workers" if o.worker_mean < 0.85 * o.worker_max => {
            format!("workers, uneven: busiest {:.0}%, mean {:.0}%", 100.0 * o.worker_max, 100.0 * o.worker_mean)
        }
        _ => format!("{name} {:.0}% busy", 100.0 * busy),
    }
}

/// Runs every table.
pub(crate) fn run(args: &Args, inputs: &Inputs, coordinator: &CoordinatorRecord, worker: &WorkerRecord) -> Result<()> {
    print_inputs(args, inputs, coordinator, worker);
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
    let mut baselines = HashMap::new();
    print_workloads(&workloads, inputs, args);
    let layout = describe(&Farm::new(args, 1).config);
    print_sweep(&format!("As it is: {layout}"), &workloads, inputs, args, &mut baselines);
    if !args.no_layouts {
        print_layouts(&workloads, inputs, args, &mut baselines);
    }
    Ok(())
}

/// A layout in words.
fn describe(c: &FarmConfig) -> String {
    match (c.coordinators, c.split) {
        (1, _) => format!("one coordinator of {} cores", c.coordinator_cores),
        (n, Split::Tiles) => format!("{n} coordinators of {} cores, each a tile of the image", c.coordinator_cores),
        (n, Split::Jobs) => format!("{n} coordinators of {} cores, each a whole job", c.coordinator_cores),
    }
}

fn print_inputs(args: &Args, inputs: &Inputs, c: &CoordinatorRecord, w: &WorkerRecord) {
    println!("## Inputs\n");
    println!(
        "Coordinator: `{}` (format {}), recorded on \"{}\" ({}), at {}, by `{}`; {} scene(s): {}.",
        args.coordinator_inputs.display(),
        c.format,
        c.processor,
        c.simd,
        c.commit,
        c.command,
        c.scenes.len(),
        c.scenes
            .iter()
            .map(|s| format!(
                "{} ({:.0} ns of CPU a piece, {:.2} tasks a piece, {:.2} pieces a pixel)",
                s.scene,
                s.cpu_ns_per_piece,
                s.tasks_per_piece(),
                s.pieces_per_pixel()
            ))
            .collect::<Vec<_>>()
            .join("; ")
    );
    println!(
        "Workers: {} on \"{}\" ({}), at {}.\n",
        if args.measure { "measured now".to_string() } else { format!("`{}`", args.worker_inputs.display()) },
        w.processor,
        w.simd,
        w.commit
    );
    println!("| coordinator stage | runs on | paid | cost | unit |\n|---|---|---|---:|---|");
    for s in &inputs.stages {
        let unit = match s.at {
            At::Intersect | At::Composite => "ns a piece",
            At::Send | At::Answer => "ns a task",
            At::Finish => "ns a pixel",
        };
        println!("| {} | {:?} | {:?} | {:.1} | {unit} |", s.name, s.runs_on, s.at, s.seconds * 1e9);
    }
    println!("\n| worker input | value | unit |\n|---|---:|---|");
    for (name, value, unit) in [
        ("cast per sample", inputs.cast_per_sample * 1e9, "core-ns"),
        ("cast per task", inputs.cast_per_task * 1e9, "core-ns"),
        ("first bind per voxel", inputs.bind_per_voxel * 1e9, "core-ns"),
        ("bind again per voxel", inputs.rebind_per_voxel * 1e9, "core-ns"),
        ("load per byte", inputs.load_per_byte * 1e9, "core-ns"),
        ("scene parse per object", inputs.parse_per_object * 1e9, "core-ns"),
        ("link", inputs.link_bytes_per_s * 8e-9, "Gbit/s (parameter)"),
        ("latency, one way", inputs.latency * 1e6, "µs (parameter)"),
        ("framing per message", inputs.message_overhead_bytes, "bytes (assumed)"),
    ] {
        println!("| {name} | {value:.3} | {unit} |");
    }
}

fn print_workloads(workloads: &[Workload], inputs: &Inputs, args: &Args) {
    println!(
        "\n## Workloads ({0}×{0} pixels, bands of {1} pixels, datasets {2}³ u16, {3} datasets per ray on average)\n",
        args.size, args.band_pixels, args.dims, args.depth
    );
    println!("| datasets | bands | tasks | samples / task | datasets per band | waves per dataset and band | MiB per band | casting (core-s) | bands' threads' per-task steps (core-s) | event loop (s) |");
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let per_task = |runs_on| inputs.cost(At::Send, runs_on) + inputs.cost(At::Answer, runs_on);
    let (loop_per_task, band_per_task) = (per_task(RunsOn::EventLoop), per_task(RunsOn::Band));
    for w in workloads {
        let cast = w.tasks() as f64 * inputs.cast_per_task + w.samples() as f64 * inputs.cast_per_sample;
        let lanes: usize = w.bands.iter().map(|b| b.lanes.len()).sum();
        let waves: usize = w.bands.iter().flat_map(|b| &b.lanes).map(|l| l.waves.len()).sum();
        let bytes = w.bands.iter().map(|b| b.bytes).sum::<u64>() as f64 / w.bands.len().max(1) as f64;
        println!(
            "| {} | {} | {} | {:.0} | {:.1} | {:.2} | {:.1} | {:.0} | {:.1} | {:.1} |",
            w.datasets,
            w.bands.len(),
            w.tasks(),
            w.samples() as f64 / w.tasks() as f64,
            lanes as f64 / w.bands.len() as f64,
            waves as f64 / lanes.max(1) as f64,
            bytes / (1 << 20) as f64,
            cast,
            w.tasks() as f64 * band_per_task,
            w.tasks() as f64 * loop_per_task
        );
    }
}

fn print_sweep(
    title: &str,
    workloads: &[Workload],
    inputs: &Inputs,
    args: &Args,
    baselines: &mut HashMap<String, f64>,
) {
    println!("\n## {title}\n");
    println!("| datasets | workers | time (s) | speedup | efficiency | bands held | bottleneck |");
    println!("|---:|---:|---:|---:|---:|---:|---|");
    for w in workloads {
        for &n in &args.workers {
            let r = scaled(&Farm::new(args, n), w, inputs, baselines);
            println!(
                "| {} | {n} | {:.2} | {:.1} | {:.2} | {:.1} | {} |",
                w.datasets,
                r.outcome.seconds,
                r.speedup,
                r.efficiency,
                r.outcome.bands_held,
                bottleneck(&r.outcome)
            );
        }
    }
}

/// Two placements an operator would try: one copy of each dataset, and two copies with the
/// busiest quarter on two more.
fn placements() -> [(&'static str, Placement); 2] {
    [
        ("1 copy", Placement::round_robin(1)),
        ("2 copies, busiest ¼ on 2 more", Placement { replicas: 2, hot_fraction: 0.25, hot_extra: 2 }),
    ]
}

fn print_layouts(workloads: &[Workload], inputs: &Inputs, args: &Args, baselines: &mut HashMap<String, f64>) {
    let targets: Vec<(&Workload, usize, f64)> =
        TARGETS.iter().filter_map(|&(d, n, e)| workloads.iter().find(|w| w.datasets == d).map(|w| (w, n, e))).collect();
    if targets.is_empty() {
        return;
    }
    println!("\n## Coordinator layouts against the targets\n");
    println!(
        "Efficiency with each layout ({} workers of {} cores); a layout meets the targets when every column does.\n",
        targets.iter().map(|t| t.1.to_string()).collect::<Vec<_>>().join("/"),
        args.worker_threads
    );
    let header: Vec<String> =
        targets.iter().map(|(w, n, e)| format!("{} datasets, {n} workers (≥ {e})", w.datasets)).collect();
    println!("| layout | placement | {} | bottleneck at the last |", header.join(" | "));
    println!("|---|---|{}---|", "---:|".repeat(targets.len()));
    let mut layouts = Vec::new();
    for &count in &args.layout_coordinators {
        for split in if count == 1 { vec![Split::Tiles] } else { vec![Split::Tiles, Split::Jobs] } {
            for &cores in &args.layout_cores {
                layouts.push((cores, count, split));
            }
        }
    }
    let mut met: Vec<(usize, String, String)> = Vec::new();
    for (cores, count, split) in layouts {
        for (pname, placement) in placements() {
            let mut cells = Vec::new();
            let mut all = true;
            let mut last = String::new();
            for &(w, n, target) in &targets {
                let mut farm = Farm::new(args, n);
                farm.config.coordinator_cores = cores;
                farm.config.coordinators = count;
                farm.config.split = split;
                farm.placement = placement.clone();
                let r = scaled(&farm, w, inputs, baselines);
                all &= r.efficiency >= target;
                cells.push(format!("{:.2}", r.efficiency));
                last = bottleneck(&r.outcome);
            }
            let name = describe(&FarmConfig {
                coordinator_cores: cores,
                coordinators: count,
                split,
                ..Farm::new(args, 1).config
            });
            println!("| {name} | {pname} | {} | {last} |", cells.join(" | "));
            if all {
                met.push((cores * count, name, pname.to_string()));
            }
        }
    }
    let mut bound = Vec::new();
    for (pname, placement) in placements() {
        let mut cells = Vec::new();
        for &(w, n, _) in &targets {
            let mut farm = Farm::new(args, n);
            farm.placement = placement.clone();
            farm.free_coordinator = true;
            cells.push(format!("{:.2}", scaled(&farm, w, inputs, baselines).efficiency));
        }
        println!("| (bound: a coordinator that costs nothing) | {pname} | {} | |", cells.join(" | "));
        bound.push(cells.join("/"));
    }
    met.sort_by(|a, b| a.0.cmp(&b.0).then(a.1.cmp(&b.1)));
    match met.first() {
        Some((cores, name, pname)) => println!(
            "\nThe smallest layout that meets every target: {name} ({cores} coordinator cores in all), placement \"{pname}\"."
        ),
        None => println!("\nNo layout above meets every target (a free coordinator allows {}).", bound.join(" and ")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn outcome(loop_busy: f64, pool_busy: f64, worker_mean: f64, worker_max: f64) -> Outcome {
        Outcome {
            seconds: 1.0,
            loop_busy,
            loop_send: 0.6,
            loop_answer: 0.3,
            loop_other: 0.1,
            band_busy: 0.0,
            band_send: 0.5,
            band_answer: 0.25,
            band_other: 0.25,
            pool_busy,
            link_busy: 0.1,
            no_band_cast: 0.0,
            bands_held: 8.0,
            worker_mean,
            worker_max,
            cast: 0.0,
            load: 0.0,
            batches: 1,
        }
    }

    #[test]
    fn the_bottleneck_is_the_busiest_resource_with_its_parts() {
        assert_eq!(bottleneck(&outcome(0.95, 0.2, 0.3, 0.4)), "event loop 95% busy (sending 60%, answers 30%)");
        assert_eq!(bottleneck(&outcome(0.3, 0.9, 0.3, 0.4)), "coordinator's other cores 90% busy");
        assert_eq!(bottleneck(&outcome(0.3, 0.2, 0.5, 0.9)), "workers, uneven: busiest 90%, mean 50%");
        assert_eq!(bottleneck(&outcome(0.3, 0.2, 0.85, 0.9)), "workers 90% busy");
        assert!(bottleneck(&outcome(0.3, 0.2, 0.3, 0.4)).starts_with("nothing saturated"));
        let bands = Outcome { band_busy: 0.97, ..outcome(0.1, 0.3, 0.3, 0.4) };
        assert_eq!(bottleneck(&bands), "bands' threads 97% busy, 8.0 bands held (handing out 50%, answers 25%)");
        // Threads waiting for full cores: the cores are the limit.
        let cores = Outcome { band_busy: 0.99, ..outcome(0.1, 0.95, 0.3, 0.4) };
        assert_eq!(bottleneck(&cores), "coordinator's other cores 95% busy");
    }
}
