//! The farm as an operator starts it: the real `trove coordinator` and two `trove-worker`
//! processes on loopback, each printing its bound address first, and a render through them
//! with the real `trove render --coordinator`, compared byte for byte with local mode.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use trove_tests::farm::spawn_server;
use trove_tests::process::{trove_worker_beside, Server};
use trove_tests::scenes::{slab_root, SLAB_AND_BALL as SCENE};
use trove_tests::scratch;

fn trove() -> &'static Path {
    Path::new(env!("CARGO_BIN_EXE_trove"))
}

/// `trove-worker`, built beside `trove`.
fn trove_worker() -> PathBuf {
    trove_worker_beside(trove())
}

/// Starts `program args`, its log on this test's stderr; the bound address with it.
fn start(program: &Path, args: &[&str]) -> (Server, String) {
    let (child, address) =
        spawn_server(program, args, Stdio::inherit()).unwrap_or_else(|e| panic!("start {}: {e}", program.display()));
    (Server(child), address)
}

#[test]
fn a_coordinator_and_two_worker_processes_render_what_local_mode_renders() {
    let dir = scratch("farm-binaries");
    slab_root(&dir.join("w0"));
    std::fs::create_dir_all(dir.join("w1")).unwrap();
    std::fs::write(dir.join("scene.toml"), SCENE).unwrap();

    let (_coordinator, address) = start(trove(), &["coordinator", "--listen", "127.0.0.1:0", "--heartbeat-ms", "100"]);
    let url = format!("http://{address}");
    let mut workers = Vec::new();
    for w in ["w0", "w1"] {
        let root = dir.join(w);
        let args = ["--coordinator", &url, "--listen", "127.0.0.1:0", "--data-root", root.to_str().unwrap()];
        workers.push(start(&trove_worker(), &args).0);
    }

    let local = dir.join("local.png");
    // One scene text: locally with w0 as the data root, and through workers whose roots hold
    // its keys (the client sends them as written). TROVE_DATA must not move either.
    let out = Command::new(trove())
        .args(["render", "scene.toml", "-o", "local.png", "--data-root", "w0"])
        .current_dir(&dir)
        .env_remove("TROVE_DATA")
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));

    // Workers register within a few heartbeats; a render before that is refused as "not
    // held", so retry briefly.
    let farm = dir.join("farm.png");
    let started = Instant::now();
    loop {
        let out = Command::new(trove())
            .args(["render", "scene.toml", "-o", "farm.png", "--stats", "farm.json", "--coordinator", &url])
            .current_dir(&dir)
            .env_remove("TROVE_DATA")
            .output()
            .unwrap();
        if out.status.success() {
            break;
        }
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(started.elapsed() < Duration::from_secs(20), "farm render failed: {stderr}");
        std::thread::sleep(Duration::from_millis(100));
    }
    assert_eq!(std::fs::read(&farm).unwrap(), std::fs::read(&local).unwrap(), "farm and local PNGs differ");
    let stats: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join("farm.json")).unwrap()).unwrap();
    assert!(stats["wire_bytes_to_workers"].as_u64().unwrap() > 0);
    assert_eq!(stats["width"], 40);
}
