//! What a coordinator keeps on disk under `--state-dir`, so that a SIGKILL loses no job: every
//! job's submission (scene text, name, options), its last recorded status, its submission and
//! finish times, and a finished job's files, in one `redb` database (`jobs.redb`).
//!
//! A job is written when it is accepted (before its id is answered), when it starts running
//! and when it ends (its status and files in one transaction, so a SUCCEEDED record always
//! has its files). Progress is not written: a job that was QUEUED or RUNNING at a crash is
//! run again from the start, which gives the same image byte for byte. Every commit is
//! durable (fsynced) and quick to repair, so a restart after a kill opens the database at
//! once. Finished jobs older than the coordinator's `--keep-results-s` are swept away.

use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use prost::Message;
use redb::{Database, ReadableDatabase, ReadableTable, TableDefinition};
use thiserror::Error;
use trove_proto::v1 as pb;

use super::jobs::{is_final, JobOutput};

/// Job records by id.
const JOBS: TableDefinition<&str, &[u8]> = TableDefinition::new("jobs");
/// A finished job's files by (job id, part: [`PART_PNG`], [`PART_PFM`], [`PART_STATS`]).
const RESULTS: TableDefinition<(&str, u8), &[u8]> = TableDefinition::new("results");
/// Counters: the last job number handed out ([`JOB_SEQ`]), the last id prefix ([`EPOCH`]).
const META: TableDefinition<&str, u64> = TableDefinition::new("meta");

const PART_PNG: u8 = 0;
const PART_PFM: u8 = 1;
const PART_STATS: u8 = 2;
const JOB_SEQ: &str = "job_seq";
const EPOCH: &str = "epoch_ms";

/// The database's file name inside the state folder.
pub const DATABASE_FILE: &str = "jobs.redb";

/// Why the state store failed.
#[derive(Debug, Error)]
pub enum StateError {
    /// The state folder cannot be made.
    #[error("cannot create the state folder {}: {source}", path.display())]
    Folder {
        /// The folder.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The database cannot be opened (another coordinator holds it, or it is not a database).
    #[error("{}: cannot open the coordinator's state database (is another coordinator using this --state-dir?): {source}", path.display())]
    Open {
        /// The database file.
        path: PathBuf,
        /// Why.
        #[source]
        source: redb::DatabaseError,
    },
    /// A read or a write failed.
    #[error("{}: the state database failed: {source}", path.display())]
    Database {
        /// The database file.
        path: PathBuf,
        /// Why.
        #[source]
        source: redb::Error,
    },
    /// A stored job record does not decode.
    #[error("{}: the record of job `{job}` is damaged: {source}", path.display())]
    Decode {
        /// The database file.
        path: PathBuf,
        /// The job.
        job: String,
        /// Why.
        #[source]
        source: prost::DecodeError,
    },
}

/// One job as stored: what it takes to run it again, and how it ended.
#[derive(Clone, PartialEq, Message)]
pub struct JobRecord {
    /// Its id.
    #[prost(string, tag = "1")]
    pub job_id: String,
    /// Its number, in submission order: resumed jobs run in this order.
    #[prost(uint64, tag = "2")]
    pub seq: u64,
    /// The scene as submitted.
    #[prost(string, tag = "3")]
    pub scene_toml: String,
    /// The scene file's name, for messages.
    #[prost(string, tag = "4")]
    pub scene_name: String,
    /// The client's options.
    #[prost(message, optional, tag = "5")]
    pub options: Option<pb::JobOptions>,
    /// Its status when last written (QUEUED, RUNNING, or how it ended).
    #[prost(message, optional, tag = "6")]
    pub status: Option<pb::JobStatus>,
    /// When it was submitted, in milliseconds since the Unix epoch.
    #[prost(uint64, tag = "7")]
    pub submitted_unix_ms: u64,
    /// When it ended, in milliseconds since the Unix epoch; 0 while it has not.
    #[prost(uint64, tag = "8")]
    pub finished_unix_ms: u64,
}

impl JobRecord {
    /// The recorded state.
    pub fn state(&self) -> pb::JobState {
        self.status.as_ref().map_or(pb::JobState::Queued, |s| s.state())
    }
}

/// Milliseconds since the Unix epoch now.
pub fn now_unix_ms() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_millis() as u64)
}

/// The coordinator's database.
pub struct StateStore {
    db: Database,
    path: PathBuf,
}

impl StateStore {
    /// Opens (or creates) the database in folder `dir`, creating the folder if needed.
    pub fn open(dir: &Path) -> Result<StateStore, StateError> {
        std::fs::create_dir_all(dir).map_err(|source| StateError::Folder { path: dir.to_path_buf(), source })?;
        let path = dir.join(DATABASE_FILE);
        let db = Database::create(&path).map_err(|source| StateError::Open { path: path.clone(), source })?;
        let store = StateStore { db, path };
        store.write(|txn| {
            txn.open_table(JOBS)?;
            txn.open_table(RESULTS)?;
            txn.open_table(META)?;
            Ok(())
        })?;
        Ok(store)
    }

    /// The database file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn failed(&self, e: impl Into<redb::Error>) -> StateError {
        StateError::Database { path: self.path.clone(), source: e.into() }
    }

    /// Runs `f` in one durable write transaction.
    fn write<T>(&self, f: impl FnOnce(&redb::WriteTransaction) -> Result<T, redb::Error>) -> Result<T, StateError> {
        let mut txn = self.db.begin_write().map_err(|e| self.failed(e))?;
        // Each commit also saves the allocator state, so opening after a kill needs no walk
        // of the whole file.
        txn.set_quick_repair(true);
        let value = f(&txn).map_err(|e| self.failed(e))?;
        txn.commit().map_err(|e| self.failed(e))?;
        Ok(value)
    }

    fn decode(&self, job: &str, bytes: &[u8]) -> Result<JobRecord, StateError> {
        JobRecord::decode(bytes).map_err(|source| StateError::Decode {
            path: self.path.clone(),
            job: job.to_string(),
            source,
        })
    }

    /// A prefix for this run's ids, in milliseconds since the Unix epoch: now, or one past the
    /// last run's if the clock went back, so that no two runs over this database share one.
    pub fn claim_epoch(&self, now_ms: u64) -> Result<u64, StateError> {
        self.write(|txn| {
            let mut meta = txn.open_table(META)?;
            let last = meta.get(EPOCH)?.map(|v| v.value());
            let epoch = last.map_or(now_ms, |last| now_ms.max(last + 1));
            meta.insert(EPOCH, epoch)?;
            Ok(epoch)
        })
    }

    /// The highest job number handed out so far (0 for a new database).
    pub fn last_job_seq(&self) -> Result<u64, StateError> {
        let txn = self.db.begin_read().map_err(|e| self.failed(e))?;
        let meta = txn.open_table(META).map_err(|e| self.failed(e))?;
        let seq = meta.get(JOB_SEQ).map_err(|e| self.failed(e))?.map_or(0, |v| v.value());
        Ok(seq)
    }

    /// Writes `record` (a new job, or a new status of one), raising the stored job number to
    /// its `seq`.
    pub fn put_job(&self, record: &JobRecord) -> Result<(), StateError> {
        let bytes = record.encode_to_vec();
        self.write(|txn| {
            txn.open_table(JOBS)?.insert(record.job_id.as_str(), bytes.as_slice())?;
            let mut meta = txn.open_table(META)?;
            let last = meta.get(JOB_SEQ)?.map_or(0, |v| v.value());
            if record.seq > last {
                meta.insert(JOB_SEQ, record.seq)?;
            }
            Ok(())
        })
    }

    /// Replaces job `id`'s status (and finish time, when it ended); false when no such job
    /// is stored.
    pub fn set_status(&self, id: &str, status: &pb::JobStatus, finished_unix_ms: u64) -> Result<bool, StateError> {
        self.finish(id, status, finished_unix_ms, None)
    }

    /// Records how job `id` ended, with its files when it succeeded, in one transaction;
    /// false when no such job is stored.
    pub fn finish(
        &self,
        id: &str,
        status: &pb::JobStatus,
        finished_unix_ms: u64,
        output: Option<&JobOutput>,
    ) -> Result<bool, StateError> {
        let Some(mut record) = self.job(id)? else { return Ok(false) };
        record.status = Some(status.clone());
        record.finished_unix_ms = finished_unix_ms;
        let bytes = record.encode_to_vec();
        self.write(|txn| {
            txn.open_table(JOBS)?.insert(id, bytes.as_slice())?;
            if let Some(output) = output {
                let mut results = txn.open_table(RESULTS)?;
                results.insert((id, PART_PNG), output.png.as_slice())?;
                if let Some(pfm) = &output.pfm {
                    results.insert((id, PART_PFM), pfm.as_slice())?;
                }
                results.insert((id, PART_STATS), output.stats_json.as_slice())?;
            }
            Ok(())
        })?;
        Ok(true)
    }

    /// Job `id`'s record, if stored.
    pub fn job(&self, id: &str) -> Result<Option<JobRecord>, StateError> {
        let txn = self.db.begin_read().map_err(|e| self.failed(e))?;
        let jobs = txn.open_table(JOBS).map_err(|e| self.failed(e))?;
        let Some(bytes) = jobs.get(id).map_err(|e| self.failed(e))? else { return Ok(None) };
        self.decode(id, bytes.value()).map(Some)
    }

    /// Every stored job, in submission order.
    pub fn jobs(&self) -> Result<Vec<JobRecord>, StateError> {
        let txn = self.db.begin_read().map_err(|e| self.failed(e))?;
        let jobs = txn.open_table(JOBS).map_err(|e| self.failed(e))?;
        let mut records = Vec::new();
        for entry in jobs.iter().map_err(|e| self.failed(e))? {
            let (id, bytes) = entry.map_err(|e| self.failed(e))?;
            records.push(self.decode(id.value(), bytes.value())?);
        }
        records.sort_by_key(|r| r.seq);
        Ok(records)
    }

    /// The files of finished job `id`, if stored.
    pub fn result(&self, id: &str) -> Result<Option<JobOutput>, StateError> {
        let txn = self.db.begin_read().map_err(|e| self.failed(e))?;
        let results = txn.open_table(RESULTS).map_err(|e| self.failed(e))?;
        let part = |p: u8| -> Result<Option<Vec<u8>>, StateError> {
            Ok(results.get((id, p)).map_err(|e| self.failed(e))?.map(|v| v.value().to_vec()))
        };
        let Some(png) = part(PART_PNG)? else { return Ok(None) };
        Ok(Some(JobOutput { png, pfm: part(PART_PFM)?, stats_json: part(PART_STATS)?.unwrap_or_default() }))
    }

    /// Removes every job that ended before `cutoff_unix_ms`, with its files; returns their ids.
    /// Jobs that have not ended are never removed.
    pub fn sweep(&self, cutoff_unix_ms: u64) -> Result<Vec<String>, StateError> {
        let expired: Vec<String> = self
            .jobs()?
            .into_iter()
            .filter(|r| is_final(r.state()) && r.finished_unix_ms < cutoff_unix_ms)
            .map(|r| r.job_id)
            .collect();
        if expired.is_empty() {
            return Ok(expired);
        }
        self.write(|txn| {
            let mut jobs = txn.open_table(JOBS)?;
            let mut results = txn.open_table(RESULTS)?;
            for id in &expired {
                jobs.remove(id.as_str())?;
                for part in [PART_PNG, PART_PFM, PART_STATS] {
                    results.remove((id.as_str(), part))?;
                }
            }
            Ok(())
        })?;
        Ok(expired)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn folder(name: &str) -> trove_tests::Scratch {
        trove_tests::scratch(&format!("state-{name}"))
    }

    fn record(id: &str, seq: u64, state: pb::JobState) -> JobRecord {
        JobRecord {
            job_id: id.to_string(),
            seq,
            scene_toml: format!("# scene of {id}\n"),
            scene_name: format!("{id}.toml"),
            options: Some(pb::JobOptions { want_pfm: seq.is_multiple_of(2), band_rows: 7, ..Default::default() }),
            status: Some(pb::JobStatus { job_id: id.to_string(), state: state as i32, ..Default::default() }),
            submitted_unix_ms: 1000 + seq,
            finished_unix_ms: 0,
        }
    }

    fn output(tag: u8, pfm: bool) -> JobOutput {
        JobOutput {
            png: vec![tag; 1000],
            pfm: pfm.then(|| vec![tag ^ 0xff; 3000]),
            stats_json: format!("{{\"tag\": {tag}}}").into_bytes(),
        }
    }

    #[test]
    fn jobs_and_results_survive_reopening() {
        let dir = folder("round-trip");
        let done = pb::JobStatus { job_id: "b".into(), state: pb::JobState::Succeeded as i32, ..Default::default() };
        {
            let store = StateStore::open(&dir).unwrap();
            // Written out of order: read back in submission order.
            store.put_job(&record("c", 3, pb::JobState::Queued)).unwrap();
            store.put_job(&record("a", 1, pb::JobState::Running)).unwrap();
            store.put_job(&record("b", 2, pb::JobState::Queued)).unwrap();
            assert!(store.finish("b", &done, 5000, Some(&output(7, true))).unwrap());
            assert!(!store.finish("nobody", &done, 5000, None).unwrap(), "an unknown job is not created");
        }
        let store = StateStore::open(&dir).unwrap();
        let jobs = store.jobs().unwrap();
        assert_eq!(jobs.iter().map(|r| r.job_id.as_str()).collect::<Vec<_>>(), ["a", "b", "c"]);
        assert_eq!(jobs[0], record("a", 1, pb::JobState::Running));
        assert_eq!(jobs[2], record("c", 3, pb::JobState::Queued));
        let b = store.job("b").unwrap().unwrap();
        assert_eq!(b.state(), pb::JobState::Succeeded);
        assert_eq!(b.finished_unix_ms, 5000);
        assert_eq!(b.scene_toml, "# scene of b\n");
        let files = store.result("b").unwrap().unwrap();
        let expected = output(7, true);
        assert_eq!((files.png, files.pfm, files.stats_json), (expected.png, expected.pfm, expected.stats_json));
        assert!(store.result("a").unwrap().is_none());
        assert!(store.job("zzz").unwrap().is_none());
    }

    #[test]
    fn the_sweep_removes_only_jobs_that_ended_before_the_cutoff() {
        let dir = folder("sweep");
        let store = StateStore::open(&dir).unwrap();
        for (i, id) in ["old", "recent", "running", "old-failed"].iter().enumerate() {
            store.put_job(&record(id, i as u64 + 1, pb::JobState::Queued)).unwrap();
        }
        let ended = |id: &str, state: pb::JobState| pb::JobStatus {
            job_id: id.into(),
            state: state as i32,
            ..Default::default()
        };
        store.finish("old", &ended("old", pb::JobState::Succeeded), 100, Some(&output(1, false))).unwrap();
        store.finish("recent", &ended("recent", pb::JobState::Succeeded), 900, Some(&output(2, false))).unwrap();
        store.finish("old-failed", &ended("old-failed", pb::JobState::Failed), 200, None).unwrap();
        store.set_status("running", &ended("running", pb::JobState::Running), 0).unwrap();

        let mut swept = store.sweep(500).unwrap();
        swept.sort();
        assert_eq!(swept, ["old", "old-failed"]);
        let left: Vec<String> = store.jobs().unwrap().into_iter().map(|r| r.job_id).collect();
        assert_eq!(left, ["recent", "running"], "a job that has not ended is kept however old");
        assert!(store.result("old").unwrap().is_none(), "its files go with it");
        assert_eq!(store.result("recent").unwrap().unwrap().png, output(2, false).png);
        assert!(store.sweep(500).unwrap().is_empty());
    }

    #[test]
    fn the_job_counter_and_the_id_prefix_only_grow_across_reopenings() {
        let dir = folder("counter");
        {
            let store = StateStore::open(&dir).unwrap();
            assert_eq!(store.last_job_seq().unwrap(), 0);
            store.put_job(&record("a", 41, pb::JobState::Queued)).unwrap();
            store.put_job(&record("b", 40, pb::JobState::Queued)).unwrap();
            assert_eq!(store.last_job_seq().unwrap(), 41, "a lower number committed later does not lower it");
            assert_eq!(store.claim_epoch(5000).unwrap(), 5000);
        }
        let store = StateStore::open(&dir).unwrap();
        assert_eq!(store.last_job_seq().unwrap(), 41);
        // A clock that went back still gives a new prefix.
        assert_eq!(store.claim_epoch(4000).unwrap(), 5001);
        assert_eq!(store.claim_epoch(9000).unwrap(), 9000);
        // A swept job's number is not handed out again.
        let done = pb::JobStatus { job_id: "a".into(), state: pb::JobState::Failed as i32, ..Default::default() };
        store.finish("a", &done, 1, None).unwrap();
        store.sweep(u64::MAX).unwrap();
        assert_eq!(store.last_job_seq().unwrap(), 41);
    }

    #[test]
    fn a_second_coordinator_on_one_folder_is_refused_with_the_path() {
        let dir = folder("twice");
        let _first = StateStore::open(&dir).unwrap();
        let Err(e) = StateStore::open(&dir) else { panic!("two stores opened one database") };
        let message = e.to_string();
        assert!(message.contains(DATABASE_FILE) && message.contains("another coordinator"), "{message}");
    }
}
