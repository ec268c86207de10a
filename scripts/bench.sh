#!/usr/bin/env bash
# canopy's benchmark suite (issue 7; not part of CI). Runs, on this machine:
#   1. fusion/benches/slam.rs         prediction / update / fusion round vs map size
#   2. node/benches/links.rs          canopy's production link path (fault layer, production
#                                     queues, DDF deltas) vs raw iceoryx2 and raw zenoh, plus the
#                                     transport-only (opaque bytes) rows
#   3. `canopy run` on generated tree teams (`canopy team N`) of 4, 8, 16, 24 vehicle
#      processes: real-time factor, link bytes / naive dense (Y, y), and the fusion stall
#      each vehicle measured (docs/benchmarks.md explains every column);
#   4. bandwidth on topologies/tree-8.toml (shortened to BENCH_DURATION), f64 and f32 deltas,
#      each plain and zstd-compressed: link bytes per second and the ratio to naive dense;
#   5. the fusion stall at the issue's size (~100 features per vehicle, 4-team, 350-feature
#      world) paced at wall-clock speed (real_time_factor = 1: 60 s of wall time),
# and prints ONE markdown table (the raw outputs stay in $OUT, default target/bench).
#
# Usage: scripts/bench.sh [--quick]     (--quick: shorter runs, noisier figures)
# Environment: BENCH_DURATION (simulated seconds per team run, default 60),
#              BENCH_TEAMS (default "4 8 16 24"), BENCH_BASELINE=1 (also run the
#              centralized reference in the monitor; off by default, as the table says).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
OUT=${OUT:-$ROOT/target/bench}
QUICK=0
[[ "${1:-}" == "--quick" ]] && QUICK=1
DURATION=${BENCH_DURATION:-60}
TEAMS=${BENCH_TEAMS:-"4 8 16 24"}
BASELINE_FLAG=--no-baseline
[[ "${BENCH_BASELINE:-0}" == "1" ]] && BASELINE_FLAG=
if [[ $QUICK == 1 ]]; then DURATION=${BENCH_DURATION:-30}; fi
mkdir -p "$OUT"
START=$(date +%s)
# The machine, named above the table (with the load before the run: other jobs on the machine
# slow every absolute figure; the ratios of a row are measured side by side).
{
  echo "cpu: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ *//')"
  echo "nproc: $(nproc)"
  echo "memory: $(awk '/MemTotal/ {printf "%.0f GiB", $2 / 1048576}' /proc/meminfo)"
  echo "os: $( (. /etc/os-release && echo "$PRETTY_NAME") 2>/dev/null || echo unknown), $(uname -sr)"
  echo "toolchain: $(rustc --version)"
  echo "load average before the run: $(cut -d' ' -f1-3 /proc/loadavg)"
  echo "date: $(date -u +%Y-%m-%d), commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown)"
} >"$OUT/machine.txt"

echo "building (release)…" >&2
cargo build --release -p canopy-node >&2
cargo bench --no-run -p canopy-fusion --bench slam >&2
cargo bench --no-run -p canopy-node --bench links >&2
CANOPY=$ROOT/target/release/canopy

echo "1/5 fusion/benches/slam.rs …" >&2
cargo bench -q -p canopy-fusion --bench slam 2>/dev/null >"$OUT/slam.md"

echo "2/5 node/benches/links.rs …" >&2
if [[ $QUICK == 1 ]]; then LINKARGS=(--quick); else LINKARGS=(); fi
cargo bench -q -p canopy-node --bench links -- "${LINKARGS[@]}" 2>/dev/null >"$OUT/links.md"

echo "3/5 canopy run, teams: $TEAMS ($DURATION s simulated each) …" >&2
# World feature counts chosen so each vehicle (which holds the team's map) ends with ~150
# features after 60 s: the team covers ~29 % (4), ~51 % (8), ~81 % (16), ~67 % (24) of the
# world in that time (measured with the built-in 400-feature world).
features_for() {
  case $1 in
    4) echo 520 ;; 8) echo 295 ;; 16) echo 185 ;; 24) echo 225 ;; *) echo 400 ;;
  esac
}
for n in $TEAMS; do
  "$CANOPY" team "$n" --duration "$DURATION" --features "$(features_for "$n")" >"$OUT/team$n.toml"
  rm -rf "$OUT/run$n"
  # shellcheck disable=SC2086
  "$CANOPY" run "$OUT/team$n.toml" --out "$OUT/run$n" --quiet $BASELINE_FLAG >"$OUT/run$n.txt" 2>&1
done

echo "4/5 topologies/tree-8.toml bandwidth ($DURATION s), f64 and f32 deltas, plain and zstd …" >&2
for prec in f64 f32; do
  for comp in none zstd; do
    name="bw-$prec-$comp"
    # The scenario file itself, shortened, with the delta encoding set in its [fusion] table.
    sed -e "s/^duration_s = .*/duration_s = $DURATION/" \
      -e "s/^\[fusion\]/[fusion]\ndelta_precision = \"$prec\"\ndelta_compression = \"$comp\"/" \
      topologies/tree-8.toml >"$OUT/$name.toml"
    grep -q "^duration_s = $DURATION" "$OUT/$name.toml"
    grep -q "^delta_precision = \"$prec\"" "$OUT/$name.toml"
    grep -q "^delta_compression = \"$comp\"" "$OUT/$name.toml"
    rm -rf "$OUT/$name"
    "$CANOPY" run "$OUT/$name.toml" --out "$OUT/$name" --quiet --no-baseline \
      >"$OUT/$name.txt" 2>&1
  done
done

echo "5/5 fusion stall at ~100 features, real-time pacing ($DURATION s wall) …" >&2
"$CANOPY" team 4 --duration "$DURATION" --features 350 |
  sed -e "s/^max_lead_s = .*/&\nreal_time_factor = 1.0/" >"$OUT/stall100.toml"
grep -q "^real_time_factor = 1.0" "$OUT/stall100.toml"
rm -rf "$OUT/stall100"
"$CANOPY" run "$OUT/stall100.toml" --out "$OUT/stall100" --quiet --no-baseline \
  >"$OUT/stall100.txt" 2>&1

python3 - "$OUT" "$TEAMS" "$DURATION" "$BASELINE_FLAG" "$(($(date +%s) - START))" <<'EOF'
import json, re, sys, pathlib, statistics
out, teams, duration, baseline_flag, elapsed = sys.argv[1:6]
out = pathlib.Path(out)

def tables(text):
    """Markdown tables of a bench output: list of (heading, header, rows)."""
    res, head, cur = [], "", None
    for line in text.splitlines():
        if line.startswith("#"):
            # A heading right after a table's last row ends that table.
            head, cur = line.lstrip("# ").strip(), None
        elif line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if cur is None:
                cur = (head, cells, [])
                res.append(cur)
            elif not set("".join(cells)) <= set("-: "):
                cur[2].append(cells)
        else:
            cur = None
    return res

rows = []
def row(what, size, value, ratio="", note=""):
    rows.append((what, size, value, ratio, note))

slam = tables((out / "slam.md").read_text())
for head, hdr, body in slam:
    if head.startswith("IMU prediction"):
        # Baseline: the textbook O(n) EKF-SLAM prediction (vehicle block and cross-covariances
        # updated every sample, `eager`); the dense ∇F P ∇Fᵀ only as a labelled secondary figure.
        for r in body:
            ratio = float(r[3]) / float(r[2])
            row("IMU prediction per sample (lazy)", f"N={r[0]}", f"{r[2]} µs",
                f"textbook O(n) / canopy = {ratio:.1f}",
                f"textbook (cross-covariances every sample) {r[3]} µs; secondary: naive dense "
                f"∇F P ∇Fᵀ {r[4]} ms = {r[5]}× canopy")
    elif head.startswith("EKF update per observation"):
        for r in body:
            row("EKF update per observation", f"N={r[0]}", f"{r[3]} ms", "",
                "10 observations per frame, stacked Joseph")
    elif head.startswith("One fusion round"):
        # A round's whole cost: the round plus keeping Y current through the 2 frames between
        # rounds (frame with Y maintained − frame without), amortised per round.
        for r in body:
            inv = float(r[1])
            upkeep = 2.0 * max(0.0, float(r[8]) - float(r[9]))
            for label, t in (("10-feature delta", float(r[2])), ("whole-map delta", float(r[4]))):
                total = t + upkeep
                # The N column reads "100 (3N = 300)".
                n = int(r[0].split()[0])
                row(f"fusion round incl. keeping Y current, {label}", f"N={n} (3N = {3 * n})",
                    f"{total:.2f} ms", f"/ raw faer Cholesky inverse = {total / inv:.2f}",
                    f"round {t:.2f} ms + Y upkeep {upkeep:.2f} ms (2 frames); inverse {inv:.2f} ms; "
                    f"secondary: round with Y re-inverted {r[6]} ms")

for head, hdr, body in tables((out / "links.md").read_text()):
    if head.startswith("Production path"):
        for r in body:
            row("iceoryx2 link latency p50, production path, DDF delta", r[0], f"{r[3]} µs",
                f"canopy / raw iceoryx2 = {r[4]}", f"raw {r[2]} µs; body {r[1]} B")
            row("zenoh link throughput, production path, DDF delta", r[0], f"{r[6]} MB/s",
                f"canopy / raw zenoh = {r[7]}", f"raw {r[5]} MB/s; dropped {r[8]}")
    elif head.startswith("Transport only"):
        for r in body:
            row("iceoryx2 link latency p50, opaque bytes (secondary)", r[0], f"{r[2]} µs",
                f"production / raw = {r[3]}", f"raw {r[1]} µs; bare link {r[4]} µs ({r[5]})")
            row("zenoh link throughput, opaque bytes (secondary)", r[0], f"{r[7]} MB/s",
                f"production / raw = {r[8]}",
                f"raw {r[6]} MB/s; bare link, 64k queue {r[10]} MB/s ({r[11]})")

def team_ratio(s):
    """Team link bytes / naive dense bytes, from the per-link figures of summary.json."""
    sent = naive = 0.0
    for l in s.get("links", []):
        b, r = l["bytes_ab"] + l["bytes_ba"], l.get("bandwidth_ratio")
        if r:
            sent, naive = sent + b, naive + b / r
    return sent / naive if naive else None

def stall_stats(run):
    lines = []
    for log in sorted((run / "logs").glob("uav*.log")):
        for line in log.read_text().splitlines():
            if line.startswith("fusion stall:"):
                lines.append(dict(kv.split("=") for kv in line.split(":", 1)[1].split()))
    return lines

def stall_row(label, run):
    st = stall_stats(run)
    if st:
        f = lambda k: max(float(x[k]) for x in st)
        med = statistics.median(float(x["cpu_p50_ms"]) for x in st)
        over = sum(int(x["cpu_over_imu_period"]) for x in st)
        wover = sum(int(x.get("wall_over_imu_period", -1)) for x in st)
        tot = sum(int(x["n"]) for x in st)
        row(label, f"~{round(statistics.mean(int(x['features']) for x in st))} features",
            f"CPU max {f('cpu_max_ms'):.1f} ms", f"p99 {f('cpu_p99_ms'):.1f} / p50 {med:.2f} ms",
            f"CPU {over}/{tot} intervals > 10 ms IMU period; wall max {f('wall_max_ms'):.1f} ms"
            + (f", wall {wover}/{tot} > 10 ms" if wover >= 0 else ""))

for n in teams.split():
    run = out / f"run{n}"
    try:
        s = json.loads((run / "summary.json").read_text())
    except FileNotFoundError:
        row(f"end-to-end {n} vehicle processes", "-", "FAILED", "", f"see {out}/run{n}.txt")
        continue
    feats = [v["map_features"] for v in s["vehicles"] if v.get("map_features") is not None]
    rss = [v["peak_rss_mb"] for v in s["vehicles"] if v.get("peak_rss_mb") is not None]
    ratio = team_ratio(s)
    row(f"end-to-end RTF, {n} vehicle processes", f"~{round(statistics.mean(feats))} features",
        f"{s['real_time_factor']:.2f}", f"sim {s['duration_s']:.0f} s / wall {s['wall_time_s']:.1f} s",
        ("reference off" if baseline_flag else "reference on")
        + (f"; peak RSS per vehicle {min(rss):.0f}–{max(rss):.0f} MB" if rss else "")
        + (f"; link bytes / naive dense = {ratio:.3f}" if ratio is not None else ""))
    stall_row(f"fusion stall, {n} vehicles", run)

stall_row("fusion stall, 4 vehicles, real-time pacing", out / "stall100")

for prec in ("f64", "f32"):
    for comp in ("none", "zstd"):
        label = f"bandwidth topologies/tree-8.toml, {prec} deltas" + (", zstd" if comp == "zstd" else "")
        try:
            s = json.loads((out / f"bw-{prec}-{comp}" / "summary.json").read_text())
            sent = sum(l["bytes_ab"] + l["bytes_ba"] for l in s.get("links", []))
            nlinks = max(1, len(s.get("links", [])))
            rss = [v["peak_rss_mb"] for v in s["vehicles"] if v.get("peak_rss_mb") is not None]
            row(label, f"{s['duration_s']:.0f} s simulated",
                f"{sent / s['duration_s'] / 1e3:.1f} kB/s", f"link bytes / naive dense (Y, y) f64 = {team_ratio(s):.3f}",
                f"all {nlinks} links, both directions, per simulated second ({sent / s['duration_s'] / nlinks / 1e3:.1f} kB/s per link); "
                f"team map ANEES {s['team']['map_anees']:.2f}, pose ANEES {s['team']['pose_anees']:.2f}"
                + (f"; peak RSS per vehicle {min(rss):.0f}–{max(rss):.0f} MB" if rss else ""))
        except FileNotFoundError:
            row(label, "-", "FAILED", "", "")

print("Machine: " + "; ".join((out / "machine.txt").read_text().strip().splitlines()) + "\n")
print(f"| measurement | size | value | ratio | notes |")
print("|---|---|---|---|---|")
for r in rows:
    print("| " + " | ".join(str(c) for c in r) + " |")
print(f"\n(total bench time {elapsed} s; raw outputs in {out})")
EOF
