"""What a record says about when and with what software it was made."""

from __future__ import annotations

import datetime as dt
import subprocess
from importlib import metadata
from typing import Any

from drivers.contract.checks import find_repo_root


def utc_now() -> str:
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def software_identity() -> dict[str, Any]:
    try:
        version = metadata.version("drivebench")
    except metadata.PackageNotFoundError:
        version = None
    root = find_repo_root()
    revision, dirty = None, None
    try:
        revision = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                                  timeout=5).stdout.strip() or None
        if revision:
            status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                                    capture_output=True, text=True, timeout=10)
            dirty = bool(status.stdout.strip()) if status.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        pass
    return {"version": version, "git_revision": revision, "git_dirty": dirty}

