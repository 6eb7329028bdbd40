"""The live view: one Rerun gRPC server for the whole service and the Rerun web viewer, both from the rerun-sdk
wheel (the viewer's Wasm ships inside it: no internet). Each run process connects to the gRPC server as its own
recording (application `drivebench`, recording id `run-<id>`) and tees to its run.rrd."""

from __future__ import annotations

_KEEP: list = []         # the gRPC server lives as long as its recording stream: keep it for the process's life
MEMORY_LIMIT = "1GiB"    # the gRPC server keeps recent data for viewers that connect late; oldest dropped first


def start_live(grpc_port: int, web_port: int, host: str = "127.0.0.1") -> tuple[str, str]:
    """Start both servers in this process; returns (gRPC URL for `--rerun-url`, web viewer URL)."""
    import rerun as rr

    service_recording = rr.RecordingStream("drivebench-service")
    _KEEP.append(service_recording)
    grpc_url = rr.serve_grpc(grpc_port=grpc_port, recording=service_recording, server_memory_limit=MEMORY_LIMIT)
    rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=grpc_url)
    return grpc_url, f"http://{host}:{web_port}"
