"""A zenoh producer that recovers: numbered batches, kept until acknowledged, resent after a
timeout, a reconnection or a restart of the service, stopped by a refusal.

Made by :meth:`ZenohClient.producer`; see the package README ("Recovery") for the semantics.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections import OrderedDict
from typing import Any, Callable, Dict, List, Optional

from .errors import BatchRefused, FactordConnectionError, FactordError, FactordTimeout
from .producer import check_producer_id, default_producer_id, stamp

JsonDict = Dict[str, Any]

# Error codes of a batch that say "send again later", not "this batch is wrong".
_TRANSIENT_STATUS = (429, 503)
_GAP = "producer_sequence_gap"
# Refusals that end within milliseconds (a recovery, a fleet move): retried after _BRIEF_RETRY
# seconds rather than their whole-second Retry-After.
_BRIEF_UNAVAILABLE = ("recovering", "session_moving", "ownership_lost")
_BRIEF_RETRY = 0.05
_FORGOTTEN = "producer_sequence_forgotten"


class _Pending:
    __slots__ = ("payload", "last_sent", "attempts")

    def __init__(self, payload: bytes, now: float) -> None:
        self.payload = payload
        self.last_sent = now
        self.attempts = 0


class StreamProducer:
    """Publishes one producer's batches on ``<prefix>/<session>/in/batch`` exactly once.

    Every batch gets ``producer`` and ``producer_seq`` (1, 2, ... after what the service already
    has for this producer when ``resume``) and stays in memory until an acknowledgement on
    ``out/acks`` (or a ``lagged`` marker) says that the service's cumulative
    ``accepted_through`` reached it. Unacknowledged batches are sent again, in order:

    * when the zenoh link to the service changed (a reconnection, a restarted service);
    * when the service reports a gap (``producer_sequence_gap``: it lost or skipped some);
    * after ``resend_after`` seconds without acknowledgement and without progress (doubling per
      attempt up to ``max_resend_after``), after asking ``producer_status`` whether they were
      applied and only their acknowledgements got lost;
    * after ``Retry-After`` when the service refused one for load (429/503).

    A repeat is never applied twice (the service answers it with the original acknowledgement,
    ``"duplicate": true``). Any other refusal of a batch stops the producer: the next call
    raises :class:`BatchRefused` naming the batch and the error. So does a ``duplicate`` answer
    to a batch published only once (code ``producer_conflict``): another sender uses the same
    producer id, and the service kept its batch under that number instead of ours.

    ``window``: at most this many unacknowledged batches; :meth:`send` blocks while it is full
    (back-pressure: a robot slows down instead of buffering without bound while the service is
    away). Publications use ``CongestionControl.BLOCK`` and reliable reliability.
    ``on_ack(event)`` is called (on a zenoh thread) for every acknowledgement of this producer.
    """

    def __init__(
        self,
        client: Any,
        session: str,
        producer: Optional[str] = None,
        *,
        window: int = 1024,
        resend_after: float = 2.0,
        max_resend_after: float = 30.0,
        resume: bool = True,
        status_timeout: float = 5.0,
        on_ack: Optional[Callable[[JsonDict], None]] = None,
    ) -> None:
        zenoh = client._zenoh
        self.client = client
        self.session = session
        self.producer = check_producer_id(producer) if producer else default_producer_id(session)
        self.window = max(1, int(window))
        self.resend_after = resend_after
        self.max_resend_after = max_resend_after
        self.status_timeout = status_timeout
        self._on_ack = on_ack
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._pub_lock = threading.Lock()  # puts in number order
        self._unacked: "OrderedDict[int, _Pending]" = OrderedDict()
        self._failure: Optional[BatchRefused] = None
        self._settling = False  # a refusal's accepted_through is being asked from the service
        self._resync = False  # level-triggered: a resend of everything unacknowledged is due
        self._not_before = 0.0  # no resend before (Retry-After of a 429/503)
        self._last_resync = 0.0
        self._checked_through = 0  # accepted_through at the last timeout check (progress?)
        self._last_status_error: Optional[str] = None
        self._closed = False
        self.counters: Dict[str, int] = {
            "sent": 0,  # batches handed to send()
            "acked": 0,  # of those, acknowledged (cumulatively)
            "resent": 0,  # publications again of unacknowledged batches
            "duplicates": 0,  # acknowledgements marked duplicate (a repeat that applied nothing)
            "acks": 0,  # acknowledgement events of this producer received
            "lagged": 0,  # lagged markers received on out/acks
            "resyncs": 0,  # resends of the unacknowledged tail
            "reconnects": 0,  # zenoh link changes seen
            "status_queries": 0,
        }
        self.accepted_through = 0
        if resume:
            status = client.producer_status(session, self.producer, timeout=status_timeout)
            self.accepted_through = int(status.get("accepted_through", 0))
        self._checked_through = self.accepted_through
        self.last_seq = self.accepted_through
        self._first_seq = self.accepted_through + 1
        try:
            self._publisher = client._session.declare_publisher(
                f"{client.prefix}/{session}/in/batch",
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
        except Exception as e:  # noqa: BLE001 - zenoh.ZError: the client's session is closed
            raise FactordConnectionError("connection_failed",
                                         f"zenoh publisher for {session}: {e}") from None
        self._subscribers = [
            client.subscribe(session, "acks", self._on_acks_topic),
            client.subscribe(session, "errors", self._on_errors_topic),
        ]
        self._links = self._link_ids()
        self._thread = threading.Thread(target=self._run, name=f"factord-producer-{session}",
                                        daemon=True)
        self._thread.start()

    # ----------------------------------------------------------------- public
    def send(self, batch: JsonDict, timeout: Optional[float] = None) -> int:
        """Publishes ``batch`` as the next number and returns that ``producer_seq``. Blocks while
        ``window`` batches are unacknowledged (``timeout`` seconds at most, then
        :class:`FactordTimeout`). Raises :class:`BatchRefused` once a batch was refused."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while True:
                self._raise_failure()
                if self._closed:
                    raise FactordError(None, "closed", "the producer is closed")
                if len(self._unacked) < self.window:
                    break
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    raise FactordTimeout(
                        f"window of {self.window} unacknowledged batches still full after "
                        f"{timeout} s (accepted through {self.accepted_through}"
                        f"{self._status_note()})")
                self._cond.wait(0.5 if left is None else min(left, 0.5))
        with self._pub_lock:
            with self._lock:
                seq = self.last_seq + 1
                self.last_seq = seq
                payload = json.dumps(stamp(batch, self.producer, seq)).encode("utf-8")
                self._unacked[seq] = _Pending(payload, time.monotonic())
                self.counters["sent"] += 1
            try:
                self._publisher.put(payload)
            except Exception as e:  # noqa: BLE001 - zenoh.ZError; the batch stays queued
                raise FactordConnectionError("connection_failed",
                                             f"zenoh put of batch {seq}: {e}") from None
        return seq

    def wait_acked(self, seq: int, timeout: Optional[float] = None) -> int:
        """Waits until batch ``seq`` (and so every earlier one) is acknowledged; returns
        ``accepted_through``. Raises :class:`FactordTimeout` after ``timeout`` seconds and
        :class:`BatchRefused` when a batch was refused."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while True:
                if self.accepted_through >= seq:
                    return self.accepted_through
                self._raise_failure()
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    raise FactordTimeout(
                        f"batch {seq} of producer {self.producer} not acknowledged after "
                        f"{timeout} s (accepted through {self.accepted_through}, "
                        f"{len(self._unacked)} unacknowledged{self._status_note()})")
                self._cond.wait(0.5 if left is None else min(left, 0.5))

    def flush(self, timeout: Optional[float] = None) -> int:
        """Waits until every batch sent so far is acknowledged (see :meth:`wait_acked`)."""
        with self._lock:
            last = self.last_seq
        return self.wait_acked(last, timeout)

    @property
    def unacked(self) -> List[int]:
        """The numbers of the batches not acknowledged yet, in order."""
        with self._lock:
            return list(self._unacked)

    def unacked_batches(self) -> List[JsonDict]:
        """The batches not acknowledged yet (as sent, with ``producer``/``producer_seq``), e.g.
        to inspect or fix them after a :class:`BatchRefused`."""
        with self._lock:
            return [json.loads(p.payload) for p in self._unacked.values()]

    def optimize(self, wait: bool = True, timeout: float = 120.0) -> JsonDict:
        """rpc ``optimize`` that first waits (on the service) for every batch sent so far, so it
        never overtakes them; retried while the service reports ``after_timeout`` and this
        producer is still resending, for at most ``timeout`` seconds."""
        return self._after(timeout, lambda after, left: self.client.optimize(
            self.session, wait=wait, timeout=left, **after))

    def estimate(self, timeout: float = 120.0, **kwargs: Any) -> JsonDict:
        """The estimate (``since``, ``from_key``, ``to_key``) once every batch sent so far is
        applied."""
        return self._after(timeout, lambda after, left: self.client.estimate(
            self.session, timeout=left, **after, **kwargs))

    def close(self) -> None:
        """Stops resending and undeclares the subscriptions (unacknowledged batches are
        dropped from memory: :meth:`flush` first to be sure)."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        self._thread.join(timeout=5)
        for s in self._subscribers:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001 - closing
                pass
        try:
            self._publisher.undeclare()
        except Exception:  # noqa: BLE001
            pass

    def __enter__(self) -> "StreamProducer":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ----------------------------------------------------------------- events (zenoh threads)
    def _on_acks_topic(self, event: JsonDict) -> None:
        kind = event.get("type")
        if kind == "ack" and event.get("producer") == self.producer:
            through = event.get("accepted_through") or event.get("producer_seq") or 0
            seq = int(event.get("producer_seq") or 0)
            with self._cond:
                self.counters["acks"] += 1
                if event.get("duplicate"):
                    self.counters["duplicates"] += 1
                    pending = self._unacked.get(seq)
                    if pending is not None and pending.attempts == 0 and self._failure is None:
                        # Published once, yet the service had that number already: another
                        # sender uses this producer id (or an earlier run, with resume=False).
                        # Its batch was applied instead of ours: stop before losing more.
                        self._failure = BatchRefused(
                            FactordError(409, "producer_conflict",
                                         f"producer id {self.producer} is used by another "
                                         "sender: the service already had this number"),
                            self.producer, seq, int(through),
                            [s for s in self._unacked if s >= seq])
                        self._cond.notify_all()
                        return
                self._advance(int(through))
            if self._on_ack is not None:
                self._on_ack(event)
        elif kind == "lagged":
            through = (event.get("producers") or {}).get(self.producer)
            with self._cond:
                self.counters["lagged"] += 1
                if through:
                    self._advance(int(through))

    def _on_errors_topic(self, event: JsonDict) -> None:
        if event.get("type") != "error" or event.get("producer") != self.producer:
            return
        seq = int(event.get("producer_seq") or 0)
        body = event.get("error") or {}
        error = FactordError(body.get("status"), str(body.get("code", "unknown")),
                             str(body.get("message", "")), body.get("field"),
                             body.get("retry_after"), body)
        with self._cond:
            if self._failure is not None or seq <= self.accepted_through:
                return  # stale: about a batch acknowledged since
            if error.code == _FORGOTTEN:
                self._advance(seq)  # a repeat of a batch applied long ago
            elif error.code == _GAP:
                self._resync = True  # the service misses earlier ones: send them again
            elif error.status in _TRANSIENT_STATUS:
                self._resync = True
                # A session recovering or moving between fleet instances is back within
                # milliseconds; Retry-After counts whole seconds, so these retry sooner.
                wait = float(error.retry_after or 1.0)
                if error.code in _BRIEF_UNAVAILABLE:
                    wait = min(wait, _BRIEF_RETRY)
                self._not_before = time.monotonic() + wait
            elif seq in self._unacked:
                self._failure = BatchRefused(error, self.producer, seq, self.accepted_through,
                                             [s for s in self._unacked if s >= seq])
                self._settling = True  # acks of earlier batches may still be on their way
            self._cond.notify_all()

    def _advance(self, through: int) -> None:
        """Under the lock: every batch up to ``through`` is applied."""
        if through <= self.accepted_through:
            return
        self.accepted_through = through
        while self._unacked:
            first = next(iter(self._unacked))
            if first > through:
                break
            del self._unacked[first]
            self.counters["acked"] += 1
        self._cond.notify_all()

    def _raise_failure(self) -> None:
        """Under the lock: raises the refusal, once its numbers are settled (see _settle)."""
        if self._failure is None:
            return
        deadline = time.monotonic() + self.status_timeout + 1.0
        while self._settling and time.monotonic() < deadline:
            self._cond.wait(0.1)
        raise self._failure

    def _settle(self) -> None:
        """After a refusal: asks the service how far this producer's batches are applied (acks
        of the batches before the refused one travel separately and may come later), so the
        exception names exactly what was applied and what was not."""
        try:
            status = self.client.producer_status(self.session, self.producer,
                                                 timeout=self.status_timeout)
        except FactordError:
            status = None
        with self._cond:
            if status is not None:
                self._advance(int(status.get("accepted_through", 0)))
            failure = self._failure
            if failure is not None:
                failure.accepted_through = self.accepted_through
                failure.unacked = list(self._unacked)
            self._settling = False
            self._cond.notify_all()

    def _status_note(self) -> str:
        return f"; last status query: {self._last_status_error}" if self._last_status_error else ""

    # ----------------------------------------------------------------- resending (own thread)
    def _after(self, timeout: float, call: Callable[[JsonDict, float], JsonDict]) -> JsonDict:
        deadline = time.monotonic() + timeout
        while True:
            with self._lock:
                self._raise_failure()
                after = {"after_producer": self.producer, "after_seq": self.last_seq}
            left = deadline - time.monotonic()
            try:
                return call(after, max(left, 1.0))
            except FactordError as e:
                if e.code != "after_timeout" or time.monotonic() + 1.0 > deadline:
                    with self._lock:
                        self._raise_failure()
                    raise
                time.sleep(min(float(e.retry_after or 1.0), 1.0))

    def _link_ids(self) -> frozenset:
        try:
            info = self.client._session.info
            return frozenset(str(z) for z in list(info.routers_zid()) + list(info.peers_zid()))
        except Exception:  # noqa: BLE001 - a closing session
            return frozenset()

    def _run(self) -> None:
        next_link_check = 0.0
        while True:
            with self._cond:
                if self._closed:
                    return
                self._cond.wait(0.05)
                if self._closed:
                    return
            now = time.monotonic()
            if now >= next_link_check:
                next_link_check = now + 0.1
                links = self._link_ids()
                if links - self._links:  # a (re)connection to a node: perhaps a new service
                    with self._lock:
                        self.counters["reconnects"] += 1
                        self._resync = True
                self._links = links
            try:
                self._step(now)
            except Exception as e:  # noqa: BLE001 - the thread must survive anything
                print(f"factord_client: producer {self.producer}: {e!r}", file=sys.stderr)
                time.sleep(0.5)

    def _timeout_of(self, pending: _Pending) -> float:
        return min(self.resend_after * (2 ** min(pending.attempts, 8)), self.max_resend_after)

    def _step(self, now: float) -> None:
        if self._settling:
            self._settle()
        with self._lock:
            if self._failure is not None or not self._unacked:
                self._resync = False
                return
            oldest = next(iter(self._unacked.values()))
            forced = self._resync and now >= self._not_before and now - self._last_resync >= 0.2
            timed_out = now >= oldest.last_sent + self._timeout_of(oldest)
            if not (forced or timed_out):
                return
            self._last_resync = now
        # Where does the service stand? (Its acknowledgements may be what was lost.)
        self.counters["status_queries"] += 1
        try:
            status = self.client.producer_status(self.session, self.producer,
                                                 timeout=self.status_timeout)
        except FactordError as e:
            with self._lock:
                self._last_status_error = str(e)
                for p in self._unacked.values():  # back off: try again after the timeout
                    p.last_sent = now
                    p.attempts += 1
            return
        with self._cond:
            self._last_status_error = None
            self._advance(int(status.get("accepted_through", 0)))
            if not forced and self.accepted_through > self._checked_through:
                # Not stalled: the service is working through them, just slower than the timer.
                self._checked_through = self.accepted_through
                for p in self._unacked.values():
                    p.last_sent = now
                return
            self._checked_through = self.accepted_through
            self._resync = False
            tail = list(self._unacked.items())
        if not tail:
            return
        with self._pub_lock:
            self.counters["resyncs"] += 1
            for seq, p in tail:
                with self._lock:
                    if seq not in self._unacked or self._failure is not None:
                        continue
                    p.last_sent = time.monotonic()
                    p.attempts += 1
                    self.counters["resent"] += 1
                self._publisher.put(p.payload)
