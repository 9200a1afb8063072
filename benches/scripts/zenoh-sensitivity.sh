#!/bin/bash
# How the `zenoh` scenario's round-trip rate answers to work on the ping side: the typed
# raw ping against the typed raw pong (shared memory off), with busy work added after each
# put and in each echo's callback (AIMRT_PROBE_SEND_SPIN_NS, AIMRT_PROBE_RECV_SPIN_NS).
# Ours spends about 2.5 k instructions a message more than the raw ping to send and 1.2 k
# more to receive (docs/benchmarks.md, tenth session); if raw slowed by that much falls as
# far as ours, the gap is the ping side's work, else it is something else.
#
#   cargo build --release --workspace && benches/scripts/zenoh-sensitivity.sh [ROUNDS] [SIZES]
#
# SIZES: comma-separated bytes (default 64,1024). SPINS (environment): space-separated
# send:recv nanoseconds (default "0:0 300:150 600:300 1200:600"). Each round runs every
# spin of every size once, in an order that turns round by round; prints one line a run
# and the median rate of each case over the rounds. Needs aimrt_zenoh_probe in
# target/release (or $BIN).
set -eu
here=$(cd "$(dirname "$0")" && pwd)
rounds=${1:-5}
sizes=${2:-64,1024}
spins=${SPINS:-0:0 300:150 600:300 1200:600}
bin=$(cd "${BIN:-target/release}" && pwd)
[ -e "$bin/aimrt_zenoh_probe" ] || { echo "missing $bin/aimrt_zenoh_probe: cargo build --release --workspace" >&2; exit 2; }
. "$here/zenoh-common.sh"
"$bin/aimrt_zenoh_probe" pong "$dir/pong.json5" "$ping_key" "$pong_key" 0 typed > "$dir/pong.log" 2>&1 &
pid=$!
sleep 1
# Warm up, and wait for the echo.
"$bin/aimrt_zenoh_probe" ping "$dir/ping.json5" "$ping_key" "$pong_key" 64 20000 10 0 typed > /dev/null
cases=()
for size in ${sizes//,/ }; do
    for s in $spins; do cases+=("$size $s"); done
done
for round in $(seq "$rounds"); do
    k=${#cases[@]}
    for i in $(seq 0 $((k - 1))); do
        c=(${cases[$(((i + round) % k))]})
        size=${c[0]}; send=${c[1]%:*}; recv=${c[1]#*:}
        r=$(AIMRT_PROBE_SEND_SPIN_NS=$send AIMRT_PROBE_RECV_SPIN_NS=$recv \
            "$bin/aimrt_zenoh_probe" ping "$dir/ping.json5" "$ping_key" "$pong_key" "$size" 20000 200 0 typed)
        rate=$(echo "$r" | sed -n 's/.*"msgs_per_s": \([0-9.]*\).*/\1/p')
        p50=$(echo "$r" | sed -n 's/.*"rtt_p50_us": \([0-9.]*\).*/\1/p')
        echo "round $round size $size spin $send:$recv msgs/s $rate p50 $p50" | tee -a "$dir/all"
    done
done
echo "median msgs/s over $rounds rounds (size, send:recv spin ns):"
for c in "${cases[@]}"; do
    set -- $c
    grep "size $1 spin $2 " "$dir/all" | awk '{print $8}' | sort -n |
        awk -v c="$1 B, $2" '{v[NR] = $1} END {m = NR % 2 ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2; printf "  %-16s %9.0f\n", c, m}'
done
