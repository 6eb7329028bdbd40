"""Path and query parameters shared by the JSON API (app.py) and the web pages (ui.py)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Path, Query

MAX_ID = 2**63 - 1                 # ids are 64-bit signed in SQLite and PostgreSQL: a larger one is 422, not a 500
Id = Annotated[int, Path(ge=1, le=MAX_ID)]
QueryId = Annotated[int, Query(ge=1, le=MAX_ID)]   # a run id in a query string (/compare?a=1&b=2)
