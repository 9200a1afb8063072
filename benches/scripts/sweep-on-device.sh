#!/bin/sh
# The scenarios that wait for a many-core machine, in one call of a lent device, from
# release binaries built here (the same five files as zenoh-on-device.sh):
#
#   cargo build --release --workspace
#   run(command: "benches/scripts/sweep-on-device.sh", timeout_s: 540,
#       carry: [target/release/aimrt-bench, target/release/aimrt_main,
#               target/release/aimrt_zenoh_probe, target/release/libaimrt_zenoh_plugin.so,
#               target/release/libpb_chn_pkg.so])
#
# In order, each under its own time limit so that one that hangs leaves the others' files:
# the thread-scaling sweep (1 to 16 workers), the zenoh scenario (zenoh-on-device.sh
# without its thread split), net_plugin's channels, and module RPC. Writes to $OUT:
# machine.txt, scaling.txt, zenoh_2.{txt,json}, net.txt, rpc.txt (6 files; the device
# returns at most 8). On the lent 16-core machine (2026-11-27) the sweep took 171 s and
# the zenoh, net and rpc steps 176 s together.
set -u
out=${OUT:-/tmp}
b=target/release/aimrt-bench
[ -x "$b" ] || { echo "missing $b: build with cargo build --release --workspace and carry it" >&2; exit 2; }
status=0
# One process per worker count, each with its own limit: all five in one process took
# more than 150 s there; one after the other they took 171 s (2026-11-27).
: > "$out/scaling.txt"
for n in 1 2 4 8 16; do
    timeout 90 "$b" --only scaling --threads $n >> "$out/scaling.txt" 2>&1 || status=$?
done
grep '^| [0-9]' "$out/scaling.txt" || true
THREADS=0 timeout 270 "$(dirname "$0")/zenoh-on-device.sh" 2 || status=$?
timeout 90 "$b" --only net > "$out/net.txt" 2>&1 || status=$?
grep -A 10 '^| backend' "$out/net.txt" || true
timeout 60 "$b" --only rpc > "$out/rpc.txt" 2>&1 || status=$?
grep -A 8 '^| case' "$out/rpc.txt" || true
grep -h '^Targets missed\|^- ' "$out/scaling.txt" "$out/net.txt" "$out/rpc.txt" || true
exit $status
