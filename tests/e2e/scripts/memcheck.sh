#!/bin/bash
# Runs the examples under config/ under a memory checker: valgrind's memcheck (default), an
# AddressSanitizer build or a ThreadSanitizer build. What it looks for: a read or write out
# of bounds, a use after free, a read of uninitialized memory (memcheck, AddressSanitizer),
# a data race or a lock-order inversion (ThreadSanitizer), anywhere on the paths the
# examples take: the C ABI between aimrt_main, plugins and module packages, the executors,
# the transports.
#
#   cargo build --workspace
#   tests/e2e/scripts/memcheck.sh                  # every example below, under valgrind
#   tests/e2e/scripts/memcheck.sh config/pb_chn.yaml config/pb_chn_tcp_sub.yaml+config/pb_chn_tcp_pub.yaml
#
#   # AddressSanitizer: a nightly toolchain (no rust-src needed), its own target dir
#   RUSTFLAGS=-Zsanitizer=address cargo +nightly build --workspace \
#       --target x86_64-unknown-linux-gnu --target-dir /tmp/asan
#   MODE=asan BIN=/tmp/asan/x86_64-unknown-linux-gnu/debug tests/e2e/scripts/memcheck.sh
#
#   # ThreadSanitizer: a nightly toolchain with rust-src (std is built instrumented too)
#   RUSTFLAGS="-Zsanitizer=thread -Clink-arg=-Wl,--export-dynamic" cargo +nightly build \
#       -Zbuild-std --workspace --target x86_64-unknown-linux-gnu --target-dir /tmp/tsan
#   MODE=tsan BIN=/tmp/tsan/x86_64-unknown-linux-gnu/debug tests/e2e/scripts/memcheck.sh
#
# An argument (a path from here or from the repository root) is one config, run alone for
# $DUR seconds (default 5), or a pair SECOND+FIRST. A zenoh config with `#unix` behind it
# runs over unix sockets (config/zenoh_native_unix_{a,b}.json5 for zenoh_native_{a,b}.json5).
# A pair SECOND+FIRST:
# FIRST (the subscriber or server) starts, SECOND 6 s later for 15 s (valgrind starts
# slowly). Each config is copied with `channel_frq` and `rpc_frq` set to 50 a second, and
# runs in a temporary directory with AIMRT_LIB_DIR=$BIN (default target/debug).
# A line a run: its exit code, the checker's verdict and the shutdown counters of what
# crossed; the logs of a run with an error are kept (the line after it says where). The
# script exits 1 when any process reports an error or exits other than 0, or when a pair
# exchanged nothing (then nothing of its transport was checked).
set -u
root=$(cd "$(dirname "$0")/../../.." && pwd)
bin=$(cd "${BIN:-$root/target/debug}" && pwd)
mode=${MODE:-valgrind}
dur=${DUR:-5}
[ -x "$bin/aimrt_main" ] || { echo "missing $bin/aimrt_main: cargo build --workspace" >&2; exit 2; }
case $mode in
    valgrind)
        command -v valgrind > /dev/null || { echo "valgrind is not installed" >&2; exit 2; }
        checker=(valgrind --error-exitcode=99 --leak-check=no --num-callers=40
            "--suppressions=$root/tests/e2e/scripts/valgrind-ring.supp")
        ;;
    asan)
        checker=()
        export ASAN_OPTIONS=${ASAN_OPTIONS:-detect_leaks=0:exitcode=99}
        ;;
    tsan)
        checker=()
        # Every report, not only the first: the verdict counts them. tsan.supp names the
        # reports of dependencies alone.
        export TSAN_OPTIONS=${TSAN_OPTIONS:-exitcode=99 halt_on_error=0 suppressions=$root/tests/e2e/scripts/tsan.supp}
        ;;
    *) echo "MODE: '$mode' is not a checker; expected valgrind, asan or tsan" >&2; exit 2 ;;
esac
if [ $# -eq 0 ]; then
    set -- config/demo.yaml config/helloworld.yaml config/executor.yaml config/executor_co.yaml \
        config/executor_co_loop.yaml config/executor_timer.yaml config/std_executors.yaml \
        config/demo_std_executors_so.yaml config/cbg_executor.yaml config/logger.yaml \
        config/log_backend_plugin.yaml config/parameter.yaml config/time_manipulator.yaml \
        config/pb_chn.yaml config/pb_chn_async.yaml config/pb_chn_inline.yaml \
        config/pb_chn_single_pkg.yaml config/pb_chn_debug_log.yaml \
        config/channel_filter_plugin.yaml config/echo_plugin_pb.yaml \
        config/proxy_plugin_local.yaml config/record_playback_plugin_record_imd.yaml \
        config/pb_rpc_sync.yaml config/pb_rpc_async.yaml config/pb_rpc_future.yaml \
        config/pb_rpc_co.yaml config/pb_rpc_single_pkg.yaml config/pb_proxy_rpc_co.yaml \
        config/rpc_filter_plugin.yaml \
        config/opentelemetry_plugin_pb_chn.yaml config/opentelemetry_plugin_pb_rpc_metrics.yaml \
        config/pb_chn_tcp_pub.yaml+config/pb_chn_tcp_sub.yaml \
        config/pb_chn_udp_pub.yaml+config/pb_chn_udp_sub.yaml \
        config/pb_chn_http_pub.yaml+config/pb_chn_http_sub.yaml \
        config/pb_rpc_http_client.yaml+config/pb_rpc_http_server.yaml \
        config/zenoh_pb_chn_pub.yaml+config/zenoh_pb_chn_sub.yaml \
        config/zenoh_pb_chn_pub_with_shm.yaml+config/zenoh_pb_chn_sub_with_shm.yaml \
        config/zenoh_pb_rpc_client.yaml+config/zenoh_pb_rpc_server.yaml \
        config/zenoh_pb_rpc_client_with_shm.yaml+config/zenoh_pb_rpc_server_with_shm.yaml \
        'config/zenoh_pb_chn_pub.yaml#unix+config/zenoh_pb_chn_sub.yaml#unix' \
        config/topic_logger_plugin.yaml+config/topic_logger_plugin_echo.yaml \
        config/grpc_pb_rpc_client.yaml+config/grpc_pb_rpc_server.yaml \
        config/mqtt_pb_chn_pub.yaml+config/mqtt_pb_chn_sub.yaml \
        config/mqtt_pb_rpc_client.yaml+config/mqtt_pb_rpc_server.yaml \
        config/mqtt_pb_chn_ssl_pub.yaml+config/mqtt_pb_chn_ssl_sub.yaml
fi
dir=$(mktemp -d)
pids=()
cleanup() {
    for p in "${pids[@]}"; do kill -9 "$p" 2> /dev/null || true; done
    rm -rf "$dir"
}
trap cleanup EXIT

# The mqtt examples talk through a broker: the tests' small one, on a free port; the
# ssl:// ones through a second one serving TLS with the test certificates.
free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
tls_port=8883
if [[ "$*" == *mqtt* ]]; then
    port=$(free_port)
    "$bin/aimrt_mqtt_test_broker" "127.0.0.1:$port" > "$dir/broker.out" 2>&1 &
    pids+=($!)
    disown $!  # killed at the end without a job notice
    export AIMRT_MQTT_BROKER=tcp://127.0.0.1:$port
    tls=$root/tests/tls
    tls_port=$(free_port)
    "$bin/aimrt_mqtt_test_broker" "127.0.0.1:$tls_port" --tls "$tls/broker.pem" "$tls/broker.key" \
        --client-ca "$tls/ca.pem" > "$dir/tls_broker.out" 2>&1 &
    pids+=($!)
    disown $!
    export AIMRT_MQTT_TLS_DIR=$tls
fi

# Starts config `$1` (a path from here or from the repository root) as `$2` for `$3`
# seconds; its pid in $started.
start() {
    local src=${1%#unix}
    [ -f "$src" ] || src=$root/$src
    sed -e 's/channel_frq: .*/channel_frq: 50/' -e 's/rpc_frq: .*/rpc_frq: 50/' \
        -e "s#\./config/#$root/config/#g" \
        -e "s#\${AIMRT_MQTT_BROKER:-ssl://127.0.0.1:8883}#ssl://127.0.0.1:$tls_port#" "$src" > "$dir/$2.yaml"
    if [[ $1 == *'#unix' ]]; then
        sed -i "s#$root/config/zenoh_native_\([ab]\)\.json5#$root/config/zenoh_native_unix_\1.json5#" "$dir/$2.yaml"
    fi
    (cd "$dir" && AIMRT_LIB_DIR=$bin exec "${checker[@]}" "$bin/aimrt_main" \
        --cfg_file_path="$dir/$2.yaml" --running_duration="$3" > "$dir/$2.log" 2>&1) &
    started=$!
    pids+=("$started")
}

# The verdict on log `$1` and exit code `$2`, with what crossed, in $told; sets bad on
# an error.
verdict() {
    local log=$1 code=$2 said
    said=$(grep -o "ERROR SUMMARY: [0-9]* errors" "$log" || true)
    if grep -q "ERROR: AddressSanitizer" "$log"; then
        said="AddressSanitizer: $(grep -m1 -o "ERROR: AddressSanitizer: [a-z-]*" "$log" | cut -d' ' -f3)"
    fi
    if grep -q "WARNING: ThreadSanitizer" "$log"; then
        said="ThreadSanitizer: $(grep -m1 -o "WARNING: ThreadSanitizer: [a-z -]*" "$log" | cut -d' ' -f3- | sed 's/ *$//') (first of $(grep -c "WARNING: ThreadSanitizer" "$log"))"
    fi
    if [ "$code" != 0 ] || { [ -n "$said" ] && [ "$said" != "ERROR SUMMARY: 0 errors" ]; }; then
        bad=1
    fi
    told="exit $code${said:+, $said} [$(crossed "$log")]"
}

# The shutdown counters of log `$1` that say what crossed.
crossed() {
    grep -hoE "Channel topic '[^']*': published [0-9]+, delivered [0-9]+|Module RPC: [0-9]+ calls, [0-9]+ answered with an error" "$1" \
        | tr '\n' ';' | sed 's/;$//'
}

failed=0
for arg in "$@"; do
    rm -f "$dir"/*.log
    bad=0
    if [[ $arg == *+* ]]; then
        second=${arg%%+*}
        first=${arg#*+}
        start "$first" first 30
        pf=$started
        sleep 6
        start "$second" second 15
        wait "$started"
        cs=$?
        wait "$pf"
        cf=$?
        verdict "$dir/first.log" "$cf"
        line="$(basename "$first" .yaml): $told"
        verdict "$dir/second.log" "$cs"
        echo "$line | $(basename "$second" .yaml): $told"
        if ! grep -qE "delivered [1-9]|Module RPC: [1-9][0-9]* calls" "$dir/first.log" "$dir/second.log"; then
            echo "  nothing crossed between the pair, so nothing of the transport was checked"
            bad=1
        fi
    else
        start "$arg" one "$dur"
        wait "$started"
        verdict "$dir/one.log" $?
        echo "$(basename "$arg" .yaml): $told"
    fi
    if [ "$bad" = 1 ]; then
        failed=1
        kept=${kept:-$(mktemp -d)}
        for log in "$dir"/*.log; do cp "$log" "$kept/$(basename "${arg//\//_}" .yaml).$(basename "$log")"; done
        echo "  its logs are in $kept"
    fi
done
exit "$failed"
