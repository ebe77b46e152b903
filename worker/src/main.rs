//! `trove-worker`: serves the datasets under a data root to a TROVE farm (SPEC §5).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Parser;
use trove_proto::auth::Token;
use trove_proto::tls::{CaCert, ServerTls};
use trove_worker::{WorkerConfig, WorkerSecurity};

/// Holds the dataset files under a data root and casts their piece tasks for a coordinator.
#[derive(Parser)]
#[command(name = "trove-worker", version)]
struct Args {
    /// A coordinator's URL, e.g. http://127.0.0.1:7000 (https://... for TLS, with
    /// --tls-ca). Repeat it, or separate URLs with commas, to serve several coordinators
    /// (each registers the worker and sends it batches of its own jobs).
    #[arg(long = "coordinator", value_name = "URL", required = true, value_delimiter = ',')]
    coordinators: Vec<String>,
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
    /// The id this worker registers under; keep it across restarts of this worker (e.g. a
    /// StatefulSet pod's name). Default: the TROVE_WORKER_ID environment variable, else a
    /// fresh random id per process. Letters, digits, '-', '_', '.'; at most 128.
    #[arg(long, value_name = "ID", value_parser = parse_worker_id)]
    worker_id: Option<String>,
    /// A file holding the worker token (one line): presented to the coordinator, and
    /// required of the coordinator's cast streams. The coordinator's --worker-token-file.
    #[arg(long, value_name = "FILE")]
    token_file: Option<PathBuf>,
    /// Serve over TLS with this certificate (PEM; with --tls-key). The coordinator then
    /// needs --tls-ca with the CA that signed it.
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// The private key of --tls-cert (PEM).
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// The CA certificate (PEM) that signed an https:// coordinator's certificate.
    #[arg(long, value_name = "FILE")]
    tls_ca: Option<PathBuf>,
    /// Cast streams served at once (each one job's dataset, on a thread of its own); one
    /// more is refused as busy, and the coordinator asks again later.
    #[arg(long, default_value_t = trove_worker::cast::DEFAULT_MAX_STREAMS as u32, value_parser = clap::value_parser!(u32).range(1..))]
    max_streams: u32,
    /// Batches held at once (queued or being cast), over every coordinator and job; one
    /// more is refused as busy unless its job has less than its share, and its coordinator
    /// sends it again later or elsewhere. Default: twice the threads (at least 4), the most
    /// one coordinator sends, so a worker of one coordinator never refuses a batch.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..))]
    max_batches: Option<u32>,
    /// Serve Prometheus metrics at http://ADDR/metrics (e.g. 0.0.0.0:9101); off when not
    /// given. Its bound address is printed as the second line of standard output.
    #[arg(long, value_name = "ADDR")]
    metrics_listen: Option<String>,
}

/// The environment variable a worker's id is read from when `--worker-id` is not given.
const WORKER_ID_ENV: &str = "TROVE_WORKER_ID";

fn parse_worker_id(id: &str) -> Result<String, String> {
    trove_worker::membership::check_worker_id(id).map(|()| id.to_string())
}

/// The worker's credentials from its flags; each error names the flag and the file.
fn security(args: &Args) -> Result<WorkerSecurity> {
    let token = match &args.token_file {
        Some(path) => Some(Token::from_file(path).context("--token-file")?),
        None => None,
    };
    let tls = match (&args.tls_cert, &args.tls_key) {
        (Some(cert), Some(key)) => Some(ServerTls::from_files(cert, key).context("--tls-cert/--tls-key")?),
        _ => None,
    };
    let coordinator_ca = match &args.tls_ca {
        Some(path) => Some(CaCert::from_file(path).context("--tls-ca")?),
        None => None,
    };
    Ok(WorkerSecurity { token, tls, coordinator_ca })
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
    // A SIMD path the processor lacks (or a misspelt one) is refused here, at start, rather
    // than as a failed batch of every job later.
    let simd = trove_core::SimdPath::configured()?;
    tracing::info!(%simd, "sampler's SIMD path");
    let security = security(&args)?;
    let worker_id = match args.worker_id {
        Some(id) => Some(id),
        None => match std::env::var(WORKER_ID_ENV) {
            Ok(id) if !id.is_empty() => Some(parse_worker_id(&id).map_err(anyhow::Error::msg).context(WORKER_ID_ENV)?),
            _ => None,
        },
    };
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
        coordinators: args.coordinators,
        advertise: args.advertise,
        data_root: args.data_root,
        memory_budget: args.memory_budget,
        worker_id,
        security,
        max_streams: args.max_streams as usize,
        max_batches: args.max_batches.map_or_else(trove_worker::cast::default_max_batches, |n| n as usize),
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
