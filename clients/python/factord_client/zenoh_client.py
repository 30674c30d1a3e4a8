"""zenoh client for factord (needs ``eclipse-zenoh``, imported when a client is created).

Key expressions (``<p>`` is the prefix, ``factord`` by default):

* ``<p>/rpc`` — queryable: the payload is a command ``{"op": "create_session", ...}``; the reply
  is the command's answer or an error reply ``{"error": {...}}``.
* ``<p>/<session>/estimate`` — queryable with selector parameters ``since``, ``from``, ``to``.
* ``<p>/<session>/in/batch`` — put a batch here (no reply: the acknowledgement is published on
  ``out/acks``, a rejection on ``out/errors``); ``<p>/<session>/in/optimize`` — solve now.
* ``<p>/<session>/out/{acks,stats,poses,summary,errors}`` — the session's events (each may also
  carry a ``lagged`` marker when this subscriber fell behind and events were coalesced).

For streaming that survives lost acknowledgements, reconnections and restarts of the service,
use :meth:`ZenohClient.producer` (a :class:`~factord_client.stream_producer.StreamProducer`).
"""

from __future__ import annotations

import json
import sys
import threading
import time
from typing import Any, Callable, Dict, List, Optional, Union

from .errors import FactordConnectionError, FactordError

JsonDict = Dict[str, Any]

TOPICS = ("acks", "stats", "poses", "summary", "errors")

# Commands that may be sent again when no queryable answered (e.g. while factord restarts):
# reads, and commands whose repeat changes nothing more. A batch is safe only with
# producer + producer_seq; create_session and delete_session are not repeated.
_SAFE_OPS = frozenset({"health", "list_sessions", "get_stats", "get_estimate", "producer_status",
                       "optimize", "cancel", "set_auto_optimize", "get_graph", "get_marginals"})


def _zenoh() -> Any:
    try:
        import zenoh  # noqa: PLC0415 - lazy on purpose: the HTTP client works without zenoh
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "factord_client.zenoh_client needs the `eclipse-zenoh` package "
            "(pip install eclipse-zenoh==1.10.2)"
        ) from e
    return zenoh


class ZenohClient:
    """A zenoh session talking to factord.

    ``connect_endpoint``: where to connect, e.g. ``tcp/127.0.0.1:7447`` (factord's own zenoh
    listener or a zenoh router it is connected to); a list connects to several. ``mode``:
    ``client`` (default) or ``peer``. Multicast scouting is off: only the given endpoints are used.

    zenoh reconnects by itself when the link drops. A query that no queryable answered (factord
    away or restarting) is sent again for up to ``reconnect_wait`` seconds when it is safe to
    repeat (reads, ``optimize``, ``cancel``, ``set_auto_optimize``, ``producer_status``, batches
    with ``producer`` + ``producer_seq``); otherwise, or after that, it raises
    :class:`FactordConnectionError` (code ``no_reply``).
    """

    def __init__(
        self,
        connect_endpoint: Union[str, List[str]],
        prefix: str = "factord",
        mode: str = "client",
        timeout: float = 150.0,
        reconnect_wait: float = 10.0,
    ) -> None:
        zenoh = _zenoh()
        endpoints = [connect_endpoint] if isinstance(connect_endpoint, str) else list(connect_endpoint)
        config = zenoh.Config()
        config.insert_json5("mode", json.dumps(mode))
        config.insert_json5("connect/endpoints", json.dumps(endpoints))
        config.insert_json5("scouting/multicast/enabled", "false")
        if mode == "peer":
            # A peer does not need to listen for factord to reach it.
            config.insert_json5("listen/endpoints", "[]")
        self.prefix = prefix.rstrip("/") or "factord"
        self.timeout = timeout
        self.reconnect_wait = reconnect_wait
        self._zenoh = zenoh
        self._session = zenoh.open(config)
        self._subscribers: List[Any] = []
        self._lock = threading.Lock()

    # ----------------------------------------------------------------- queries
    def _query(self, selector: str, payload: Optional[bytes], timeout: Optional[float],
               safe: bool = True) -> Any:
        kwargs: JsonDict = {"timeout": self.timeout if timeout is None else timeout}
        if payload is not None:
            kwargs["payload"] = payload
        deadline = time.monotonic() + (self.reconnect_wait if safe else 0.0)
        attempt = 0
        while True:
            attempt += 1
            started = time.monotonic()
            replies = self._session.get(selector, **kwargs)
            for reply in replies:  # the first answer wins (there is one factord per prefix)
                ok = reply.ok
                if ok is not None:
                    return json.loads(ok.payload.to_bytes().decode("utf-8"))
                raise FactordError.from_body(reply.err.payload.to_bytes())
            # No answer at once: no queryable matched (not reachable now). An answer that did
            # not come within the timeout is not repeated (the request may be running).
            quick = time.monotonic() - started < 1.0
            if not quick or time.monotonic() >= deadline:
                raise FactordConnectionError(
                    "no_reply",
                    f"no zenoh queryable answered `{selector}` (is factord reachable with "
                    f"prefix `{self.prefix}`?)", attempts=attempt)
            time.sleep(min(0.05 * 2 ** attempt, 0.5))

    def rpc(self, command: JsonDict, timeout: Optional[float] = None) -> JsonDict:
        """Sends a command (``{"op": ..., ...}``) to ``<prefix>/rpc`` and returns its answer;
        an error reply raises :class:`FactordError` (with the status from the error body)."""
        batch = command.get("batch") if command.get("op") == "apply_batch" else None
        safe = command.get("op") in _SAFE_OPS or (
            isinstance(batch, dict) and "producer" in batch and "producer_seq" in batch)
        return self._query(f"{self.prefix}/rpc", json.dumps(command).encode("utf-8"), timeout,
                           safe=safe)

    # Convenience wrappers over rpc (same answers as the HTTP routes).
    def health(self) -> JsonDict:
        return self.rpc({"op": "health"})

    def list_sessions(self) -> JsonDict:
        return self.rpc({"op": "list_sessions"})

    def create_session(
        self,
        kind: str,
        session: Optional[str] = None,
        options: Optional[JsonDict] = None,
        auto_optimize: Union[None, str, JsonDict] = None,
        factor_types: Optional[list] = None,
    ) -> JsonDict:
        command: JsonDict = {"op": "create_session", "kind": kind}
        if session is not None:
            command["session"] = session
        if options is not None:
            command["options"] = options
        if auto_optimize is not None:
            command["auto_optimize"] = (
                {"policy": auto_optimize} if isinstance(auto_optimize, str) else auto_optimize
            )
        if factor_types:
            command["factor_types"] = factor_types
        return self.rpc(command)

    def define_factor_types(self, session: str, factor_types: list) -> JsonDict:
        """Declares more user-defined factor types in a running graph session (all or none);
        answers the session's info with every declared name."""
        return self.rpc({"op": "define_factor_types", "session": session, "factor_types": factor_types})

    def delete_session(self, session: str) -> JsonDict:
        return self.rpc({"op": "delete_session", "session": session})

    def apply_batch(self, session: str, batch: JsonDict, wait: bool = False) -> JsonDict:
        """A batch with an answer (``apply_batch`` over rpc), unlike :meth:`publish_batch`."""
        return self.rpc({"op": "apply_batch", "session": session, "batch": batch, "wait": wait})

    def optimize(self, session: str, wait: bool = False, after_producer: Optional[str] = None,
                 after_seq: Optional[int] = None, after_timeout_ms: Optional[int] = None,
                 timeout: Optional[float] = None) -> JsonDict:
        """rpc ``optimize``; with ``after_producer`` + ``after_seq`` the service first waits
        until that producer's batches through ``after_seq`` are applied."""
        command: JsonDict = {"op": "optimize", "session": session, "wait": wait}
        command.update(_after(after_producer, after_seq, after_timeout_ms))
        return self.rpc(command, timeout=timeout)

    def producer_status(self, session: str, producer: str,
                        timeout: Optional[float] = None) -> JsonDict:
        """rpc ``producer_status``: ``{"session", "producer", "accepted_through", "sequence",
        "reflected_sequence"}``."""
        return self.rpc({"op": "producer_status", "session": session, "producer": producer},
                        timeout=timeout)

    def producer(self, session: str, producer: Optional[str] = None, **options: Any) -> Any:
        """A :class:`~factord_client.stream_producer.StreamProducer` of ``session``: numbered,
        acknowledged, resent batches (``options``: ``window``, ``resend_after``, ``resume``,
        ``on_ack``, ...)."""
        from .stream_producer import StreamProducer  # noqa: PLC0415

        return StreamProducer(self, session, producer, **options)

    def stats(self, session: str) -> JsonDict:
        return self.rpc({"op": "get_stats", "session": session})

    def cancel(self, session: str) -> JsonDict:
        return self.rpc({"op": "cancel", "session": session})

    def set_auto_optimize(self, session: str, policy: Union[str, JsonDict], **params: Any) -> JsonDict:
        auto = {**policy, **params} if isinstance(policy, dict) else {"policy": policy, **params}
        return self.rpc({"op": "set_auto_optimize", "session": session, "auto_optimize": auto})

    def estimate(
        self,
        session: str,
        since: Optional[int] = None,
        from_key: Optional[int] = None,
        to_key: Optional[int] = None,
        timeout: Optional[float] = None,
        after_producer: Optional[str] = None,
        after_seq: Optional[int] = None,
        after_timeout_ms: Optional[int] = None,
    ) -> JsonDict:
        """Reads the estimate from the ``<prefix>/<session>/estimate`` queryable (selector
        parameters ``since``, ``from``, ``to``, and ``after_producer``/``after_seq``: first wait
        until that producer's batches through ``after_seq`` are applied)."""
        params = [f"{name}={int(value)}" for name, value in
                  (("since", since), ("from", from_key), ("to", to_key)) if value is not None]
        params += [f"{k}={v}" for k, v in
                   _after(after_producer, after_seq, after_timeout_ms).items()]
        selector = f"{self.prefix}/{session}/estimate"
        if params:
            selector += "?" + ";".join(params)
        return self._query(selector, None, timeout)

    # ----------------------------------------------------------------- streams
    def publish_batch(self, session: str, batch: JsonDict) -> None:
        """Puts a batch on ``<prefix>/<session>/in/batch`` (fire and forget: watch ``out/acks``
        and ``out/errors``)."""
        # Block rather than drop when the link is congested: a lost batch would make every later
        # batch that refers to its variables fail.
        self._session.put(f"{self.prefix}/{session}/in/batch", json.dumps(batch).encode("utf-8"),
                          congestion_control=self._zenoh.CongestionControl.BLOCK)

    def publish_optimize(self, session: str) -> None:
        """Puts on ``<prefix>/<session>/in/optimize``: solve now."""
        self._session.put(f"{self.prefix}/{session}/in/optimize", b"{}",
                          congestion_control=self._zenoh.CongestionControl.BLOCK)

    def subscribe(self, session: str, topic: str, callback: Callable[[JsonDict], None]) -> Any:
        """Calls ``callback(event)`` for every publication on ``<prefix>/<session>/out/<topic>``
        (``topic``: acks, stats, poses, summary, errors, or ``*`` for all; the event's ``type``
        field tells them apart). The callback runs on a zenoh thread; exceptions are printed.
        Returns the subscriber (undeclared by :meth:`close`, or call its ``undeclare()``)."""
        key = f"{self.prefix}/{session}/out/{topic}"

        def on_sample(sample: Any) -> None:
            try:
                event = json.loads(sample.payload.to_bytes().decode("utf-8"))
                callback(event)
            except Exception as e:  # noqa: BLE001 - never let an exception kill zenoh's thread
                print(f"factord_client: subscriber of {key}: {e!r}", file=sys.stderr)

        subscriber = self._session.declare_subscriber(key, on_sample)
        with self._lock:
            self._subscribers.append(subscriber)
        return subscriber

    def close(self) -> None:
        """Undeclares the subscribers and closes the zenoh session."""
        with self._lock:
            subscribers, self._subscribers = self._subscribers, []
        for s in subscribers:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001
                pass
        self._session.close()

    def __enter__(self) -> "ZenohClient":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _after(producer: Optional[str], seq: Optional[int],
           timeout_ms: Optional[int]) -> JsonDict:
    if producer is None or seq is None:
        return {}
    out: JsonDict = {"after_producer": producer, "after_seq": int(seq)}
    if timeout_ms is not None:
        out["after_timeout_ms"] = int(timeout_ms)
    return out
