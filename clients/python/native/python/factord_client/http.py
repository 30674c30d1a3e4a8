"""HTTP client for factord (standard library only).

Every method maps onto one route of the ``/v1`` API and returns the parsed JSON answer; an error
answer raises :class:`~factord_client.errors.FactordError`, a service that cannot be reached
:class:`~factord_client.errors.FactordConnectionError` (an ``OSError`` too).

Retries (bounded by ``retries`` attempts and ``retry_budget`` seconds of waiting):

* 429 (``too_many_pending``, ...): the service refused before doing anything, so every request
  is retried after its ``Retry-After`` (at most ``max_retry_wait`` seconds per wait);
* 503 and connection failures (refused, reset, socket timeout): retried only for requests that
  are safe to repeat: reads, ``PUT``, ``optimize``, ``cancel``, batch jobs, and batches that carry
  ``producer`` + ``producer_seq`` (a repeat is answered with the original acknowledgement and
  applies nothing). A plain batch or a ``create_session`` is not repeated: the error is raised.
"""

from __future__ import annotations

import http.client
import json
import os
import random
import time
import urllib.error
import urllib.parse
import urllib.request
from typing import TYPE_CHECKING, Any, Dict, Iterable, Iterator, List, Optional, Tuple, Union

import numpy as np

from . import wire
from .batch import (Batch, EstimateArray, as_batch, dumps, estimate_to_array,
                    marginals_to_arrays)
from .errors import FactordConnectionError, FactordError
from .geometry import AnyPose

if TYPE_CHECKING:
    from .producer import HttpProducer

JsonDict = Dict[str, Any]
BatchLike = Union[Batch, wire.Batch, JsonDict]
_DEFAULT = object()
#: What ``export`` serves (``GET .../estimate?format=``).
EXPORT_FORMATS = ("tum", "kitti", "g2o", "ply", "json")


def _quote(segment: str) -> str:
    return urllib.parse.quote(str(segment), safe="")


class EventStream:
    """An open Server-Sent Events stream of one session.

    The connection (and with it the subscription on the server) exists as soon as
    :meth:`HttpClient.events` returns, so events of requests sent afterwards are not missed.
    Iterate to get ``(event_name, data)`` pairs: ``event_name`` is the topic (``acks``,
    ``stats``, ``poses``, ``summary``, ``errors``, or ``lagged`` when this reader fell behind),
    ``data`` the parsed JSON (the raw text if it is not JSON). Keep-alive comments are skipped.
    Use as a context manager or call :meth:`close`.
    """

    def __init__(self, response: Any) -> None:
        self._response = response
        self.closed = False

    def __iter__(self) -> Iterator[Tuple[str, Any]]:
        event_name: Optional[str] = None
        data_lines: list = []
        try:
            while True:
                try:
                    raw = self._response.readline()
                except (OSError, http.client.HTTPException) as e:
                    if self.closed:  # closed by us from another thread: just the end
                        return
                    raise FactordConnectionError(
                        "connection_failed", f"event stream broke: {e!r}") from None
                if not raw:  # the server closed the stream (session deleted, shutdown)
                    return
                line = raw.decode("utf-8").rstrip("\r\n")
                if line == "":
                    if data_lines:
                        text = "\n".join(data_lines)
                        try:
                            data: Any = json.loads(text)
                        except ValueError:
                            data = text
                        yield (event_name or "message", data)
                    event_name, data_lines = None, []
                    continue
                if line.startswith(":"):  # comment (keep-alive)
                    continue
                name, _, value = line.partition(":")
                if value.startswith(" "):
                    value = value[1:]
                if name == "event":
                    event_name = value
                elif name == "data":
                    data_lines.append(value)
                # `id:` and `retry:` are not used by factord.
        finally:
            self.close()

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            try:
                self._response.close()
            except Exception:  # noqa: BLE001 - closing a broken stream
                pass

    def __enter__(self) -> "EventStream":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class HttpClient:
    """Client of the factord HTTP API.

    >>> c = HttpClient("http://127.0.0.1:8080", token="...")   # token: or $FACTORD_TOKEN
    >>> c.create_session("pose_graph_2d", session="demo")
    """

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8080",
        timeout: float = 150.0,
        token: Optional[str] = None,
        retries: int = 5,
        max_retry_wait: float = 30.0,
        retry_budget: float = 120.0,
    ) -> None:
        """``timeout`` (seconds) applies to every request; it is longer than the server's
        default wait timeout (120 s) so that ``wait=True`` requests get their answer.
        ``token``: the bearer token (default: ``$FACTORD_TOKEN``; none when unset).
        ``retries``: at most this many attempts after the first; ``max_retry_wait``: the longest
        single wait (a larger ``Retry-After`` is cut to it); ``retry_budget``: the most seconds
        spent waiting between attempts of one request."""
        self.base_url = base_url.rstrip("/")
        self.timeout = timeout
        self.token = token if token is not None else (os.environ.get("FACTORD_TOKEN") or None)
        self.retries = max(0, int(retries))
        self.max_retry_wait = max_retry_wait
        self.retry_budget = retry_budget
        #: How many requests were sent again (any cause), for monitoring.
        self.retried = 0

    # ----------------------------------------------------------------- plumbing
    def _url(self, path: str, query: Optional[Dict[str, Any]] = None) -> str:
        url = f"{self.base_url}{path}"
        params = {k: _param(v) for k, v in (query or {}).items() if v is not None}
        if params:
            url += "?" + urllib.parse.urlencode(params)
        return url

    def _build(
        self,
        method: str,
        path: str,
        body: Union[None, bytes, str, JsonDict] = None,
        query: Optional[Dict[str, Any]] = None,
        headers: Optional[Dict[str, str]] = None,
    ) -> urllib.request.Request:
        data: Optional[bytes] = None
        hdrs = {"Accept": "application/json"}
        if self.token:
            hdrs["Authorization"] = f"Bearer {self.token}"
        if isinstance(body, (dict, list, Batch)):
            data = dumps(body).encode("utf-8")
            hdrs["Content-Type"] = "application/json"
        elif isinstance(body, str):
            data = body.encode("utf-8")
            hdrs["Content-Type"] = "text/plain; charset=utf-8"
        elif isinstance(body, bytes):
            # Raw bytes are JSON already encoded (graph files go as `str`, text/plain); the
            # server refuses other types on its JSON routes (415).
            data = body
            hdrs["Content-Type"] = "application/json"
        elif method in ("POST", "PUT"):
            data = b""
        hdrs.update(headers or {})
        return urllib.request.Request(self._url(path, query), data=data, method=method,
                                      headers=hdrs)

    def _attempts(self, method: str, path: str, safe: Optional[bool],
                  send: Any, **kwargs: Any) -> Any:
        """Runs ``send(request)`` with the retry rules of the module docstring."""
        if safe is None:
            safe = method in ("GET", "HEAD", "PUT")
        request = self._build(method, path, **kwargs)
        waited = 0.0
        attempt = 0
        while True:
            attempt += 1
            try:
                return send(request)
            except urllib.error.HTTPError as e:
                raw = e.read()
                error = FactordError.from_body(raw, e.code, e.headers.get("Retry-After"))
                retryable = e.code == 429 or (e.code == 503 and safe)
                wait = error.retry_after if error.retry_after is not None else _backoff(attempt)
                failure: FactordError = error
            except (urllib.error.URLError, http.client.HTTPException, OSError) as e:
                reason = getattr(e, "reason", e)
                failure = FactordConnectionError(
                    "connection_failed",
                    f"{method} {self.base_url}{path}: {reason!r}", attempts=attempt)
                retryable = safe
                wait = _backoff(attempt)
            wait = min(wait, self.max_retry_wait)
            if not retryable or attempt > self.retries or waited + wait > self.retry_budget:
                if isinstance(failure, FactordConnectionError):
                    failure.attempts = attempt
                    raise failure from None
                raise failure from None
            waited += wait
            self.retried += 1
            time.sleep(wait)

    def _open(
        self,
        method: str,
        path: str,
        body: Union[None, bytes, str, JsonDict] = None,
        query: Optional[Dict[str, Any]] = None,
        headers: Optional[Dict[str, str]] = None,
        timeout: Any = _DEFAULT,
        safe: Optional[bool] = None,
    ) -> Any:
        """Opens the request (with retries) and returns the open response."""
        t = self.timeout if timeout is _DEFAULT else timeout
        return self._attempts(method, path, safe,
                              lambda r: urllib.request.urlopen(r, timeout=t),
                              body=body, query=query, headers=headers)

    def _request(self, method: str, path: str, body: Union[None, bytes, str, JsonDict] = None,
                 query: Optional[Dict[str, Any]] = None,
                 headers: Optional[Dict[str, str]] = None,
                 safe: Optional[bool] = None) -> Any:
        """Sends the request and reads the whole answer (a failure while reading the answer is
        retried like one while connecting)."""

        def send(request: urllib.request.Request) -> Tuple[bytes, str]:
            with urllib.request.urlopen(request, timeout=self.timeout) as response:
                return response.read(), response.headers.get("Content-Type", "")

        raw, content_type = self._attempts(method, path, safe, send, body=body, query=query,
                                           headers=headers)
        try:
            text = raw.decode("utf-8")
            return json.loads(text) if content_type.startswith("application/json") else text
        except ValueError as e:  # a proxy's page, a truncated body: still one error family
            raise FactordError(None, "unexpected_response",
                               f"{method} {path}: unreadable answer ({e})",
                               body=raw[:1000]) from None

    def _session_path(self, session: str, tail: str = "") -> str:
        return f"/v1/sessions/{_quote(session)}{tail}"

    # ----------------------------------------------------------------- routes
    def health(self) -> wire.Health:
        """``GET /v1/health``: status, version, workers, sessions, session kinds, uptime."""
        return self._request("GET", "/v1/health")

    def create_session(
        self,
        kind: str,
        session: Optional[str] = None,
        options: Optional[JsonDict] = None,
        auto_optimize: Union[None, str, JsonDict] = None,
        factor_types: Optional[list] = None,
        robots: Optional[JsonDict] = None,
        outliers: Optional[str] = None,
        max_update_ms: Optional[int] = None,
    ) -> wire.SessionInfo:
        """``POST /v1/sessions``. ``kind``: ``pose_graph_2d`` | ``pose_graph_3d``; ``options``:
        solver options (``method``, ``max_iterations``, ``function_tolerance``, ...), each
        one given overriding the kind's default (``{"max_iterations": 20}`` on a
        ``bundle_adjustment`` keeps its damped Levenberg-Marquardt);
        ``auto_optimize``: a policy dict such as ``{"policy": "every_n_factors", "factors": 50}``
        or just the policy name (``"every_batch"``, ``"manual"``); ``factor_types``: user-defined
        factor types (proto/v1/factor-type.schema.json), used by name in batches; ``robots``:
        the session holds several robots (``{}`` or ``{"min_closures": 3}``, see
        docs/guide/many-robots.md); ``outliers``: ``"auto"`` holds every loop closure out of the
        estimate until it is found consistent (see :meth:`outliers`); ``max_update_ms``: a latency
        budget, updates the exact solve has not reflected in time answered provisionally (see
        docs/guide/latency.md)."""
        body: JsonDict = {"kind": kind}
        if session is not None:
            body["session"] = session
        if options is not None:
            body["options"] = options
        if auto_optimize is not None:
            body["auto_optimize"] = auto_optimize_policy(auto_optimize)
        if factor_types:
            body["factor_types"] = factor_types
        if robots is not None:
            body["robots"] = robots
        if outliers is not None:
            body["outliers"] = outliers
        if max_update_ms is not None:
            body["max_update_ms"] = max_update_ms
        return self._request("POST", "/v1/sessions", body=body)

    def list_sessions(self) -> wire.SessionList:
        """``GET /v1/sessions``: ``{"sessions": [{session, kind, options, auto_optimize}, ...]}``."""
        return self._request("GET", "/v1/sessions")

    def stats(self, session: str) -> wire.SessionStats:
        """``GET /v1/sessions/{session}``: sequence, solved_sequence, chi2, solves, ..."""
        return self._request("GET", self._session_path(session))

    def define_factor_types(self, session: str, factor_types: list) -> wire.SessionInfo:
        """``POST /v1/sessions/{session}/factor_types``: declares more user-defined factor
        types in a running graph session (all or none); answers the session's info with every
        declared name."""
        return self._request("POST", self._session_path(session, "/factor_types"),
                             body={"factor_types": factor_types})

    def delete_session(self, session: str) -> JsonDict:
        """``DELETE /v1/sessions/{session}``."""
        return self._request("DELETE", self._session_path(session))

    def apply_batch(self, session: str, batch: BatchLike, wait: bool = False) -> wire.BatchAck:
        """``POST /v1/sessions/{session}/batches``: the acknowledgement (``sequence``,
        ``factor_ids``, ``predicted``); with ``wait``, also ``solved`` once the estimate
        reflects the batch (when a solve is due under the policy).

        A batch with ``producer`` and ``producer_seq`` is exactly-once: it is resent after a
        connection failure or a 503, and a repeat answers the original acknowledgement with
        ``"duplicate": true`` (see :meth:`producer` for a client that numbers batches).
        ``batch``: a dict (numpy arrays and poses allowed as values) or a :class:`Batch`."""
        batch = as_batch(batch)
        stamped = "producer" in batch and "producer_seq" in batch
        return self._request("POST", self._session_path(session, "/batches"), body=batch,
                             query={"wait": True} if wait else None, safe=stamped)

    def producer(self, session: str, producer: Optional[str] = None,
                 resume: bool = True) -> "HttpProducer":
        """A numbering producer on this session (see :class:`HttpProducer`)."""
        from .producer import HttpProducer  # noqa: PLC0415 - avoids an import cycle

        return HttpProducer(self, session, producer, resume=resume)

    def producer_status(self, session: str, producer: str) -> wire.ProducerStatus:
        """``GET /v1/sessions/{session}/producers/{producer}``: ``{"session", "producer",
        "accepted_through", "sequence", "reflected_sequence"}`` (``accepted_through`` 0 for a
        producer the session has not seen)."""
        return self._request("GET", self._session_path(session, f"/producers/{_quote(producer)}"))

    def list_producers(self, session: str) -> wire.ProducerList:
        """``GET /v1/sessions/{session}/producers``: every producer the session has seen, by id,
        each as :meth:`producer_status` answers for it."""
        return self._request("GET", self._session_path(session, "/producers"))

    def robots(self, session: str) -> JsonDict:
        """``GET /v1/sessions/{session}/robots`` (a session created with ``robots``): every
        robot with its frame (``map_from_odom``) and component, the held (``pending``) and
        ``rejected`` closures, and the merges."""
        return self._request("GET", self._session_path(session, "/robots"))

    def outliers(self, session: str) -> JsonDict:
        """``GET /v1/sessions/{session}/outliers``: the possibly wrong loop closures (factors
        sent with ``"outlier": "auto"``, or every loop closure of a session created with
        ``outliers="auto"``): how many were ``accepted``, the ``pending`` and ``rejected`` ones
        with their gate ``distance``, and the ``consolidations`` so far."""
        return self._request("GET", self._session_path(session, "/outliers"))

    def optimize(self, session: str, wait: bool = False, after_producer: Optional[str] = None,
                 after_seq: Optional[int] = None,
                 after_timeout_ms: Optional[int] = None) -> wire.OptimizeAnswer:
        """``POST /v1/sessions/{session}/optimize``: solve now; with ``wait`` the answer has
        the statistics after the solve under ``stats``. With ``after_producer`` + ``after_seq``
        the solve first waits until that producer's batches through ``after_seq`` are applied
        (503 ``after_timeout`` after ``after_timeout_ms``, default 10 s)."""
        query: Dict[str, Any] = {"wait": True} if wait else {}
        query.update(_after(after_producer, after_seq, after_timeout_ms))
        return self._request("POST", self._session_path(session, "/optimize"),
                             query=query or None, safe=True)

    def set_auto_optimize(self, session: str, policy: Union[str, JsonDict],
                          **params: Any) -> wire.SessionInfo:
        """``PUT /v1/sessions/{session}/auto_optimize``, e.g.
        ``set_auto_optimize(s, "every_n_factors", factors=50)`` or
        ``set_auto_optimize(s, {"policy": "every_ms", "milliseconds": 200})``."""
        return self._request("PUT", self._session_path(session, "/auto_optimize"),
                             body=auto_optimize_policy(policy, **params))

    def estimate(
        self,
        session: str,
        since: Optional[int] = None,
        from_key: Optional[int] = None,
        to_key: Optional[int] = None,
        after_producer: Optional[str] = None,
        after_seq: Optional[int] = None,
        after_timeout_ms: Optional[int] = None,
        robot: Optional[str] = None,
        frame: Optional[str] = None,
    ) -> wire.Estimate:
        """``GET /v1/sessions/{session}/estimate``: ``{"session", "sequence", "variables":
        [{"key", "kind", "value", "changed"}, ...]}``; ``since`` keeps the variables changed
        after that sequence, ``from_key``/``to_key`` an inclusive key range;
        ``after_producer`` + ``after_seq``: first wait until that producer's batches through
        ``after_seq`` are applied; ``robot`` (a session with robots): only that robot's poses,
        in the map or, with ``frame="odom"``, in its own odometry frame."""
        query: Dict[str, Any] = {"since": since, "from": from_key, "to": to_key,
                                 "robot": robot, "frame": frame}
        query.update(_after(after_producer, after_seq, after_timeout_ms))
        return self._request("GET", self._session_path(session, "/estimate"), query=query)

    def summary(self, session: str) -> wire.Summary:
        """``GET /v1/sessions/{session}/summary``: the last solve's Summary (404 ``no_summary``
        before the first solve)."""
        return self._request("GET", self._session_path(session, "/summary"))

    def cancel(self, session: str) -> JsonDict:
        """``POST /v1/sessions/{session}/cancel``: ``{"session", "cancelled"}``."""
        return self._request("POST", self._session_path(session, "/cancel"), safe=True)

    def run_job(
        self,
        graph_text: Union[str, bytes],
        format: Optional[str] = None,
        output: Optional[str] = None,
        **solver_params: Any,
    ) -> Union[JsonDict, str]:
        """``POST /v1/jobs``: optimise a whole graph file in one request.

        ``format``: ``g2o`` | ``toro`` (detected when absent); ``output``: ``json`` (default:
        ``{"summary": ..., "estimate": {"variables": [...]}}``), ``g2o`` or ``tum`` (text, returned
        as ``str``). ``solver_params``: ``method`` (gn | lm | dogleg), ``max_iterations``,
        ``init`` (none | chordal | auto), ``robust`` (e.g. ``huber:1.0``),
        ``function_tolerance``.
        """
        query: Dict[str, Any] = {"format": format, "output": output}
        query.update(solver_params)
        body = graph_text if isinstance(graph_text, str) else graph_text.decode("utf-8")
        return self._request("POST", "/v1/jobs", body=body, query=query, safe=True)

    def estimate_array(self, session: str, kind: Optional[str] = None,
                       **query: Any) -> EstimateArray:
        """The estimate as arrays: ``keys, values = c.estimate_array(s)`` with ``values``
        (N, 3) for se2 poses, (N, 7) for se3 (see :class:`EstimateArray`; ``stamps`` too).
        ``kind`` picks one kind in a session that has several (``"point2"`` for landmarks);
        ``query``: :meth:`estimate`'s filters (``since``, ``from_key``, ``after_seq``, ...)."""
        return estimate_to_array(self.estimate(session, **query), kind)

    def estimate_poses(self, session: str, **query: Any) -> Dict[int, AnyPose]:
        """``{key: Pose2 | Pose3}`` of the session's poses."""
        return self.estimate_array(session, **query).poses()

    def export(self, session: str, format: str = "tum") -> str:
        """``GET /v1/sessions/{session}/estimate?format=``: the estimate as a file's text:
        ``tum`` (``stamp tx ty tz qx qy qz qw`` per pose, for evo), ``kitti``, ``g2o``,
        ``ply``, or ``json``."""
        if format not in EXPORT_FORMATS:
            raise ValueError(f"format must be one of {EXPORT_FORMATS}, not {format!r}")
        answer = self._request("GET", self._session_path(session, "/estimate"),
                               query={"format": format},
                               headers={"Accept": "text/plain, application/json"})
        return answer if isinstance(answer, str) else json.dumps(answer)

    def graph(self, session: str) -> wire.Graph:
        """``GET /v1/sessions/{session}/graph``: what the web view draws (positions now and
        initially, edges)."""
        return self._request("GET", self._session_path(session, "/graph"))

    def history(self, session: str) -> JsonDict:
        """``GET /v1/sessions/{session}/history``: the session's timeline (χ², solve time, update
        latency per solve), its last events, rejected inputs and ``last_error``."""
        return self._request("GET", self._session_path(session, "/history"))

    def marginals(self, session: str, keys: Iterable[int], joint: bool = False) -> wire.Marginals:
        """``GET /v1/sessions/{session}/marginals?keys=…``: each variable's covariance in its
        tangent space (se2: x, y, θ; se3: body translation, rotation), with ``joint`` the
        cross-covariances too. :meth:`covariances` gives numpy arrays."""
        key_list = ",".join(str(int(k)) for k in np.asarray(list(keys)).reshape(-1))
        return self._request("GET", self._session_path(session, "/marginals"),
                             query={"keys": key_list, "joint": True if joint else None})

    def covariances(self, session: str, keys: Iterable[int], joint: bool = False
                    ) -> Tuple[Dict[int, np.ndarray], Optional[np.ndarray]]:
        """``({key: (d, d) covariance}, joint (n, n) or None)`` as numpy arrays."""
        return marginals_to_arrays(self.marginals(session, keys, joint))

    def fusion(self, session: str, messages: List[JsonDict]) -> JsonDict:
        """``POST /v1/sessions/{session}/fusion``: messages for a ``sliding_window`` session
        (``start``, ``imu``, ``keyframe``, ``relative_pose``, ``pose_prior``, ...; numpy
        arrays allowed as values)."""
        return self._request("POST", self._session_path(session, "/fusion"),
                             body={"messages": messages})

    def openapi(self) -> JsonDict:
        """``GET /v1/openapi.json``: the API's description."""
        return self._request("GET", "/v1/openapi.json")

    def metrics(self) -> str:
        """``GET /metrics``: Prometheus text."""
        return self._request("GET", "/metrics", headers={"Accept": "text/plain"})

    def close(self) -> None:
        """Nothing stays open between requests (each opens its own connection); here so that
        both clients are used the same way (``with HttpClient(...) as c:``)."""

    def __enter__(self) -> "HttpClient":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def events(self, session: str, timeout: Optional[float] = None) -> EventStream:
        """``GET /v1/sessions/{session}/events``: the session's Server-Sent Events.

        Returns an :class:`EventStream` (already connected) that yields ``(event_name, data)``.
        ``timeout`` bounds each socket read (the server sends a keep-alive comment every 15 s);
        ``None`` waits forever."""
        response = self._open("GET", self._session_path(session, "/events"),
                              headers={"Accept": "text/event-stream"},
                              timeout=timeout)
        return EventStream(response)


def _after(producer: Optional[str], seq: Optional[int],
           timeout_ms: Optional[int]) -> Dict[str, Any]:
    if producer is None or seq is None:
        return {}
    out: Dict[str, Any] = {"after_producer": producer, "after_seq": int(seq)}
    if timeout_ms is not None:
        out["after_timeout_ms"] = int(timeout_ms)
    return out


def _backoff(attempt: int) -> float:
    """0.1, 0.2, 0.4, ... seconds (with ±25 % jitter) before attempt ``attempt + 1``."""
    return 0.1 * (2 ** (attempt - 1)) * random.uniform(0.75, 1.25)


def _param(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def auto_optimize_policy(policy: Union[str, JsonDict], **params: Any) -> JsonDict:
    """``"every_n_factors", factors=10`` -> ``{"policy": "every_n_factors", "factors": 10}``."""
    if isinstance(policy, dict):
        return {**policy, **params}
    return {"policy": policy, **params}
