//! `trove bench …`: measurements that produce the project's documented numbers and plots.

pub mod accuracy;
