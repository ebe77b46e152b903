//! `trove-bench farm-sim`: the render farm beyond one machine, as a discrete-event
//! simulation. It predicts how a job's time falls with 8 to 256 workers on scenes of 16 to
//! 1024 datasets, where the coordinator becomes the bottleneck, and which coordinator layout
//! (cores, count, tiles or whole jobs) reaches the targets.
//!
//! * [`scene`] generates the scenes (cubes scattered in front of the camera, seeded);
//! * [`workload`] takes a job's work from `trove-core` itself: bands, and per band the waves
//!   of each dataset with their tasks and samples;
//! * [`recorded`] reads the measured costs: the real coordinator's, recorded by
//!   `trove-bench coordinator --record`, and the workers', timed by [`measure`] with the
//!   worker's own caster; [`inputs`] turns them into costs per step;
//! * [`placement`] puts datasets on workers;
//! * [`sim`] is the model of the coordinator's driver (the job's event loop, and a thread per
//!   band in flight that does the band's per-task steps) and the workers, over [`pool`]'s
//!   cores and links;
//! * [`report`] runs the sweeps and prints the tables.
//!
//! The simulation is deterministic: the same options and recorded files give the same
//! tables. `--measure` times the workers on this processor instead of reading their file.

mod inputs;
mod measure;
mod placement;
mod pool;
pub(crate) mod recorded;
mod report;
mod scene;
mod sim;
mod workload;

use std::path::PathBuf;

use anyhow::Result;
use trove_coordinator::farm::DriverConfig;

use inputs::Inputs;

/// `trove-bench farm-sim` options.
#[derive(clap::Args, Clone, Debug)]
pub struct Args {
    /// The coordinator's costs: a `trove-bench coordinator --record` file.
    #[arg(long, default_value_os_t = recorded_file("coordinator.json"))]
    coordinator_inputs: PathBuf,
    /// The workers' costs: a `farm-sim --measure --record-worker` file (unless `--measure`).
    #[arg(long, default_value_os_t = recorded_file("worker.json"))]
    worker_inputs: PathBuf,
    /// Time the workers' costs on this processor now (some 20 s) instead of reading them.
    #[arg(long)]
    measure: bool,
    /// With `--measure`: also write what was measured to this file.
    #[arg(long, requires = "measure")]
    record_worker: Option<PathBuf>,
    /// Image width and height in pixels.
    #[arg(long, default_value_t = 4096)]
    size: u32,
    /// Voxels per axis of every dataset (u16): 256 gives 32 MiB datasets.
    #[arg(long, default_value_t = 256)]
    dims: u32,
    /// Mean number of datasets a ray crosses.
    #[arg(long, default_value_t = 4.0)]
    depth: f64,
    /// Dataset counts to simulate.
    #[arg(long, value_delimiter = ',', default_value = "16,64,256,1024")]
    datasets: Vec<usize>,
    /// Worker counts to simulate.
    #[arg(long, value_delimiter = ',', default_value = "8,16,32,64,128,256")]
    workers: Vec<usize>,
    /// Cores per worker.
    #[arg(long, default_value_t = 8)]
    worker_threads: usize,
    /// Cores of each coordinator (the job's event loop takes one; the bands' threads,
    /// rayon's work and the transport share the others).
    #[arg(long, default_value_t = 16)]
    coordinator_cores: usize,
    /// Coordinators sharing the workers, each a tile of the image (or, with
    /// `--split-jobs`, each a whole job of its own).
    #[arg(long, default_value_t = 1)]
    coordinators: usize,
    #[arg(long)]
    split_jobs: bool,
    /// Bands a job holds at once (the driver's `max_bands`).
    #[arg(long, default_value_t = DriverConfig::default().max_bands)]
    max_bands: usize,
    /// MiB of band bookkeeping a job holds at once (the driver's `memory_bound`,
    /// `--band-memory`).
    #[arg(long, default_value_t = DriverConfig::default().memory_bound >> 20)]
    band_memory_mib: u64,
    /// Link bandwidth of every machine, each way, in Gbit/s.
    #[arg(long, default_value_t = 10.0)]
    link_gbit: f64,
    /// One-way latency between machines, in microseconds.
    #[arg(long, default_value_t = 50.0)]
    latency_us: f64,
    /// Pixels per band (the driver's default).
    #[arg(long, default_value_t = workload::BAND_PIXELS)]
    band_pixels: u32,
    /// Rows per band intersected to take the workload (more: finer, slower).
    #[arg(long, default_value_t = 4)]
    sampled_rows: u32,
    /// Seed of the scene's layout.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Coordinator counts of the layout table.
    #[arg(long, value_delimiter = ',', default_value = "1,2,4,8,16")]
    layout_coordinators: Vec<usize>,
    /// Cores per coordinator of the layout table.
    #[arg(long, value_delimiter = ',', default_value = "4,8,16")]
    layout_cores: Vec<usize>,
    /// Skip the layout table.
    #[arg(long)]
    no_layouts: bool,
}

/// A file of `bench/recorded/`.
fn recorded_file(name: &str) -> PathBuf {
    trove_tests::repo_root().join("bench/recorded").join(name)
}

/// Runs the simulation and prints its tables.
pub fn run(args: Args) -> Result<()> {
    let started = std::time::Instant::now();
    let coordinator = recorded::CoordinatorRecord::read(&args.coordinator_inputs)?;
    let worker = if args.measure {
        eprintln!("measuring the workers' costs on this processor…");
        let w = measure::measure(measure::Size::FULL)?;
        if let Some(file) = &args.record_worker {
            w.write(file)?;
            eprintln!("recorded them in {}", file.display());
        }
        w
    } else {
        recorded::WorkerRecord::read(&args.worker_inputs)?
    };
    let here = (recorded::processor(), recorded::simd_path());
    for (what, p, simd) in
        [("coordinator", &coordinator.processor, &coordinator.simd), ("worker", &worker.processor, &worker.simd)]
    {
        if (p.as_str(), simd.as_str()) != (here.0.as_str(), here.1) {
            eprintln!("note: the {what} inputs were recorded on \"{p}\" ({simd}); this is \"{}\" ({})", here.0, here.1);
        }
    }
    let inputs = Inputs::from_records(&coordinator, &worker).with_link(args.link_gbit, args.latency_us);
    report::run(&args, &inputs, &coordinator, &worker)?;
    println!("\n(simulated in {:.1} s)", started.elapsed().as_secs_f64());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The repository's recorded inputs are of the code's formats: a change that bumps a
    /// format must record them again.
    #[test]
    fn the_recorded_inputs_in_the_repository_are_of_the_current_format() {
        let c = recorded::CoordinatorRecord::read(&recorded_file("coordinator.json")).unwrap();
        let w = recorded::WorkerRecord::read(&recorded_file("worker.json")).unwrap();
        let inputs = Inputs::from_records(&c, &w);
        for place in [recorded::RunsOn::EventLoop, recorded::RunsOn::Band] {
            assert!(inputs.stages.iter().any(|s| s.runs_on == place && s.seconds > 0.0), "{place:?}");
        }
        assert!(inputs.cast_per_sample > 0.0);
    }
}
