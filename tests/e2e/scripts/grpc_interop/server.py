"""grpcio (Google's gRPC, C core) as a server of ExampleService for grpc_plugin's client:
GetFooData answers "python echo <msg>" and prints what arrived (the deadline left, the
function name meta); it serves for argv[2] seconds."""
import sys
import time
from concurrent import futures

import grpc

import rpc_pb2
import rpc_pb2_grpc


class Service(rpc_pb2_grpc.ExampleServiceServicer):
    def GetFooData(self, req, ctx):
        md = dict(ctx.invocation_metadata())
        print(
            "server got %r, deadline left %.1f s, aimrt-function_name %s"
            % (req.msg, ctx.time_remaining(), md.get("aimrt-function_name")),
            flush=True,
        )
        return rpc_pb2.GetFooDataRsp(code=0, msg="python echo " + req.msg)


server = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
rpc_pb2_grpc.add_ExampleServiceServicer_to_server(Service(), server)
server.add_insecure_port(sys.argv[1])
server.start()
time.sleep(float(sys.argv[2]))
