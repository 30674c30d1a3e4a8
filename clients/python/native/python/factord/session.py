"""A server session in this process: ``IncrementalSession`` takes the batches a running factord
takes over HTTP or zenoh (the same dicts, or ``factord_client.Batch``), solves them with the same
incremental engine and answers with the same JSON (acknowledgements, estimates, stats, wrong
closures held out, robots, marginals), without a server, a socket or a journal.

It is the service's own command API run in process (``factord.Service``: a third adapter beside
HTTP and zenoh), so what a session does here is what it does on a server, refusals included:
they raise ``ServiceError`` with the error body a server sends (``status``, ``code``,
``message``, ``field``)::

    import factord
    s = factord.IncrementalSession("pose_graph_2d")
    s.apply_batch({"variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0]}, ...],
                   "factors": [{"type": "prior_se2", "keys": [0], ...}]}, wait=True)
    keys, poses = s.estimate_array()

Every session of the process shares one ``Service`` (its worker pool), made at first use.
"""

import itertools
import json
import threading

from . import _native

# The wheel carries the wire client: its batch helpers and estimate arrays.
from factord_client.batch import as_batch as _as_batch
from factord_client.batch import estimate_to_array as _estimate_to_array

Service = _native.Service
ServiceError = _native.ServiceError

_shared = None
_shared_lock = threading.Lock()
_names = itertools.count(1)


def shared_service():
    """The process's ``Service``, made at first use."""
    global _shared
    with _shared_lock:
        if _shared is None:
            _shared = Service()
        return _shared


def _call(service, command):
    return json.loads(service.execute(json.dumps(command)))


class IncrementalSession:
    """A session, as ``POST /v1/sessions`` creates one: ``kind`` (``pose_graph_2d``,
    ``pose_graph_3d``, ``sliding_window``, …) and the creation request's other fields
    (``options``, ``auto_optimize``, ``factor_types``, ``robots``, ``outliers``,
    ``max_update_ms``), given as keywords."""

    def __init__(self, kind="pose_graph_2d", name=None, service=None, **creation):
        self._service = service or shared_service()
        self.name = name or f"in-process-{next(_names)}"
        if "auto_optimize" in creation and isinstance(creation["auto_optimize"], str):
            creation["auto_optimize"] = {"policy": creation["auto_optimize"]}
        self.info = self._call({"op": "create_session", "session": self.name, "kind": kind, **creation})

    def _call(self, command):
        return _call(self._service, command)

    def apply_batch(self, batch, wait=False):
        """Validates and applies a batch whole (or refuses it whole): the acknowledgement; with
        ``wait``, once the estimate reflects it (``solved``)."""
        return self._call({"op": "apply_batch", "session": self.name, "batch": _as_batch(batch), "wait": wait})

    def optimize(self, wait=True):
        """A full solve (``wait``: answered once it is done)."""
        return self._call({"op": "optimize", "session": self.name, "wait": wait})

    def estimate(self, since=None, from_key=None, to_key=None, robot=None, frame=None):
        """The estimate as ``GET …/estimate`` answers it: ``{"session", "sequence",
        "variables": [{"key", "kind", "value", "changed"}, …]}``."""
        command = {"op": "get_estimate", "session": self.name}
        for field, value in (("since", since), ("from", from_key), ("to", to_key), ("robot", robot), ("frame", frame)):
            if value is not None:
                command[field] = value
        return self._call(command)

    def estimate_array(self, kind=None, **query):
        """``keys, values = s.estimate_array()``: one kind's variables as arrays (see
        ``factord_client.EstimateArray``)."""
        return _estimate_to_array(self.estimate(**query), kind)

    def stats(self):
        return self._call({"op": "get_stats", "session": self.name})

    def define_factor_types(self, factor_types):
        """Declares more user-defined factor types (``FactorType.definition`` or the wire's
        dicts), all or none."""
        types = [t.definition if hasattr(t, "definition") else t for t in factor_types]
        return self._call({"op": "define_factor_types", "session": self.name, "factor_types": types})

    def outliers(self):
        """The loop closures held out of the estimate and why (sessions with ``outliers``)."""
        return self._call({"op": "list_outliers", "session": self.name})

    def robots(self):
        return self._call({"op": "list_robots", "session": self.name})

    def marginals(self, keys, joint=False):
        return self._call({"op": "get_marginals", "session": self.name, "keys": list(keys), "joint": joint})

    def graph(self):
        return self._call({"op": "get_graph", "session": self.name})

    def close(self):
        """Deletes the session (its memory is freed); also when the object is collected."""
        if getattr(self, "name", None) is not None:
            self._call({"op": "delete_session", "session": self.name})
            self.name = None

    def __del__(self):
        # A session nobody holds any more is deleted, so the shared service does not keep it.
        try:
            self.close()
        except Exception:  # noqa: BLE001 (interpreter shutdown, a service already gone)
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __repr__(self):
        return f"IncrementalSession({self.name!r}, {self.info.get('kind')!r})"
