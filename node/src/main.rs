//! The `canopy` binary: parses the command line and hands over to the library.

use clap::Parser;

fn main() -> anyhow::Result<()> {
    canopy_node::cli::run_cli(canopy_node::cli::Cli::parse())
}
