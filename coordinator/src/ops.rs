//! The operator's commands against a running coordinator: `trove jobs`, `trove jobs result`,
//! `trove workers` and `trove cancel`. Each prints aligned text for a person, or with
//! `--json` one JSON document for a script; an unreachable coordinator or an unknown job is
//! an error (non-zero exit) naming the URL or the job.

use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use anyhow::{bail, Context, Result};
use serde::Serialize;
use trove_coordinator::client::FarmClient;
use trove_coordinator::farm::jobs::is_final;
use trove_proto::v1 as pb;

use crate::cli::{check_output, is_pfm, ConnectArgs};

/// `trove jobs`: list the coordinator's jobs, or (`trove jobs result`) fetch one's files.
#[derive(clap::Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct JobsArgs {
    #[command(subcommand)]
    command: Option<JobsCommand>,
    #[command(flatten)]
    connect: Option<ConnectArgs>,
    /// One JSON array of the jobs instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(clap::Subcommand)]
enum JobsCommand {
    /// Write a finished job's image (and its statistics) to files.
    Result(ResultArgs),
}

#[derive(clap::Args)]
struct ResultArgs {
    /// The job's id, as `trove jobs` lists it.
    job: String,
    /// Output image: .png, or .pfm when the job was submitted for one (its output ended in .pfm).
    #[arg(short, long)]
    output: PathBuf,
    /// Write the job's statistics (JSON, as `trove render --stats` writes them).
    #[arg(long)]
    stats: Option<PathBuf>,
    #[command(flatten)]
    connect: ConnectArgs,
}

/// `trove workers`.
#[derive(clap::Args)]
pub struct WorkersArgs {
    #[command(flatten)]
    connect: ConnectArgs,
    /// One JSON array of the workers instead of a table.
    #[arg(long)]
    json: bool,
}

/// `trove cancel JOB`.
#[derive(clap::Args)]
pub struct CancelArgs {
    /// The job's id, as `trove jobs` lists it.
    job: String,
    #[command(flatten)]
    connect: ConnectArgs,
    /// One JSON object (the job and its state) instead of a sentence.
    #[arg(long)]
    json: bool,
}

/// Runs `f` with a client of the coordinator `connect` names, on a runtime of its own.
fn with_client<T>(
    connect: &ConnectArgs,
    f: impl AsyncFnOnce(&mut FarmClient) -> Result<T, trove_coordinator::client::ClientError>,
) -> Result<T> {
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(async {
        let mut client = connect.connect().await?;
        f(&mut client).await.with_context(|| format!("asking the coordinator at {}", connect.url().unwrap_or("?")))
    })
}

/// A job as `trove jobs --json` writes it.
#[derive(Serialize)]
struct JobLine<'a> {
    job_id: &'a str,
    scene_name: &'a str,
    state: &'static str,
    pieces_done: u64,
    pieces_total: u64,
    queue_position: u32,
    submitted_unix_ms: u64,
    age_s: f64,
}

/// A worker as `trove workers --json` writes it.
#[derive(Serialize)]
struct WorkerLine<'a> {
    worker_id: &'a str,
    address: &'a str,
    alive: bool,
    files: u32,
    file_bytes: u64,
    batches_in_flight: u64,
    batches_done: u64,
    millis_since_heartbeat: u64,
}

/// A state as people and scripts read it: `queued`, `running`, `succeeded`, ...
fn state_name(state: pb::JobState) -> &'static str {
    match state {
        pb::JobState::Unspecified => "unknown",
        pb::JobState::Queued => "queued",
        pb::JobState::Running => "running",
        pb::JobState::Succeeded => "succeeded",
        pb::JobState::Failed => "failed",
        pb::JobState::Cancelled => "cancelled",
    }
}

/// Time since `unix_ms`, by this machine's clock (never negative).
fn age(unix_ms: u64) -> Duration {
    let now = SystemTime::now().duration_since(UNIX_EPOCH).unwrap_or_default();
    now.saturating_sub(Duration::from_millis(unix_ms))
}

/// `4s`, `3m07s`, `2h05m`, `3d04h`: the two largest units.
fn short_duration(d: Duration) -> String {
    let s = d.as_secs();
    match s {
        0..60 => format!("{s}s"),
        60..3600 => format!("{}m{:02}s", s / 60, s % 60),
        3600..86400 => format!("{}h{:02}m", s / 3600, s % 3600 / 60),
        _ => format!("{}d{:02}h", s / 86400, s % 86400 / 3600),
    }
}

/// `1.5 MiB`-style byte counts for the table.
fn short_bytes(bytes: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut value = bytes as f64;
    let mut unit = 0;
    while value >= 1024.0 && unit + 1 < UNITS.len() {
        value /= 1024.0;
        unit += 1;
    }
    if unit == 0 {
        format!("{bytes} B")
    } else {
        format!("{value:.1} {}", UNITS[unit])
    }
}

/// Rows under a header, each column padded to its widest cell; the last column unpadded.
fn table(header: &[&str], rows: &[Vec<String>]) -> String {
    let mut widths: Vec<usize> = header.iter().map(|h| h.chars().count()).collect();
    for row in rows {
        for (w, cell) in widths.iter_mut().zip(row) {
            *w = (*w).max(cell.chars().count());
        }
    }
    let line = |cells: Vec<&str>| {
        let last = cells.len().saturating_sub(1);
        let padded: Vec<String> = cells
            .iter()
            .enumerate()
            .map(|(i, c)| if i == last { c.to_string() } else { format!("{c:<w$}", w = widths[i]) })
            .collect();
        padded.join("  ").trim_end().to_string() + "\n"
    };
    let mut out = line(header.to_vec());
    for row in rows {
        out += &line(row.iter().map(String::as_str).collect());
    }
    out
}

fn jobs_text(jobs: &[pb::JobSummary]) -> String {
    if jobs.is_empty() {
        return "no jobs\n".to_string();
    }
    let rows: Vec<Vec<String>> = jobs
        .iter()
        .map(|j| {
            let progress = match j.pieces_total {
                0 => "-".to_string(),
                total => format!("{}/{} ({:.0}%)", j.pieces_done, total, 100.0 * j.pieces_done as f64 / total as f64),
            };
            let queue = if j.queue_position > 0 { j.queue_position.to_string() } else { "-".to_string() };
            vec![
                j.job_id.clone(),
                state_name(j.state()).to_string(),
                j.scene_name.clone(),
                progress,
                queue,
                short_duration(age(j.submitted_unix_ms)),
            ]
        })
        .collect();
    table(&["ID", "STATE", "SCENE", "PROGRESS", "QUEUE", "AGE"], &rows)
}

fn jobs_json(jobs: &[pb::JobSummary]) -> Result<String> {
    let lines: Vec<JobLine> = jobs
        .iter()
        .map(|j| JobLine {
            job_id: &j.job_id,
            scene_name: &j.scene_name,
            state: state_name(j.state()),
            pieces_done: j.pieces_done,
            pieces_total: j.pieces_total,
            queue_position: j.queue_position,
            submitted_unix_ms: j.submitted_unix_ms,
            age_s: age(j.submitted_unix_ms).as_secs_f64(),
        })
        .collect();
    Ok(serde_json::to_string_pretty(&lines).context("serialising the jobs")? + "\n")
}

fn workers_text(workers: &[pb::WorkerInfo]) -> String {
    if workers.is_empty() {
        return "no workers\n".to_string();
    }
    let rows: Vec<Vec<String>> = workers
        .iter()
        .map(|w| {
            vec![
                w.worker_id.clone(),
                w.address.clone(),
                if w.alive { "alive" } else { "lost" }.to_string(),
                w.files.to_string(),
                short_bytes(w.file_bytes),
                w.batches_in_flight.to_string(),
                w.batches_done.to_string(),
                short_duration(Duration::from_millis(w.millis_since_heartbeat)),
            ]
        })
        .collect();
    table(&["ID", "ADDRESS", "STATE", "FILES", "BYTES", "IN FLIGHT", "DONE", "LAST HEARTBEAT"], &rows)
}

fn workers_json(workers: &[pb::WorkerInfo]) -> Result<String> {
    let lines: Vec<WorkerLine> = workers
        .iter()
        .map(|w| WorkerLine {
            worker_id: &w.worker_id,
            address: &w.address,
            alive: w.alive,
            files: w.files,
            file_bytes: w.file_bytes,
            batches_in_flight: w.batches_in_flight,
            batches_done: w.batches_done,
            millis_since_heartbeat: w.millis_since_heartbeat,
        })
        .collect();
    Ok(serde_json::to_string_pretty(&lines).context("serialising the workers")? + "\n")
}

/// `trove jobs` and `trove jobs result`.
pub fn jobs_command(args: JobsArgs) -> Result<()> {
    match (args.command, args.connect) {
        (Some(JobsCommand::Result(result)), _) => result_command(result),
        (None, Some(connect)) => {
            let jobs = with_client(&connect, async |c| c.jobs().await)?;
            print!("{}", if args.json { jobs_json(&jobs)? } else { jobs_text(&jobs) });
            Ok(())
        }
        (None, None) => bail!("trove jobs needs --coordinator URL"),
    }
}

/// `trove jobs result JOB -o FILE [--stats FILE]`.
fn result_command(args: ResultArgs) -> Result<()> {
    check_output(&args.output, &["png", "pfm"])?;
    if let Some(stats) = &args.stats {
        check_output(stats, &["json"])?;
    }
    let job = args.job.clone();
    let files = with_client(&args.connect, async |c| c.result(&job).await)
        .with_context(|| format!("fetching the result of job `{job}`"))?;
    let image = if is_pfm(&args.output) {
        let Some(pfm) = files.pfm else {
            bail!(
                "cannot write {}: job `{job}` kept no PFM (only a job submitted for a .pfm output keeps one); \
                 ask for a .png instead",
                args.output.display()
            );
        };
        pfm
    } else {
        files.png
    };
    write(&args.output, &image)?;
    if let Some(path) = &args.stats {
        write(path, &files.stats_json)?;
    }
    Ok(())
}

fn write(path: &Path, bytes: &[u8]) -> Result<()> {
    std::fs::write(path, bytes).with_context(|| format!("cannot write {}", path.display()))
}

/// `trove workers`.
pub fn workers_command(args: WorkersArgs) -> Result<()> {
    let workers = with_client(&args.connect, async |c| c.workers().await)?;
    print!("{}", if args.json { workers_json(&workers)? } else { workers_text(&workers) });
    Ok(())
}

/// `trove cancel JOB`.
pub fn cancel_command(args: CancelArgs) -> Result<()> {
    let job = args.job.clone();
    let state = with_client(&args.connect, async |c| c.cancel(&job).await)
        .with_context(|| format!("cancelling job `{job}`"))?;
    if args.json {
        let line = serde_json::json!({ "job_id": job, "state": state_name(state) });
        println!("{line}");
    } else if is_final(state) && state != pb::JobState::Cancelled {
        println!("{job}: already {}; nothing to cancel", state_name(state));
    } else {
        // A running job stops within a batch; its state then turns `cancelled`.
        println!("{job}: cancel requested (now {})", state_name(state));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_and_bytes_read_short() {
        assert_eq!(short_duration(Duration::from_secs(4)), "4s");
        assert_eq!(short_duration(Duration::from_secs(187)), "3m07s");
        assert_eq!(short_duration(Duration::from_secs(2 * 3600 + 5 * 60)), "2h05m");
        assert_eq!(short_duration(Duration::from_secs(3 * 86400 + 4 * 3600)), "3d04h");
        assert_eq!(short_bytes(900), "900 B");
        assert_eq!(short_bytes(3 << 19), "1.5 MiB");
    }

    #[test]
    fn tables_align_their_columns() {
        let rows = vec![
            vec!["job-10".into(), "running".into(), "x".into()],
            vec!["job-9".into(), "queued".into(), "y".into()],
        ];
        assert_eq!(
            table(&["ID", "STATE", "SCENE"], &rows),
            "ID      STATE    SCENE\njob-10  running  x\njob-9   queued   y\n"
        );
    }
}
