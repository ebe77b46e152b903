//! The example client in another language (`examples/python/trove_client.py`): its stubs
//! generated from `proto/trove.proto` by grpcio-tools at run time, it renders through an
//! in-process farm to the very PNG local mode writes. Where `grpc_tools` is not importable
//! the test skips, saying so; with `TROVE_REQUIRE_TOOLS=1` (set by `.ci/run`, which installs
//! the packages) that skip is a failure.

use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use trove_core::render::{render, RenderOptions};
use trove_core::scene::Scene;
use trove_tests::farm::{data_root, TestFarm};
use trove_tests::{repo_root, scratch};

/// The variable that turns a missing toolchain into a failure.
const REQUIRE_TOOLS: &str = "TROVE_REQUIRE_TOOLS";

/// A child process killed when dropped, so a hung script cannot outlive the test.
struct Killed(Option<Child>);

impl Drop for Killed {
    fn drop(&mut self) {
        if let Some(mut child) = self.0.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Runs `python3 args` for at most `limit`.
fn python(args: &[&std::ffi::OsStr], limit: Duration) -> std::io::Result<Output> {
    let child = Command::new("python3")
        .args(args)
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()?;
    let mut child = Killed(Some(child));
    let started = Instant::now();
    loop {
        let running = child.0.as_mut().expect("held until the end");
        if running.try_wait()?.is_some() {
            return child.0.take().expect("held").wait_with_output();
        }
        if started.elapsed() > limit {
            return Err(std::io::Error::other(format!("python3 {args:?} ran past {limit:?}")));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Whether python3 with grpcio-tools is here; otherwise the skip is reported (or fails).
fn tools_at_hand() -> bool {
    let probe = python(&["-c".as_ref(), "import grpc, grpc_tools".as_ref()], Duration::from_secs(60));
    let missing = match probe {
        Ok(out) if out.status.success() => return true,
        Ok(out) => String::from_utf8_lossy(&out.stderr).trim().lines().last().unwrap_or("").to_string(),
        Err(e) => format!("python3 cannot run: {e}"),
    };
    let test = std::thread::current().name().unwrap_or("a test").to_string();
    let reason = format!("python3 with grpcio and grpcio-tools is not at hand ({missing})");
    if std::env::var_os(REQUIRE_TOOLS).is_some_and(|v| !v.is_empty() && v != "0") {
        panic!("{test}: {reason}, and {REQUIRE_TOOLS} is set, so this is a failure, not a skip");
    }
    // Past libtest's capture, so the skip shows beside the test's `ok`.
    use std::io::Write;
    let _ = writeln!(
        std::io::stderr().lock(),
        "SKIPPED in {test}: {reason}; pip install grpcio grpcio-tools, or set {REQUIRE_TOOLS}=1 to fail instead"
    );
    false
}

const SCENE: &str = "[image]\nwidth = 24\nheight = 20\nbackground = [0.1, 0.1, 0.2]\n\
    [camera]\neye = [0.5, 0.6, 3.0]\ntarget = [0.5, 0.5, 0.5]\nup = [0, 1, 0]\nfov_y = 35.0\n\
    [[datasets]]\nname = \"ball\"\ndims = [24, 24, 24]\n[datasets.channels.voxel]\n\
    generator = { kind = \"sphere\", radius = 0.5, profile = \"radial\", value = 1.0, type = \"f32\" }\n\
    [[objects]]\nname = \"ball\"\ndataset = \"ball\"\n\
    colour = { type = \"ramp\", points = [[0.0, 0.9, 0.3, 0.1], [1.0, 0.2, 0.5, 1.0]] }\n\
    opacity = { type = \"ramp\", points = [[0.0, 0.0], [1.0, 0.3]] }\n";

#[test]
fn the_python_example_client_renders_through_the_farm_as_local_mode_does() {
    if !tools_at_hand() {
        return;
    }
    let dir = scratch("example-python");
    let farm = TestFarm::start(&[data_root(&dir.join("w0"), &dir, &[])]);
    let (scene, out) = (dir.join("ball.toml"), dir.join("ball.png"));
    std::fs::write(&scene, SCENE).unwrap();
    let script = repo_root().join("examples/python/trove_client.py");
    let args = [
        script.as_os_str(),
        "--coordinator".as_ref(),
        farm.url.as_ref(),
        scene.as_os_str(),
        "-o".as_ref(),
        out.as_os_str(),
    ];
    let ran = python(&args, Duration::from_secs(120)).expect("run the example client");
    let stderr = String::from_utf8_lossy(&ran.stderr);
    assert!(ran.status.success(), "the example client failed: {stderr}");
    assert!(stderr.contains("JOB_STATE_SUCCEEDED"), "it watched the job: {stderr}");
    let expected = render(&Scene::parse(SCENE, &scene).unwrap(), &RenderOptions::default()).unwrap();
    let png = std::fs::read(&out).expect("the client wrote its PNG");
    assert!(png == expected.image.encode_png().unwrap(), "the Python client's PNG differs from local mode's");

    // A refusal comes back as the coordinator's typed failure, and exit 1.
    std::fs::write(&scene, SCENE.replace("fov_y = 35.0", "fov_y = 235.0")).unwrap();
    let ran = python(&args, Duration::from_secs(120)).expect("run the example client");
    let stderr = String::from_utf8_lossy(&ran.stderr);
    assert_eq!(ran.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("REASON_SCENE_INVALID") && stderr.contains("key camera.fov_y"), "{stderr}");
}
