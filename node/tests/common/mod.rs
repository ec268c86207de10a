//! Helpers shared by node's integration tests.

use std::ffi::OsStr;
use std::process::Command;

/// Runs the `canopy` binary with `args`: (success, stdout, stderr). Backtraces are off: what a
/// user reads is the error chain, and a backtrace would only add noise to match on.
pub fn canopy<S: AsRef<OsStr>>(args: &[S]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_canopy"))
        .args(args)
        .env("RUST_BACKTRACE", "0")
        .env("RUST_LIB_BACKTRACE", "0")
        .output()
        .expect("the canopy binary runs");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}
