//! `trove`: renders TROVE scenes (SPEC §5), in this process or through a farm, and serves
//! a farm's coordinator. The binary only parses arguments and reports errors; the work is in
//! `trove-core` (rendering) and this crate's library (the farm and its client).

mod cli;
mod data;
mod ops;

use std::process::ExitCode;

fn main() -> ExitCode {
    trove_proto::init_logging();
    match cli::run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // One paragraph: the chain of causes on one line.
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
