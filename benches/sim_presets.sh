#!/usr/bin/env bash
# Simulator throughput per preset, written to files (EVT 3.0 recording +
# truth CSV), as a user runs it: `ebptv simulate --preset P --seconds S`.
#
#   benches/sim_presets.sh [SECONDS] [REPEATS] [PRESET...]
#
# Defaults: 1 simulated second, 2 repeats, every preset. Prints one
# Markdown row per run: events, wall s, user+sys CPU-s, peak RSS, Mev/s of
# wall time and Mev per CPU-s. Each run writes into a fresh directory under
# $TMPDIR (default /tmp) that is deleted right after, so runs do not pay
# for each other's page-cache write-back. Wall time is only meaningful on
# an otherwise idle machine; CPU-s are meaningful under load.
#
# Needs GNU time (/usr/bin/time) and a release build (`cargo build
# --release`; the script builds it if missing).
set -euo pipefail

cd "$(dirname "$0")/.."
seconds=${1:-1}
repeats=${2:-2}
shift $(( $# < 2 ? $# : 2 ))
bin=target/release/ebptv
[ -x "$bin" ] || cargo build --release --quiet
if [ $# -gt 0 ]; then
    presets=("$@")
else
    # The first column of `ebptv simulate --list-presets`.
    mapfile -t presets < <("$bin" simulate --list-presets | awk 'NF {print $1}')
fi
[ -x /usr/bin/time ] || { echo "sim_presets.sh: needs GNU time at /usr/bin/time" >&2; exit 1; }

work=$(mktemp -d "${TMPDIR:-/tmp}/ebptv-sim-presets.XXXXXX")
trap 'rm -rf "$work"' EXIT

echo "| preset | seconds | events | wall s | CPU-s (user+sys) | peak RSS MB | Mev/s wall | Mev per CPU-s |"
echo "|---|---|---|---|---|---|---|---|"
for p in "${presets[@]}"; do
    for ((r = 1; r <= repeats; r++)); do
        out="$work/$p"
        rm -rf "$out"
        /usr/bin/time -f "%e %U %S %M" -o "$work/time" \
            "$bin" simulate --preset "$p" --seconds "$seconds" --out "$out" >/dev/null
        events=$(sed -n 's/.*"events": \([0-9]*\).*/\1/p' "$out/summary.json" | head -1)
        read -r wall user sys rss <"$work/time"
        awk -v p="$p" -v s="$seconds" -v e="$events" -v w="$wall" -v u="$user" -v y="$sys" -v m="$rss" 'BEGIN {
            cpu = u + y
            printf "| %s | %s | %.2f M | %.2f | %.2f | %.0f | %.1f | %.1f |\n", p, s, e / 1e6, w, cpu, m / 1024, e / 1e6 / w, e / 1e6 / cpu
        }'
        rm -rf "$out"
    done
done
