# Sourced by the zenoh scripts (zenoh-threads.sh, zenoh-sensitivity.sh): a temporary
# directory removed on exit with the side in $pid killed, the bench's keys, and the two
# native configs $dir/ping.json5 and $dir/pong.json5: the pong listens on a port picked by
# this process's id, the ping connects to it (explicit endpoints, no scouting; one
# connection, benches/zenoh_native.json5). Needs $here (the scripts' folder).
dir=$(mktemp -d)
pid=
cleanup() {
    if [ -n "$pid" ]; then
        kill -9 "$pid" 2>/dev/null || true
        wait "$pid" 2>/dev/null || true
    fi
    rm -rf "$dir"
}
trap cleanup EXIT
ping_key='channel/%2Fbench%2Fping/pb%3Aaimrt.protocols.example.ExampleEventMsg'
pong_key='channel/%2Fbench%2Fpong/pb%3Aaimrt.protocols.example.ExampleEventMsg'
base=$((20000 + $$ % 20000))
native() { # name listen-endpoints connect-endpoints
    sed -e "s|LISTEN_ENDPOINTS|$2|" -e "s|CONNECT_ENDPOINTS|$3|" "$here/../zenoh_native.json5" > "$dir/$1.json5"
}
native ping "" "\"tcp/127.0.0.1:$base\""
native pong "\"tcp/127.0.0.1:$base\"" ""
