//! `trove_tests::fuzzing::nrrd` under libFuzzer (docs/fuzzing.md): any input must come
//! back as a value or a typed error, never a panic.
#![no_main]

libfuzzer_sys::fuzz_target!(|bytes: &[u8]| {
    let _ = trove_tests::fuzzing::nrrd(bytes);
});
