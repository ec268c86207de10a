//! canopy-node: the `canopy` binary's library.
//!
//! # Layout
//! (filled in as the node grows)
