#!/usr/bin/env python3
"""A dray client that knows nothing of dray's .proto files.

Everything it uses -- services, methods, message types, field names, enum values -- comes
from the server's gRPC reflection service, as it would for any third-party tool. It
submits one job (its spec given as proto3 JSON, the same text grpcurl takes), watches it
to a terminal state, fetches the PNG, writes it, and prints a JSON summary on stdout.
It also submits a job with spp 0 and records the status code it gets.

Used by cli/tests/reflection.rs with the venv that .ci/run builds from requirements.txt.
Exit status: 0 when the job succeeded and the image was written, 1 otherwise (the reason
on stderr).
"""

import argparse
import json
import sys

import grpc
from google.protobuf import descriptor_pool, json_format, message_factory
from grpc_reflection.v1alpha import reflection_pb2
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import (
    ProtoReflectionDescriptorDatabase,
)

SERVICE = "dray.v1.RenderService"
TERMINAL = {"JOB_STATE_SUCCEEDED", "JOB_STATE_FAILED", "JOB_STATE_CANCELLED"}


def reflection_database(channel):
    """A descriptor database fed by the server's reflection service.

    grpcio-reflection's client speaks grpc.reflection.v1alpha only. Servers may offer only
    grpc.reflection.v1 (tonic-reflection's build_v1 does), whose messages are identical on
    the wire; only the method path differs. So: v1alpha first, and on UNIMPLEMENTED the
    same database pointed at the v1 path -- what grpcurl does the other way round.
    Returns (database, service names, protocol used).
    """
    db = ProtoReflectionDescriptorDatabase(channel)
    try:
        return db, list(db.get_services()), "v1alpha"
    except grpc.RpcError as e:
        if e.code() != grpc.StatusCode.UNIMPLEMENTED:
            raise
    db = ProtoReflectionDescriptorDatabase(channel)
    db._stub.ServerReflectionInfo = channel.stream_stream(
        "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo",
        request_serializer=reflection_pb2.ServerReflectionRequest.SerializeToString,
        response_deserializer=reflection_pb2.ServerReflectionResponse.FromString,
    )
    return db, list(db.get_services()), "v1"


class Service:
    """Callables for a service's methods, built from its reflected descriptor."""

    def __init__(self, channel, pool, name):
        self.descriptor = pool.FindServiceByName(name)
        self.channel = channel
        self.name = name

    def _method(self, method):
        m = self.descriptor.FindMethodByName(method)
        if m is None:
            raise KeyError(f"{self.name} has no method {method}")
        req = message_factory.GetMessageClass(m.input_type)
        resp = message_factory.GetMessageClass(m.output_type)
        path = f"/{self.name}/{method}"
        kind = "unary_stream" if m.server_streaming else "unary_unary"
        call = getattr(self.channel, kind)(
            path,
            request_serializer=req.SerializeToString,
            response_deserializer=resp.FromString,
        )
        return req, call

    def call(self, method, request_json, timeout=None):
        """Call `method` with a request given as proto3 JSON; returns the response(s)."""
        req_cls, call = self._method(method)
        request = json_format.Parse(json.dumps(request_json), req_cls())
        return call(request, timeout=timeout)


def as_json(message):
    # Proto3 JSON, as grpcurl prints it: lowerCamelCase names, enums by name.
    return json_format.MessageToDict(message)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--addr", required=True, help="host:port of a dray coordinator")
    ap.add_argument("--spec", required=True, help="JobSpec as proto3 JSON")
    ap.add_argument("--out", required=True, help="PNG file to write")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds for the whole job")
    args = ap.parse_args()

    # GetImage replies can exceed gRPC's default 4 MiB receive limit.
    channel = grpc.insecure_channel(
        args.addr, options=[("grpc.max_receive_message_length", -1)]
    )
    grpc.channel_ready_future(channel).result(timeout=30)
    db, services, protocol = reflection_database(channel)
    if SERVICE not in services:
        print(f"{SERVICE} is not among the reflected services {services}", file=sys.stderr)
        return 1
    pool = descriptor_pool.DescriptorPool(db)
    render = Service(channel, pool, SERVICE)
    spec = json.loads(args.spec)

    # An invalid job must be INVALID_ARGUMENT with a message naming the field.
    try:
        render.call("SubmitJob", {"spec": {**spec, "spp": 0}}, timeout=30)
        invalid = {"code": "OK", "message": ""}
    except grpc.RpcError as e:
        invalid = {"code": e.code().name, "message": e.details()}

    submitted = as_json(render.call("SubmitJob", {"spec": spec}, timeout=args.timeout))
    job_id = submitted["jobId"]
    states = []
    last = {}
    messages = 0
    for progress in render.call("WatchJob", {"jobId": job_id}, timeout=args.timeout):
        last = as_json(progress)
        messages += 1
        state = last.get("state", "JOB_STATE_UNSPECIFIED")
        if not states or states[-1] != state:
            states.append(state)
        if state in TERMINAL:
            break
    final = states[-1] if states else "JOB_STATE_UNSPECIFIED"
    summary = {
        "reflection": protocol,
        "services": sorted(services),
        "invalid_spp": invalid,
        "job_id": job_id,
        "states": states,
        "progress_messages": messages,
        "tiles_done": last.get("tilesDone", 0),
        "tiles_total": last.get("tilesTotal", 0),
        # uint64 is a JSON string in proto3 JSON.
        "rays_traced": int(last.get("raysTraced", "0")),
        "final_state": final,
    }
    if final != "JOB_STATE_SUCCEEDED":
        summary["error"] = last.get("error", "")
        print(json.dumps(summary))
        print(f"job {job_id} ended {final}: {summary['error']}", file=sys.stderr)
        return 1

    image = render.call(
        "GetImage", {"jobId": job_id, "format": "IMAGE_FORMAT_PNG"}, timeout=args.timeout
    )
    with open(args.out, "wb") as f:
        f.write(image.data)
    summary.update(
        {
            "output": args.out,
            "bytes": len(image.data),
            "width": image.width,
            "height": image.height,
            "content_type": image.content_type,
            "format": as_json(image).get("format", ""),
        }
    )
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except grpc.RpcError as e:
        print(f"gRPC error: {e.code().name}: {e.details()}", file=sys.stderr)
        sys.exit(1)
