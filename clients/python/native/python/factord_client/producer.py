"""Exactly-once batches over HTTP: a producer id and a counter on every batch.

The service keeps, per session and producer, ``accepted_through``: every batch of that producer
numbered up to it is applied. A batch numbered ``accepted_through + 1`` is applied; a repeat
(a smaller number) applies nothing and is answered with the original acknowledgement and
``"duplicate": true``; a larger number is refused (409 ``producer_sequence_gap``). So a batch
whose answer was lost can be sent again safely, as often as needed.
"""

from __future__ import annotations

import re
import socket
from typing import Any, Dict, Optional, Tuple

from .batch import as_batch
from .errors import BatchRefused, FactordConnectionError, FactordError

JsonDict = Dict[str, Any]

_INVALID = re.compile(r"[^A-Za-z0-9._-]+")


def default_producer_id(session: str) -> str:
    """``<hostname>-<session>`` reduced to the producer alphabet (``[A-Za-z0-9._-]``, at most
    64 characters): stable across restarts of the same robot program on the same machine."""
    raw = f"{socket.gethostname() or 'host'}-{session}"
    return check_producer_id(_INVALID.sub("-", raw).strip("-")[:64] or "producer")


def check_producer_id(producer: str) -> str:
    if not (1 <= len(producer) <= 64) or _INVALID.search(producer):
        raise ValueError(f"producer id {producer!r}: 1..64 characters of [A-Za-z0-9._-]")
    return producer


def stamp(batch: Any, producer: str, seq: int) -> JsonDict:
    """A copy of ``batch`` (a dict, numpy values allowed, or a :class:`Batch`) with
    ``producer`` and ``producer_seq``."""
    return {**as_batch(batch), "producer": producer, "producer_seq": seq}


class HttpProducer:
    """Numbers the batches of one producer on one session and sends them over HTTP.

    ``send(batch)`` stamps the next ``producer_seq`` and posts it; the HTTP client resends it
    after a connection failure, a 429 or a 503 (bounded by its retry settings), which is safe.
    When the retries run out, ``send`` raises :class:`FactordConnectionError` and keeps the batch:
    the next ``send`` or :meth:`flush` delivers it first, under the same number, so it is applied
    exactly once whether or not the lost attempt reached the service. A refusal (4xx) does not
    use up the number: the batch is dropped and the error raised; the next batch takes that
    number.

    A ``duplicate`` answer to a batch sent once (no retry) raises :class:`BatchRefused` with
    code ``producer_conflict``: another sender uses the same producer id.

    ``resume`` (default): start after the producer's ``accepted_through`` on the service, so a
    restarted program that keeps its producer id continues the numbering instead of having its
    new batches taken for repeats of old ones.
    """

    def __init__(self, client: Any, session: str, producer: Optional[str] = None,
                 resume: bool = True) -> None:
        self.client = client
        self.session = session
        self.producer = check_producer_id(producer) if producer else default_producer_id(session)
        self.accepted_through = 0
        if resume:
            status = client.producer_status(session, self.producer)
            self.accepted_through = int(status.get("accepted_through", 0))
        self.next_seq = self.accepted_through + 1
        self._pending: Optional[Tuple[int, JsonDict, bool]] = None
        self.counters = {"sent": 0, "acked": 0, "duplicates": 0, "retried_sends": 0}

    @property
    def last_seq(self) -> int:
        """The number of the last batch handed to :meth:`send` (0: none)."""
        return self.next_seq - 1

    def _post(self, seq: int, batch: JsonDict, wait: bool, fresh: bool = False) -> JsonDict:
        retried_before = self.client.retried
        try:
            ack = self.client.apply_batch(self.session, stamp(batch, self.producer, seq),
                                          wait=wait)
        except FactordConnectionError:
            self._pending = (seq, batch, wait)
            raise
        except FactordError:
            self._pending = None
            raise
        self._pending = None
        if ack.get("duplicate") and fresh and self.client.retried == retried_before:
            # Sent once, yet the service had the number: another sender uses this producer id
            # (or an earlier run, with resume=False); its batch holds the number, not ours.
            raise BatchRefused(
                FactordError(409, "producer_conflict",
                             f"producer id {self.producer} is used by another sender: the "
                             f"service already had batch {seq}"),
                self.producer, seq, int(ack.get("accepted_through", seq)), [seq])
        self.counters["acked"] += 1
        if ack.get("duplicate"):
            self.counters["duplicates"] += 1
        self.accepted_through = max(self.accepted_through,
                                    int(ack.get("accepted_through", seq)))
        return ack

    def flush(self) -> Optional[JsonDict]:
        """Delivers the batch kept by a failed :meth:`send` (if any) and returns its ack."""
        if self._pending is None:
            return None
        seq, batch, wait = self._pending
        self.counters["retried_sends"] += 1
        return self._post(seq, batch, wait)

    def send(self, batch: JsonDict, wait: bool = False) -> JsonDict:
        """Sends ``batch`` as the next number and returns its acknowledgement."""
        self.flush()
        seq = self.next_seq
        self.counters["sent"] += 1
        try:
            ack = self._post(seq, batch, wait, fresh=True)
        except FactordConnectionError:
            self.next_seq += 1  # kept as pending under this number
            raise
        except FactordError:
            self.counters["sent"] -= 1  # refused: the number is not used
            raise
        self.next_seq += 1
        return ack

    def optimize(self, wait: bool = True, after_timeout_ms: Optional[int] = None) -> JsonDict:
        """``optimize`` after every batch sent so far is applied."""
        self.flush()
        return self.client.optimize(self.session, wait=wait, after_producer=self.producer,
                                    after_seq=self.last_seq, after_timeout_ms=after_timeout_ms)

    def estimate(self, **kwargs: Any) -> JsonDict:
        """The estimate once every batch sent so far is applied."""
        self.flush()
        return self.client.estimate(self.session, after_producer=self.producer,
                                    after_seq=self.last_seq, **kwargs)
