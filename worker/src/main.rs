//! `trove-worker`: serves the datasets under a data root to a TROVE farm (SPEC §5).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Parser;
use trove_worker::WorkerConfig;

/// Holds the dataset files under a data root and casts their piece tasks for a coordinator.
#[derive(Parser)]
#[command(name = "trove-worker", version)]
struct Args {
    /// The coordinator's URL, e.g. http://127.0.0.1:7000.
    #[arg(long)]
    coordinator: String,
    /// Address to listen on (port 0 picks a free port); the bound address is printed as the
    /// first line of standard output.
    #[arg(long, default_value = "127.0.0.1:0")]
    listen: String,
    /// The folder whose files this worker holds, by key (path under it). Nothing outside it
    /// is ever read.
    #[arg(long)]
    data_root: PathBuf,
    /// Most voxel bytes kept resident (e.g. 512MiB).
    #[arg(long, value_name = "BYTES", value_parser = trove_proto::parse_bytes)]
    memory_budget: Option<u64>,
    /// The address the coordinator should use to reach this worker (default: the bound
    /// address; on a cluster, the pod's address and port).
    #[arg(long)]
    advertise: Option<String>,
    /// Serve Prometheus metrics at http://ADDR/metrics (e.g. 0.0.0.0:9101); off when not
    /// given. Its bound address is printed as the second line of standard output.
    #[arg(long, value_name = "ADDR")]
    metrics_listen: Option<String>,
}

fn main() -> ExitCode {
    trove_proto::init_logging();
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

#[tokio::main]
async fn run() -> Result<()> {
    let args = Args::parse();
    let listener = tokio::net::TcpListener::bind(&args.listen)
        .await
        .with_context(|| format!("cannot listen on {}", args.listen))?;
    // Bound before the address is printed, so a caller that read it can scrape at once.
    let metrics_listener = match &args.metrics_listen {
        Some(addr) => Some(
            tokio::net::TcpListener::bind(addr)
                .await
                .with_context(|| format!("cannot listen on {addr} (--metrics-listen)"))?,
        ),
        None => None,
    };
    let bound = listener.local_addr().context("the listener has no address")?;
    println!("{bound}");
    let config = WorkerConfig {
        coordinator: args.coordinator,
        advertise: args.advertise,
        data_root: args.data_root,
        memory_budget: args.memory_budget,
        metrics: Default::default(),
    };
    // The metrics server stops when the worker does.
    let (stop_metrics, metrics_stopped) = tokio::sync::oneshot::channel::<()>();
    if let Some(metrics_listener) = metrics_listener {
        let address = metrics_listener.local_addr().context("the metrics listener has no address")?;
        tracing::info!(%address, "serving metrics at /metrics");
        println!("{address}");
        let metrics = config.metrics.clone();
        tokio::spawn(async move {
            let stopped = async {
                let _ = metrics_stopped.await;
            };
            if let Err(e) = trove_worker::metrics::serve(metrics_listener, stopped, metrics).await {
                tracing::error!(error = %e, "the metrics server stopped");
            }
        });
    }
    let served = trove_worker::run(listener, trove_proto::shutdown_signal(), config).await.context("worker");
    let _ = stop_metrics.send(());
    served
}
