#!/usr/bin/env bash
# canopy's test command (README). Installs what the suites need on a fresh Debian machine, then
# builds everything once in release mode and runs every test.
set -euo pipefail
cd "$(dirname "$0")/.."

# iproute2 provides `ip netns` / veth for the across-hosts suites (tests/tests/netns.rs skips with
# a message where namespaces are not permitted; tests/tests/hosts.rs FAILS there unless
# CANOPY_TEST_NO_NAMESPACES=1, see the README).
# openssl makes the test certificates of the TLS suite (tests/tests/hosts.rs) at test time.
for tool in ip:iproute2 openssl:openssl; do
  if ! command -v "${tool%%:*}" >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then
    pkg="${tool##*:}"
    (apt-get install -y "$pkg" || (apt-get update && apt-get install -y "$pkg")) >/dev/null
  fi
done

cargo build --release --workspace --all-targets
cargo test --release --workspace "$@"
