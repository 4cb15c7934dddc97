#!/usr/bin/env bash
# Damaged copies of the real recordings through `ebptv pulses` and `ebptv track`
# under a memory limit: every run must end within 60 s with exit 0 or 1 and
# an `error:` line, peak memory below 1 GB, and a failed run must leave no
# file in its output folder.
#
#   benches/mutants.sh [N] [DATA_DIR] [EBPTV]
#
# N mutants (default 200) are made from the files in DATA_DIR (default
# ../shared/data/real) by a seeded generator: bit flips, overwritten byte
# runs, truncation, a corrupted EVT 2.0 TIME_HIGH word, header edits
# (`% format EVT3;height=65535;width=65535`, `% Width 0`, `% geometry 0x0`).
# Prints one line per failure and a summary (runs, exit codes, slowest run,
# largest peak RSS). Needs python3 and GNU time (/usr/bin/time).
set -euo pipefail
N=${1:-200}
DATA=${2:-$(dirname "$0")/../../shared/data/real}
EBPTV=${3:-$(dirname "$0")/../target/release/ebptv}
WORK=$(mktemp -d)
[ -n "${KEEP:-}" ] && echo "keeping $WORK" || trap 'rm -rf "$WORK"' EXIT
python3 - "$N" "$DATA" "$WORK" <<'EOF'
import os, random, struct, sys
n, data, work = int(sys.argv[1]), sys.argv[2], sys.argv[3]
files = sorted(f for f in os.listdir(data) if not f.endswith('.md'))
rng = random.Random(23)
def split_header(b):
    i = 0
    while b[i:i+2] == b'% ':
        j = b.find(b'\n', i)
        if j < 0: break
        i = j + 1
    return b[:i], bytearray(b[i:])
for k in range(n):
    name = files[k % len(files)]
    src = open(os.path.join(data, name), 'rb').read()
    hdr, pay = split_header(src)
    kind = rng.choice(['flip', 'flip', 'overwrite', 'truncate', 'time', 'header'])
    if kind == 'flip':
        for _ in range(rng.choice([1, 3, 30])):
            p = rng.randrange(len(pay)); pay[p] ^= 1 << rng.randrange(8)
    elif kind == 'overwrite':
        p = rng.randrange(len(pay)); L = rng.choice([4, 64, 4096])
        pay[p:p+L] = bytes(rng.randrange(256) for _ in range(min(L, len(pay) - p)))
    elif kind == 'truncate':
        pay = pay[:rng.randrange(len(pay))]
    elif kind == 'time' and name.endswith('.raw') and b'evt 2.0' in hdr:
        ths = [i for i in range(0, len(pay) - 3, 4) if pay[i+3] >> 4 == 0x8]
        i = rng.choice(ths)
        w = struct.unpack_from('<I', pay, i)[0] ^ (1 << rng.randrange(14, 28))
        struct.pack_into('<I', pay, i, w)
    else:
        edit = rng.choice([b'% format EVT3;height=65535;width=65535\n', b'% Width 0\n% Height 0\n',
                           b'% geometry 0x0\n', b'% format EVT2;height=720;width=1280\n'])
        hdr = edit + hdr if hdr else hdr
        if not hdr: pay[0:0] = b''
    ext = os.path.splitext(name)[1]
    open(os.path.join(work, f'm{k:04d}_{kind}{ext}'), 'wb').write(hdr + pay)
EOF
runs=0; ok=0; err=0; bad=0; maxkb=0; maxs=0
for f in "$WORK"/m*; do
  for stage in pulses track; do
    out="$WORK/out_$(basename "$f")_$stage"
    set +e
    /usr/bin/time -f "%e %M" -o "$WORK/time" timeout 60 prlimit --as=2000000000 \
      "$EBPTV" "$stage" "$f" --out "$out" >/dev/null 2>"$WORK/err"
    rc=$?
    set -e
    read -r secs kb < <(tail -1 "$WORK/time")
    runs=$((runs + 1))
    kb=${kb:-0}; [ "$kb" -gt "$maxkb" ] && maxkb=$kb
    awk -v a="$secs" -v b="$maxs" 'BEGIN{exit !(a>b)}' && maxs=$secs
    if [ $rc -eq 0 ]; then ok=$((ok + 1)); echo "exit 0: $stage $(basename "$f")";
    elif [ $rc -eq 1 ] && grep -q '^error:' "$WORK/err"; then
      err=$((err + 1))
      if [ -e "$out" ]; then bad=$((bad + 1)); echo "LEFT OUTPUT: $stage $(basename "$f"): $(ls -A "$out" | head -3)"; fi
    else bad=$((bad + 1)); echo "FAIL rc=$rc: $stage $(basename "$f"): $(tail -2 "$WORK/err" | cut -c1-200)"; fi
    if [ "$kb" -ge 1000000 ]; then bad=$((bad + 1)); echo "MEMORY ${kb} KB: $stage $(basename "$f")"; fi
    rm -rf "$out"
  done
done
echo "mutants: $N, runs: $runs, exit 0: $ok, clear error (exit 1): $err, failures: $bad, slowest: ${maxs} s, peak RSS: $((maxkb / 1024)) MB"
[ $bad -eq 0 ]
