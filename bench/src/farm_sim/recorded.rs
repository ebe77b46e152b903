//! The files that carry measured costs into the simulation, so that it models the code as
//! it is rather than replicas of it:
//!
//! * `bench/recorded/coordinator.json`, written by `trove-bench coordinator --record PATH`:
//!   the real coordinator's CPU per piece, in all and by stage, with where each stage runs
//!   (the job's one event loop, serial per job; a band's own thread, serial per band and
//!   parallel across the bands in flight; or the coordinator's other threads, in parallel)
//!   and at which step of a job it is paid;
//! * `bench/recorded/worker.json`, written by `trove-bench farm-sim --measure --record-worker
//!   PATH`: the worker's costs (casting per sample and per task, binding, loading, parsing),
//!   timed with the code a worker runs.
//!
//! Each carries a `format` number. A file whose format is not the code's is refused: its
//! numbers describe stages, or a driver, that the model no longer has.

use std::path::Path;

use anyhow::{bail, ensure, Context, Result};
use serde_json::{json, Value};

/// The coordinator file's format. Bump it whenever the stages of
/// `trove_coordinator::farm::stats::CoordinatorSeconds`, their meaning, where they run
/// ([`place_of`]) or the shape of the driver the simulation models change: a file recorded
/// before then is refused until it is recorded again.
///
/// 2: each band in flight has a thread of its own (`coordinator/src/farm/driver/band.rs`)
/// that does the per-task steps (dispatch, encoding, decoding, recording) and planning; the
/// job's event loop keeps only per-batch work (`loop_rest`: all of the loop's time).
pub(crate) const COORDINATOR_FORMAT: u64 = 2;

/// The worker file's format. Bump it whenever the inputs in it, or what they mean (the
/// worker's cast loop, its binding), change.
pub(crate) const WORKER_FORMAT: u64 = 1;

/// Where a coordinator stage runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum RunsOn {
    /// The job's one event loop: one step at a time, serial per job.
    EventLoop,
    /// The thread of the band the step is for (a blocking thread that owns the band's
    /// scheduler): one step at a time per band, bands in flight side by side, on the
    /// coordinator's cores.
    Band,
    /// Blocking threads with rayon within: as many of the coordinator's cores as it has.
    Parallel,
    /// One blocking thread per occurrence (the image's encoding): one step on one core,
    /// waiting for nothing else of the job.
    OneThread,
}

/// The step of a job at which a stage's cost is paid, and what its cost is per.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum At {
    /// Before a band casts, per piece of the band.
    Intersect,
    /// For each batch sent, per task.
    Send,
    /// For each answer taken, per task.
    Answer,
    /// After a band is cast, per piece of the band.
    Composite,
    /// Once at the end of the job, per pixel.
    Finish,
}

impl RunsOn {
    fn name(self) -> &'static str {
        match self {
            RunsOn::EventLoop => "event_loop",
            RunsOn::Band => "band",
            RunsOn::Parallel => "parallel",
            RunsOn::OneThread => "one_thread",
        }
    }

    fn parse(s: &str) -> Option<RunsOn> {
        [RunsOn::EventLoop, RunsOn::Band, RunsOn::Parallel, RunsOn::OneThread].into_iter().find(|r| r.name() == s)
    }
}

impl At {
    fn name(self) -> &'static str {
        match self {
            At::Intersect => "intersect",
            At::Send => "send",
            At::Answer => "answer",
            At::Composite => "composite",
            At::Finish => "finish",
        }
    }

    fn parse(s: &str) -> Option<At> {
        [At::Intersect, At::Send, At::Answer, At::Composite, At::Finish].into_iter().find(|a| a.name() == s)
    }
}

/// Where each stage the recorder writes runs and when it is paid, as the driver
/// (`coordinator/src/farm/driver/`) does it today: a band's thread (`driver/band.rs`)
/// intersects its band (rayon within: [`RunsOn::Parallel`]) and plans it, hands out and
/// encodes the batches the job's loop asks of it (`dispatch`, `encoding`), decodes and
/// records each answer the loop forwards (`decoding`, `recording`) and composites the band
/// (rayon within). `loop_rest` is the event loop's time outside the stages placed on it
/// (none but itself now: keeping the stock of batches, sending them, asking bands for more,
/// validating and forwarding answers, opening streams, the tick); `transport` is the CPU
/// of the runtime's worker threads outside the job's task (gRPC, HTTP/2 and protobuf, on
/// whichever worker thread is free). A stage of `coordinator_seconds` missing here stops
/// the recording: say where it runs and bump [`COORDINATOR_FORMAT`].
pub(crate) fn place_of(stage: &str) -> Option<(RunsOn, At)> {
    Some(match stage {
        "intersection" => (RunsOn::Parallel, At::Intersect),
        "planning" => (RunsOn::Band, At::Intersect),
        "dispatch" | "encoding" => (RunsOn::Band, At::Send),
        "decoding" | "recording" => (RunsOn::Band, At::Answer),
        "loop_rest" => (RunsOn::EventLoop, At::Answer),
        "transport" => (RunsOn::Parallel, At::Answer),
        "composition" => (RunsOn::Parallel, At::Composite),
        "image_encoding" => (RunsOn::OneThread, At::Finish),
        _ => return None,
    })
}

/// One stage of one recorded scene.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Stage {
    pub name: String,
    /// Estimated coordinator CPU per piece of the scene (see [`SceneCosts`]).
    pub cpu_ns_per_piece: f64,
    /// Wall time per piece on the thread doing the step, as the job's statistics give it
    /// (`None` for `transport`, which has no timer).
    pub wall_ns_per_piece: Option<f64>,
    pub runs_on: RunsOn,
    pub at: At,
}

/// What the coordinator spent on one scene. The CPU in all is measured (the run time of
/// the coordinator's own threads); so is the CPU of the runtime's worker threads, which run
/// the job's event loop and the transport. The stages' own timers are wall clocks, which on
/// a shared core count the waits for it too; so a stage's CPU is its wall time scaled so
/// that each group adds up to its measured CPU: the event-loop stages to the loop's wall
/// time capped by the worker threads' CPU, `transport` to the rest of the worker threads'
/// CPU, and the stages on blocking threads (the bands' threads and rayon's) to the rest of
/// the coordinator's CPU.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct SceneCosts {
    pub scene: String,
    pub pixels: u64,
    pub pieces: u64,
    /// Tasks sent to workers (culling sends fewer than there are pieces; a batch given up
    /// and sent again counts twice).
    pub tasks_sent: u64,
    /// Coordinator CPU per piece, all of its threads.
    pub cpu_ns_per_piece: f64,
    pub stages: Vec<Stage>,
}

impl SceneCosts {
    pub(crate) fn tasks_per_piece(&self) -> f64 {
        self.tasks_sent as f64 / self.pieces.max(1) as f64
    }

    pub(crate) fn pieces_per_pixel(&self) -> f64 {
        self.pieces as f64 / self.pixels.max(1) as f64
    }
}

/// A `trove-bench coordinator --record` file.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct CoordinatorRecord {
    pub format: u64,
    pub processor: String,
    pub simd: String,
    pub commit: String,
    /// The command that recorded it.
    pub command: String,
    /// Coordinator cores of the measurement.
    pub cores: u64,
    pub scenes: Vec<SceneCosts>,
}

impl CoordinatorRecord {
    pub(crate) fn to_json(&self) -> Value {
        let scenes: Vec<Value> = self
            .scenes
            .iter()
            .map(|s| {
                let stages: Vec<Value> = s
                    .stages
                    .iter()
                    .map(|st| {
                        json!({
                            "name": st.name,
                            "cpu_ns_per_piece": st.cpu_ns_per_piece,
                            "wall_ns_per_piece": st.wall_ns_per_piece,
                            "runs_on": st.runs_on.name(),
                            "at": st.at.name(),
                        })
                    })
                    .collect();
                json!({
                    "scene": s.scene,
                    "pixels": s.pixels,
                    "pieces": s.pieces,
                    "tasks_sent": s.tasks_sent,
                    "tasks_per_piece": s.tasks_per_piece(),
                    "pieces_per_pixel": s.pieces_per_pixel(),
                    "cpu_ns_per_piece": s.cpu_ns_per_piece,
                    "stages": stages,
                })
            })
            .collect();
        json!({
            "format": self.format,
            "processor": self.processor,
            "simd": self.simd,
            "commit": self.commit,
            "command": self.command,
            "cores": self.cores,
            "scenes": scenes,
        })
    }

    /// Reads `value`, the contents of `file` (named in errors); refuses another format.
    pub(crate) fn from_json(value: &Value, file: &Path) -> Result<CoordinatorRecord> {
        check_format(value, file, COORDINATOR_FORMAT, "trove-bench coordinator --record")?;
        let f = Fields { file, what: "" };
        let mut scenes = Vec::new();
        for (i, s) in f.array(value, "scenes")?.iter().enumerate() {
            let what = format!("scenes[{i}].");
            let fs = Fields { file, what: &what };
            let mut stages = Vec::new();
            for (j, st) in fs.array(s, "stages")?.iter().enumerate() {
                let what = format!("scenes[{i}].stages[{j}].");
                let ft = Fields { file, what: &what };
                let runs_on = ft.string(st, "runs_on")?;
                let at = ft.string(st, "at")?;
                stages.push(Stage {
                    name: ft.string(st, "name")?,
                    cpu_ns_per_piece: ft.number(st, "cpu_ns_per_piece")?,
                    wall_ns_per_piece: st.get("wall_ns_per_piece").and_then(Value::as_f64),
                    runs_on: RunsOn::parse(&runs_on)
                        .with_context(|| ft.bad("runs_on", "event_loop, band, parallel or one_thread"))?,
                    at: At::parse(&at).with_context(|| ft.bad("at", "intersect, send, answer, composite or finish"))?,
                });
            }
            scenes.push(SceneCosts {
                scene: fs.string(s, "scene")?,
                pixels: fs.integer(s, "pixels")?,
                pieces: fs.integer(s, "pieces")?,
                tasks_sent: fs.integer(s, "tasks_sent")?,
                cpu_ns_per_piece: fs.number(s, "cpu_ns_per_piece")?,
                stages,
            });
        }
        ensure!(!scenes.is_empty(), "{}: `scenes` is empty", file.display());
        Ok(CoordinatorRecord {
            format: COORDINATOR_FORMAT,
            processor: f.string(value, "processor")?,
            simd: f.string(value, "simd")?,
            commit: f.string(value, "commit")?,
            command: f.string(value, "command")?,
            cores: f.integer(value, "cores")?,
            scenes,
        })
    }

    pub(crate) fn read(file: &Path) -> Result<CoordinatorRecord> {
        CoordinatorRecord::from_json(&read_json(file)?, file)
    }

    pub(crate) fn write(&self, file: &Path) -> Result<()> {
        write_json(file, &self.to_json())
    }
}

/// The worker's costs, core-seconds; see `super::inputs::Inputs` for each.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct WorkerRecord {
    pub processor: String,
    pub simd: String,
    pub commit: String,
    pub cast_per_sample: f64,
    pub cast_per_task: f64,
    pub bind_per_voxel: f64,
    pub rebind_per_voxel: f64,
    pub load_per_byte: f64,
    pub parse_per_object: f64,
}

impl WorkerRecord {
    pub(crate) fn to_json(&self) -> Value {
        json!({
            "format": WORKER_FORMAT,
            "processor": self.processor,
            "simd": self.simd,
            "commit": self.commit,
            "cast_per_sample_ns": self.cast_per_sample * 1e9,
            "cast_per_task_ns": self.cast_per_task * 1e9,
            "bind_per_voxel_ns": self.bind_per_voxel * 1e9,
            "rebind_per_voxel_ns": self.rebind_per_voxel * 1e9,
            "load_per_byte_ns": self.load_per_byte * 1e9,
            "parse_per_object_ns": self.parse_per_object * 1e9,
        })
    }

    pub(crate) fn from_json(value: &Value, file: &Path) -> Result<WorkerRecord> {
        check_format(value, file, WORKER_FORMAT, "trove-bench farm-sim --measure --record-worker")?;
        let f = Fields { file, what: "" };
        let ns = |key: &str| f.number(value, key).map(|v| v * 1e-9);
        Ok(WorkerRecord {
            processor: f.string(value, "processor")?,
            simd: f.string(value, "simd")?,
            commit: f.string(value, "commit")?,
            cast_per_sample: ns("cast_per_sample_ns")?,
            cast_per_task: ns("cast_per_task_ns")?,
            bind_per_voxel: ns("bind_per_voxel_ns")?,
            rebind_per_voxel: ns("rebind_per_voxel_ns")?,
            load_per_byte: ns("load_per_byte_ns")?,
            parse_per_object: ns("parse_per_object_ns")?,
        })
    }

    pub(crate) fn read(file: &Path) -> Result<WorkerRecord> {
        WorkerRecord::from_json(&read_json(file)?, file)
    }

    pub(crate) fn write(&self, file: &Path) -> Result<()> {
        write_json(file, &self.to_json())
    }
}

/// Refuses a file whose `format` is not `expected`, naming the file, the field and the
/// format this code reads.
fn check_format(value: &Value, file: &Path, expected: u64, recorder: &str) -> Result<()> {
    let found = value.get("format").and_then(Value::as_u64);
    if found != Some(expected) {
        let found = value.get("format").map_or("missing".to_string(), Value::to_string);
        bail!(
            "{}: field `format` is {found}, but this code reads format {expected}: the file was recorded for \
             another shape of the code; record it again (`{recorder} {}`)",
            file.display(),
            file.display()
        );
    }
    Ok(())
}

fn read_json(file: &Path) -> Result<Value> {
    let text = std::fs::read_to_string(file).with_context(|| format!("reading {}", file.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{}: not JSON", file.display()))
}

fn write_json(file: &Path, value: &Value) -> Result<()> {
    let mut text = serde_json::to_string_pretty(value)?;
    text.push('\n');
    if let Some(dir) = file.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    std::fs::write(file, text).with_context(|| format!("writing {}", file.display()))
}

/// Field access with errors that name the file and the field.
struct Fields<'a> {
    file: &'a Path,
    what: &'a str,
}

impl Fields<'_> {
    fn bad(&self, key: &str, expected: &str) -> String {
        format!("{}: field `{}{key}`: expected {expected}", self.file.display(), self.what)
    }

    fn number(&self, v: &Value, key: &str) -> Result<f64> {
        v.get(key).and_then(Value::as_f64).filter(|x| x.is_finite()).with_context(|| self.bad(key, "a number"))
    }

    fn integer(&self, v: &Value, key: &str) -> Result<u64> {
        v.get(key).and_then(Value::as_u64).with_context(|| self.bad(key, "a whole number"))
    }

    fn string(&self, v: &Value, key: &str) -> Result<String> {
        v.get(key).and_then(Value::as_str).map(str::to_string).with_context(|| self.bad(key, "a string"))
    }

    fn array<'v>(&self, v: &'v Value, key: &str) -> Result<&'v Vec<Value>> {
        v.get(key).and_then(Value::as_array).with_context(|| self.bad(key, "a list"))
    }
}

/// The processor's model name and how many processors this process may use.
pub(crate) fn processor() -> String {
    let info = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let model =
        info.lines().find(|l| l.starts_with("model name")).and_then(|l| l.split_once(':')).map(|(_, m)| m.trim());
    model.unwrap_or("unknown").to_string()
}

/// The widest SIMD path the sampler takes on this processor.
pub(crate) fn simd_path() -> &'static str {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            return "AVX-512";
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            return "AVX2";
        }
    }
    "scalar"
}

/// The commit the binary runs from (`git rev-parse HEAD` in the repository), or "unknown".
pub(crate) fn commit() -> String {
    let out = std::process::Command::new("git")
        .args(["rev-parse", "--short=12", "HEAD"])
        .current_dir(trove_tests::repo_root())
        .stderr(std::process::Stdio::null())
        .output();
    match out {
        Ok(o) if o.status.success() => {
            let id = String::from_utf8_lossy(&o.stdout).trim().to_string();
            let dirty = std::process::Command::new("git")
                .args(["status", "--porcelain", "--untracked-files=no"])
                .current_dir(trove_tests::repo_root())
                .output()
                .is_ok_and(|s| !s.stdout.is_empty());
            if dirty {
                format!("{id} (with uncommitted changes)")
            } else {
                id
            }
        }
        _ => "unknown".to_string(),
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A record of one scene with one stage at each step of a job and at each place.
    pub(crate) fn sample() -> CoordinatorRecord {
        let stage = |name: &str, cpu: f64| {
            let (runs_on, at) = place_of(name).unwrap();
            Stage { name: name.into(), cpu_ns_per_piece: cpu, wall_ns_per_piece: Some(2.0 * cpu), runs_on, at }
        };
        CoordinatorRecord {
            format: COORDINATOR_FORMAT,
            processor: "test processor".into(),
            simd: "AVX2".into(),
            commit: "abc".into(),
            command: "test".into(),
            cores: 1,
            scenes: vec![SceneCosts {
                scene: "one".into(),
                pixels: 1000,
                pieces: 2000,
                tasks_sent: 1000,
                cpu_ns_per_piece: 105.0,
                stages: vec![
                    stage("intersection", 40.0),
                    stage("planning", 10.0),
                    stage("dispatch", 20.0),
                    stage("recording", 10.0),
                    stage("loop_rest", 5.0),
                    stage("composition", 15.0),
                    stage("image_encoding", 5.0),
                ],
            }],
        }
    }

    #[test]
    fn a_coordinator_record_round_trips_through_its_file() {
        let dir = std::env::temp_dir().join(format!("trove-recorded-{}", std::process::id()));
        let file = dir.join("coordinator.json");
        let record = sample();
        record.write(&file).unwrap();
        let back = CoordinatorRecord::read(&file);
        let _ = std::fs::remove_dir_all(&dir);
        assert_eq!(back.unwrap(), record);
        assert_eq!(record.to_json()["scenes"][0]["tasks_per_piece"], json!(0.5));
        assert_eq!(record.to_json()["scenes"][0]["pieces_per_pixel"], json!(2.0));
    }

    #[test]
    fn a_worker_record_round_trips() {
        let w = WorkerRecord {
            processor: "p".into(),
            simd: "AVX-512".into(),
            commit: "c".into(),
            cast_per_sample: 12.5e-9,
            cast_per_task: 100e-9,
            bind_per_voxel: 0.5e-9,
            rebind_per_voxel: 0.001e-9,
            load_per_byte: 0.25e-9,
            parse_per_object: 50e-6,
        };
        let back = WorkerRecord::from_json(&w.to_json(), Path::new("w.json")).unwrap();
        for (a, b) in [
            (back.cast_per_sample, w.cast_per_sample),
            (back.cast_per_task, w.cast_per_task),
            (back.bind_per_voxel, w.bind_per_voxel),
            (back.rebind_per_voxel, w.rebind_per_voxel),
            (back.load_per_byte, w.load_per_byte),
            (back.parse_per_object, w.parse_per_object),
        ] {
            assert!((a / b - 1.0).abs() < 1e-12, "{a} vs {b}");
        }
    }

    #[test]
    fn a_file_of_another_format_is_refused_naming_the_file_the_field_and_the_format() {
        let mut value = sample().to_json();
        value["format"] = json!(COORDINATOR_FORMAT + 1);
        let e = CoordinatorRecord::from_json(&value, Path::new("old/coordinator.json")).unwrap_err().to_string();
        assert!(e.contains("old/coordinator.json"), "{e}");
        assert!(e.contains("`format`"), "{e}");
        assert!(e.contains(&format!("reads format {COORDINATOR_FORMAT}")), "{e}");
        assert!(e.contains(&format!("is {}", COORDINATOR_FORMAT + 1)), "{e}");
        value.as_object_mut().unwrap().remove("format");
        let e = CoordinatorRecord::from_json(&value, Path::new("c.json")).unwrap_err().to_string();
        assert!(e.contains("is missing"), "{e}");
        let mut w = json!({ "format": WORKER_FORMAT + 1 });
        assert!(WorkerRecord::from_json(&w, Path::new("w.json")).unwrap_err().to_string().contains("`format`"));
        w["format"] = json!(WORKER_FORMAT);
        let e = WorkerRecord::from_json(&w, Path::new("w.json")).unwrap_err().to_string();
        assert!(e.contains("w.json") && e.contains("`processor`"), "a missing field is named: {e}");
    }

    #[test]
    fn a_stage_with_an_unknown_place_is_refused() {
        let mut value = sample().to_json();
        value["scenes"][0]["stages"][0]["runs_on"] = json!("somewhere");
        let e = CoordinatorRecord::from_json(&value, Path::new("c.json")).unwrap_err().to_string();
        assert!(e.contains("scenes[0].stages[0].runs_on"), "{e}");
        assert!(place_of("a stage nobody placed").is_none());
    }
}
