"""HTTP client for factord (standard library only).

Every method maps onto one route of the ``/v1`` API and returns the parsed JSON answer; an error
answer raises :class:`~factord_client.errors.FactordError`. Network failures (connection refused,
timeouts) propagate as the usual ``urllib.error.URLError`` / ``OSError``.
"""

from __future__ import annotations

import json
import urllib.error
import urllib.parse
import urllib.request
from typing import Any, Dict, Iterator, Optional, Tuple, Union

from .errors import FactordError

JsonDict = Dict[str, Any]
_DEFAULT = object()


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
                raw = self._response.readline()
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

    >>> c = HttpClient("http://127.0.0.1:8080")
    >>> c.create_session("pose_graph_2d", session="demo")
    """

    def __init__(self, base_url: str = "http://127.0.0.1:8080", timeout: float = 150.0) -> None:
        """``timeout`` (seconds) applies to every request; it is longer than the server's
        default wait timeout (120 s) so that ``wait=True`` requests get their answer."""
        self.base_url = base_url.rstrip("/")
        self.timeout = timeout

    # ----------------------------------------------------------------- plumbing
    def _url(self, path: str, query: Optional[Dict[str, Any]] = None) -> str:
        url = f"{self.base_url}{path}"
        params = {k: _param(v) for k, v in (query or {}).items() if v is not None}
        if params:
            url += "?" + urllib.parse.urlencode(params)
        return url

    def _open(
        self,
        method: str,
        path: str,
        body: Union[None, bytes, str, JsonDict] = None,
        query: Optional[Dict[str, Any]] = None,
        headers: Optional[Dict[str, str]] = None,
        timeout: Any = _DEFAULT,
    ) -> Any:
        data: Optional[bytes] = None
        hdrs = {"Accept": "application/json"}
        if isinstance(body, (dict, list)):
            data = json.dumps(body).encode("utf-8")
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
        request = urllib.request.Request(self._url(path, query), data=data, method=method,
                                         headers=hdrs)
        try:
            return urllib.request.urlopen(
                request, timeout=self.timeout if timeout is _DEFAULT else timeout
            )
        except urllib.error.HTTPError as e:
            raw = e.read()
            raise FactordError.from_body(raw, e.code, e.headers.get("Retry-After")) from None

    def _request(self, method: str, path: str, **kwargs: Any) -> Any:
        with self._open(method, path, **kwargs) as response:
            raw = response.read()
            content_type = response.headers.get("Content-Type", "")
        if content_type.startswith("application/json"):
            return json.loads(raw.decode("utf-8"))
        return raw.decode("utf-8")

    def _session_path(self, session: str, tail: str = "") -> str:
        return f"/v1/sessions/{_quote(session)}{tail}"

    # ----------------------------------------------------------------- routes
    def health(self) -> JsonDict:
        """``GET /v1/health``: status, version, workers, sessions, session kinds, uptime."""
        return self._request("GET", "/v1/health")

    def create_session(
        self,
        kind: str,
        session: Optional[str] = None,
        options: Optional[JsonDict] = None,
        auto_optimize: Union[None, str, JsonDict] = None,
    ) -> JsonDict:
        """``POST /v1/sessions``. ``kind``: ``pose_graph_2d`` | ``pose_graph_3d``; ``options``:
        solver options (``method``, ``max_iterations``, ``function_tolerance``, ...);
        ``auto_optimize``: a policy dict such as ``{"policy": "every_n_factors", "factors": 50}``
        or just the policy name (``"every_batch"``, ``"manual"``)."""
        body: JsonDict = {"kind": kind}
        if session is not None:
            body["session"] = session
        if options is not None:
            body["options"] = options
        if auto_optimize is not None:
            body["auto_optimize"] = auto_optimize_policy(auto_optimize)
        return self._request("POST", "/v1/sessions", body=body)

    def list_sessions(self) -> JsonDict:
        """``GET /v1/sessions``: ``{"sessions": [{session, kind, options, auto_optimize}, ...]}``."""
        return self._request("GET", "/v1/sessions")

    def stats(self, session: str) -> JsonDict:
        """``GET /v1/sessions/{session}``: sequence, solved_sequence, chi2, solves, ..."""
        return self._request("GET", self._session_path(session))

    def delete_session(self, session: str) -> JsonDict:
        """``DELETE /v1/sessions/{session}``."""
        return self._request("DELETE", self._session_path(session))

    def apply_batch(self, session: str, batch: JsonDict, wait: bool = False) -> JsonDict:
        """``POST /v1/sessions/{session}/batches``: the acknowledgement (``sequence``,
        ``factor_ids``, ``predicted``); with ``wait``, also ``solved`` once the estimate
        reflects the batch (when a solve is due under the policy)."""
        return self._request("POST", self._session_path(session, "/batches"), body=batch,
                             query={"wait": True} if wait else None)

    def optimize(self, session: str, wait: bool = False) -> JsonDict:
        """``POST /v1/sessions/{session}/optimize``: solve now; with ``wait`` the answer has
        the statistics after the solve under ``stats``."""
        return self._request("POST", self._session_path(session, "/optimize"),
                             query={"wait": True} if wait else None)

    def set_auto_optimize(self, session: str, policy: Union[str, JsonDict],
                          **params: Any) -> JsonDict:
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
    ) -> JsonDict:
        """``GET /v1/sessions/{session}/estimate``: ``{"session", "sequence", "variables":
        [{"key", "kind", "value", "changed"}, ...]}``; ``since`` keeps the variables changed
        after that sequence, ``from_key``/``to_key`` an inclusive key range."""
        return self._request("GET", self._session_path(session, "/estimate"),
                             query={"since": since, "from": from_key, "to": to_key})

    def summary(self, session: str) -> JsonDict:
        """``GET /v1/sessions/{session}/summary``: the last solve's Summary (404 ``no_summary``
        before the first solve)."""
        return self._request("GET", self._session_path(session, "/summary"))

    def cancel(self, session: str) -> JsonDict:
        """``POST /v1/sessions/{session}/cancel``: ``{"session", "cancelled"}``."""
        return self._request("POST", self._session_path(session, "/cancel"))

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
        return self._request("POST", "/v1/jobs", body=body, query=query)

    def events(self, session: str, timeout: Optional[float] = None) -> EventStream:
        """``GET /v1/sessions/{session}/events``: the session's Server-Sent Events.

        Returns an :class:`EventStream` (already connected) that yields ``(event_name, data)``.
        ``timeout`` bounds each socket read (the server sends a keep-alive comment every 15 s);
        ``None`` waits forever."""
        response = self._open("GET", self._session_path(session, "/events"),
                              headers={"Accept": "text/event-stream"},
                              timeout=timeout)
        return EventStream(response)


def _param(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def auto_optimize_policy(policy: Union[str, JsonDict], **params: Any) -> JsonDict:
    """``"every_n_factors", factors=10`` -> ``{"policy": "every_n_factors", "factors": 10}``."""
    if isinstance(policy, dict):
        return {**policy, **params}
    return {"policy": policy, **params}
