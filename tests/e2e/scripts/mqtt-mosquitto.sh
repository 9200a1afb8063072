#!/bin/bash
# mqtt_plugin's example pairs through mosquitto, a production MQTT broker, instead of the
# tests' small broker: the channel pair, and the RPC client against two servers sharing
# the function (`$share/aimrt/…`: each request goes to one of them), and the TLS channel
# pair (`config/mqtt_pb_chn_ssl_*`, client certificates required) through a TLS listener
# with the test certificates. Not part of CI (it needs mosquitto: `apt install mosquitto`).
#
#   cargo build --workspace
#   tests/e2e/scripts/mqtt-mosquitto.sh
#
# Exits 1 when a message or a call does not arrive as it must; prints what each side saw.
set -u
root=$(cd "$(dirname "$0")/../../.." && pwd)
bin=$root/target/debug
[ -x "$bin/aimrt_main" ] || { echo "missing $bin/aimrt_main: cargo build --workspace" >&2; exit 2; }
command -v mosquitto > /dev/null || { echo "mosquitto is not installed: apt install mosquitto" >&2; exit 2; }
work=$(mktemp -d)
pids=()
cleanup() {
    for p in "${pids[@]}"; do kill "$p" 2> /dev/null || true; done
    rm -rf "$work"
}
trap cleanup EXIT
free() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
port=$(free)
tls_port=$(free)
tls=$root/tests/tls
cat > "$work/mosquitto.conf" << EOF
allow_anonymous true
set_tcp_nodelay true
listener $port 127.0.0.1
listener $tls_port 127.0.0.1
cafile $tls/ca.pem
certfile $tls/broker.pem
keyfile $tls/broker.key
require_certificate true
EOF
mosquitto -c "$work/mosquitto.conf" > "$work/mosquitto.log" 2>&1 &
pids+=($!)
sleep 0.5
export AIMRT_LIB_DIR=$bin AIMRT_MQTT_BROKER=tcp://127.0.0.1:$port
run() { # name config seconds [sed expression]
    sed "${4:-s/^//}" "$root/config/$2.yaml" > "$work/$1.yaml"
    (cd "$work" && exec "$bin/aimrt_main" --cfg_file_path="$1.yaml" --running_duration="$3" > "$1.log" 2>&1) &
    pids+=($!)
    for _ in $(seq 100); do grep -q "Module manager start completed" "$work/$1.log" 2> /dev/null && break; sleep 0.1; done
}
failed=0

run sub mqtt_pb_chn_sub 8
run pub mqtt_pb_chn_pub 5 's/channel_frq: 0.5/channel_frq: 20/'
run server_a mqtt_pb_rpc_server 8
run server_b mqtt_pb_rpc_server 8 's/client_id: example_pb_rpc_server/client_id: example_pb_rpc_server_b/'
run client mqtt_pb_rpc_client 5 's/rpc_frq: 1/rpc_frq: 10/'
# A topic of their own: what the TLS subscriber hears came through TLS.
AIMRT_MQTT_BROKER=ssl://127.0.0.1:$tls_port AIMRT_MQTT_TLS_DIR=$tls run ssl_sub mqtt_pb_chn_ssl_sub 8 's/topic_name: test_topic/topic_name: tls_topic/'
AIMRT_MQTT_BROKER=ssl://127.0.0.1:$tls_port AIMRT_MQTT_TLS_DIR=$tls run ssl_pub mqtt_pb_chn_ssl_pub 5 's/channel_frq: 0.5/channel_frq: 20/;s/topic_name: test_topic/topic_name: tls_topic/'
wait "${pids[@]:1}"

received=$(grep -c 'Receive new pb event' "$work/sub.log")
published=$(grep -c 'Publish new pb event' "$work/pub.log")
echo "channel: $published published, $received received"
grep -q '{"aimrt-backend":"mqtt"}' "$work/sub.log" || { echo "FAILED: no message with its context"; failed=1; }
[ "$received" -ge 50 ] || { echo "FAILED: too few messages"; failed=1; }
ok=$(grep -c 'Client get rpc ret, status: suc' "$work/client.log")
errors=$(grep -c 'Client get rpc error ret' "$work/client.log")
a=$(grep -c 'Server handle new rpc call' "$work/server_a.log")
b=$(grep -c 'Server handle new rpc call' "$work/server_b.log")
echo "rpc: $ok answered, $errors errors; server a served $a, server b served $b"
[ "$ok" -ge 20 ] && [ "$errors" -eq 0 ] || { echo "FAILED: calls"; failed=1; }
[ "$a" -gt 0 ] && [ "$b" -gt 0 ] || { echo "FAILED: the servers did not share the calls"; failed=1; }
ssl_received=$(grep -c 'Receive new pb event' "$work/ssl_sub.log")
echo "channel over TLS: $ssl_received received"
[ "$ssl_received" -ge 50 ] || { echo "FAILED: too few messages over TLS"; failed=1; }
grep -h 'mqtt_plugin: .* payloads sent' "$work"/*.log
if [ "$failed" -ne 0 ]; then
    tail -n 20 "$work"/*.log
    echo FAILED
    exit 1
fi
echo OK
