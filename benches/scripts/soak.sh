#!/bin/bash
# A long run of one of the example pairs under config/, watching each process's memory,
# file descriptors and threads: what a robot that runs for days would show as growth.
#
#   cargo build --release --workspace
#   benches/scripts/soak.sh SECONDS CONFIG_A [CONFIG_B]
#   benches/scripts/soak.sh --churn STAY SECONDS CONFIG_A CONFIG_B
#
# CONFIG_B (the subscriber or server of a pair) starts first, CONFIG_A 2 s later; both run
# for SECONDS. With --churn, CONFIG_A runs for SECONDS while CONFIG_B is started, run for
# STAY seconds and stopped with SIGINT, again and again (a peer that restarts).
# Each config is copied with `channel_frq` and `rpc_frq` set to $RATE (default 2000 a
# second) and its modules' `log_lvl` to WARN, so the run is the transport's, not the
# console's. Every $EVERY seconds (default 15; with --churn, after each restart) a line
# gives each process's VmRSS, open descriptors and threads. At the end: the first and
# last samples, each process's shutdown counters, and exit codes; the script exits 1 when
# a process did not exit 0.
#
# Needs aimrt_main and the libraries in target/release (or $BIN). The configs' ./config/
# paths are made absolute, and the processes run in a temporary directory (their logs and
# bags go there) and are removed at the end, unless $KEEP names a directory to copy
# them into. docs/benchmarks.md ("Long runs") has the runs made with it.
set -eu
root=$(cd "$(dirname "$0")/../.." && pwd)
churn=
if [ "${1:-}" = --churn ]; then
    churn=$2
    shift 2
fi
[ $# -ge 2 ] || { sed -n '2,/^set -eu/p' "$0" | sed '$d' >&2; exit 2; }
secs=$1
a=$2
b=${3:-}
[ -z "$churn" ] || [ -n "$b" ] || { echo "--churn needs CONFIG_B" >&2; exit 2; }
rate=${RATE:-2000}
every=${EVERY:-15}
bin=$(cd "${BIN:-$root/target/release}" && pwd)
[ -x "$bin/aimrt_main" ] || { echo "missing $bin/aimrt_main: cargo build --release --workspace" >&2; exit 2; }
dir=$(mktemp -d)
pids=()
cleanup() {
    for p in "${pids[@]}"; do kill -9 "$p" 2>/dev/null || true; done
    if [ -n "${KEEP:-}" ]; then mkdir -p "$KEEP" && cp "$dir"/*.log "$KEEP"/ 2>/dev/null || true; fi
    rm -rf "$dir"
}
trap cleanup EXIT

# The config `$1` as run here, written to $dir/$2.yaml.
prepare() {
    sed -e "s/channel_frq: .*/channel_frq: $rate/" -e "s/rpc_frq: .*/rpc_frq: $rate/" \
        -e 's/log_lvl: .*/log_lvl: WARN/' -e "s#\./config/#$root/config/#g" "$1" > "$dir/$2.yaml"
}

# Starts `$1` (a or b) for `$2` seconds (0: until stopped); its pid in $started.
start() {
    local args=(--cfg_file_path="$dir/$1.yaml")
    [ "$2" = 0 ] || args+=(--running_duration="$2")
    (cd "$dir" && AIMRT_LIB_DIR=$bin exec "$bin/aimrt_main" "${args[@]}" >> "$dir/$1.log" 2>&1) &
    started=$!
    pids+=("$started")
}

# `name rss=… fds=… threads=…` of pid `$2`.
sample() {
    local p=$2
    echo "$1 rss=$(awk '/^VmRSS/ {print $2}' "/proc/$p/status")kB fds=$(ls "/proc/$p/fd" | wc -l) threads=$(awk '/^Threads/ {print $2}' "/proc/$p/status")"
}

prepare "$a" a
[ -z "$b" ] || prepare "$b" b
: > "$dir/samples"
t0=$SECONDS
failed=0
if [ -z "$churn" ]; then
    pb=
    if [ -n "$b" ]; then
        start b "$((secs + 4))"
        pb=$started
        sleep 2
    fi
    start a "$secs"
    pa=$started
    while [ $((SECONDS - t0 + every)) -lt "$secs" ]; do
        sleep "$every"
        line="$((SECONDS - t0))s $(sample a "$pa")"
        [ -z "$pb" ] || line="$line | $(sample b "$pb")"
        echo "$line" | tee -a "$dir/samples"
    done
    wait "$pa" || { echo "a exited $?"; failed=1; }
    [ -z "$pb" ] || wait "$pb" || { echo "b exited $?"; failed=1; }
else
    start a "$secs"
    pa=$started
    n=0
    while [ $((SECONDS - t0 + churn + 5)) -lt "$secs" ]; do
        start b 0
        sleep "$churn"
        kill -INT "$started"
        if ! wait "$started"; then
            echo "b #$((n + 1)) exited $?"
            failed=1
        fi
        n=$((n + 1))
        echo "$((SECONDS - t0))s after b #$n $(sample a "$pa")" | tee -a "$dir/samples"
    done
    wait "$pa" || { echo "a exited $?"; failed=1; }
fi
echo "first: $(head -n 1 "$dir/samples")"
echo "last:  $(tail -n 1 "$dir/samples")"
for side in a b; do
    [ -e "$dir/$side.log" ] || continue
    echo "$side's counters at its (last) shutdown:"
    grep -E "Channel topic '[^']*': published|Module RPC:|(zenoh|mqtt)_plugin: [0-9]|net_plugin [a-z ]+: [0-9]|executor '.*' shut down" "$dir/$side.log" \
        | tail -n 8 | sed -e 's/^\[[^]]*\]\[[^]]*\]\[[^]]*\]\[[^]]*\]\[[^]]*\]/  /'
done
exit "$failed"
