//! canopy-transport: links between canopy processes.
//!
//! # Layout
//! (filled in by the transport work)
