#!/bin/bash
# Runs each transport's example pair as two hosts on one machine and cuts the network
# between them for a while: what each side says, and whether every message and call is
# delivered or counted. Needs root (network namespaces) and `ip` (iproute2).
#
#   cargo build --workspace
#   sudo tests/e2e/scripts/two-hosts.sh                 # every transport, a 15 s cut
#   sudo CUT=5 tests/e2e/scripts/two-hosts.sh zenoh_chn grpc_rpc
#
# Three namespaces: host A (10.77.0.1), host B (10.77.0.2) and a switch between them (a
# bridge). The cut takes B's cable out of the switch (the switch's port to B goes down):
# A's own link stays up, so A's packets go into the switch and vanish, as over a cable
# pulled at the far end or a switch that stopped. B (subscriber, server, broker) starts
# first, A (publisher, client) a second later, at 50 messages or 5 calls a second; the
# cut starts 4 s after A and lasts $CUT seconds (default 15); A runs 30 s, B 35 s.
#
# Transports (arguments, default all): zenoh_chn zenoh_rpc tcp_chn udp_chn http_chn
# http_rpc grpc_rpc mqtt_chn. Each prints the shutdown counters of both sides, and the
# logs are kept under $OUT (default a temporary directory, printed at the end).
# docs/limits-and-errors.md ("A network cut between two hosts") has what a run showed.
set -u
root=$(cd "$(dirname "$0")/../../.." && pwd)
bin=${BIN:-$root/target/debug}
cut=${CUT:-15}
out=${OUT:-$(mktemp -d)}
mkdir -p "$out"
ns=a2h$$  # interface names below: at most 15 characters
a=${ns}a b=${ns}b sw=${ns}s

cleanup() {
    for n in "$a" "$b" "$sw"; do ip netns pids "$n" 2>/dev/null | xargs -r kill -9 2>/dev/null; done
    for n in "$a" "$b" "$sw"; do ip netns del "$n" 2>/dev/null; done
}
trap cleanup EXIT

set -e
for n in "$a" "$b" "$sw"; do ip netns add "$n"; ip -n "$n" link set lo up; done
ip link add "${ns}A" type veth peer name "${ns}a1"
ip link add "${ns}B" type veth peer name "${ns}b1"
ip link set "${ns}A" netns "$a"; ip link set "${ns}a1" netns "$sw"
ip link set "${ns}B" netns "$b"; ip link set "${ns}b1" netns "$sw"
ip -n "$sw" link add br0 type bridge
ip -n "$sw" link set "${ns}a1" master br0; ip -n "$sw" link set "${ns}b1" master br0
for i in br0 "${ns}a1" "${ns}b1"; do ip -n "$sw" link set "$i" up; done
ip -n "$a" addr add 10.77.0.1/24 dev "${ns}A"; ip -n "$a" link set "${ns}A" up
ip -n "$b" addr add 10.77.0.2/24 dev "${ns}B"; ip -n "$b" link set "${ns}B" up
set +e

# The example config $1 as $2: 127.0.0.1 made 10.77.0.2 (B's address, where A connects
# and B listens), 50 messages or 5 calls a second, modules logging warnings only.
config() {
    sed -e 's/127\.0\.0\.1/10.77.0.2/g' -e 's/channel_frq: [0-9.]*/channel_frq: 50/' \
        -e 's/rpc_frq: [0-9.]*/rpc_frq: 5/' -e 's/log_lvl: INFO/log_lvl: WARN/' \
        "$root/config/$1.yaml" > "$out/$2.yaml"
}

# zenoh's native configs of the two hosts (docs/zenoh.md, "Two machines").
for side in 1:2 2:1; do
    cat > "$out/zenoh_${side%%:*}.json5" <<EOF
{ mode: "peer", listen: { endpoints: ["tcp/0.0.0.0:7447"] },
  connect: { endpoints: ["tcp/10.77.0.${side##*:}:7447"] },
  scouting: { multicast: { enabled: false } } }
EOF
done

# run NAME B_CONFIG A_CONFIG: B in its namespace, then A, then the cut.
run() {
    local name=$1
    (cd "$out" && AIMRT_LIB_DIR=$bin AIMRT_ZENOH_NATIVE_CFG=$out/zenoh_2.json5 \
        AIMRT_MQTT_BROKER=tcp://10.77.0.2:1883 timeout -s INT 35 \
        ip netns exec "$b" "$bin/aimrt_main" --cfg_file_path="$out/$2.yaml" > "$out/$name.b.log" 2>&1) &
    local pid_b=$!
    sleep 1
    (cd "$out" && AIMRT_LIB_DIR=$bin AIMRT_ZENOH_NATIVE_CFG=$out/zenoh_1.json5 \
        AIMRT_MQTT_BROKER=tcp://10.77.0.2:1883 timeout -s INT 30 \
        ip netns exec "$a" "$bin/aimrt_main" --cfg_file_path="$out/$3.yaml" > "$out/$name.a.log" 2>&1) &
    local pid_a=$!
    sleep 4
    ip -n "$sw" link set "${ns}b1" down
    sleep "$cut"
    ip -n "$sw" link set "${ns}b1" up
    wait "$pid_a" "$pid_b"
    echo "== $name (a ${cut} s cut)"
    for side in a b; do
        grep -h "Channel topic .*: published\|Module RPC:\|_plugin: [0-9]* payloads sent\|net_plugin [a-z ]*: [0-9]* messages sent\|is gone\|matches '\|lost the connection\|the connection to .* brought no answer" \
            "$out/$name.$side.log" | sed -e "s/^.*\]\[[^]]*\]\[[^]]*\]\[[^]]*\]\[[^ ]* @[a-z_]*\]/  $side: /" | cut -c1-260
    done
}

want=${*:-zenoh_chn zenoh_rpc tcp_chn udp_chn http_chn http_rpc grpc_rpc mqtt_chn}
for t in $want; do
    case $t in
    zenoh_chn) config zenoh_pb_chn_sub sub; config zenoh_pb_chn_pub pub; run "$t" sub pub ;;
    zenoh_rpc) config zenoh_pb_rpc_server srv; config zenoh_pb_rpc_client cli; run "$t" srv cli ;;
    tcp_chn) config pb_chn_tcp_sub sub; config pb_chn_tcp_pub pub; run "$t" sub pub ;;
    udp_chn) config pb_chn_udp_sub sub; config pb_chn_udp_pub pub; run "$t" sub pub ;;
    http_chn) config pb_chn_http_sub sub; config pb_chn_http_pub pub; run "$t" sub pub ;;
    http_rpc) config pb_rpc_http_server srv; config pb_rpc_http_client cli; run "$t" srv cli ;;
    grpc_rpc) config grpc_pb_rpc_server srv; config grpc_pb_rpc_client cli; run "$t" srv cli ;;
    mqtt_chn)
        ip netns exec "$b" timeout 40 "$bin/aimrt_mqtt_test_broker" 10.77.0.2:1883 > "$out/broker.log" 2>&1 &
        sleep 0.5
        config mqtt_pb_chn_sub sub; config mqtt_pb_chn_pub pub; run "$t" sub pub
        wait
        ;;
    *) echo "unknown transport '$t'" >&2; exit 2 ;;
    esac
done
echo "logs: $out"
