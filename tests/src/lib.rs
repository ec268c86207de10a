//! Shared helpers for canopy's integration suites.
