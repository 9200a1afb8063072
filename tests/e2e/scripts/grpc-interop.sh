#!/bin/bash
# grpc_plugin against grpcio, Google's gRPC (its C core), both ways: grpcio's client calls
# config/grpc_pb_rpc_server.yaml, and config/grpc_pb_rpc_client.yaml calls a grpcio
# server. Not part of CI (it installs grpcio from PyPI into a virtual environment).
#
#   cargo build --workspace
#   tests/e2e/scripts/grpc-interop.sh          # VENV=/tmp/aimrt-grpcio by default
#
# Exits 1 when a call does not end as it must; prints what each side saw.
set -u
root=$(cd "$(dirname "$0")/../../.." && pwd)
here=$root/tests/e2e/scripts/grpc_interop
bin=$root/target/debug
venv=${VENV:-/tmp/aimrt-grpcio}
[ -x "$bin/aimrt_main" ] || { echo "missing $bin/aimrt_main: cargo build --workspace" >&2; exit 2; }
if [ ! -x "$venv/bin/python" ]; then
    python3 -m venv "$venv" && "$venv/bin/pip" install -q grpcio==1.84.0 grpcio-tools==1.84.0 || exit 2
fi
work=$(mktemp -d)
pids=()
cleanup() {
    for p in "${pids[@]}"; do kill "$p" 2> /dev/null || true; done
    rm -rf "$work"
}
trap cleanup EXIT
cp "$root/protocols/proto/example/rpc.proto" "$root/protocols/proto/example/common.proto" "$here"/*.py "$work/"
(cd "$work" && "$venv/bin/python" -m grpc_tools.protoc -I. --python_out=. --grpc_python_out=. rpc.proto common.proto) || exit 2
port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
failed=0

# grpcio's client -> our server.
p=$(port)
sed "s/listen_port: 50050/listen_port: $p/" "$root/config/grpc_pb_rpc_server.yaml" > "$work/server.yaml"
(cd "$work" && AIMRT_LIB_DIR=$bin exec "$bin/aimrt_main" --cfg_file_path=server.yaml --running_duration=15 > server.log 2>&1) &
pids+=($!)
for _ in $(seq 100); do grep -q "Module manager start completed" "$work/server.log" 2> /dev/null && break; sleep 0.1; done
(cd "$work" && "$venv/bin/python" client.py "127.0.0.1:$p") || failed=1
grep -q '{"trace-id":"py-1"}' "$work/server.log" || { echo "the server did not get grpcio's metadata"; failed=1; }

# Our client -> grpcio's server.
p=$(port)
(cd "$work" && exec "$venv/bin/python" server.py "127.0.0.1:$p" 12 > pyserver.log 2>&1) &
pids+=($!)
sleep 2
sed -e "s#http://127.0.0.1:50050#http://127.0.0.1:$p#" -e "s/rpc_frq: 0.5/rpc_frq: 2/" \
    "$root/config/grpc_pb_rpc_client.yaml" > "$work/client.yaml"
(cd "$work" && AIMRT_LIB_DIR=$bin "$bin/aimrt_main" --cfg_file_path=client.yaml --running_duration=3 > client.log 2>&1)
grep -o "Client get rpc ret.*" "$work/client.log" | head -2
grep -o "Module RPC: .*" "$work/client.log"
cat "$work/pyserver.log"
grep -q 'rsp: {"code":"0","msg":"python echo hello world foo, count 1"}' "$work/client.log" || failed=1
grep -q "Module RPC: [1-9][0-9]* calls, 0 answered with an error" "$work/client.log" || failed=1
grep -q "aimrt-function_name pb:/aimrt.protocols.example.ExampleService/GetFooData" "$work/pyserver.log" || failed=1
[ "$failed" = 0 ] && echo "grpc interop: both ways OK" || echo "grpc interop: FAILED"
exit "$failed"
