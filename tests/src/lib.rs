//! Shared helpers for canopy's integration suites.
//!
//! # Layout
//! - [`montecarlo`]: ANEES statistics and χ² bands over seeded runs.

pub mod montecarlo;
