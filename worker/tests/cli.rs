//! `trove-worker` run as an operator runs it: bad arguments are one clear paragraph and a
//! non-zero exit, never a panic. (Being an integration test of this package also makes
//! `cargo test --workspace` build the binary, which the farm's end-to-end test starts.)

use std::process::Command;

#[test]
fn a_data_root_that_does_not_exist_is_a_clear_error() {
    let out = Command::new(env!("CARGO_BIN_EXE_trove-worker"))
        .args([
            "--coordinator",
            "http://127.0.0.1:9",
            "--listen",
            "127.0.0.1:0",
            "--data-root",
            "/nonexistent/trove-data",
        ])
        .env("RUST_BACKTRACE", "1")
        .output()
        .expect("run trove-worker");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(stderr.starts_with("error: ") && stderr.contains("/nonexistent/trove-data"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    // The bound address was printed first, before the data root was read.
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.lines().next().is_some_and(|l| l.starts_with("127.0.0.1:")), "{stdout}");
}

#[test]
fn a_budget_without_a_unit_it_knows_is_refused() {
    let out = Command::new(env!("CARGO_BIN_EXE_trove-worker"))
        .args(["--coordinator", "http://127.0.0.1:9", "--data-root", ".", "--memory-budget", "12 MB"])
        .output()
        .expect("run trove-worker");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("KiB, MiB or GiB"));
}

#[test]
fn a_simd_path_it_does_not_know_is_refused_at_start() {
    let out = Command::new(env!("CARGO_BIN_EXE_trove-worker"))
        .args(["--coordinator", "http://127.0.0.1:9", "--listen", "127.0.0.1:0", "--data-root", "."])
        .env("TROVE_SIMD", "avx9000")
        .output()
        .expect("run trove-worker");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(stderr.contains("`avx9000` is not a SIMD path (TROVE_SIMD)"), "{stderr}");
    // Refused before it listens: no address printed.
    assert!(out.stdout.is_empty(), "{}", String::from_utf8_lossy(&out.stdout));
}

#[test]
fn coordinators_are_given_by_repeating_the_flag_or_with_commas_and_each_only_once() {
    // A list and a repeated flag make one list: the third URL repeats the first.
    let out = Command::new(env!("CARGO_BIN_EXE_trove-worker"))
        .args([
            "--coordinator",
            "http://127.0.0.1:9,http://127.0.0.1:10",
            "--coordinator",
            "http://127.0.0.1:9",
            "--listen",
            "127.0.0.1:0",
            "--data-root",
            ".",
        ])
        .output()
        .expect("run trove-worker");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(stderr.contains("coordinator http://127.0.0.1:9 is listed twice"), "{stderr}");
    // None at all is refused by the parser.
    let out = Command::new(env!("CARGO_BIN_EXE_trove-worker"))
        .args(["--listen", "127.0.0.1:0", "--data-root", "."])
        .output()
        .expect("run trove-worker");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--coordinator <URL>"));
}
