"""zenoh client for factord (needs ``eclipse-zenoh``, imported when a client is created).

Key expressions (``<p>`` is the prefix, ``factord`` by default):

* ``<p>/rpc`` — queryable: the payload is a command ``{"op": "create_session", ...}``; the reply
  is the command's answer or an error reply ``{"error": {...}}``.
* ``<p>/<session>/estimate`` — queryable with selector parameters ``since``, ``from``, ``to``.
* ``<p>/<session>/in/batch`` — put a batch here (no reply: the acknowledgement is published on
  ``out/acks``, a rejection on ``out/errors``); ``<p>/<session>/in/optimize`` — solve now.
* ``<p>/<session>/out/{acks,stats,poses,summary,errors}`` — the session's events (each may also
  carry a ``lagged`` marker when this subscriber fell behind and events were coalesced).
* ``<p>/<session>/bin/poses`` — the estimates of ``out/poses`` in binary, read into numpy arrays
  (:meth:`ZenohClient.subscribe_binary_poses`, layout in ``proto/v1/poses-binary.md``).

For streaming that survives lost acknowledgements, reconnections and restarts of the service,
use :meth:`ZenohClient.producer` (a :class:`~factord_client.stream_producer.StreamProducer`).

**A forgotten** :meth:`ZenohClient.close` **does not keep the process alive.** zenoh-python runs
a Python callback on a non-daemon thread of its own, which the interpreter waits for at exit
(before ``atexit`` handlers run): a script that subscribed and forgot ``close()`` hung. Here
zenoh's receiving thread only appends each sample to a queue (a direct callback, no thread of
zenoh-python's), a *daemon* thread of ours calls the user's callback, and a ``weakref.finalize``
closes the zenoh session when the client is garbage-collected or the interpreter exits. (A
FIFO channel read by our thread would do too, but undeclaring it while the thread waits in
``recv()`` fails with "Already borrowed".)
"""

from __future__ import annotations

import json
import queue
import sys
import threading
import time
import weakref
from typing import Any, Callable, Dict, Iterable, List, Optional, Tuple, Union

import numpy as np

from . import poses_binary, wire
from .http import auto_optimize_policy
from .robots import robot_id
from .batch import Batch, EstimateArray, as_batch, dumps, estimate_to_array, marginals_to_arrays
from .errors import FactordConnectionError, FactordError
from .geometry import AnyPose

JsonDict = Dict[str, Any]
BatchLike = Union[Batch, wire.Batch, JsonDict]
_END = object()  # queued when zenoh drops the subscriber: the draining thread stops

TOPICS = ("acks", "stats", "poses", "summary", "errors")

# Commands that may be sent again when no queryable answered (e.g. while factord restarts):
# reads, and commands whose repeat changes nothing more. A batch is safe only with
# producer + producer_seq; create_session and delete_session are not repeated.
_SAFE_OPS = frozenset({"health", "list_sessions", "get_stats", "get_estimate", "producer_status",
                       "optimize", "cancel", "set_auto_optimize", "get_graph", "get_marginals"})


def _zenoh_failure(what: str, error: BaseException) -> FactordConnectionError:
    """zenoh's own exceptions (``ZError``, a closed session) as the client's error family."""
    return FactordConnectionError("connection_failed", f"zenoh {what}: {error}")


#: Events a subscription holds for a callback that has not caught up (see :class:`Subscription`).
MAX_PENDING = 10_000


class Subscription:
    """One subscriber: zenoh's thread queues each sample, a daemon thread calls the callback for
    each, in order. :meth:`undeclare` stops both (also called by :meth:`ZenohClient.close`).

    The queue holds at most ``max_pending`` events. zenoh's thread never waits for Python code
    (it would stall every subscriber of the session), so when the callback falls that far
    behind, newer events are dropped and counted in :attr:`dropped`; the callback then gets,
    where the gap is (before the next event that fits), a marker ``{"type": "lagged",
    "skipped": n, "source": "client"}`` like the service's own ``lagged`` (which this client
    passes on as it comes, without ``source``), so a consumer can resynchronise (e.g. read the
    estimate) instead of missing a silent gap."""

    def __init__(self, session: Any, zenoh: Any, key: str,
                 callback: Callable[[JsonDict], None], max_pending: int = MAX_PENDING,
                 decode: Callable[[bytes], JsonDict] = lambda b: json.loads(b.decode("utf-8"))
                 ) -> None:
        self.key = key
        self._decode = decode
        self.dropped = 0  # events dropped because the queue was full
        self._skipped = 0  # dropped since the last event that got into the queue
        self._offer_lock = threading.Lock()  # zenoh may call from more than one thread
        self._callback = callback
        self._undeclared = False
        self._queue: "queue.Queue[Any]" = queue.Queue(maxsize=max_pending)
        handler = zenoh.handlers.Callback(self._offer, drop=lambda: self._offer(_END),
                                          indirect=False)
        self._subscriber = session.declare_subscriber(key, handler)
        self._thread = threading.Thread(target=self._drain, name=f"factord-sub-{key}",
                                        daemon=True)
        self._thread.start()

    def _offer(self, item: Any) -> None:
        """Queues without waiting, with the number of samples dropped just before it; a full
        queue drops the sample (``_END`` need not get in: a full queue means the draining
        thread is not waiting, and it checks ``_undeclared``)."""
        with self._offer_lock:
            try:
                self._queue.put_nowait((item, self._skipped))
                self._skipped = 0
            except queue.Full:
                if item is not _END:
                    self.dropped += 1
                    self._skipped += 1

    def _drain(self) -> None:
        while True:
            sample, skipped_before = self._queue.get()
            if sample is _END or self._undeclared:
                return
            if skipped_before:
                self._call({"type": "lagged", "skipped": skipped_before, "source": "client"})
            try:
                event = self._decode(sample.payload.to_bytes())
            except Exception as e:  # noqa: BLE001 - unreadable: reported, the stream goes on
                print(f"factord_client: subscriber of {self.key}: {e!r}", file=sys.stderr)
                continue
            self._call(event)

    def _call(self, event: JsonDict) -> None:
        try:
            self._callback(event)
        except Exception as e:  # noqa: BLE001 - a failing callback must not end the stream
            print(f"factord_client: subscriber of {self.key}: {e!r}", file=sys.stderr)

    def undeclare(self) -> None:
        if self._undeclared:
            return
        self._undeclared = True
        try:
            self._subscriber.undeclare()
        except Exception:  # noqa: BLE001 - the session may be closed already
            pass
        self._offer(_END)
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=1.0)


def _close_session(session: Any, subscriptions: List[Subscription], lock: threading.Lock) -> None:
    """Undeclares the subscriptions and closes the session. Run once: by ``close()``, when the
    client is garbage-collected, or at interpreter exit (``weakref.finalize``)."""
    with lock:
        pending, subscriptions[:] = list(subscriptions), []
    for subscription in pending:
        subscription.undeclare()
    try:
        session.close()
    except Exception:  # noqa: BLE001 - closing twice or during shutdown
        pass


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
        user: Optional[str] = None,
        password: Optional[str] = None,
        config_file: Optional[str] = None,
    ) -> None:
        """``user`` / ``password``: zenoh's own user-password authentication (the server's
        ``--zenoh-config`` with ``transport/auth/usrpwd``; HTTP bearer tokens do not apply to
        zenoh). ``config_file``: a zenoh JSON5 configuration to start from (TLS, ...)."""
        zenoh = _zenoh()
        endpoints = [connect_endpoint] if isinstance(connect_endpoint, str) else list(connect_endpoint)
        try:
            config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
            config.insert_json5("mode", json.dumps(mode))
            config.insert_json5("connect/endpoints", json.dumps(endpoints))
            config.insert_json5("scouting/multicast/enabled", "false")
            if mode == "peer":
                # A peer does not need to listen for factord to reach it.
                config.insert_json5("listen/endpoints", "[]")
            if user is not None and password is not None:
                config.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
                config.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
            session = zenoh.open(config)
        except Exception as e:  # noqa: BLE001 - zenoh.ZError and configuration errors
            raise _zenoh_failure(f"session to {endpoints}", e) from None
        self.prefix = prefix.rstrip("/") or "factord"
        self.timeout = timeout
        self.reconnect_wait = reconnect_wait
        self._zenoh = zenoh
        self._session = session
        self._subscriptions: List[Subscription] = []
        self._lock = threading.Lock()
        # Holds no reference to self, so an unreferenced client is collected and closed.
        self._finalizer = weakref.finalize(self, _close_session, session, self._subscriptions,
                                           self._lock)

    @property
    def closed(self) -> bool:
        return not self._finalizer.alive

    def _check_open(self) -> None:
        if self.closed:
            raise FactordError(None, "closed", "this ZenohClient is closed")

    # ----------------------------------------------------------------- queries
    def _query(self, selector: str, payload: Optional[bytes], timeout: Optional[float],
               safe: bool = True, text: bool = False) -> Any:
        """The first reply's payload: parsed JSON, or the text with ``text``."""
        self._check_open()
        kwargs: JsonDict = {"timeout": self.timeout if timeout is None else timeout}
        if payload is not None:
            kwargs["payload"] = payload
        deadline = time.monotonic() + (self.reconnect_wait if safe else 0.0)
        attempt = 0
        while True:
            attempt += 1
            started = time.monotonic()
            try:
                # The first answer wins (there is one factord per prefix): no waiting for the
                # query to end.
                reply = next(iter(self._session.get(selector, **kwargs)), None)
            except Exception as e:  # noqa: BLE001 - ZError, a session closed meanwhile
                raise _zenoh_failure(f"query `{selector}`", e) from None
            if reply is not None:
                ok = reply.ok
                if ok is not None:
                    return _decode(ok.payload.to_bytes(), selector, text)
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

    def rpc(self, command: JsonDict, timeout: Optional[float] = None) -> Any:
        """Sends a command (``{"op": ..., ...}``) to ``<prefix>/rpc`` and returns its answer;
        an error reply raises :class:`FactordError` (with the status from the error body).
        numpy arrays, poses and :class:`Batch` objects may appear in the command."""
        batch = command.get("batch") if command.get("op") == "apply_batch" else None
        safe = command.get("op") in _SAFE_OPS or (
            isinstance(batch, dict) and "producer" in batch and "producer_seq" in batch)
        return self._query(f"{self.prefix}/rpc", dumps(command).encode("utf-8"), timeout,
                           safe=safe)

    # Convenience wrappers over rpc (same answers as the HTTP routes).
    def health(self) -> wire.Health:
        return self.rpc({"op": "health"})

    def list_sessions(self) -> wire.SessionList:
        return self.rpc({"op": "list_sessions"})

    def create_session(
        self,
        kind: str,
        session: Optional[str] = None,
        options: Optional[JsonDict] = None,
        auto_optimize: Union[None, str, JsonDict] = None,
        factor_types: Optional[list] = None,
    ) -> wire.SessionInfo:
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

    def define_factor_types(self, session: str, factor_types: list) -> wire.SessionInfo:
        """Declares more user-defined factor types in a running graph session (all or none);
        answers the session's info with every declared name."""
        return self.rpc({"op": "define_factor_types", "session": session, "factor_types": factor_types})

    def delete_session(self, session: str) -> JsonDict:
        return self.rpc({"op": "delete_session", "session": session})

    def apply_batch(self, session: str, batch: BatchLike, wait: bool = False) -> wire.BatchAck:
        """A batch with an answer (``apply_batch`` over rpc), unlike :meth:`publish_batch`;
        a dict (numpy values allowed) or a :class:`Batch`."""
        return self.rpc({"op": "apply_batch", "session": session, "batch": as_batch(batch),
                         "wait": wait})

    def optimize(self, session: str, wait: bool = False, after_producer: Optional[str] = None,
                 after_seq: Optional[int] = None, after_timeout_ms: Optional[int] = None,
                 timeout: Optional[float] = None) -> wire.OptimizeAnswer:
        """rpc ``optimize``; with ``after_producer`` + ``after_seq`` the service first waits
        until that producer's batches through ``after_seq`` are applied."""
        command: JsonDict = {"op": "optimize", "session": session, "wait": wait}
        command.update(_after(after_producer, after_seq, after_timeout_ms))
        return self.rpc(command, timeout=timeout)

    def producer_status(self, session: str, producer: str,
                        timeout: Optional[float] = None) -> wire.ProducerStatus:
        """rpc ``producer_status``: ``{"session", "producer", "accepted_through", "sequence",
        "reflected_sequence"}``."""
        return self.rpc({"op": "producer_status", "session": session, "producer": producer},
                        timeout=timeout)

    def list_producers(self, session: str,
                       timeout: Optional[float] = None) -> wire.ProducerList:
        """rpc ``list_producers``: every producer the session has seen, by id."""
        return self.rpc({"op": "list_producers", "session": session}, timeout=timeout)

    def robots(self, session: str, timeout: Optional[float] = None) -> JsonDict:
        """rpc ``list_robots`` (a session created with ``robots``): its robots, held and rejected
        closures and merges (see :meth:`HttpClient.robots`)."""
        return self.rpc({"op": "list_robots", "session": session}, timeout)

    def outliers(self, session: str, timeout: Optional[float] = None) -> JsonDict:
        """rpc ``list_outliers``: the session's possibly wrong loop closures and the decisions
        (see :meth:`HttpClient.outliers`)."""
        return self.rpc({"op": "list_outliers", "session": session}, timeout)

    def producer(self, session: str, producer: Optional[str] = None, **options: Any) -> Any:
        """A :class:`~factord_client.stream_producer.StreamProducer` of ``session``: numbered,
        acknowledged, resent batches (``options``: ``window``, ``resend_after``, ``resume``,
        ``on_ack``, ...)."""
        from .stream_producer import StreamProducer  # noqa: PLC0415

        return StreamProducer(self, session, producer, **options)

    def stats(self, session: str) -> wire.SessionStats:
        return self.rpc({"op": "get_stats", "session": session})

    def cancel(self, session: str) -> JsonDict:
        return self.rpc({"op": "cancel", "session": session})

    def set_auto_optimize(self, session: str, policy: Union[str, JsonDict], **params: Any) -> JsonDict:
        return self.rpc({"op": "set_auto_optimize", "session": session,
                         "auto_optimize": auto_optimize_policy(policy, **params)})

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
        robot: Optional[str] = None,
        frame: Optional[str] = None,
    ) -> wire.Estimate:
        """Reads the estimate from the ``<prefix>/<session>/estimate`` queryable (selector
        parameters ``since``, ``from``, ``to``, and ``after_producer``/``after_seq``: first wait
        until that producer's batches through ``after_seq`` are applied; ``robot``/``frame`` as
        :meth:`HttpClient.estimate`)."""
        params = [f"{name}={int(value)}" for name, value in
                  (("since", since), ("from", from_key), ("to", to_key)) if value is not None]
        params += [f"{name}={value}" for name, value in (("robot", robot), ("frame", frame))
                   if value is not None]
        params += [f"{k}={v}" for k, v in
                   _after(after_producer, after_seq, after_timeout_ms).items()]
        selector = f"{self.prefix}/{session}/estimate"
        if params:
            selector += "?" + ";".join(params)
        return self._query(selector, None, timeout)

    def estimate_array(self, session: str, kind: Optional[str] = None,
                       **query: Any) -> EstimateArray:
        """The estimate as arrays: ``keys, values = z.estimate_array(s)`` (see
        :meth:`HttpClient.estimate_array`)."""
        return estimate_to_array(self.estimate(session, **query), kind)

    def estimate_poses(self, session: str, **query: Any) -> Dict[int, AnyPose]:
        """``{key: Pose2 | Pose3}`` of the session's poses."""
        return self.estimate_array(session, **query).poses()

    def export(self, session: str, format: str = "tum",
               timeout: Optional[float] = None) -> str:
        """The estimate as a file's text from the estimate queryable (``?format=tum``,
        ``kitti``, ``g2o``, ``ply``)."""
        return self._query(f"{self.prefix}/{session}/estimate?format={format}", None, timeout,
                           text=True)

    def graph(self, session: str) -> wire.Graph:
        """rpc ``get_graph``: what the web view draws."""
        return self.rpc({"op": "get_graph", "session": session})

    def marginals(self, session: str, keys: Iterable[int], joint: bool = False) -> wire.Marginals:
        """rpc ``get_marginals``: covariances of ``keys`` (``joint``: cross-covariances)."""
        key_list = [int(k) for k in np.asarray(list(keys)).reshape(-1)]
        return self.rpc({"op": "get_marginals", "session": session, "keys": key_list,
                         "joint": joint})

    def covariances(self, session: str, keys: Iterable[int], joint: bool = False
                    ) -> Tuple[Dict[int, np.ndarray], Optional[np.ndarray]]:
        """``({key: (d, d) covariance}, joint (n, n) or None)`` as numpy arrays."""
        return marginals_to_arrays(self.marginals(session, keys, joint))

    def fusion(self, session: str, messages: List[JsonDict]) -> JsonDict:
        """rpc ``fusion``: messages for a ``sliding_window`` session (with an answer; or
        :meth:`publish_fusion` without)."""
        return self.rpc({"op": "fusion", "session": session, "messages": messages})

    # ----------------------------------------------------------------- streams
    def _put(self, key: str, payload: bytes) -> None:
        self._check_open()
        try:
            self._session.put(key, payload,
                              congestion_control=self._zenoh.CongestionControl.BLOCK)
        except Exception as e:  # noqa: BLE001 - ZError
            raise _zenoh_failure(f"put on `{key}`", e) from None

    def publish_fusion(self, session: str, messages: List[JsonDict]) -> None:
        """Puts ``{"messages": [...]}`` on ``<prefix>/<session>/in/fusion`` (no reply)."""
        self._put(f"{self.prefix}/{session}/in/fusion",
                  dumps({"messages": messages}).encode("utf-8"))

    def publish_batch(self, session: str, batch: BatchLike) -> None:
        """Puts a batch on ``<prefix>/<session>/in/batch`` (fire and forget: watch ``out/acks``
        and ``out/errors``)."""
        # Block rather than drop when the link is congested (_put): a lost batch would make
        # every later batch that refers to its variables fail.
        self._put(f"{self.prefix}/{session}/in/batch", dumps(as_batch(batch)).encode("utf-8"))

    def publish_optimize(self, session: str) -> None:
        """Puts on ``<prefix>/<session>/in/optimize``: solve now."""
        self._put(f"{self.prefix}/{session}/in/optimize", b"{}")

    def subscribe(self, session: str, topic: str, callback: Callable[[JsonDict], None],
                  max_pending: int = MAX_PENDING) -> Any:
        """Calls ``callback(event)`` for every publication on ``<prefix>/<session>/out/<topic>``
        (``topic``: acks, stats, poses, summary, errors, or ``*`` for all; the event's ``type``
        field tells them apart). The callback runs on a daemon thread of this subscription, one
        event at a time in order; its exceptions are printed. A callback more than
        ``max_pending`` events behind loses the newer ones and is told so by a ``lagged``
        event with ``"source": "client"`` (memory stays bounded; see :class:`Subscription`).
        Returns the :class:`Subscription` (undeclared by :meth:`close`, or call its
        ``undeclare()``)."""
        return self._subscribe(f"{self.prefix}/{session}/out/{topic}", callback, max_pending)

    def subscribe_binary_poses(self, session: str, callback: Callable[[JsonDict], None],
                               max_pending: int = MAX_PENDING) -> Any:
        """Like :meth:`subscribe` to ``poses``, from ``<prefix>/<session>/bin/poses``: the
        same estimates, sent in binary (about 40 bytes an SE(2) pose against about 100 in
        JSON), given to ``callback`` as ``{"type": "estimate", "sequence": n, "arrays": {kind:
        EstimateArray}}`` (with ``changed`` per variable; no stamps). A ``lagged`` marker comes
        as on the JSON topics."""
        return self._subscribe(f"{self.prefix}/{session}/bin/poses", callback, max_pending,
                               lambda payload: poses_binary.decode_event(payload, session))

    def subscribe_robot_poses(self, session: str, robot: str,
                              callback: Callable[[JsonDict], None], frame: str = "map",
                              binary: bool = False, max_pending: int = MAX_PENDING) -> Any:
        """Like :meth:`subscribe` to ``poses`` for one robot of a session with robots: its
        changed poses only, from ``<prefix>/<session>/robot/<id>/poses`` (``frame="odom"``:
        ``odom_poses``, in the robot's own odometry frame; ``binary``: under ``bin/``, decoded
        as :meth:`subscribe_binary_poses`). The first event is the robot's whole trajectory."""
        if frame not in ("map", "odom"):
            raise ValueError(f"frame is `map` or `odom`, not {frame!r}")
        name = "odom_poses" if frame == "odom" else "poses"
        key = f"{self.prefix}/{session}/robot/{robot_id(robot)}/{'bin/' if binary else ''}{name}"
        decode = (lambda payload: poses_binary.decode_event(payload, session)) if binary else None
        return self._subscribe(key, callback, max_pending, decode)

    def subscribe_robot_frame(self, session: str, robot: str,
                              callback: Callable[[JsonDict], None],
                              max_pending: int = MAX_PENDING) -> Any:
        """``callback(report)`` each time robot ``robot``'s place in the map changes (its first
        pose, a merge): ``{"session", "robot", "component", "in_map", "map_from_odom", …}``
        from ``<prefix>/<session>/robot/<id>/map_from_odom``."""
        key = f"{self.prefix}/{session}/robot/{robot_id(robot)}/map_from_odom"
        return self._subscribe(key, callback, max_pending)

    def robot_estimate(self, session: str, robot: str, frame: str = "map",
                       since: Optional[int] = None,
                       timeout: Optional[float] = None) -> wire.Estimate:
        """Robot ``robot``'s estimate from its own queryable
        (``<prefix>/<session>/robot/<id>/estimate``), in the map or its odometry frame."""
        params = [f"frame={frame}"] + ([] if since is None else [f"since={int(since)}"])
        selector = f"{self.prefix}/{session}/robot/{robot_id(robot)}/estimate?" + ";".join(params)
        return self._query(selector, None, timeout)

    def robot_frame(self, session: str, robot: str, timeout: Optional[float] = None) -> JsonDict:
        """Where robot ``robot``'s odometry frame sits in the map now (the
        ``robot/<id>/map_from_odom`` queryable)."""
        selector = f"{self.prefix}/{session}/robot/{robot_id(robot)}/map_from_odom"
        return self._query(selector, None, timeout)

    def _subscribe(self, key: str, callback: Callable[[JsonDict], None], max_pending: int,
                   decode: Optional[Callable[[bytes], JsonDict]] = None) -> Any:
        self._check_open()
        if max_pending < 1:
            raise ValueError(f"max_pending must be at least 1, not {max_pending}")
        extra = {} if decode is None else {"decode": decode}
        try:
            subscription = Subscription(self._session, self._zenoh, key, callback, max_pending,
                                        **extra)
        except Exception as e:  # noqa: BLE001 - ZError
            raise _zenoh_failure(f"subscriber on `{key}`", e) from None
        with self._lock:
            self._subscriptions.append(subscription)
        return subscription

    def close(self) -> None:
        """Undeclares the subscriptions and closes the zenoh session (once; later calls do
        nothing). Also done when the client is garbage-collected or the interpreter exits."""
        self._finalizer()

    def __enter__(self) -> "ZenohClient":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _decode(payload: bytes, selector: str, text: bool) -> Any:
    try:
        body = payload.decode("utf-8")
        return body if text else json.loads(body)
    except ValueError as e:
        raise FactordError(None, "unexpected_response",
                           f"`{selector}` answered something unreadable ({e})",
                           body=payload[:1000]) from None


def _after(producer: Optional[str], seq: Optional[int],
           timeout_ms: Optional[int]) -> JsonDict:
    if producer is None or seq is None:
        return {}
    out: JsonDict = {"after_producer": producer, "after_seq": int(seq)}
    if timeout_ms is not None:
        out["after_timeout_ms"] = int(timeout_ms)
    return out
