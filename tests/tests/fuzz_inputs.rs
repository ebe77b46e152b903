//! The fuzz targets' inputs as a short proptest run, in CI: arbitrary bytes and mutated
//! valid inputs through the same entry points the `cargo fuzz` targets call
//! (`trove_tests::fuzzing`), each of which must come back with a value or a typed error,
//! never a panic. The long runs and what they found are in `docs/fuzzing.md`.

use proptest::prelude::*;
use trove_tests::fuzzing::{self, seeds, JobRefusal, Planned, TARGETS};

/// Cases per target and kind of input: a few hundred in all per target, seconds in total.
const CASES: u32 = 128;

/// Runs `target`'s entry point on `bytes`, failing the case on a panic (the entry points'
/// own results are values or typed errors, which are both fine here).
fn run(target: &str, bytes: &[u8]) -> Result<(), TestCaseError> {
    let ran = std::panic::catch_unwind(|| match target {
        "scene" => drop(fuzzing::scene(bytes)),
        "nrrd" => drop(fuzzing::nrrd(bytes)),
        "nifti" => drop(fuzzing::nifti(bytes)),
        "submit_job" => drop(fuzzing::submit_job(bytes)),
        "cast_batch" => drop(fuzzing::cast_batch(bytes)),
        other => panic!("no target {other}"),
    });
    prop_assert!(ran.is_ok(), "{target} panicked on {} bytes: {:?}", bytes.len(), String::from_utf8_lossy(bytes));
    Ok(())
}

/// Values that break naive number handling, spliced over a number in text inputs.
const NUMBERS: [&str; 12] =
    ["0", "-0", "1e308", "-1e308", "1e-308", "nan", "inf", "-1", "4294967296", "65536", "18446744073709551616", "0.5"];

/// One edit of a byte string.
#[derive(Clone, Debug)]
enum Edit {
    Flip { at: usize, bit: u8 },
    Set { at: usize, byte: u8 },
    Insert { at: usize, bytes: Vec<u8> },
    Remove { at: usize, len: usize },
    Truncate { at: usize },
    Duplicate { at: usize, len: usize },
    Number { at: usize, number: usize },
}

fn edit() -> impl Strategy<Value = Edit> {
    let at = any::<usize>();
    prop_oneof![
        (at, 0u8..8).prop_map(|(at, bit)| Edit::Flip { at, bit }),
        (at, any::<u8>()).prop_map(|(at, byte)| Edit::Set { at, byte }),
        (at, prop::collection::vec(any::<u8>(), 1..8)).prop_map(|(at, bytes)| Edit::Insert { at, bytes }),
        (at, 1usize..32).prop_map(|(at, len)| Edit::Remove { at, len }),
        at.prop_map(|at| Edit::Truncate { at }),
        (at, 1usize..64).prop_map(|(at, len)| Edit::Duplicate { at, len }),
        (at, 0..NUMBERS.len()).prop_map(|(at, number)| Edit::Number { at, number }),
    ]
}

/// `seed` with `edits` applied, each position taken modulo the current length.
fn mutate(seed: &[u8], edits: &[Edit]) -> Vec<u8> {
    let mut b = seed.to_vec();
    for e in edits {
        let n = b.len().max(1);
        match e {
            Edit::Flip { at, bit } if !b.is_empty() => b[at % n] ^= 1 << bit,
            Edit::Set { at, byte } if !b.is_empty() => b[at % n] = *byte,
            Edit::Insert { at, bytes } => {
                let at = at % (b.len() + 1);
                b.splice(at..at, bytes.iter().copied());
            }
            Edit::Remove { at, len } => {
                let at = at % n;
                b.drain(at.min(b.len())..(at + len).min(b.len()));
            }
            Edit::Truncate { at } => b.truncate(at % n),
            Edit::Duplicate { at, len } => {
                let at = (at % n).min(b.len());
                let part = b[at..(at + len).min(b.len())].to_vec();
                b.splice(at..at, part);
            }
            Edit::Number { at, number } => {
                // Replace the run of digits at or after `at`, if any.
                let start = at % n;
                if let Some(i) = b.iter().skip(start).position(|c| c.is_ascii_digit()) {
                    let i = start + i;
                    let end = i + b[i..].iter().take_while(|c| c.is_ascii_digit() || **c == b'.').count();
                    b.splice(i..end, NUMBERS[*number].bytes());
                }
            }
            _ => {}
        }
    }
    b
}

/// A target's seeds, mutated.
fn mutated(target: &'static str) -> impl Strategy<Value = Vec<u8>> {
    let seeds = seeds(target);
    (0..seeds.len(), prop::collection::vec(edit(), 1..6)).prop_map(move |(i, edits)| mutate(&seeds[i], &edits))
}

fn config() -> ProptestConfig {
    ProptestConfig { cases: CASES, failure_persistence: None, ..ProptestConfig::default() }
}

#[test]
fn every_seed_is_accepted_by_its_entry_point() {
    // Valid seeds are what make the mutations reach past the first check; and where
    // TROVE_WRITE_FUZZ_SEEDS names a folder, they are written there as the fuzzer's
    // corpus (`fuzz/corpus/<target>/`, see docs/fuzzing.md).
    let out = std::env::var_os("TROVE_WRITE_FUZZ_SEEDS").map(std::path::PathBuf::from);
    for target in TARGETS {
        for (i, seed) in seeds(target).iter().enumerate() {
            match target {
                "scene" => drop(fuzzing::scene(seed).unwrap_or_else(|e| panic!("scene seed {i}: {e}"))),
                "nrrd" => assert!(fuzzing::nrrd(seed).unwrap_or_else(|e| panic!("nrrd seed {i}: {e}")) > 0),
                "nifti" => assert!(fuzzing::nifti(seed).unwrap_or_else(|e| panic!("nifti seed {i}: {e}")) > 0),
                "submit_job" => match fuzzing::submit_job(seed) {
                    Ok(Planned::Counted { band_rows, tasks }) => assert!(band_rows > 0 && tasks > 0, "job seed {i}"),
                    other => panic!("job seed {i}: {other:?}"),
                },
                // The first casts samples; the others are an answer's results and no tasks.
                "cast_batch" if i == 0 => {
                    assert!(fuzzing::cast_batch(seed).unwrap_or_else(|e| panic!("batch seed 0: {e:?}")) > 0)
                }
                "cast_batch" => assert!(
                    fuzzing::cast_batch(seed).is_ok() || trove_core::render::wire::decode_results(seed).is_ok(),
                    "batch seed {i}: {:?}",
                    fuzzing::cast_batch(seed)
                ),
                _ => unreachable!(),
            }
            if let Some(dir) = &out {
                let dir = dir.join(target);
                std::fs::create_dir_all(&dir).unwrap();
                std::fs::write(dir.join(format!("seed-{i}")), seed).unwrap();
            }
        }
    }
}

#[test]
fn refusals_are_typed_with_the_file_named() {
    // A job over the PFM cap and one whose scene is not TOML: refused with the failure the
    // coordinator would send, naming the scene file.
    let mut seed = seeds("submit_job")[1].clone();
    let job = <trove_proto::v1::SubmitJobRequest as prost::Message>::decode(&seed[..]).unwrap();
    let big = job.scene_toml.replacen("width = 8", "width = 16384", 1).replacen("height = 8", "height = 16384", 1);
    seed = prost::Message::encode_to_vec(&trove_proto::v1::SubmitJobRequest { scene_toml: big, ..job.clone() });
    match fuzzing::submit_job(&seed) {
        Err(JobRefusal::Refused(f)) => {
            assert_eq!((f.reason(), f.file.as_str()), (trove_proto::v1::Reason::LimitExceeded, "job.toml"), "{f:?}");
        }
        other => panic!("{other:?}"),
    }
    let broken = trove_proto::v1::SubmitJobRequest { scene_toml: "[image".into(), ..job };
    match fuzzing::submit_job(&prost::Message::encode_to_vec(&broken)) {
        Err(JobRefusal::Refused(f)) => assert_eq!(f.reason(), trove_proto::v1::Reason::SceneInvalid, "{f:?}"),
        other => panic!("{other:?}"),
    }
    assert!(matches!(fuzzing::submit_job(&[0xff, 0xff]), Err(JobRefusal::Decode(_))));
}

macro_rules! target_props {
    ($($name:ident: $target:literal),* $(,)?) => {
        $(
            mod $name {
                use super::*;
                proptest! {
                    #![proptest_config(config())]
                    #[test]
                    fn arbitrary_bytes(bytes in prop::collection::vec(any::<u8>(), 0..512)) {
                        run($target, &bytes)?;
                    }
                    #[test]
                    fn mutated_valid_inputs(bytes in mutated($target)) {
                        run($target, &bytes)?;
                    }
                }
            }
        )*
    };
}

target_props! {
    scene: "scene",
    nrrd: "nrrd",
    nifti: "nifti",
    submit_job: "submit_job",
    cast_batch: "cast_batch",
}
