//! The command line: argument parsing, the `render` and `coordinator` commands; the
//! operator's commands against a running coordinator are in `ops.rs`.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use trove_coordinator::client::FarmClient;
use trove_coordinator::farm::{self, FarmConfig, FarmSecurity};
use trove_core::render::{self, Algorithm, RenderOptions};
use trove_core::scene::{DataRoot, Scene, DATA_ROOT_ENV};
use trove_proto::auth::Token;
use trove_proto::connect::Connector;
use trove_proto::parse_bytes;
use trove_proto::tls::{CaCert, ServerTls};
use trove_proto::v1 as pb;

#[derive(Parser)]
#[command(name = "trove", version, about = "Renders scenes composed of many volumetric datasets (Leu & Chen 1997)")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene to a PNG (or a .pfm float image), in this process or through a farm.
    Render(RenderArgs),
    /// Serve a farm's job API and worker membership (SPEC §5).
    Coordinator(CoordinatorArgs),
    /// Check or fetch the public datasets the example scenes read (docs/data.md).
    #[command(subcommand)]
    Data(crate::data::DataCommand),
    /// List a coordinator's jobs, or fetch a finished one's files (`trove jobs result`).
    Jobs(crate::ops::JobsArgs),
    /// List the workers registered with a coordinator.
    Workers(crate::ops::WorkersArgs),
    /// Cancel a queued or running job.
    Cancel(crate::ops::CancelArgs),
}

#[derive(clap::Args)]
struct RenderArgs {
    /// The scene file (TOML, SPEC §1).
    scene: PathBuf,
    /// Output image: .png (8-bit) or .pfm (linear float).
    #[arg(short, long)]
    output: PathBuf,
    /// Ray-casting algorithm.
    #[arg(long, value_enum, default_value_t = AlgorithmArg::Grouped)]
    algorithm: AlgorithmArg,
    /// Most voxel bytes kept resident (e.g. 512MiB, 1.5GiB, 4000000); datasets beyond it
    /// are evicted least-recently-used and loaded again when needed. It must hold the
    /// largest dataset.
    #[arg(long, value_name = "BYTES", value_parser = parse_bytes)]
    memory_budget: Option<u64>,
    /// Most bytes of pieces and their results held at once by the grouped algorithm
    /// (default 1GiB); a larger image renders in bands of rows within it.
    #[arg(long, value_name = "BYTES", value_parser = parse_bytes)]
    band_memory: Option<u64>,
    /// Write counts and the Table-1 timing breakdown as JSON.
    #[arg(long)]
    stats: Option<PathBuf>,
    /// Override the scene's `[render] distorted_sampling` for every distorted box.
    #[arg(long, value_enum)]
    distorted_sampling: Option<DistortedSampling>,
    /// The folder under which the scene's dataset paths (keys) resolve. Default: the
    /// TROVE_DATA environment variable, else the scene file's folder. Local renders only: a
    /// farm's workers resolve the keys under their own --data-root.
    #[arg(long, value_name = "DIR")]
    data_root: Option<PathBuf>,
    #[command(flatten)]
    connect: ConnectArgs,
}

/// How a client command reaches a coordinator: its URL, the client token and, for
/// `https://`, the CA that signed the coordinator's certificate.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct ConnectArgs {
    /// The coordinator's URL, e.g. http://127.0.0.1:7000 (https://... for TLS, with
    /// --tls-ca). For `render`: render through that farm instead of in this process; the
    /// scene's dataset paths are keys that the workers resolve under their data roots.
    #[arg(long, value_name = "URL")]
    pub coordinator: Option<String>,
    /// A file holding the client token (one line): the coordinator's --client-token-file.
    #[arg(long, value_name = "FILE")]
    pub token_file: Option<PathBuf>,
    /// The CA certificate (PEM) that signed an https:// coordinator's certificate.
    #[arg(long, value_name = "FILE")]
    pub tls_ca: Option<PathBuf>,
}

impl ConnectArgs {
    /// The coordinator's URL; an error naming the flag when it is missing.
    pub fn url(&self) -> Result<&str> {
        self.coordinator.as_deref().context("--coordinator URL is required: the coordinator to ask")
    }

    /// A client of the coordinator, with the token and CA; an error names its URL when it
    /// cannot be reached.
    pub async fn connect(&self) -> Result<FarmClient> {
        let url = self.url()?;
        Ok(FarmClient::connect_with(url, &self.connector()?).await?)
    }

    /// The token and CA from their files; each error names the flag and the file.
    pub fn connector(&self) -> Result<Connector> {
        let token = match &self.token_file {
            Some(path) => Some(Token::from_file(path).context("--token-file")?),
            None => None,
        };
        let ca = match &self.tls_ca {
            Some(path) => Some(CaCert::from_file(path).context("--tls-ca")?),
            None => None,
        };
        Ok(Connector::new(ca, token))
    }

    /// Refuses the connection flags in a command that does not connect (a local render).
    fn refuse_for_local(&self) -> Result<()> {
        if self.token_file.is_some() || self.tls_ca.is_some() {
            bail!("--token-file and --tls-ca apply to renders through a farm (--coordinator URL)");
        }
        Ok(())
    }
}

#[derive(clap::Args)]
struct CoordinatorArgs {
    /// Address to listen on (port 0 picks a free port); the bound address is printed as the
    /// first line of standard output.
    #[arg(long, default_value = "127.0.0.1:7000")]
    listen: String,
    /// How often workers send heartbeats, in milliseconds; one that misses five is lost.
    #[arg(long, default_value_t = 1000)]
    heartbeat_ms: u64,
    /// Seconds a batch may take before it is given to another worker.
    #[arg(long, default_value_t = 120)]
    batch_deadline_s: u64,
    /// Most bytes of pieces and their results one job holds at once (e.g. 256MiB); its
    /// image is worked through in bands of rows within it.
    #[arg(long, value_name = "BYTES", value_parser = parse_bytes, default_value = "256MiB")]
    band_memory: u64,
    /// Bands of one job in flight at once, at most: more keep more datasets busy.
    #[arg(long, default_value_t = 8)]
    bands_in_flight: usize,
    /// Jobs running at once, at most; later ones wait QUEUED, in order, their place in the
    /// queue in their status.
    #[arg(long, default_value_t = farm::DEFAULT_MAX_JOBS)]
    max_jobs: usize,
    /// Seconds a job may run before it fails with DEADLINE_EXCEEDED.
    #[arg(long, default_value_t = 3600)]
    job_deadline_s: u64,
    /// Most pixels of a job that asks for a PFM; larger ones are refused at submission.
    #[arg(long, default_value_t = render::limits::MAX_PFM_PIXELS)]
    max_pfm_pixels: u64,
    /// Keep jobs and finished results in a database in this folder: after a crash or a
    /// restart, queued and running jobs run again and finished results are still served.
    /// Default: memory only.
    #[arg(long, value_name = "DIR")]
    state_dir: Option<PathBuf>,
    /// Seconds a finished job and its result files are kept before they are removed.
    #[arg(long, value_name = "N", default_value_t = farm::DEFAULT_KEEP_RESULTS.as_secs())]
    keep_results_s: u64,

    /// Serve over TLS with this certificate (PEM; with --tls-key): clients and workers then
    /// use https:// and --tls-ca with the CA that signed it.
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// The private key of --tls-cert (PEM).
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// The CA certificate (PEM) that signed the workers' certificates: the coordinator then
    /// reaches its workers over TLS (their --tls-cert) and verifies them against it.
    #[arg(long, value_name = "FILE")]
    tls_ca: Option<PathBuf>,
    /// A file holding the client token (one line): every job API call must present it
    /// (`trove render --token-file`).
    #[arg(long, value_name = "FILE")]
    client_token_file: Option<PathBuf>,
    /// A file holding the worker token (one line): workers must present it to register
    /// (`trove-worker --token-file`), and the coordinator presents it on its cast streams.
    #[arg(long, value_name = "FILE")]
    worker_token_file: Option<PathBuf>,
    /// Seconds a stopping coordinator (SIGTERM) lets running jobs finish, refusing new ones,
    /// before it stops.
    #[arg(long, default_value_t = farm::DEFAULT_DRAIN_GRACE.as_secs())]
    drain_grace_s: u64,
    /// Serve Prometheus metrics at http://ADDR/metrics (e.g. 0.0.0.0:9100); off when not
    /// given. Its bound address is printed as the second line of standard output.
    #[arg(long, value_name = "ADDR")]
    metrics_listen: Option<String>,
}

impl CoordinatorArgs {
    /// The coordinator's credentials from its flags; each error names the flag and the file.
    fn security(&self) -> Result<FarmSecurity> {
        let token = |path: &Option<PathBuf>, flag: &'static str| -> Result<Option<Token>> {
            path.as_deref().map(|p| Token::from_file(p).context(flag)).transpose()
        };
        let tls = match (&self.tls_cert, &self.tls_key) {
            (Some(cert), Some(key)) => Some(ServerTls::from_files(cert, key).context("--tls-cert/--tls-key")?),
            _ => None,
        };
        let worker_ca = self.tls_ca.as_deref().map(|p| CaCert::from_file(p).context("--tls-ca")).transpose()?;
        Ok(FarmSecurity {
            tls,
            worker_ca,
            client_token: token(&self.client_token_file, "--client-token-file")?,
            worker_token: token(&self.worker_token_file, "--worker-token-file")?,
        })
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum DistortedSampling {
    /// Invert the trilinear map at every sample (SPEC §4.2).
    Exact,
    /// The paper's approximation: the straight VC line between the mapped end points.
    Straight,
}

#[derive(Clone, Copy, ValueEnum)]
enum AlgorithmArg {
    /// Algorithm 1: per ray, datasets in ray order.
    PerRay,
    /// Algorithm 2: grouped by dataset, each loaded once (the default).
    Grouped,
}

impl From<AlgorithmArg> for Algorithm {
    fn from(a: AlgorithmArg) -> Algorithm {
        match a {
            AlgorithmArg::PerRay => Algorithm::PerRay,
            AlgorithmArg::Grouped => Algorithm::Grouped,
        }
    }
}

/// Parses the arguments and runs the command.
pub fn run() -> Result<()> {
    match Cli::parse().command {
        Command::Render(args) if args.connect.coordinator.is_some() => farm_render(args),
        Command::Render(args) => render_command(args),
        Command::Coordinator(args) => coordinator_command(args),
        Command::Data(data) => data.run(),
        Command::Jobs(args) => crate::ops::jobs_command(args),
        Command::Workers(args) => crate::ops::workers_command(args),
        Command::Cancel(args) => crate::ops::cancel_command(args),
    }
}

fn render_command(args: RenderArgs) -> Result<()> {
    args.connect.refuse_for_local()?;
    check_output(&args.output, &["png", "pfm"])?;
    if let Some(stats) = &args.stats {
        check_output(stats, &["json"])?;
    }
    let root = DataRoot::choose(args.data_root.clone(), std::env::var_os(DATA_ROOT_ENV));
    let mut scene = Scene::load_in(&args.scene, &root)?;
    if is_pfm(&args.output) {
        let (w, h) = (scene.image().width, scene.image().height);
        render::limits::check_pfm(w, h, render::limits::MAX_PFM_PIXELS)
            .with_context(|| format!("cannot write {}", args.output.display()))?;
    }
    if let Some(mode) = args.distorted_sampling {
        scene.set_straight_distorted_sampling(matches!(mode, DistortedSampling::Straight));
    }
    let bar = progress_bar(scene.image().height as u64);
    let options = RenderOptions {
        algorithm: args.algorithm.into(),
        memory_budget: args.memory_budget,
        band_memory: args.band_memory,
        progress: bar.clone().map(|b| Arc::new(move |rows: u64| b.set_position(rows)) as render::Progress),
        store: None,
    };
    // The image as its file holds it (3 bytes a pixel, plus f32 values for a PFM), not the
    // library's 24 bytes of f64: an 8192² PNG then renders within the band memory plus
    // 192 MiB.
    let rendered = render::render_raster(&scene, &options, is_pfm(&args.output)).map_err(|e| {
        let hint = match &e {
            render::RenderError::Store(render::StoreError::BudgetTooSmall { .. }) => " (see --memory-budget)",
            _ => "",
        };
        anyhow::Error::new(e).context(format!("rendering {}{hint}", args.scene.display()))
    })?;
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    rendered.image.save(&args.output)?;
    if let Some(path) = &args.stats {
        let json = serde_json::to_string_pretty(&rendered.stats).context("serialising statistics")?;
        std::fs::write(path, json + "\n").with_context(|| format!("writing statistics to {}", path.display()))?;
    }
    tracing::info!(seconds = rendered.stats.seconds.total, samples = rendered.stats.samples, "rendered");
    Ok(())
}

/// Refuses, before any work, an output whose folder does not exist or whose extension we do
/// not write — a long render should not be lost to a typo in `-o`.
pub(crate) fn check_output(path: &Path, extensions: &[&str]) -> Result<()> {
    let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    if !ext.as_deref().is_some_and(|e| extensions.contains(&e)) {
        bail!("cannot write {}: expected a file ending in .{}", path.display(), extensions.join(" or ."));
    }
    let folder = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    if !folder.is_dir() {
        bail!("cannot write {}: folder {} does not exist", path.display(), folder.display());
    }
    Ok(())
}

/// A bar over image rows, shown only when stderr is a terminal.
fn progress_bar(rows: u64) -> Option<ProgressBar> {
    if !std::io::stderr().is_terminal() {
        return None;
    }
    let bar = ProgressBar::new(rows);
    bar.set_style(
        ProgressStyle::with_template("{spinner} rendering [{bar:40}] {pos}/{len} rows, {elapsed} (eta {eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    Some(bar)
}

/// `trove render --coordinator URL`: the same files as local mode, made by a farm.
fn farm_render(args: RenderArgs) -> Result<()> {
    let url = args.connect.url()?.to_string();
    check_output(&args.output, &["png", "pfm"])?;
    if let Some(stats) = &args.stats {
        check_output(stats, &["json"])?;
    }
    if args.memory_budget.is_some()
        || args.band_memory.is_some()
        || args.distorted_sampling.is_some()
        || !matches!(args.algorithm, AlgorithmArg::Grouped)
    {
        bail!("--memory-budget, --band-memory, --distorted-sampling and --algorithm apply to local renders; a farm's workers set their own budgets, its coordinator its band memory (`trove coordinator --band-memory`), and it always casts grouped by dataset");
    }
    if let Some(dir) = &args.data_root {
        bail!(
            "--data-root {} applies to local renders: through a farm the scene's dataset paths are sent as \
             written, as keys that each worker resolves under its own --data-root (start the workers on \
             copies of that folder)",
            dir.display()
        );
    }
    let text = std::fs::read_to_string(&args.scene)
        .with_context(|| format!("{}: cannot read the scene file", args.scene.display()))?;
    let name = args.scene.display().to_string();
    let want_pfm = is_pfm(&args.output);
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    let connector = args.connect.connector()?;
    let files = runtime.block_on(async {
        let mut client = FarmClient::connect_with(&url, &connector).await?;
        let bar = progress_bar(0);
        let options = pb::JobOptions { want_pfm, ..Default::default() };
        let files = client
            .render(text, name.clone(), options, |status| {
                if let Some(b) = &bar {
                    b.set_length(status.pieces_total.max(1));
                    b.set_position(status.pieces_done);
                }
            })
            .await;
        if let Some(b) = bar {
            b.finish_and_clear();
        }
        files
    });
    let files = files.with_context(|| format!("rendering {name} through {url}"))?;
    let image = if want_pfm { files.pfm.context("the farm sent no PFM")? } else { files.png };
    std::fs::write(&args.output, image).with_context(|| format!("cannot write {}", args.output.display()))?;
    if let Some(path) = &args.stats {
        std::fs::write(path, &files.stats_json).with_context(|| format!("writing statistics to {}", path.display()))?;
    }
    Ok(())
}

/// `trove coordinator`: serves until Ctrl-C or SIGTERM.
fn coordinator_command(args: CoordinatorArgs) -> Result<()> {
    let security = args.security()?;
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(async {
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
        println!("{}", listener.local_addr().context("the listener has no address")?);
        let config = FarmConfig {
            heartbeat: std::time::Duration::from_millis(args.heartbeat_ms.max(10)),
            driver: farm::DriverConfig {
                batch_deadline: std::time::Duration::from_secs(args.batch_deadline_s.max(1)),
                memory_bound: args.band_memory,
                max_bands: args.bands_in_flight.max(1),
                job_deadline: std::time::Duration::from_secs(args.job_deadline_s.max(1)),
                max_pfm_pixels: args.max_pfm_pixels,
                ..farm::DriverConfig::default()
            },
            max_jobs: args.max_jobs.max(1),
            state_dir: args.state_dir,
            keep_results: std::time::Duration::from_secs(args.keep_results_s),

            security,
            drain_grace: std::time::Duration::from_secs(args.drain_grace_s),
        };
        // The metrics server stops when the coordinator does.
        let (stop_metrics, metrics_stopped) = tokio::sync::oneshot::channel::<()>();
        if let Some(metrics_listener) = metrics_listener {
            let address = metrics_listener.local_addr().context("the metrics listener has no address")?;
            tracing::info!(%address, "serving metrics at /metrics");
            println!("{address}");
            let metrics = config.driver.metrics.clone();
            tokio::spawn(async move {
                let stopped = async {
                    let _ = metrics_stopped.await;
                };
                if let Err(e) = farm::metrics::serve(metrics_listener, stopped, metrics).await {
                    tracing::error!(error = %e, "the metrics server stopped");
                }
            });
        }
        let served = farm::run(listener, trove_proto::shutdown_signal(), config).await.context("coordinator");
        let _ = stop_metrics.send(());
        served
    })
}

pub(crate) fn is_pfm(path: &Path) -> bool {
    path.extension().is_some_and(|e| e.eq_ignore_ascii_case("pfm"))
}
