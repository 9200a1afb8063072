#!/bin/sh
# The zenoh scenario on a lent many-core machine, from release binaries built here:
#
#   cargo build --release --workspace
#   (cd target/release && strip aimrt-bench aimrt_main aimrt_zenoh_probe \
#       libaimrt_zenoh_plugin.so libpb_chn_pkg.so)  # unstripped, they and the tree are over 64 MiB
#   run(command: "benches/scripts/zenoh-on-device.sh 1", timeout_s: 540,
#       carry: [target/release/aimrt-bench, target/release/aimrt_main,
#               target/release/aimrt_zenoh_probe, target/release/libaimrt_zenoh_plugin.so,
#               target/release/libpb_chn_pkg.so])
#
# Arguments after <n> go to aimrt-bench, e.g. `zenoh-on-device.sh 3 --rounds 11
# --zenoh-sizes 64,1024,65536 --zenoh-shm off` for many rounds of the cases whose verdict
# earlier runs could not settle (docs/benchmarks.md), without shared memory.
#
# Writes $OUT/zenoh_<n>.json and .txt (the table and the targets missed),
# $OUT/machine.txt and $OUT/threads_<n>.txt: the relay's and the raw pong's CPU by
# thread (`benches/scripts/zenoh-threads.sh 64 200000 2`; THREADS=0 skips it). One full
# run took about 4 minutes on 16 cores; the whole script, thread split included, took
# 2 min 5 s on the 2-core VM (2026-11-26). Since "shm off" crosses TCP for large messages
# too (2026-11-27), the run alone took 4 min 6 s on the 2-core VM. On the lent 16-core
# machine (2026-11-27), `--rounds 9 --zenoh-sizes 64,1024,65536` took 164 s and every size
# with `--rounds 6` 161 s (THREADS=0). Since every measurement starts its own processes
# (2026-11-27, thirteenth session), `--rounds 3` of every size took 2 min 39 s on the
# 2-core VM, about 40 s a round as before. On the lent 16-core machine (2026-11-30),
# `--rounds 9` of every size took 314 s; since each pair of sides has one connection
# that the ping opens without zenoh's 1 s connect retry, `--rounds 7` took 66 s with
# `--zenoh-shm off` and 93 s with `on`. One run per call keeps each call under the
# device's 10-minute limit.
set -eu
n=${1:-1}
[ $# -gt 0 ] && shift
out=${OUT:-/tmp}
bin=target/release
for f in aimrt-bench aimrt_main aimrt_zenoh_probe libaimrt_zenoh_plugin.so libpb_chn_pkg.so; do
    [ -e "$bin/$f" ] || { echo "missing $bin/$f: build with cargo build --release --workspace and carry it" >&2; exit 2; }
done
{ nproc; uname -r; grep -m1 'model name' /proc/cpuinfo || true; git rev-parse --short HEAD 2>/dev/null || true; } > "$out/machine.txt"
status=0
"$bin/aimrt-bench" --only zenoh "$@" --json "$out/zenoh_$n.json" > "$out/zenoh_$n.txt" 2>&1 || status=$?
grep -A 12 '^| size B' "$out/zenoh_$n.txt" || true
grep '^Targets missed\|^- zenoh' "$out/zenoh_$n.txt" || true
if [ "${THREADS:-1}" != 0 ]; then
    "$(dirname "$0")/zenoh-threads.sh" 64 200000 2 > "$out/threads_$n.txt" 2>&1 || true
    cat "$out/threads_$n.txt"
fi
exit $status
