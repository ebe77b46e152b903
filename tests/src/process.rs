//! The farm's binaries as child processes, for the tests that start the real `trove
//! coordinator` and `trove-worker`: a handle that kills its process when dropped (so a
//! failing test leaves no server behind), signals it, and waits for it to exit.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus};
use std::time::{Duration, Instant};

/// A child process killed (SIGKILL, which ends a stopped one too) and reaped when dropped.
pub struct Server(pub Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Server {
    /// Sends `signal` (`-TERM`, `-STOP`, …) with `kill`.
    pub fn signal(&self, signal: &str) {
        let status = Command::new("kill").args([signal, &self.0.id().to_string()]).status().expect("run kill");
        assert!(status.success(), "kill {signal} failed");
    }

    /// Waits for the process to exit, at most `limit`.
    pub fn exit_within(&mut self, limit: Duration) -> ExitStatus {
        let started = Instant::now();
        loop {
            if let Some(status) = self.0.try_wait().expect("wait for the process") {
                return status;
            }
            assert!(started.elapsed() < limit, "the process did not exit within {limit:?}");
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

/// `trove-worker`, built beside `trove` (the path a coordinator test has as
/// `env!("CARGO_BIN_EXE_trove")`) by the same `cargo test --workspace`.
pub fn trove_worker_beside(trove: &Path) -> PathBuf {
    let path = trove.with_file_name(format!("trove-worker{}", std::env::consts::EXE_SUFFIX));
    assert!(path.exists(), "{} is missing: run the workspace's tests (cargo test --workspace)", path.display());
    path
}
