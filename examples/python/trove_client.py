#!/usr/bin/env python3
"""A TROVE farm client in Python: submit a scene, watch the job, write its PNG.

The gRPC stubs are generated from proto/trove.proto at run time with grpcio-tools, into a
temporary folder (no generated code is kept), so this script follows the protocol as it is.

    pip install grpcio grpcio-tools
    python3 examples/python/trove_client.py --coordinator 127.0.0.1:7000 scene.toml -o out.png

The scene's dataset paths are keys that the farm's workers resolve under their data roots,
exactly as with `trove render --coordinator`; the PNG is the one local mode writes.
A refusal or a failed job prints the coordinator's typed Failure and exits 1.
"""

import argparse
import importlib
import os
import sys
import tempfile

import grpc
from grpc_tools import protoc

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_PROTO = os.path.normpath(os.path.join(HERE, "..", "..", "proto", "trove.proto"))


def load_stubs(proto_path, out_dir):
    """Compiles trove.proto into out_dir and imports its messages and services."""
    folder, name = os.path.split(os.path.abspath(proto_path))
    code = protoc.main(
        ["grpc_tools.protoc", f"-I{folder}", f"--python_out={out_dir}", f"--grpc_python_out={out_dir}", name]
    )
    if code != 0:
        sys.exit(f"error: cannot compile {proto_path} (protoc exit {code})")
    sys.path.insert(0, out_dir)
    module = os.path.splitext(name)[0]
    return importlib.import_module(f"{module}_pb2"), importlib.import_module(f"{module}_pb2_grpc")


def target(coordinator):
    """grpc's target from a URL as `trove` takes it (http://host:port) or a bare host:port."""
    for scheme in ("http://", "https://"):
        if coordinator.startswith(scheme):
            return coordinator[len(scheme):].rstrip("/")
    return coordinator


def failure_text(pb, error):
    """The typed Failure a gRPC error carries (trove puts it in the status details)."""
    details = dict(error.trailing_metadata() or ()).get("grpc-status-details-bin")
    if details:
        f = pb.Failure.FromString(details)
        about = ", ".join(f"{k} {v}" for k, v in (("file", f.file), ("key", f.key), ("dataset", f.dataset)) if v)
        reason = pb.Reason.Name(f.reason)
        return f"{f.message} ({reason}{', ' + about if about else ''})"
    return f"{error.code().name}: {error.details()}"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", help="the scene file (TOML)")
    parser.add_argument("-o", "--output", required=True, help="the PNG to write")
    parser.add_argument("--coordinator", required=True, help="the coordinator, e.g. http://127.0.0.1:7000")
    parser.add_argument("--proto", default=DEFAULT_PROTO, help="trove.proto (default: the repository's)")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds to wait for the job")
    args = parser.parse_args()

    with open(args.scene, encoding="utf-8") as f:
        scene_toml = f.read()
    with tempfile.TemporaryDirectory(prefix="trove-stubs-") as stubs:
        pb, rpc = load_stubs(args.proto, stubs)
        with grpc.insecure_channel(target(args.coordinator)) as channel:
            client = rpc.CoordinatorStub(channel)
            try:
                job = client.SubmitJob(
                    pb.SubmitJobRequest(scene_toml=scene_toml, scene_name=args.scene, options=pb.JobOptions()),
                    timeout=60,
                ).job_id
                print(f"submitted {job}", file=sys.stderr)
                last = None
                for status in client.WatchJob(pb.WatchJobRequest(job_id=job), timeout=args.timeout):
                    last = status
                    state = pb.JobState.Name(status.state)
                    print(f"{job}: {state} {status.pieces_done}/{status.pieces_total} pieces", file=sys.stderr)
                if last is None or last.state != pb.JOB_STATE_SUCCEEDED:
                    why = last.failure.message if last is not None and last.HasField("failure") else "no status"
                    sys.exit(f"error: job {job} did not succeed: {why}")
                png = bytearray()
                for chunk in client.GetResult(pb.GetResultRequest(job_id=job), timeout=args.timeout):
                    if chunk.part != pb.RESULT_PART_PNG:
                        continue
                    if chunk.offset != len(png):
                        sys.exit(f"error: job {job}'s PNG arrived out of order")
                    png += chunk.data
            except grpc.RpcError as e:
                sys.exit(f"error: {failure_text(pb, e)}")
    with open(args.output, "wb") as f:
        f.write(png)
    print(f"wrote {args.output} ({len(png)} bytes)", file=sys.stderr)


if __name__ == "__main__":
    main()
