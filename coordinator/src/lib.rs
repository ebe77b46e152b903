//! The TROVE coordinator: the farm's job API, intersection phase, sharding by dataset,
//! gathering and composition ([`farm`]), and the client that submits jobs to it
//! ([`client`]). The `trove` binary is a thin command line over this library and
//! `trove-core`.

pub mod client;
pub mod farm;
