"""grpcio (Google's gRPC, C core) as the client of grpc_plugin's server: prints one line a
call; exits 1 when an answer is not what the server must answer."""
import sys

import grpc

import rpc_pb2
import rpc_pb2_grpc

addr = sys.argv[1]
failed = False
with grpc.insecure_channel(addr) as channel:
    stub = rpc_pb2_grpc.ExampleServiceStub(channel)
    rsp = stub.GetFooData(
        rpc_pb2.GetFooDataReq(msg="hello from grpcio"),
        timeout=2.0,
        metadata=[("trace-id", "py-1")],
    )
    print("GetFooData ->", repr(rsp.msg))
    failed |= rsp.msg != "echo hello from grpcio"
    nope = channel.unary_unary(
        "/aimrt.protocols.example.ExampleService/Nope",
        request_serializer=lambda b: b,
        response_deserializer=lambda b: b,
    )
    try:
        nope(b"", timeout=2.0)
        print("Nope -> answered")
        failed = True
    except grpc.RpcError as e:
        print("Nope ->", e.code(), e.details())
        failed |= e.code() != grpc.StatusCode.UNIMPLEMENTED
sys.exit(1 if failed else 0)
