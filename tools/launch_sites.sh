#!/usr/bin/env bash
# Which code launches a `cuda` build's kernels: every launch of one offline `paper` step (the
# driver of tools/cuda-offline.sh) traced back to f3g's function that caused it.
#
#   tools/launch_sites.sh F3G [OUT_DIR]      # F3G: a cuda build of f3g (e.g. CI's GPU build's)
#
# Why not the driver: CubeCL launches from its device thread, so a stack taken in
# cuLaunchKernel ends in CubeCL's server loop. A uprobe on CubeCL's `Client::launch` (which
# runs on the caller's thread) with perf's DWARF call graphs sees the caller. Needs root, perf
# and tracefs (mounted here if absent). Writes OUT_DIR (default target/launch-sites) with
# `sites.txt`: the second step's launches (the first makes the optimisers' moments and
# compiles), counted by kernel and by the first f3g function up the stack; and `stacks.txt`,
# every launch's stack (perf script's text) for questions the counts do not answer.
# perf drops samples when its buffer fills (it says how many): the counts are then shares.
# F3G_PERF_PAGES (perf's buffer in pages, default 65536) and F3G_PERF_STACK (bytes of stack
# kept per launch, default 65528): 262144 and 40960 record every launch of a `paper` step, but
# some stacks through CubeK's convolutions then end before reaching f3g's frames.
set -euo pipefail
cd "$(dirname "$0")/.."
f3g=$(realpath "${1:?a cuda build of f3g}")
out=${2:-target/launch-sites}
mkdir -p "$out"
[ -e /sys/kernel/tracing/uprobe_events ] || mount -t tracefs nodev /sys/kernel/tracing
symbol=$(nm "$f3g" | awk '/ T _ZN14cubecl_runtime6client6Client6launch17h/ {s = $1} END {print s}')
[ -n "$symbol" ] || { echo "no cubecl_runtime::client::Client::launch in $f3g" >&2; exit 1; }
# perf probe takes a file offset: the symbol's address less its segment's address, plus the
# segment's offset in the file.
offset=$(readelf -lW "$f3g" | python3 -c '
import sys
address = int(sys.argv[1], 16)
for line in sys.stdin:
    f = line.split()
    if f[:1] == ["LOAD"]:
        offset, start, size = int(f[1], 16), int(f[2], 16), int(f[5], 16)
        if start <= address < start + size:
            print(hex(address - start + offset))
' "$symbol")
perf probe -q -d 'probe_f3g:*' 2>/dev/null || true
perf probe -q -x "$f3g" --add "launch=$offset"
F3G_KERNEL_CACHE=${F3G_KERNEL_CACHE:-target/kernel-cache} perf record -q -m ${F3G_PERF_PAGES:-65536} \
    -e probe_f3g:launch --call-graph dwarf,${F3G_PERF_STACK:-65528} -o "$out/perf.data" -- \
    tools/cuda-offline.sh run "$f3g" bench train --preset paper --device cuda --steps 1 --warmup 1 \
    > "$out/bench.log" 2>&1
perf probe -q -d 'probe_f3g:*'
perf script -i "$out/perf.data" -F ip,sym 2>/dev/null > "$out/stacks.txt"
rm "$out/perf.data"
python3 tools/launch_sites.py < "$out/stacks.txt" > "$out/sites.txt"
head -n 40 "$out/sites.txt"
