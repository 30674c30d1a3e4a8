"""The error every factord client raises for an error answer of the service."""

from __future__ import annotations

import json
from typing import Any, Optional


class FactordError(Exception):
    """An error answer of the service: ``{"error": {"code", "message", "field"?, "status",
    "retry_after"?}}`` on HTTP (with the matching status code) and on zenoh error replies.

    Attributes:
        status: HTTP-equivalent status (400, 404, 409, 422, 429, 503, ...); ``None`` when the
            failure happened before the service answered (e.g. no zenoh queryable replied).
        code: stable machine-readable code, e.g. ``unknown_variable``.
        message: human-readable explanation.
        field: where in the request the problem is, e.g. ``factors[3].information`` (or ``None``).
        retry_after: seconds to wait before retrying (back-pressure), or ``None``.
        body: the whole parsed error object (or the raw text when it was not JSON).
    """

    def __init__(
        self,
        status: Optional[int],
        code: str,
        message: str,
        field: Optional[str] = None,
        retry_after: Optional[float] = None,
        body: Any = None,
    ) -> None:
        self.status = status
        self.code = code
        self.message = message
        self.field = field
        self.retry_after = retry_after
        self.body = body
        where = f" at {field}" if field else ""
        super().__init__(f"{status} {code}{where}: {message}")

    @classmethod
    def from_body(
        cls,
        raw: bytes,
        status: Optional[int] = None,
        retry_after_header: Optional[str] = None,
    ) -> "FactordError":
        """Builds the error from an error body (``{"error": {...}}``), tolerating other bodies."""
        text = raw.decode("utf-8", errors="replace")
        try:
            parsed = json.loads(text)
        except ValueError:
            parsed = None
        error = parsed.get("error") if isinstance(parsed, dict) else None
        if not isinstance(error, dict):
            return cls(status, "unexpected_response", text.strip() or "empty error body",
                       body=parsed if parsed is not None else text)
        retry_after: Optional[float] = error.get("retry_after")
        if retry_after is None and retry_after_header:
            try:
                retry_after = float(retry_after_header)
            except ValueError:
                retry_after = None
        return cls(
            status=status if status is not None else error.get("status"),
            code=str(error.get("code", "unknown")),
            message=str(error.get("message", "")),
            field=error.get("field"),
            retry_after=retry_after,
            body=error,
        )
