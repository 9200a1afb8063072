#!/bin/bash
# Where a zenoh echo side spends its CPU, thread by thread: our relay (`aimrt_main` with
# RelayModule and the zenoh plugin) and the raw typed pong (`aimrt_zenoh_probe pong`),
# each against the typed raw ping, ROUNDS rounds of N messages of SIZE bytes, shared
# memory off. Prints echoes a second, then user and system CPU a message (µs) and
# voluntary context switches a message of every busy thread of the echo side, from
# /proc/<pid>/task/*/stat.
#
#   cargo build --release --workspace && benches/scripts/zenoh-threads.sh [SIZE] [N] [ROUNDS]
#
# Needs aimrt_main, aimrt_zenoh_probe, libaimrt_zenoh_plugin.so and libpb_chn_pkg.so in
# target/release (or $BIN). The docs/benchmarks.md table of the eighth session came from it.
#
# How each round starts, to compare with the `zenoh` scenario (which starts the ping at
# once, warms nothing up and lists `shm_enabled: false` for every topic):
#   HEAD=s     seconds between starting the echo side and the first ping (default 2);
#   WARM=n     messages of a first ping process before the measured one (default 20000;
#              0: none);
#   TOPIC_OPTS=1  the relay's zenoh backend lists the scenario's `pub_topics_options`.
#
# Also prints how full the batches are: the bytes each side has sent over TCP a data
# segment (one zenoh batch of small messages a segment on loopback), read with `ss`
# SEGS_AT seconds (default 0.5) into the measured ping, over its connection so far.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
size=${1:-64}
n=${2:-200000}
rounds=${3:-2}
bin=$(cd "${BIN:-target/release}" && pwd)
head_start=${HEAD:-2}
warm=${WARM:-20000}
if [ "${TOPIC_OPTS:-0}" = 1 ]; then
    topic_opts='
        options:
          pub_topics_options:
            - topic_name: "(.*)"
              shm_enabled: false'
else
    topic_opts=
fi
for f in aimrt_main aimrt_zenoh_probe libaimrt_zenoh_plugin.so libpb_chn_pkg.so; do
    [ -e "$bin/$f" ] || { echo "missing $bin/$f: cargo build --release --workspace" >&2; exit 2; }
done
. "$here/zenoh-common.sh"
cat > "$dir/relay.yaml" <<EOF
aimrt:
  plugin:
    plugins:
      - name: zenoh_plugin
        path: $bin/libaimrt_zenoh_plugin.so
        options:
          native_cfg_path: $dir/pong.json5
          shm_pool_size: 67108864 # as the benchmark's relay; unused with shared memory off
  log:
    core_lvl: Warn
    backends:
      - type: console
  channel:
    backends:
      - type: zenoh$topic_opts
    pub_topics_options:
      - topic_name: "(.*)"
        enable_backends: [zenoh]
    sub_topics_options:
      - topic_name: "(.*)"
        enable_backends: [zenoh]
  module:
    pkgs:
      - path: $bin/libpb_chn_pkg.so
        enable_modules: [RelayModule]
    modules:
      - name: RelayModule
        log_lvl: Warn
RelayModule:
  sub_topic_name: /bench/ping
  pub_topic_name: /bench/pong
EOF
# name user sys voluntary tid, one line a thread
snap() {
    for t in /proc/"$pid"/task/*; do
        echo "$(tr ' ' _ < "$t/comm") $(cut -d' ' -f14,15 "$t/stat") $(awk '/^voluntary/ {print $2}' "$t/status") ${t##*/}"
    done | sort -k5
}
ping() { # messages (exec: in the background, its process is the probe's)
    exec "$bin/aimrt_zenoh_probe" ping "$dir/ping.json5" "$ping_key" "$pong_key" "$size" "$1" 10 0 typed
}
# bytes sent and data segments sent over the TCP connections of process $1, so far
sent() {
    ss -tnpi 2>/dev/null | awk -v p="pid=$1," 'index($0, p) {
        getline
        if (match($0, / bytes_sent:[0-9]+/)) b += substr($0, RSTART + 12, RLENGTH - 12)
        if (match($0, /data_segs_out:[0-9]+/)) s += substr($0, RSTART + 14, RLENGTH - 14)
    } END { if (s > 0) printf "%.0f", b / s; else printf "-" }'
}
hz=$(getconf CLK_TCK)
for round in $(seq "$rounds"); do
    for side in relay raw; do
        if [ $side = relay ]; then
            "$bin/aimrt_main" --cfg_file_path="$dir/relay.yaml" > "$dir/side.log" 2>&1 &
        else
            "$bin/aimrt_zenoh_probe" pong "$dir/pong.json5" "$ping_key" "$pong_key" 0 typed > "$dir/side.log" 2>&1 &
        fi
        pid=$!
        sleep "$head_start"
        if [ "$warm" != 0 ]; then
            (ping "$warm" > /dev/null) # warm up, and wait for the echo
        fi
        snap > "$dir/a"
        ping "$n" > "$dir/ping.out" &
        pinger=$!
        sleep "${SEGS_AT:-0.5}"
        batches="bytes a segment: echo side $(sent "$pid"), ping $(sent "$pinger")"
        wait "$pinger" || true
        result=$(grep "^{" "$dir/ping.out" || true)
        snap > "$dir/b"
        kill -INT "$pid"; sleep 1; kill -9 "$pid" 2>/dev/null || true; wait "$pid" 2>/dev/null || true
        pid=
        echo "round $round, $side: $result"
        echo "  $batches"
        # A thread missing from the first snapshot (started after it, e.g. with WARM=0)
        # counts from zero.
        awk -v n="$n" -v hz="$hz" 'NR == FNR { u0[$5] = $2; s0[$5] = $3; v0[$5] = $4; next }
        {
            u = ($2 - u0[$5]) * 1e6 / hz / n; s = ($3 - s0[$5]) * 1e6 / hz / n
            if (u + s > 0) printf "  %-10s user %.2f  sys %.2f  vol %.3f\n", $1, u, s, ($4 - v0[$5]) / n
        }' "$dir/a" "$dir/b"
    done
done
