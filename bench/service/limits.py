"""What one request and one client may cost the service (docs/service.md, "Limits"). Standard library only: the CI
client (bench/service/client.py) checks a scenario against the same number before sending it."""

from __future__ import annotations

MAX_SCENARIO_CHARS = 256 * 1024      # a submitted scenario's text (the paper scenarios are 1-3 kB; queue.py checks
                                      # the same number of UTF-8 bytes)
MAX_SUBMIT_BODY_BYTES = 1024 * 1024   # POST /api/runs: the scenario JSON-escaped, with room for the other fields
MAX_BODY_BYTES = 64 * 1024            # every other route (a lease, a token, a form)
BODY_IDLE_TIMEOUT_S = 10.0            # a client that stops sending its body this long gets 408
HEAD_TIMEOUT_S = 10.0                 # a connection must send a complete request head within this (idle, slowloris)
KEEP_ALIVE_S = 5                      # an idle keep-alive connection is closed after this (uvicorn's own option)
FD_RESERVE = 256                      # descriptors kept for the database, run processes, logs (not for clients)
MAX_CONNECTIONS = 4096                # at most this many client connections; beyond, the oldest idle ones are closed
MAX_RENDERS = 2                       # plots rendered at once (each a matplotlib figure on a worker thread)
RENDER_WAIT_S = 10.0                  # a plot request waits this long for a renderer, then 503 with Retry-After
SWITCH_INTERVAL_S = 0.001             # the service process's interpreter-lock switch interval (Python's default: 5 ms)
READ_CACHE_S = 1.0                    # a JSON API answer is at most this old (bench/service/fresh.py)
READ_CACHE_ENTRIES = 512
ROUTE_BODY_LIMITS = {("POST", "/api/runs"): MAX_SUBMIT_BODY_BYTES}


def body_limit(method: str, path: str) -> int:
    return ROUTE_BODY_LIMITS.get((method, path), MAX_BODY_BYTES)
