"""An API error: an HTTP status and a detail (a string, or for 422 the `file: field: reason` lines)."""

from __future__ import annotations


class ApiError(Exception):
    def __init__(self, status: int, detail: str | list[str]):
        super().__init__(detail if isinstance(detail, str) else "\n".join(detail))
        self.status = status
        self.detail = detail


def not_found(what: str) -> ApiError:
    return ApiError(404, f"{what}: not found")


def bad_input(lines: list[str]) -> ApiError:
    return ApiError(422, lines)
