#!/usr/bin/env bash
# Soak test of canopy's multi-process suites (issue 15): runs each suite N times in a row while
# the machine is loaded, and logs pass/fail per run. A suite that passes here only by luck of
# the scheduler is a flaky suite; every run must pass.
#
# Usage: scripts/soak.sh [N] [SUITE...]      (default N = 10, every suite below)
#   SUITE is PACKAGE:TEST, e.g. canopy-tests:scale or canopy-node:real_data.
# Environment:
#   SOAK_LOAD       stress (default: stress-ng on every core), build (a parallel `cargo build`
#                   of the workspace into a scratch target directory, restarted while the soak
#                   runs), none
#   SOAK_CPU_LOAD   per-core load of stress-ng in percent (default 100)
#   SOAK_OUT        log directory (default target/soak)
#   SOAK_NO_BUILD=1 skip the initial `cargo build --release --workspace --all-targets` (the
#                   suites' own `cargo test` still builds what they need)
# stress-ng is installed with apt-get when missing (Debian). The record is $SOAK_OUT/soak.log
# (one line per run: suite, run, PASS/FAIL, seconds, log file) and a summary at the end; the
# exit status is non-zero when any run failed.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
N=${1:-10}
shift || true
SUITES=("$@")
if [[ ${#SUITES[@]} -eq 0 ]]; then
  SUITES=(
    canopy-tests:system canopy-tests:outage canopy-tests:netns canopy-tests:hosts
    canopy-tests:radio canopy-tests:scale
    canopy-transport:multiprocess
    canopy-node:bad_config canopy-node:bad_recordings canopy-node:real_data
  )
fi
LOAD=${SOAK_LOAD:-stress}
CPU_LOAD=${SOAK_CPU_LOAD:-100}
OUT=${SOAK_OUT:-$ROOT/target/soak}
mkdir -p "$OUT"
LOG=$OUT/soak.log

if [[ ${SOAK_NO_BUILD:-0} != 1 ]]; then
  echo "building (release, all targets)…" >&2
  cargo build --release --workspace --all-targets >&2
fi

LOAD_PID=
stop_load() {
  if [[ -n $LOAD_PID ]]; then
    kill -- -"$LOAD_PID" 2>/dev/null || kill "$LOAD_PID" 2>/dev/null || true
    wait "$LOAD_PID" 2>/dev/null || true
    LOAD_PID=
  fi
}
trap stop_load EXIT

case $LOAD in
  stress)
    if ! command -v stress-ng >/dev/null 2>&1; then
      (apt-get install -y stress-ng || (apt-get update && apt-get install -y stress-ng)) >&2
    fi
    # Its own process group, so that stop_load ends exactly it and its workers.
    set -m
    stress-ng --cpu "$(nproc)" --cpu-load "$CPU_LOAD" --timeout 0 --quiet &
    LOAD_PID=$!
    set +m
    ;;
  build)
    set -m
    (
      while true; do
        rm -rf "$OUT/load-target"
        CARGO_TARGET_DIR=$OUT/load-target cargo build --release --workspace -j "$(nproc)" \
          >/dev/null 2>&1 || true
      done
    ) &
    LOAD_PID=$!
    set +m
    ;;
  none) ;;
  *)
    echo "SOAK_LOAD must be stress, build or none (got $LOAD)" >&2
    exit 2
    ;;
esac

{
  echo "# soak $(date -u +%Y-%m-%dT%H:%M:%SZ): N=$N, load=$LOAD (cpu-load $CPU_LOAD %), $(nproc) cores"
  echo "# commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown)$(git diff --quiet 2>/dev/null || echo ' (modified)')"
} | tee -a "$LOG"

declare -A PASS FAIL
for suite in "${SUITES[@]}"; do
  pkg=${suite%%:*}
  test=${suite#*:}
  PASS[$suite]=0
  FAIL[$suite]=0
  for i in $(seq 1 "$N"); do
    file=$OUT/$pkg-$test-$i.log
    start=$(date +%s)
    if cargo test --release -q -p "$pkg" --test "$test" >"$file" 2>&1; then
      verdict=PASS
      PASS[$suite]=$((PASS[$suite] + 1))
    else
      verdict=FAIL
      FAIL[$suite]=$((FAIL[$suite] + 1))
    fi
    printf '%-32s run %2d/%d  %s  %4ds  load %s  %s\n' "$suite" "$i" "$N" "$verdict" \
      "$(($(date +%s) - start))" "$(cut -d' ' -f1 /proc/loadavg)" "$file" | tee -a "$LOG"
  done
done

echo "# summary" | tee -a "$LOG"
failed=0
for suite in "${SUITES[@]}"; do
  printf '%-32s %d passed, %d failed\n' "$suite" "${PASS[$suite]}" "${FAIL[$suite]}" | tee -a "$LOG"
  failed=$((failed + FAIL[$suite]))
done
exit $((failed > 0))
