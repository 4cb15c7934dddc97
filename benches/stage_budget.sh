#!/usr/bin/env bash
# CPU per stage of `ebptv track`, from the threads' names: perf samples the
# whole process and attributes each sample to the thread that took it.
#
#   benches/stage_budget.sh RECORDING [TRACK OPTIONS...]
#
# Stages and their threads: decode + pulse timing (`ebptv-pulses-*` and the
# main thread `ebptv`), clustering (`ebptv-cluster-*`), linking
# (`ebptv-track`), output fits (`ebptv-fit` and the shared pool
# `ebptv-pool-*`, where the fits run in parallel), writing
# (`ebptv-track-wri*`, `ebptv-table-*`). Prints per stage the CPU-s, the
# share and the ns per event, then the whole run's wall time and CPU-s
# (GNU time, a second run without perf). Needs perf (Debian's linux-perf)
# and a release build; BIN=PATH measures another binary (default
# target/release/ebptv), e.g. two builds in the same run.
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -ge 1 ] || { echo "usage: $0 RECORDING [TRACK OPTIONS...]" >&2; exit 2; }
rec=$1; shift
bin=${BIN:-target/release/ebptv}
[ -x "$bin" ] || cargo build --release --quiet
work=$(mktemp -d); trap 'rm -rf "$work"' EXIT
events=$("$bin" info --json "$rec" | python3 -c 'import json,sys; print(json.load(sys.stdin)["events"])')
perf record -q -F 2000 -o "$work/perf.data" "$bin" track "$rec" "$@" --out "$work/a" >/dev/null 2>&1
perf report -i "$work/perf.data" --no-children --sort comm -F comm,sample -g none --stdio 2>/dev/null \
    | awk -v ev="$events" -v hz=2000 -v main="$(basename "$bin" | cut -c1-15)" '
    /^#/ || NF < 2 { next }
    {
        c = $1; n = $NF
        if (c ~ /^ebptv-pulses/ || c == "ebptv" || c == main) s = "decode + pulse timing"
        else if (c ~ /^ebptv-cluster/) s = "clustering"
        else if (c == "ebptv-track") s = "linking"
        else if (c ~ /^ebptv-fit/ || c ~ /^ebptv-pool/) s = "output fits"
        else if (c ~ /^ebptv-track-wri/ || c ~ /^ebptv-table/) s = "writing"
        else s = "other (" c ")"
        cpu[s] += n / hz; tot += n / hz
    }
    END {
        printf "| stage | CPU-s | share | ns/event |\n|---|---|---|---|\n"
        for (s in cpu) printf "| %s | %.2f | %.0f %% | %.0f |\n", s, cpu[s], 100 * cpu[s] / tot, 1e9 * cpu[s] / ev
        printf "| all (perf) | %.2f | 100 %% | %.0f |\n", tot, 1e9 * tot / ev
    }'
/usr/bin/time -f "wall %e s, CPU %U + %S s, peak %M KB" "$bin" track "$rec" "$@" --out "$work/b" 2>&1 >/dev/null | tail -1
echo "events $events"
