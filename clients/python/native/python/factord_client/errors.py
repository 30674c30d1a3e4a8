"""The errors factord's clients raise: one family under :class:`FactordError`.

* :class:`FactordError` — an error answer of the service (``status``, ``code``, ``field``).
* :class:`FactordConnectionError` — the service could not be reached (after the retries that were
  safe); also an :class:`OSError` (``ConnectionError``), as before.
* :class:`FactordTimeout` — a client-side wait (``flush``, ``wait_acked``, a full window) ran out;
  also a ``TimeoutError``.
* :class:`BatchRefused` — a streamed batch of a producer was refused by the service; the producer
  stopped and raises this from its next call.
"""

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


class FactordConnectionError(FactordError, ConnectionError):
    """The service did not answer: connection refused or reset, a socket timeout, no zenoh
    queryable replied. ``status`` is ``None``; ``code`` is ``connection_failed`` (or
    ``no_reply`` over zenoh); ``attempts`` says how many times the request was sent."""

    def __init__(self, code: str, message: str, attempts: int = 1) -> None:
        super().__init__(None, code, message)
        self.attempts = attempts


class FactordTimeout(FactordError, TimeoutError):
    """A wait of the client ran out (``code`` ``timeout``), e.g. :meth:`flush` with batches
    still unacknowledged. Nothing is lost: the batches stay queued and are still resent."""

    def __init__(self, message: str) -> None:
        super().__init__(None, "timeout", message)


class BatchRefused(FactordError):
    """The service refused a producer's batch (validation, unknown session, ...): that batch and
    every later one of the producer were not applied (the later ones would follow it). Carries
    the service's error (``status``, ``code``, ``field``, ``message``) plus ``producer``,
    ``producer_seq`` (the refused batch's number), ``accepted_through`` (every batch up to it
    is applied) and ``unacked`` (the numbers not applied, in order)."""

    def __init__(self, error: FactordError, producer: str, producer_seq: int,
                 accepted_through: int, unacked: "list[int]") -> None:
        super().__init__(error.status, error.code, error.message, error.field,
                         error.retry_after, error.body)
        self.producer = producer
        self.producer_seq = producer_seq
        self.accepted_through = accepted_through
        self.unacked = list(unacked)

    def __str__(self) -> str:
        tail = (f"; batches {self.unacked[0]}..{self.unacked[-1]} not applied"
                if self.unacked else "")
        return (f"batch {self.producer_seq} of producer {self.producer} refused: "
                f"{self.status} {self.code}{' at ' + self.field if self.field else ''}: "
                f"{self.message} (applied through {self.accepted_through}{tail})")
