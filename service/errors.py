"""Errors of the service layer, each with the HTTP status and problem type it maps to.

They cross the process boundary as plain dicts (`as_dict` / `from_dict`), so a
worker's refusal reaches the API process intact.
"""

from __future__ import annotations

import errno
import sqlite3
from typing import Any


class ServiceError(Exception):
    """A request the service refuses; rendered as RFC 9457 problem+json by the API.

    `slug` names the problem type, `title` is its short fixed summary, `detail`
    says precisely what was wrong (which field, what value), `extra` holds
    additional members (e.g. ``field``).
    """

    def __init__(self, status: int, slug: str, title: str, detail: str, **extra: Any) -> None:
        super().__init__(detail)
        self.status = status
        self.slug = slug
        self.title = title
        self.detail = detail
        self.extra = extra

    def as_dict(self) -> dict[str, Any]:
        return {
            "status": self.status,
            "slug": self.slug,
            "title": self.title,
            "detail": self.detail,
            "extra": self.extra,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ServiceError:
        return cls(d["status"], d["slug"], d["title"], d["detail"], **d.get("extra", {}))


def unknown_map(map_id: str) -> ServiceError:
    return ServiceError(404, "unknown-map", "Unknown map", f"no map with id {map_id!r}")


def unknown_robot(map_id: str, robot: str, hint: str = "") -> ServiceError:
    detail = f"robot: map {map_id!r} has no robot {robot!r}{hint}"
    return ServiceError(404, "unknown-robot", "Unknown robot", detail, field="robot")


def invalid_frame(field: str, detail: str) -> ServiceError:
    return ServiceError(422, "invalid-frame", "Invalid frame", f"{field}: {detail}", field=field)


def out_of_order(field: str, detail: str) -> ServiceError:
    return ServiceError(
        409, "out-of-order", "Frame out of order", f"{field}: {detail}", field=field
    )


PG_DISK_FULL = "53100"
"""PostgreSQL's SQLSTATE disk_full (psycopg errors carry it as `sqlstate`)."""


def _disk_full(exc: BaseException) -> bool:
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    if type(exc).__module__.split(".")[0] == "psycopg":
        return getattr(exc, "sqlstate", None) == PG_DISK_FULL
    return isinstance(exc, sqlite3.Error) and getattr(exc, "sqlite_errorcode", None) == getattr(
        sqlite3, "SQLITE_FULL", 13
    )


def internal_error(exc: BaseException) -> ServiceError:
    """What a client is told about an unexpected exception: 400 for a body nested too
    deeply to parse, 507 when the disk is full, else a bare 500. Never the exception's
    class or message (GTSAM, SQLite and paths stay in the server's log)."""
    if isinstance(exc, RecursionError):  # json.loads of a deeply nested document
        return ServiceError(400, "malformed-body", "Malformed body", "body: JSON nested too deeply")
    if _disk_full(exc):
        return ServiceError(
            507,
            "insufficient-storage",
            "Insufficient storage",
            "the service's disk is full; the request was not completed. Retry once space is freed",
        )
    return ServiceError(
        500,
        "internal",
        "Internal error",
        "the service failed on this request (the details are in the server's log)",
    )


class WorkerUnavailable(Exception):
    """The map's worker crashed or did not answer in time: retry later (503)."""

    def __init__(self, detail: str, *, retry_after_s: int) -> None:
        super().__init__(detail)
        self.detail = detail
        self.retry_after_s = retry_after_s
