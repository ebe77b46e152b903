//! What `deploy/` and the operator docs tell the binaries is what the binaries take: every
//! `--flag` that the Kubernetes manifests, the TLS overlay, the compose file and the shell
//! blocks of `README.md` and `deploy/README.md` pass to `trove coordinator`, `trove-worker` or
//! a `trove` client command appears in that command's `--help`; and the ports, paths and
//! image names agree between the files and the Dockerfile (a probe checks the port the
//! server listens on, a file flag names a mounted path, …). No tool is needed: the files are
//! read as text by the small extractors below, each tested on its own. Their schemas are
//! checked in `tests/tests/deploy.rs`.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};
use trove_tests::process::trove_worker_beside;
use trove_tests::scratch;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn trove() -> &'static Path {
    Path::new(env!("CARGO_BIN_EXE_trove"))
}

/// `trove-worker`, built beside `trove`.
fn trove_worker() -> PathBuf {
    trove_worker_beside(trove())
}

/// A command the files run: `trove-worker`, or `trove` and the words before its first flag
/// (the subcommand, and any positional arguments: `--help` after them still asks the
/// subcommand).
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Program {
    Worker,
    Trove(Vec<String>),
}

impl std::fmt::Display for Program {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Program::Worker => write!(f, "trove-worker"),
            Program::Trove(words) if words.is_empty() => write!(f, "trove"),
            Program::Trove(words) => write!(f, "trove {}", words.join(" ")),
        }
    }
}

fn coordinator() -> Program {
    Program::Trove(vec!["coordinator".into()])
}

/// One `--flag` (with its `=value`, if written so) passed to `program` (`None`: to no
/// command the extractor recognised), at a 1-based line.
#[derive(Clone, Debug, PartialEq)]
struct FlagUse {
    program: Option<Program>,
    flag: String,
    value: Option<String>,
    line: usize,
}

fn flag_use(program: Option<Program>, token: &str, line: usize) -> FlagUse {
    let (flag, value) = match token.split_once('=') {
        Some((flag, value)) => (flag.to_string(), Some(value.to_string())),
        None => (token.to_string(), None),
    };
    FlagUse { program, flag, value, line }
}

/// A long flag: `--` and a letter or digit (not YAML's `---`, nor a bare `--`).
fn is_flag(token: &str) -> bool {
    token.strip_prefix("--").is_some_and(|rest| rest.starts_with(|c: char| c.is_ascii_alphanumeric()))
}

/// A YAML line without its comment.
fn strip_comment(line: &str) -> &str {
    if line.trim_start().starts_with('#') {
        return "";
    }
    line.find(" #").map_or(line, |i| &line[..i])
}

fn unquote(s: &str) -> String {
    s.trim().trim_matches(|c| c == '"' || c == '\'').to_string()
}

/// A YAML line as `(key, words)`: the key of a `key: value` line (after any `- ` list
/// markers), and the value's words: a flow list's elements (`["trove", "coordinator"]`) or
/// the one scalar, unquoted. A bare list item (`- --listen=…`) has no key.
fn yaml_line(line: &str) -> (Option<String>, Vec<String>) {
    let mut rest = strip_comment(line).trim();
    while let Some(r) = rest.strip_prefix("- ") {
        rest = r.trim_start();
    }
    if rest == "-" {
        rest = "";
    }
    let plain_key = !rest.starts_with(['"', '\'', '[', '-']);
    let (key, value) = match rest.find(": ") {
        Some(i) if plain_key => (Some(rest[..i].to_string()), rest[i + 2..].trim()),
        _ if plain_key && rest.ends_with(':') => (Some(rest[..rest.len() - 1].to_string()), ""),
        _ => (None, rest),
    };
    let words = if value.is_empty() {
        Vec::new()
    } else if let Some(list) = value.strip_prefix('[').and_then(|v| v.strip_suffix(']')) {
        list.split(',').map(unquote).filter(|w| !w.is_empty()).collect()
    } else {
        vec![unquote(value)]
    };
    (key, words)
}

/// Every `--flag` a YAML file passes to a TROVE binary. A `command:` or `entrypoint:` starts
/// a command; in it, and in bare list items and `value:`s (a JSON patch's) after it, the word
/// `trove-worker` names the worker, `trove` and the next word a `trove` subcommand, and a
/// `--` word is a flag of the command last named. A `name: trove-coordinator` or
/// `name: trove-worker` line (a manifest's or a patch target's) names the binary that the
/// flags after it go to, for patches that add arguments to it.
fn yaml_flag_uses(text: &str) -> Vec<FlagUse> {
    let mut uses = Vec::new();
    let mut current: Option<Program> = None;
    let mut after_trove = false;
    for (i, line) in text.lines().enumerate() {
        let (key, words) = yaml_line(line);
        match key.as_deref() {
            Some("name") => {
                match words.first().map(String::as_str) {
                    Some("trove-coordinator") => current = Some(coordinator()),
                    Some("trove-worker") => current = Some(Program::Worker),
                    _ => {}
                }
                continue;
            }
            Some("command" | "entrypoint") => {
                current = None;
                after_trove = false;
            }
            None | Some("args" | "value") => {}
            Some(_) => continue,
        }
        for word in words {
            if word == "trove-worker" {
                current = Some(Program::Worker);
                after_trove = false;
            } else if word == "trove" {
                current = Some(Program::Trove(Vec::new()));
                after_trove = true;
            } else if is_flag(&word) {
                uses.push(flag_use(current.clone(), &word, i + 1));
                after_trove = false;
            } else if after_trove {
                current = Some(Program::Trove(vec![word]));
                after_trove = false;
            }
        }
    }
    uses
}

/// Every `--flag` passed to `trove` or `trove-worker` in a Markdown file's fenced blocks. A
/// command starts a line, follows `&&`, `||`, `|`, `;`, `&`, a `--` (as in `kubectl exec …
/// -- trove jobs`) or leading `VAR=value`s, and may be a path (`target/release/trove`); it
/// ends at a separator, a redirection or a comment. Lines ending in `\` continue.
fn markdown_flag_uses(text: &str) -> Vec<FlagUse> {
    let mut uses = Vec::new();
    let mut fenced = false;
    let mut joined = String::new();
    let mut first_line = 0;
    for (i, line) in text.lines().enumerate() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            joined.clear();
            continue;
        }
        if !fenced {
            continue;
        }
        if joined.is_empty() {
            first_line = i + 1;
        }
        match line.strip_suffix('\\') {
            Some(part) => {
                joined.push_str(part);
                joined.push(' ');
                continue;
            }
            None => joined.push_str(line),
        }
        let command = std::mem::take(&mut joined);
        let command = command.find(" #").map_or(command.as_str(), |c| &command[..c]);
        shell_flag_uses(command, first_line, &mut uses);
    }
    uses
}

fn shell_flag_uses(line: &str, line_number: usize, uses: &mut Vec<FlagUse>) {
    let tokens: Vec<&str> = line.split_whitespace().collect();
    let is_separator = |t: &str| matches!(t, "&&" | "||" | "|" | ";" | "&" | "$" | "--");
    let mut at_start = true;
    let mut i = 0;
    while i < tokens.len() {
        let token = tokens[i];
        i += 1;
        if is_separator(token) {
            at_start = true;
            continue;
        }
        if !at_start || (token.contains('=') && !token.starts_with('-')) {
            continue;
        }
        at_start = false;
        // A synopsis's `verify|fetch` is each of the alternatives.
        let programs = match token.rsplit('/').next().unwrap() {
            "trove-worker" => vec![Program::Worker],
            "trove" => {
                let mut programs = vec![Vec::new()];
                while i < tokens.len() && !tokens[i].starts_with(['-', '>', '[']) && !is_separator(tokens[i]) {
                    programs = programs
                        .into_iter()
                        .flat_map(|words: Vec<String>| {
                            tokens[i].split('|').map(move |w| [words.clone(), vec![w.to_string()]].concat())
                        })
                        .collect();
                    i += 1;
                }
                programs.into_iter().map(Program::Trove).collect()
            }
            _ => continue,
        };
        while i < tokens.len() && !is_separator(tokens[i]) && !tokens[i].starts_with('>') {
            let flag = tokens[i].trim_start_matches('[').trim_end_matches([']', ',']);
            if is_flag(flag) {
                for program in &programs {
                    uses.push(flag_use(Some(program.clone()), flag, line_number));
                }
            }
            i += 1;
        }
    }
}

/// The long flags a command's `--help` lists; `Err` with its output when it is not a
/// command of these binaries.
fn help_flags(program: &Program) -> Result<BTreeSet<String>, String> {
    let mut command = match program {
        Program::Worker => Command::new(trove_worker()),
        Program::Trove(words) => {
            let mut c = Command::new(trove());
            c.args(words);
            c
        }
    };
    let out = output_within(command.arg("--help"), Duration::from_secs(30));
    let text = String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    if !out.status.success() {
        return Err(text.lines().next().unwrap_or("").to_string());
    }
    Ok(text
        .split(|c: char| !(c.is_ascii_alphanumeric() || c == '-'))
        .filter(|w| w.starts_with("--") && w.len() > 2)
        .map(str::to_string)
        .collect())
}

/// Runs `command` to its end, its output piped to files (so that no pipe fills), killing it
/// past `limit`. Each call has a folder of its own: tests run it from several threads.
fn output_within(command: &mut Command, limit: Duration) -> Output {
    static CALLS: AtomicU32 = AtomicU32::new(0);
    let dir = scratch(&format!("deploy-help-{}", CALLS.fetch_add(1, Ordering::Relaxed)));
    let (stdout, stderr) = (dir.join("stdout"), dir.join("stderr"));
    let mut child = command
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&stdout).unwrap())
        .stderr(std::fs::File::create(&stderr).unwrap())
        .spawn()
        .unwrap();
    let started = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if started.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{command:?} ran past {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    Output { status, stdout: std::fs::read(&stdout).unwrap(), stderr: std::fs::read(&stderr).unwrap() }
}

/// The deployment files, relative to the repository root, with their flag uses.
fn deploy_flag_uses() -> Vec<(String, Vec<FlagUse>)> {
    let mut files = vec![
        "deploy/docker-compose.yml".to_string(),
        "deploy/k8s-tls/kustomization.yaml".to_string(),
        "deploy/k8s-multi/kustomization.yaml".to_string(),
        "deploy/k8s-multi/coordinators.yaml".to_string(),
    ];
    for entry in std::fs::read_dir(repo().join("deploy/k8s")).unwrap() {
        let name = entry.unwrap().file_name().into_string().unwrap();
        if name.ends_with(".yaml") {
            files.push(format!("deploy/k8s/{name}"));
        }
    }
    files.sort();
    let mut all: Vec<(String, Vec<FlagUse>)> = files
        .into_iter()
        .map(|f| {
            let uses = yaml_flag_uses(&std::fs::read_to_string(repo().join(&f)).unwrap());
            (f, uses)
        })
        .collect();
    for doc in ["README.md", "deploy/README.md"] {
        let uses = markdown_flag_uses(&std::fs::read_to_string(repo().join(doc)).unwrap());
        all.push((doc.to_string(), uses));
    }
    all
}

#[test]
fn every_flag_deploy_and_the_operator_docs_pass_is_in_the_binaries_help() {
    let files = deploy_flag_uses();
    let count = |file: &str, program: &Program| {
        files
            .iter()
            .filter(|(f, _)| f == file)
            .flat_map(|(_, u)| u)
            .filter(|u| u.program.as_ref() == Some(program))
            .count()
    };
    // The extractor sees the commands it must: a check that finds nothing checks nothing.
    assert!(count("deploy/k8s/coordinator.yaml", &coordinator()) >= 8);
    assert!(count("deploy/k8s/workers.yaml", &Program::Worker) >= 8);
    assert!(count("deploy/docker-compose.yml", &coordinator()) >= 8);
    assert!(count("deploy/docker-compose.yml", &Program::Worker) >= 24);
    assert!(count("deploy/k8s-tls/kustomization.yaml", &Program::Worker) >= 3);
    assert!(count("deploy/k8s-multi/coordinators.yaml", &coordinator()) >= 8);
    assert!(count("deploy/k8s-multi/kustomization.yaml", &Program::Worker) >= 2);

    let mut helps: BTreeMap<Program, Result<BTreeSet<String>, String>> = BTreeMap::new();
    let mut missing: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    let mut problems = Vec::new();
    for (file, uses) in &files {
        for u in uses {
            let Some(program) = &u.program else {
                problems.push(format!("{file}:{}: {} is passed to no trove command", u.line, u.flag));
                continue;
            };
            match helps.entry(program.clone()).or_insert_with(|| help_flags(program)) {
                Ok(flags) if flags.contains(&u.flag) => {}
                Ok(_) => {
                    missing.entry(program.to_string()).or_default().insert(u.flag.clone());
                    problems.push(format!("{file}:{}: `{program}` has no {}", u.line, u.flag));
                }
                Err(e) => {
                    let problem = format!("`{program} --help` fails: {e}");
                    if !problems.contains(&problem) {
                        problems.push(problem);
                    }
                }
            }
        }
    }
    let summary: Vec<String> =
        missing.iter().map(|(p, f)| format!("{p}: {}", Vec::from_iter(f.clone()).join(" "))).collect();
    assert!(problems.is_empty(), "{}\n\nmissing, by command:\n{}", problems.join("\n"), summary.join("\n"));
}

/// The port of a `HOST:PORT` (or `[V6]:PORT`) address.
fn port_of(address: &str) -> Option<u16> {
    address.rsplit(':').next()?.parse().ok()
}

/// What the YAML text of one file says, besides its flags: ports of `containerPort:`s, of
/// probes (`grpc:` and `tcpSocket:`, and compose's `/dev/tcp/HOST/PORT` checks), of
/// Prometheus annotations and of compose's published `HOST:PUBLISHED:CONTAINER` ports, and
/// the paths mounted (`mountPath:`, compose's `target:`, and `/run/secrets/NAME` for each
/// compose secret).
#[derive(Debug, Default)]
struct Facts {
    container_ports: BTreeSet<u16>,
    probe_ports: BTreeSet<u16>,
    scrape_ports: BTreeSet<u16>,
    published_ports: BTreeSet<u16>,
    mounts: BTreeSet<String>,
    images: BTreeSet<String>,
}

fn facts(text: &str) -> Facts {
    let mut facts = Facts::default();
    let mut probe = false;
    let mut top_level = String::new();
    let mut in_ports = false;
    for line in text.lines() {
        let (key, words) = yaml_line(line);
        if !line.starts_with([' ', '#', '-']) && !line.is_empty() {
            top_level = key.clone().unwrap_or_default();
        }
        let word = words.first().cloned().unwrap_or_default();
        match key.as_deref() {
            Some("containerPort") => facts.container_ports.extend(word.parse::<u16>().ok()),
            Some("port") if probe => facts.probe_ports.extend(word.parse::<u16>().ok()),
            Some("prometheus.io/port") => facts.scrape_ports.extend(word.parse::<u16>().ok()),
            Some("mountPath" | "target") => {
                facts.mounts.insert(word.clone());
            }
            Some("image") => {
                facts.images.insert(word.clone());
            }
            Some("test") => {
                for w in &words {
                    if let Some(address) = w.split("/dev/tcp/").nth(1) {
                        facts.probe_ports.extend(address.rsplit('/').next().and_then(|p| p.parse::<u16>().ok()));
                    }
                }
            }
            _ => {}
        }
        // Compose: the service's `ports:` list, and the secrets' names (two-space keys
        // under the top-level `secrets:`).
        if key.as_deref() == Some("ports") && words.is_empty() {
            in_ports = true;
        } else if in_ports && key.is_none() && line.trim_start().starts_with("- ") {
            facts.published_ports.extend(port_of(&word));
        } else {
            in_ports = false;
        }
        if top_level == "secrets" && line.starts_with("  ") && !line.starts_with("   ") {
            if let Some(name) = key.as_deref() {
                facts.mounts.insert(format!("/run/secrets/{name}"));
            }
        }
        probe = matches!(key.as_deref(), Some("grpc" | "tcpSocket")) && words.is_empty();
    }
    facts
}

/// Flags whose value is a path inside the container.
fn is_path_flag(flag: &str) -> bool {
    flag.ends_with("-file") || flag.ends_with("-dir") || flag.ends_with("-root") || flag.starts_with("--tls-")
}

fn under(path: &str, mounts: &BTreeSet<String>) -> bool {
    mounts.iter().any(|m| path == m || path.starts_with(&format!("{m}/")))
}

/// The two ways to run a farm from `deploy/`: the files of each, read together.
struct Farm {
    name: &'static str,
    files: Vec<String>,
}

fn farms() -> [Farm; 2] {
    let mut k8s = vec!["deploy/k8s-tls/kustomization.yaml".to_string()];
    for entry in std::fs::read_dir(repo().join("deploy/k8s")).unwrap() {
        let name = entry.unwrap().file_name().into_string().unwrap();
        if name.ends_with(".yaml") {
            k8s.push(format!("deploy/k8s/{name}"));
        }
    }
    [Farm { name: "Kubernetes", files: k8s }, Farm { name: "compose", files: vec!["deploy/docker-compose.yml".into()] }]
}

#[test]
fn ports_paths_and_images_agree_across_the_manifests_compose_and_the_dockerfile() {
    let dockerfile = std::fs::read_to_string(repo().join("deploy/Dockerfile")).unwrap();
    let exposed: BTreeSet<u16> = dockerfile
        .lines()
        .filter_map(|l| l.strip_prefix("EXPOSE "))
        .flat_map(|l| l.split_whitespace().map(|p| p.parse::<u16>().unwrap()))
        .collect();
    let kustomization = std::fs::read_to_string(repo().join("deploy/k8s/kustomization.yaml")).unwrap();
    let image_setting = |key: &str| {
        let line = kustomization.lines().find(|l| l.trim_start().trim_start_matches("- ").starts_with(key)).unwrap();
        unquote(line.split_once(": ").unwrap().1)
    };
    let (image, new_name, new_tag) = (image_setting("name:"), image_setting("newName:"), image_setting("newTag:"));

    let mut problems = Vec::new();
    for farm in farms() {
        let mut listen: BTreeMap<Program, BTreeSet<u16>> = BTreeMap::new();
        let mut metrics = BTreeSet::new();
        let mut coordinator_urls = Vec::new();
        let mut all = Facts::default();
        let mut paths = Vec::new();
        for file in &farm.files {
            let text = std::fs::read_to_string(repo().join(file)).unwrap();
            let f = facts(&text);
            let uses = yaml_flag_uses(&text);
            // A manifest that starts a server probes that server's own port (across the
            // farm, below, a probe may still name another container's).
            let own: BTreeSet<u16> =
                uses.iter().filter(|u| u.flag == "--listen").filter_map(|u| port_of(u.value.as_deref()?)).collect();
            if !own.is_empty() && !f.probe_ports.is_subset(&own) {
                problems.push(format!("{file}: probes check {:?}, but its servers listen on {own:?}", f.probe_ports));
            }
            for u in uses {
                let (Some(program), Some(value)) = (u.program.clone(), u.value.clone()) else { continue };
                let at = format!("{file}:{}", u.line);
                match u.flag.as_str() {
                    "--listen" => listen.entry(program).or_default().extend(port_of(&value)),
                    "--metrics-listen" => metrics.extend(port_of(&value)),
                    "--coordinator" => coordinator_urls.push((at.clone(), value.clone())),
                    flag if is_path_flag(flag) => paths.push((at, flag.to_string(), value)),
                    _ => {}
                }
            }
            if !file.contains("k8s-tls") {
                for p in &f.images {
                    let expected = if file.ends_with("docker-compose.yml") {
                        format!("${{TROVE_IMAGE:-{image}:{new_tag}}}")
                    } else {
                        image.clone()
                    };
                    if *p != expected {
                        problems
                            .push(format!("{file}: image {p}, expected {expected} (deploy/k8s/kustomization.yaml)"));
                    }
                }
            }
            all.container_ports.extend(f.container_ports);
            all.probe_ports.extend(f.probe_ports);
            all.scrape_ports.extend(f.scrape_ports);
            all.published_ports.extend(f.published_ports);
            all.mounts.extend(f.mounts);
        }
        let name = farm.name;
        let grpc: BTreeSet<u16> = listen.values().flatten().copied().collect();
        let served: BTreeSet<u16> = grpc.union(&metrics).copied().collect();
        let coordinator_ports = listen.get(&coordinator()).cloned().unwrap_or_default();
        if grpc.len() < 2 || metrics.is_empty() || coordinator_ports.is_empty() {
            problems.push(format!("{name}: listen ports {grpc:?}, metrics ports {metrics:?}: a server is missing"));
        }
        for (what, ports, within) in [
            ("a probe checks", &all.probe_ports, &grpc),
            ("Prometheus scrapes", &all.scrape_ports, &metrics),
            ("a containerPort is", &all.container_ports, &served),
            ("a published port is", &all.published_ports, &served),
            ("a port listened on is", &served, &exposed),
        ] {
            for p in ports.difference(within) {
                problems.push(format!("{name}: {what} {p}, not among {within:?}"));
            }
        }
        if name == "Kubernetes" {
            for p in served.difference(&all.container_ports) {
                problems.push(format!("{name}: port {p} is listened on but declared by no containerPort"));
            }
        }
        for (at, url) in coordinator_urls {
            if !port_of(&url).is_some_and(|p| coordinator_ports.contains(&p)) {
                problems.push(format!("{at}: --coordinator {url} is not a port the coordinator listens on"));
            }
        }
        for (at, flag, path) in paths {
            if !under(&path, &all.mounts) {
                problems.push(format!("{at}: {flag}={path} is under no mounted path ({:?})", all.mounts));
            }
        }
    }
    // The image: built as the Dockerfile says, and the shard loader runs the pushed one.
    if !dockerfile.contains(&format!("-t {image}:{new_tag} ")) {
        problems.push(format!("deploy/Dockerfile: its build command does not tag {image}:{new_tag}"));
    }
    let loader = facts(&std::fs::read_to_string(repo().join("deploy/shard-loader.yaml")).unwrap());
    if loader.images != BTreeSet::from([format!("{new_name}:{new_tag}")]) {
        problems.push(format!("deploy/shard-loader.yaml: images {:?}, expected {new_name}:{new_tag}", loader.images));
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn yaml_flags_go_to_the_command_that_takes_them() {
    let k8s = "\
containers:
  - name: coordinator
    image: trove
    command: [\"trove\"]
    args:
      - coordinator
      - --listen=0.0.0.0:7000 # a comment
      # - --commented-out
    lifecycle:
      preStop:
        exec:
          command: [\"sleep\", \"5\"]
  - name: worker
    command: [\"trove-worker\", \"--data-root\", \"/data\"]
    args: [\"--listen=0.0.0.0:7001\"]
";
    let uses = yaml_flag_uses(k8s);
    let got: Vec<(Option<Program>, &str, Option<&str>, usize)> =
        uses.iter().map(|u| (u.program.clone(), u.flag.as_str(), u.value.as_deref(), u.line)).collect();
    assert_eq!(
        got,
        [
            (Some(coordinator()), "--listen", Some("0.0.0.0:7000"), 7),
            (Some(Program::Worker), "--data-root", None, 14),
            (Some(Program::Worker), "--listen", Some("0.0.0.0:7001"), 15),
        ]
    );

    let compose = "\
services:
  coordinator:
    command:
      - trove
      - coordinator
      - --state-dir=/state
    healthcheck:
      test: [\"CMD\", \"bash\", \"-c\", \"exec 3<>/dev/tcp/127.0.0.1/7000\"]
  worker-0:
    command:
      - trove-worker
      - --worker-id=worker-0
";
    let uses = yaml_flag_uses(compose);
    assert_eq!(uses.len(), 2);
    assert_eq!((uses[0].program.clone(), uses[0].flag.as_str()), (Some(coordinator()), "--state-dir"));
    assert_eq!((uses[1].program.clone(), uses[1].flag.as_str()), (Some(Program::Worker), "--worker-id"));

    // A JSON patch's added argument goes to the patch target's binary.
    let patch = "\
  - target:
      kind: StatefulSet
      name: trove-worker
    patch: |-
      - op: add
        path: /spec/template/spec/containers/0/args/-
        value: --tls-ca=/etc/trove/tls/ca.crt
";
    let uses = yaml_flag_uses(patch);
    assert_eq!(uses, [flag_use(Some(Program::Worker), "--tls-ca=/etc/trove/tls/ca.crt", 7)]);

    // A document separator is no flag.
    assert!(yaml_flag_uses("---\ncommand: [\"trove-worker\"]\n---\n").is_empty());

    // A flag under no command is reported as such, not dropped.
    let stray = yaml_flag_uses("args:\n  - --listen=0.0.0.0:1\n");
    assert_eq!(stray, [flag_use(None, "--listen=0.0.0.0:1", 2)]);
}

#[test]
fn markdown_flags_come_from_shell_blocks_only() {
    let md = "\
Text mentions `trove render --not-this`.

```sh
target/release/trove coordinator --listen 127.0.0.1:7000 &
RUST_LOG=info trove-worker --coordinator http://127.0.0.1:7000 \\
    --data-root ../shared/data  # comment --nope
kubectl -n trove exec deploy/trove-coordinator -- trove jobs --token-file /t > jobs.txt
cargo build --release --bin trove --bin trove-worker
trove render scene.toml -o out.png --coordinator=http://x:7000 | tee log
trove coordinator [--heartbeat-ms N]
trove data verify|fetch [--data-root DIR] | list
```
---
";
    let got: Vec<(String, String, usize)> =
        markdown_flag_uses(md).into_iter().map(|u| (u.program.unwrap().to_string(), u.flag, u.line)).collect();
    let want = [
        ("trove coordinator", "--listen", 4),
        ("trove-worker", "--coordinator", 5),
        ("trove-worker", "--data-root", 5),
        ("trove jobs", "--token-file", 7),
        ("trove render scene.toml", "--coordinator", 9),
        ("trove coordinator", "--heartbeat-ms", 10),
        ("trove data verify", "--data-root", 11),
        ("trove data fetch", "--data-root", 11),
    ];
    assert_eq!(got, want.map(|(p, f, l)| (p.to_string(), f.to_string(), l)));
}

#[test]
fn facts_read_ports_mounts_and_secrets() {
    let k8s = "\
          ports:
            - name: grpc
              containerPort: 7000
          readinessProbe:
            grpc:
              port: 7000
          volumeMounts:
            - name: state
              mountPath: /state
      annotations:
        prometheus.io/port: \"9100\"
---
spec:
  ports:
    - name: grpc
      port: 7777
";
    let f = facts(k8s);
    assert_eq!(f.container_ports, BTreeSet::from([7000]));
    assert_eq!(f.probe_ports, BTreeSet::from([7000]), "a Service's port is no probe");
    assert_eq!(f.scrape_ports, BTreeSet::from([9100]));
    assert_eq!(f.mounts, BTreeSet::from(["/state".to_string()]));

    let compose = "\
services:
  c:
    image: trove
    ports:
      - \"127.0.0.1:9101:9100\"
    healthcheck:
      test: [\"CMD\", \"bash\", \"-c\", \"exec 3<>/dev/tcp/127.0.0.1/7001\"]
secrets:
  worker_token:
    file: x
";
    let f = facts(compose);
    assert_eq!(f.published_ports, BTreeSet::from([9100]));
    assert_eq!(f.probe_ports, BTreeSet::from([7001]));
    assert!(under("/run/secrets/worker_token", &f.mounts));
    assert!(!under("/run/secrets/worker", &f.mounts));
    assert_eq!(f.images, BTreeSet::from(["trove".to_string()]));
}
