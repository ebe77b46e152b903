//! `deploy/` against its schemas, offline: every Kubernetes manifest (the shard loader's too)
//! with `kubernetes-validate --strict` (the schemas ship in the package) at the oldest and the
//! newest Kubernetes the manifests are written for, the compose file with `check-jsonschema`'s
//! vendored compose-spec schema, and, where `kubectl` is at hand, what `kubectl kustomize`
//! renders of `deploy/k8s`, `deploy/k8s-tls` and `deploy/k8s-multi`. Each tool is also shown a broken copy, which
//! it must refuse: a validator that accepts anything would otherwise pass here.
//!
//! The Python tools come from PyPI (`.ci/run` installs them, pinned). Where one is missing its
//! check is skipped with a message, unless `TROVE_REQUIRE_TOOLS=1` (set by `.ci/run`), when
//! the skip is a failure. `kubectl` is not a registry package, so it is never required.
//!
//! The flags, ports and paths the files pass to the binaries are checked against the binaries
//! themselves in `coordinator/tests/deploy.rs`.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use trove_tests::{repo_root, scratch};

/// The oldest Kubernetes the manifests are written for (native gRPC probes are GA from 1.27,
/// `persistentVolumeClaimRetentionPolicy` is on by default from 1.27) and the newest whose
/// schemas `kubernetes-validate` ships.
const KUBERNETES_VERSIONS: [&str; 2] = ["1.28.0", "1.37.0"];

/// The variable that turns a missing tool into a failure (`.ci/run` sets it).
const REQUIRE_TOOLS: &str = "TROVE_REQUIRE_TOOLS";

fn deploy() -> PathBuf {
    repo_root().join("deploy")
}

/// Reports a skipped check past libtest's capture, or fails it when tools are required.
fn skip(reason: &str) {
    let test = std::thread::current().name().unwrap_or("a test").to_string();
    if std::env::var_os(REQUIRE_TOOLS).is_some_and(|v| !v.is_empty() && v != "0") {
        panic!("{test}: {reason}, and {REQUIRE_TOOLS} is set, so this is a failure, not a skip");
    }
    let _ = writeln!(
        std::io::stderr().lock(),
        "SKIPPED in {test}: {reason} (pip install kubernetes-validate check-jsonschema; {REQUIRE_TOOLS}=1 fails instead)"
    );
}

/// A finished command's status and its stdout and stderr together.
struct Run {
    success: bool,
    output: String,
}

/// Runs `program args`, killing it after a minute; `None` when it cannot be started at all.
fn run(program: &str, args: &[&str]) -> Option<Run> {
    let mut child = Command::new(program)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .ok()?;
    // Both pipes are drained on threads, so a chatty tool cannot block on a full pipe.
    let drain = |mut pipe: Box<dyn Read + Send>| {
        std::thread::spawn(move || {
            let mut text = String::new();
            let _ = pipe.read_to_string(&mut text);
            text
        })
    };
    let stdout = drain(Box::new(child.stdout.take().unwrap()));
    let stderr = drain(Box::new(child.stderr.take().unwrap()));
    let started = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if started.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{program} {args:?} ran past a minute");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let output = stdout.join().unwrap() + &stderr.join().unwrap();
    Some(Run { success: status.success(), output })
}

/// Whether `program` runs here (`--version` answers).
fn have(program: &str) -> bool {
    run(program, &["--version"]).is_some_and(|r| r.success)
}

/// The files a `kustomization.yaml` lists under `resources:`.
fn kustomization_resources(text: &str) -> Vec<String> {
    let mut resources = Vec::new();
    let mut inside = false;
    for line in text.lines() {
        if line.trim_start().starts_with('#') {
            continue;
        }
        if !line.starts_with(' ') && !line.starts_with('-') {
            inside = line.trim_end() == "resources:";
            continue;
        }
        if inside {
            if let Some(item) = line.trim().strip_prefix("- ") {
                resources.push(item.trim().to_string());
            }
        }
    }
    resources
}

/// The Kubernetes manifests of `deploy/k8s`: every YAML file there but the kustomization.
fn farm_manifests() -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(deploy().join("k8s"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "yaml") && p.file_name().unwrap() != "kustomization.yaml")
        .collect();
    files.sort();
    files
}

/// `kubernetes-validate --strict` of `files` at one Kubernetes version.
fn kubernetes_validate_at(version: &str, files: &[PathBuf]) -> Run {
    let mut args = vec!["--strict", "--kubernetes-version", version];
    args.extend(files.iter().map(|f| f.to_str().unwrap()));
    run("kubernetes-validate", &args).expect("kubernetes-validate was found but does not start")
}

/// Validates `files` strictly at every version in [`KUBERNETES_VERSIONS`]; returns the
/// failures. A kind without a schema is only a warning to the tool: here it is a failure.
fn kubernetes_validate(files: &[PathBuf]) -> Vec<String> {
    let mut failures = Vec::new();
    for version in KUBERNETES_VERSIONS {
        let out = kubernetes_validate_at(version, files);
        if !out.success || out.output.contains("Couldn't find schema") {
            failures.push(format!("kubernetes-validate at {version}:\n{}", out.output));
        }
    }
    failures
}

#[test]
fn the_kustomization_lists_every_manifest_and_the_tls_overlay_builds_on_it() {
    let listed = kustomization_resources(&std::fs::read_to_string(deploy().join("k8s/kustomization.yaml")).unwrap());
    let present: Vec<String> =
        farm_manifests().iter().map(|p| p.file_name().unwrap().to_str().unwrap().to_string()).collect();
    let mut sorted = listed.clone();
    sorted.sort();
    assert_eq!(sorted, present, "deploy/k8s/kustomization.yaml must list exactly the manifests beside it");
    let tls = kustomization_resources(&std::fs::read_to_string(deploy().join("k8s-tls/kustomization.yaml")).unwrap());
    assert_eq!(tls, ["../k8s"], "deploy/k8s-tls/kustomization.yaml must build on deploy/k8s alone");
    let multi =
        kustomization_resources(&std::fs::read_to_string(deploy().join("k8s-multi/kustomization.yaml")).unwrap());
    assert_eq!(
        multi,
        ["../k8s", "coordinators.yaml"],
        "deploy/k8s-multi/kustomization.yaml must build on deploy/k8s and its coordinators.yaml"
    );
}

#[test]
fn kustomization_resources_reads_only_the_resources_list() {
    let text = "# comment\nresources:\n  - a.yaml\n  # not this\n  - b.yaml\nimages:\n  - name: trove\n";
    assert_eq!(kustomization_resources(text), ["a.yaml", "b.yaml"]);
    assert!(kustomization_resources("images:\n  - x\n").is_empty());
}

#[test]
fn the_kubernetes_manifests_validate_strictly() {
    if !have("kubernetes-validate") {
        return skip("kubernetes-validate is not installed");
    }
    let mut files = farm_manifests();
    assert!(files.len() >= 3, "deploy/k8s has {} manifests", files.len());
    files.push(deploy().join("shard-loader.yaml"));
    files.push(deploy().join("k8s-multi/coordinators.yaml"));
    let failures = kubernetes_validate(&files);
    assert!(failures.is_empty(), "{}", failures.join("\n"));

    // The tool refuses what it should: a misspelt field, and a kind it has no schema for.
    let dir = scratch("deploy-k8s-broken");
    let workers = std::fs::read_to_string(deploy().join("k8s/workers.yaml")).unwrap();
    let misspelt = workers.replacen("readOnlyRootFilesystem", "readOnlyRootFilesytem", 1);
    assert_ne!(misspelt, workers);
    std::fs::write(dir.join("misspelt.yaml"), misspelt).unwrap();
    std::fs::write(dir.join("unknown.yaml"), "apiVersion: example.com/v1\nkind: Farm\nmetadata:\n  name: x\n").unwrap();
    let out = kubernetes_validate_at(KUBERNETES_VERSIONS[1], &[dir.join("misspelt.yaml"), dir.join("unknown.yaml")]);
    assert!(!out.success, "kubernetes-validate accepted a misspelt field:\n{}", out.output);
    assert!(out.output.contains("readOnlyRootFilesytem"), "{}", out.output);
    assert!(out.output.contains("unknown.yaml Couldn't find schema"), "{}", out.output);
}

#[test]
fn what_kustomize_renders_validates_strictly() {
    if !have("kubernetes-validate") {
        return skip("kubernetes-validate is not installed");
    }
    if !run("kubectl", &["version", "--client"]).is_some_and(|r| r.success) {
        // Not required even in CI: kubectl comes from no package registry. The base's
        // manifests are validated one by one above; the TLS overlay's patches only here.
        let _ = writeln!(std::io::stderr().lock(), "SKIPPED: kubectl is absent, so deploy/k8s-tls is not rendered");
        return;
    }
    let dir = scratch("deploy-kustomize");
    for overlay in ["k8s", "k8s-tls", "k8s-multi"] {
        let path = deploy().join(overlay);
        let out = run("kubectl", &["kustomize", path.to_str().unwrap()]).unwrap();
        assert!(out.success, "kubectl kustomize deploy/{overlay}:\n{}", out.output);
        assert!(out.output.contains("kind: StatefulSet"), "deploy/{overlay} renders no StatefulSet");
        if overlay == "k8s-multi" {
            // The one coordinator gives way to the StatefulSet, which the workers list.
            assert!(!out.output.contains("kind: Deployment"), "deploy/k8s-multi keeps the one coordinator");
            assert!(!out.output.contains("claimName: trove-coordinator-state"), "deploy/k8s-multi keeps its claim");
            for i in 0..4 {
                let url = format!("http://trove-coordinator-{i}.trove-coordinators:7000");
                assert!(out.output.contains(&url), "deploy/k8s-multi's workers do not list {url}");
            }
        }
        let rendered = dir.join(format!("{overlay}.yaml"));
        std::fs::write(&rendered, &out.output).unwrap();
        let failures = kubernetes_validate(&[rendered]);
        assert!(failures.is_empty(), "deploy/{overlay}, rendered: {}", failures.join("\n"));
    }
}

#[test]
fn the_compose_file_validates_against_the_compose_spec() {
    if !have("check-jsonschema") {
        return skip("check-jsonschema is not installed");
    }
    let check = |path: &Path| {
        run("check-jsonschema", &["--builtin-schema", "vendor.compose-spec", path.to_str().unwrap()]).unwrap()
    };
    let compose = deploy().join("docker-compose.yml");
    let out = check(&compose);
    assert!(out.success, "{}:\n{}", compose.display(), out.output);

    let dir = scratch("deploy-compose-broken");
    let text = std::fs::read_to_string(&compose).unwrap();
    let broken = text.replacen("stop_grace_period:", "stop_grace_periode:", 1);
    assert_ne!(broken, text);
    std::fs::write(dir.join("docker-compose.yml"), broken).unwrap();
    let out = check(&dir.join("docker-compose.yml"));
    assert!(!out.success, "check-jsonschema accepted a misspelt key:\n{}", out.output);
}
