//! canopy-node: the `canopy` binary's library.
//!
//! # Layout
//! - [`record`]: what a run gathers (estimates vs truth, maps, link statistics, events).
//! - [`output`]: summary.json, TUM trajectories, CSVs and report.html.

pub mod output;
pub mod record;
