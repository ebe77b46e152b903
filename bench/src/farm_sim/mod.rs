//! `trove-bench farm-sim`: the render farm beyond one machine, as a discrete-event
//! simulation. It predicts how a job's time falls with 8 to 256 workers on scenes of 16 to
//! 1024 datasets, where the coordinator becomes the bottleneck, and what lifts that limit.
//!
//! * [`scene`] generates the scenes (cubes scattered in front of the camera, seeded);
//! * [`workload`] takes a job's work from `trove-core` itself: bands, and per band the waves
//!   of each dataset with their tasks and samples;
//! * [`inputs`] holds the cost of every step, [`measure`] measures them here with the code
//!   the farm runs;
//! * [`placement`] puts datasets on workers;
//! * [`sim`] is the model of the coordinator's driver and the workers, over [`pool`]'s cores
//!   and links;
//! * [`report`] runs the sweeps and prints the tables.
//!
//! The simulation is deterministic: the same options give the same tables. Only `--measure`
//! (which times this machine) changes the inputs.

mod inputs;
mod measure;
mod placement;
mod pool;
pub(crate) mod recorded;
mod report;
mod scene;
mod sim;
mod workload;

use anyhow::Result;

use inputs::Inputs;

/// `trove-bench farm-sim` options.
#[derive(clap::Args, Clone, Debug)]
pub struct Args {
    /// Measure the inputs on this machine (about 10 s) instead of using the recorded ones.
    #[arg(long)]
    measure: bool,
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
    /// Cores of the coordinator.
    #[arg(long, default_value_t = 16)]
    coordinator_cores: usize,
    /// Link bandwidth of every machine, each way, in Gbit/s.
    #[arg(long, default_value_t = 10.0)]
    link_gbit: f64,
    /// One-way latency between machines, in microseconds.
    #[arg(long, default_value_t = 50.0)]
    latency_us: f64,
    /// Pixels per band (the driver's default is 262144 = 2^18; a job may ask for fewer
    /// rows per band).
    #[arg(long, default_value_t = workload::BAND_PIXELS)]
    band_pixels: u32,
    /// Rows per band intersected to take the workload (more: finer, slower).
    #[arg(long, default_value_t = 4)]
    sampled_rows: u32,
    /// Seed of the scene's layout.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

/// Runs the simulation and prints its tables.
pub fn run(args: Args) -> Result<()> {
    let started = std::time::Instant::now();
    let recorded = Inputs::recorded().with_link(args.link_gbit, args.latency_us);
    let inputs = if args.measure {
        eprintln!("measuring the inputs on this machine…");
        measure::measure(measure::Size::FULL, &recorded)?
    } else {
        recorded
    };
    report::run(&args, &inputs)?;
    println!("\n(simulated in {:.1} s)", started.elapsed().as_secs_f64());
    Ok(())
}
