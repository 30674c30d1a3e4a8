#!/usr/bin/env python3
"""Checks the factord wire schemas (proto/v1) and, optionally, a running server against them.

Usage:
    python proto/validate.py [--server http://127.0.0.1:8080] [--save-examples]

Without --server:
  (a) every proto/v1/*.schema.json is a valid draft 2020-12 schema whose $refs resolve, and every
      proto/v1/examples/<name>.example.json validates against the schema its name starts with
      (longest match; when the rest of the name is one of that schema's $defs, e.g.
      `reply-deleted`, against that definition);
  (b) proto/v1/openapi.json is OpenAPI 3.1 and its $refs resolve. It is generated from the
      server's types and handlers; `cargo test --test api openapi::` keeps it equal to what the server
      serves, checks its routes against the router's and its schemas against the files here.
With --server it also (c) drives that server through a scripted sequence (sessions, batches,
estimates, graphs, marginal covariances, events over SSE, a batch job, error cases, the web
view's pages, Prometheus metrics) and validates every real JSON response body and SSE event against the schema it
should match (the web view's pages: status and content type; /metrics: content type, exposition
format, every documented metric, and its counters moving after an accepted and a rejected batch). --save-examples then rewrites the examples the
sequence captures (proto/v1/examples/).

Prints one line per check; exits 1 listing every mismatch. Needs the PyPI packages `jsonschema`
and `referencing`; HTTP uses only the standard library.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import secrets
import sys
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path
from typing import Any

try:
    from jsonschema import Draft202012Validator
    from referencing import Registry, Resource
    from referencing.exceptions import Unresolvable
except ImportError:  # pragma: no cover - a hint, not a check
    sys.exit("validate.py needs `pip install jsonschema referencing`")

PROTO = Path(__file__).resolve().parent
V1 = PROTO / "v1"
EXAMPLES = V1 / "examples"
BASE = "https://factord.invalid/proto/v1/"


# --------------------------------------------------------------------------------------------
# Reporting


class Report:
    def __init__(self) -> None:
        self.passed = 0
        self.failures: list[str] = []

    def check(self, name: str, ok: bool, detail: str = "") -> bool:
        if ok:
            self.passed += 1
            print(f"ok    {name}")
        else:
            self.failures.append(f"{name}: {detail}" if detail else name)
            print(f"FAIL  {name}" + (f": {detail}" if detail else ""))
        return ok

    def finish(self) -> int:
        print(f"\n{self.passed} passed, {len(self.failures)} failed")
        if self.failures:
            print("\nMismatches:")
            for f in self.failures:
                print(f"  - {f}")
            return 1
        return 0


def compact(value: Any, indent: int = 0, width: int = 120) -> str:
    """JSON with short containers kept on one line (how the files in proto/ are laid out)."""
    flat = json.dumps(value, ensure_ascii=False)
    if not isinstance(value, (dict, list)) or len(flat) + indent <= width or not value:
        return flat
    pad = " " * (indent + 2)
    if isinstance(value, dict):
        items = [f"{pad}{json.dumps(k, ensure_ascii=False)}: {compact(v, indent + 2, width)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + "\n" + " " * indent + "}"
    items = [pad + compact(v, indent + 2, width) for v in value]
    return "[\n" + ",\n".join(items) + "\n" + " " * indent + "]"


# --------------------------------------------------------------------------------------------
# Schemas


class Schemas:
    def __init__(self, report: Report) -> None:
        self.report = report
        self.docs: dict[str, dict] = {}  # file name -> schema
        resources = []
        for path in sorted(V1.glob("*.schema.json")):
            try:
                doc = json.loads(path.read_text())
            except json.JSONDecodeError as e:
                report.check(f"schema {path.name} parses", False, str(e))
                continue
            self.docs[path.name] = doc
            resources.append((doc.get("$id", BASE + path.name), Resource.from_contents(doc)))
        self.registry = Registry().with_resources(resources)

    def validator(self, ref: str) -> Draft202012Validator:
        """`ref` is `file.schema.json` or `file.schema.json#/$defs/x`."""
        return Draft202012Validator({"$ref": BASE + ref}, registry=self.registry)

    def errors(self, ref: str, instance: Any) -> list[str]:
        try:
            errs = sorted(self.validator(ref).iter_errors(instance), key=lambda e: list(e.absolute_path))
        except Unresolvable as e:
            return [f"unresolvable reference {e}"]
        out = []
        for e in errs:
            where = "/".join(str(p) for p in e.absolute_path) or "(root)"
            # oneOf/anyOf failures: name the closest sub-error too.
            best = min(e.context, key=lambda c: len(list(c.relative_path)), default=None) if e.context else None
            extra = f" [{'/'.join(str(p) for p in best.absolute_path) or '(root)'}: {best.message[:160]}]" if best else ""
            out.append(f"{where}: {e.message[:200]}{extra}")
        return out

    def resolves(self, ref: str) -> str | None:
        """None when `ref` (absolute URI) resolves, else the reason."""
        try:
            self.registry.resolver().lookup(ref)
            return None
        except Unresolvable as e:
            return str(e) or type(e).__name__

    def check_all(self) -> None:
        r = self.report
        for name, doc in self.docs.items():
            try:
                Draft202012Validator.check_schema(doc)
                ok, detail = True, ""
            except Exception as e:  # SchemaError
                ok, detail = False, str(e).splitlines()[0]
            r.check(f"schema {name} is valid draft 2020-12", ok, detail)
            r.check(f"schema {name} $id", doc.get("$id") == BASE + name, f"$id is {doc.get('$id')!r}, expected {BASE + name!r}")
            bad = []
            for ref in refs_in(doc):
                target = urllib.parse.urljoin(BASE + name, ref)
                why = self.resolves(target)
                if why:
                    bad.append(f"{ref} ({why})")
            r.check(f"schema {name} $refs resolve", not bad, "; ".join(bad))

    def schema_for_example(self, example: str) -> tuple[str | None, str | None]:
        """Maps `batch-ack-x.example.json` to (`batch-ack.schema.json`, def or None)."""
        stem = example[: -len(".example.json")]
        best = None
        for name in self.docs:
            base = name[: -len(".schema.json")]
            if (stem == base or stem.startswith(base + "-")) and (best is None or len(base) > len(best)):
                best = base
        if best is None:
            return None, None
        rest = stem[len(best) + 1 :].replace("-", "_")
        defs = self.docs[best + ".schema.json"].get("$defs", {})
        return best + ".schema.json", (rest if rest in defs else None)

    def check_examples(self) -> None:
        r = self.report
        covered = set()
        for path in sorted(EXAMPLES.glob("*.example.json")):
            schema, definition = self.schema_for_example(path.name)
            if not r.check(f"example {path.name} names a schema", schema is not None, "no schema name is a prefix of it"):
                continue
            covered.add(schema)
            ref = schema + (f"#/$defs/{definition}" if definition else "")
            try:
                instance = json.loads(path.read_text())
            except json.JSONDecodeError as e:
                r.check(f"example {path.name} parses", False, str(e))
                continue
            errs = self.errors(ref, instance)
            r.check(f"example {path.name} validates against {ref}", not errs, "; ".join(errs[:5]))
        for name in self.docs:
            if name != "common.schema.json":
                r.check(f"schema {name} has an example", name in covered, "add examples/" + name.replace(".schema.json", ".example.json"))

    def check_counter_examples(self) -> None:
        for ref, instance, why in COUNTER_EXAMPLES:
            self.report.check(f"{ref} refuses {why}", bool(self.errors(ref, instance)), f"{json.dumps(instance)[:200]} validates")


# Instances each schema must refuse (so that a rule is not documented without being checked):
# (reference, instance, why).
_ACK = {"session": "s", "sequence": 2, "factor_ids": [0], "predicted": [], "reflected": False}
COUNTER_EXAMPLES = [
    ("batch.schema.json", {"producer": "robot-7"}, "producer without producer_seq"),
    ("batch.schema.json", {"producer_seq": 1}, "producer_seq without producer"),
    ("batch.schema.json", {"producer": "a/b", "producer_seq": 1}, "a producer id outside [A-Za-z0-9._-]"),
    ("batch.schema.json", {"producer": "x" * 65, "producer_seq": 1}, "a producer id of 65 characters"),
    ("batch.schema.json", {"producer": "robot-7", "producer_seq": 0}, "producer_seq 0"),
    ("batch-ack.schema.json", dict(_ACK, producer="robot-7", producer_seq=2), "a producer's ack without accepted_through"),
    ("batch-ack.schema.json", dict(_ACK, duplicate=False), "duplicate false (absent instead)"),
    ("batch-ack.schema.json", dict(_ACK, duplicate=True), "a duplicate without its producer"),
    ("event.schema.json", {"type": "lagged", "session": "s", "skipped": 3, "sequence": 9, "reflected_sequence": 9}, "lagged without producers"),
    ("event.schema.json", {"type": "lagged", "missed": 3}, "the old SSE lagged body"),
    ("event.schema.json", {"type": "error", "session": "s", "sequence": None, "error": {"code": "x", "message": "m", "status": 409},
                           "producer_sequence": 3}, "an unknown error event field"),
    ("command.schema.json", {"op": "optimize", "session": "s", "after_producer": "r", "after_seq": 1, "after_timeout_ms": 60001},
     "after_timeout_ms beyond 60000"),
    ("command.schema.json", {"op": "producer_status", "session": "s"}, "producer_status without producer"),
    ("estimate-query.schema.json", {"after_seq": -1}, "a negative after_seq"),
    ("producer-status.schema.json", {"session": "s", "producer": "p", "accepted_through": 1, "sequence": 1}, "without reflected_sequence"),
]


def values_of(node: Any, key: str):
    """Every string value of `key` anywhere in a JSON document."""
    if isinstance(node, dict):
        for k, v in node.items():
            if k == key and isinstance(v, str):
                yield v
            else:
                yield from values_of(v, key)
    elif isinstance(node, list):
        for v in node:
            yield from values_of(v, key)


def refs_in(node: Any):
    return values_of(node, "$ref")


# --------------------------------------------------------------------------------------------
# OpenAPI


def check_openapi(schemas: Schemas, report: Report) -> dict | None:
    r = report
    path = V1 / "openapi.json"
    try:
        api = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        r.check("openapi.json parses", False, str(e))
        return None
    r.check("openapi.json is OpenAPI 3.1", str(api.get("openapi", "")).startswith("3.1"), f"openapi: {api.get('openapi')!r}")
    try:  # optional, when installed
        from openapi_spec_validator import validate as validate_spec

        try:
            validate_spec(api, base_uri=path.as_uri())
            r.check("openapi.json passes openapi-spec-validator", True)
        except Exception as e:
            r.check("openapi.json passes openapi-spec-validator", False, str(e).splitlines()[0][:300])
    except ImportError:
        print("skip  openapi-spec-validator not installed (optional)")

    bad = []
    for ref in sorted(set(refs_in(api))):
        target: Any = api
        try:
            assert ref.startswith("#/")
            for part in ref[2:].split("/"):
                target = target[part.replace("~1", "/").replace("~0", "~")]
        except (AssertionError, KeyError, TypeError):
            bad.append(ref)
    r.check("openapi.json $refs resolve inside it", not bad, "; ".join(bad))
    return api


# --------------------------------------------------------------------------------------------
# Live server


class Response:
    def __init__(self, status: int, headers, body: bytes) -> None:
        self.status = status
        self.headers = headers
        self.body = body

    @property
    def content_type(self) -> str:
        return self.headers.get("Content-Type", "") if self.headers else ""

    def json(self) -> Any:
        return json.loads(self.body)


class Live:
    def __init__(self, url: str, schemas: Schemas, report: Report, save: bool, lag_batches: int = 0) -> None:
        self.url = url.rstrip("/")
        self.lag_batches = lag_batches
        self.schemas = schemas
        self.report = report
        self.save = save
        self.saved: list[str] = []
        # Fixed names when saving examples (so they read well), else unique ones.
        tag = "" if save else "-" + secrets.token_hex(3)
        self.s2 = f"robot-2d{tag}"
        self.s3 = f"robot-3d{tag}"
        self.sx = f"diverging{tag}"
        self.sp = f"producers{tag}"
        self.created: list[str] = []

    # -- plumbing ------------------------------------------------------------------------------

    def request(self, method: str, path: str, body: Any = None, raw: bytes | None = None,
                headers: dict | None = None, timeout: float = 60) -> Response:
        data = raw if raw is not None else (json.dumps(body).encode() if body is not None else None)
        req = urllib.request.Request(self.url + path, data=data, method=method, headers=headers or {})
        if data is not None and "Content-Type" not in (headers or {}):
            req.add_header("Content-Type", "application/json")
        try:
            with urllib.request.urlopen(req, timeout=timeout) as resp:
                return Response(resp.status, resp.headers, resp.read())
        except urllib.error.HTTPError as e:
            return Response(e.code, e.headers, e.read())

    def example(self, name: str | None, value: Any) -> None:
        if self.save and name:
            (EXAMPLES / f"{name}.example.json").write_text(compact(value) + "\n")
            self.saved.append(name)

    def validate(self, label: str, ref: str, value: Any, example: str | None = None) -> bool:
        errs = self.schemas.errors(ref, value)
        ok = self.report.check(f"{label}: body matches {ref}", not errs, "; ".join(errs[:5]) + f" (body: {json.dumps(value)[:300]})")
        if ok:
            self.example(example, value)
        return ok

    def call(self, label: str, method: str, path: str, status: int, ref: str, body: Any = None,
             raw: bytes | None = None, example: str | None = None, request_example: str | None = None,
             error_code: str | None = None, headers: dict | None = None, error_field: str | None = None) -> Any:
        """One request; checks status, content type and body schema (and, for errors, the code and
        `field` when given). Returns the parsed body."""
        if request_example and body is not None:
            self.example(request_example, body)
        r = self.request(method, path, body=body, raw=raw, headers=headers)
        name = f"{method} {path} {label}".strip()
        self.report.check(f"{name}: status {status}", r.status == status, f"got {r.status}: {r.body[:300]!r}")
        if not self.report.check(f"{name}: application/json", r.content_type.startswith("application/json"), f"Content-Type {r.content_type!r}"):
            return None
        try:
            value = r.json()
        except json.JSONDecodeError as e:
            self.report.check(f"{name}: JSON body", False, str(e))
            return None
        if self.validate(name, ref, value, example) and ref.startswith("error.schema.json"):
            err = value["error"]
            if error_code is not None:
                self.report.check(f"{name}: error code {error_code}", err["code"] == error_code, f"got {err['code']!r}")
            if error_field is not None:
                self.report.check(f"{name}: error field {error_field}", err.get("field") == error_field, f"got {err.get('field')!r}")
            self.report.check(f"{name}: error.status equals the HTTP status", err["status"] == r.status, f"{err['status']} vs {r.status}")
            if "retry_after" in err:
                self.report.check(f"{name}: Retry-After header", r.headers.get("Retry-After") == str(err["retry_after"]),
                                  f"header {r.headers.get('Retry-After')!r}")
        return value

    # -- SSE -----------------------------------------------------------------------------------

    def open_events(self, session: str, want: set[str], timeout: float = 30.0, until=None):
        """Subscribes to a session's SSE stream; returns (thread, events list, error list).

        Reads until every event name in `want` was seen, or, given `until` (a predicate over the
        events list), until it holds. The subscription exists once this returns (the server
        subscribes before it answers)."""
        events: list[tuple[str, str]] = []
        problems: list[str] = []
        req = urllib.request.Request(f"{self.url}/v1/sessions/{session}/events", headers={"Accept": "text/event-stream"})
        resp = urllib.request.urlopen(req, timeout=timeout)
        ctype = resp.headers.get("Content-Type", "")
        self.report.check(f"GET /v1/sessions/{session}/events: text/event-stream", ctype.startswith("text/event-stream"), f"Content-Type {ctype!r}")

        def reader() -> None:
            deadline = time.monotonic() + timeout
            name, data = None, []
            seen: set[str] = set()
            try:
                while time.monotonic() < deadline and not (until(events) if until else want <= seen):
                    line = resp.readline()
                    if not line:
                        break
                    line = line.decode().rstrip("\r\n")
                    if line.startswith(":"):
                        continue  # keep-alive comment
                    if line == "":
                        if data:
                            events.append((name or "message", "\n".join(data)))
                            seen.add(name or "message")
                        name, data = None, []
                    elif line.startswith("event:"):
                        name = line[6:].strip()
                    elif line.startswith("data:"):
                        data.append(line[5:].lstrip(" "))
            except Exception as e:  # timeouts end the read
                problems.append(f"{type(e).__name__}: {e}")
            finally:
                resp.close()

        thread = threading.Thread(target=reader, daemon=True)
        thread.start()
        return thread, events, problems

    def check_events(self, label: str, events: list[tuple[str, str]], want: set[str], examples: dict[str, str]) -> None:
        topic_type = {"acks": "ack", "stats": "iteration", "poses": "estimate", "summary": "summary", "errors": "error",
                      "state": "state", "window": "window"}
        seen = {n for n, _ in events}
        self.report.check(f"SSE {label}: received {', '.join(sorted(want))}", want <= seen, f"got {sorted(seen)}")
        saved = set()
        for name, data in events:
            try:
                value = json.loads(data)
            except json.JSONDecodeError as e:
                self.report.check(f"SSE {label} `{name}` data is JSON", False, f"{e}: {data[:200]}")
                continue
            expected = "lagged" if name == "lagged" else topic_type.get(name)
            if not self.report.check(f"SSE {label}: event name `{name}` is a known topic", expected is not None):
                continue
            self.report.check(f"SSE {label} `{name}`: type is {expected}", isinstance(value, dict) and value.get("type") == expected,
                              f"type {value.get('type') if isinstance(value, dict) else value!r}")
            ex = examples.get(expected) if expected not in saved else None
            if self.validate(f"SSE {label} `{name}`", "event.schema.json", value, ex) and ex:
                saved.add(expected)

    # -- graph, marginals, web view ------------------------------------------------------------

    def check_covariances(self, label: str, m: dict, keys: list[int], dims: list[int]) -> None:
        """Marginals answer: variables in the order asked, d×d symmetric blocks, zero when fixed,
        a positive diagonal otherwise, and `joint` (when present) made of them."""
        r = self.report
        got = [v["key"] for v in m["variables"]]
        r.check(f"{label}: variables in the order asked", got == keys, f"{got} vs {keys}")
        bad = []
        for v, d in zip(m["variables"], dims):
            c = v["covariance"]
            if len(c) != d or any(len(row) != d for row in c):
                bad.append(f"{v['key']}: not {d}x{d}")
                continue
            if any(abs(c[i][j] - c[j][i]) > 1e-9 * max(1.0, abs(c[i][j])) for i in range(d) for j in range(d)):
                bad.append(f"{v['key']}: not symmetric")
            if v["fixed"] != (v["key"] in m["gauge_fixed"]):
                bad.append(f"{v['key']}: fixed={v['fixed']} but gauge_fixed={m['gauge_fixed']}")
            if v["fixed"] and any(x != 0 for row in c for x in row):
                bad.append(f"{v['key']}: fixed but its covariance is not zero")
            if not v["fixed"] and not all(c[i][i] > 0 for i in range(d)):
                bad.append(f"{v['key']}: free but its diagonal is not positive")
        r.check(f"{label}: covariances are d×d, symmetric, zero exactly when fixed", not bad, "; ".join(bad))
        if "joint" in m:
            n, joint = sum(dims), m["joint"]
            ok = len(joint) == n and all(len(row) == n for row in joint)
            if ok:
                starts = [sum(dims[:i]) for i in range(len(dims))]
                ok = all(joint[starts[i] + a][starts[i] + b] == v["covariance"][a][b]
                         for i, v in enumerate(m["variables"]) for a in range(dims[i]) for b in range(dims[i]))
            r.check(f"{label}: joint is {n}×{n} with the variables' covariances as diagonal blocks", ok)
            if ok:
                r.check(f"{label}: joint is symmetric",
                        all(abs(joint[i][j] - joint[j][i]) <= 1e-9 * max(1.0, abs(joint[i][j])) for i in range(n) for j in range(i)))

    # -- Prometheus metrics --------------------------------------------------------------------

    METRICS_CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
    METRICS = {  # name -> TYPE
        "factord_sessions": "gauge", "factord_sessions_recovering": "gauge", "factord_queue_depth": "gauge",
        "factord_busy_workers": "gauge", "factord_workers": "gauge", "factord_session_memory_bytes": "gauge",
        "factord_uptime_seconds": "gauge", "factord_solves_total": "counter", "factord_solver_iterations_total": "counter",
        "factord_batches_accepted_total": "counter", "factord_rejected_inputs_total": "counter",
        "factord_solve_duration_seconds": "histogram", "factord_journal_fsync_seconds": "histogram",
    }
    SAMPLE = re.compile(r'^([a-zA-Z_:][a-zA-Z0-9_:]*)(\{(?:[a-zA-Z_][a-zA-Z0-9_]*="(?:[^"\\]|\\.)*",?)*\})? (\S+)(?: -?\d+)?$')

    def scrape(self, label: str, check_format: bool = False) -> dict[str, float] | None:
        """GET /metrics: checks status and content type; returns {`name{labels}`: value}. With
        check_format also the exposition format, every documented metric and the histograms."""
        r = self.report
        resp = self.request("GET", "/metrics")
        name = f"GET /metrics ({label})"
        if not r.check(f"{name}: status 200", resp.status == 200, f"got {resp.status}: {resp.body[:200]!r}"):
            return None
        r.check(f"{name}: {self.METRICS_CONTENT_TYPE}", resp.content_type.replace(" ", "") == self.METRICS_CONTENT_TYPE.replace(" ", ""),
                f"Content-Type {resp.content_type!r}")
        samples: dict[str, float] = {}
        types: dict[str, str] = {}
        bad = []
        for line in resp.body.decode("utf-8", "replace").splitlines():
            if line.startswith("# TYPE "):
                parts = line.split()
                if len(parts) == 4:
                    types[parts[2]] = parts[3]
                continue
            if not line or line.startswith("#"):
                continue
            m = self.SAMPLE.match(line)
            try:
                samples[m.group(1) + (m.group(2) or "")] = float(m.group(3)) if m else math.nan
            except ValueError:
                m = None
            if not m:
                bad.append(line[:120])
        if not check_format:
            return samples
        r.check(f"{name}: every line is a comment or `name{{labels}} value`", not bad, "; ".join(bad[:5]))
        for metric, kind in self.METRICS.items():
            r.check(f"{name}: {metric} is a {kind}", types.get(metric) == kind, f"TYPE {types.get(metric)!r}")
            if kind == "histogram":
                buckets = [(k, v) for k, v in samples.items() if k.startswith(metric + "_bucket{")]
                counts = [v for _, v in buckets]
                ok = (bool(buckets) and buckets[-1][0].endswith('le="+Inf"}') and counts == sorted(counts)
                      and samples.get(metric + "_count") == counts[-1] and metric + "_sum" in samples)
                r.check(f"{name}: {metric} has cumulative buckets up to +Inf, _sum and _count", ok,
                        f"{len(buckets)} buckets, _count {samples.get(metric + '_count')}")
            elif metric != "factord_rejected_inputs_total":  # its samples appear with their first reason
                r.check(f"{name}: {metric} has a sample", metric in samples)
        return samples

    @staticmethod
    def rejected(samples: dict[str, float] | None, reason: str) -> float | None:
        return None if samples is None else samples.get(f'factord_rejected_inputs_total{{reason="{reason}"}}')

    def web_page(self, path: str, content_type: str, contains: bytes) -> None:
        resp = self.request("GET", path)
        name = f"GET {path}"
        r = self.report
        r.check(f"{name}: status 200", resp.status == 200, f"got {resp.status}: {resp.body[:200]!r}")
        r.check(f"{name}: {content_type}", resp.content_type.startswith(content_type), f"Content-Type {resp.content_type!r}")
        r.check(f"{name}: body has {contains.decode()!r}", contains in resp.body, f"{resp.body[:120]!r}")

    @staticmethod
    def bal_batch() -> dict:
        """Three Snavely cameras looking at 25 points, measurements exact (BAL's model, no distortion)."""
        def rotate(w, x):
            th = (w[0] ** 2 + w[1] ** 2 + w[2] ** 2) ** 0.5
            k = [a / th for a in w]
            c, s = math.cos(th), math.sin(th)
            kx = [k[1] * x[2] - k[2] * x[1], k[2] * x[0] - k[0] * x[2], k[0] * x[1] - k[1] * x[0]]
            kd = sum(k[i] * x[i] for i in range(3))
            return [x[i] * c + kx[i] * s + k[i] * kd * (1 - c) for i in range(3)]

        cameras = [[0.01, 0.0, 0.0, 0, 0, -10, 500, 0, 0], [0.02, 0.05, 0.01, -1, 0, -10, 500, 0, 0],
                   [-0.03, -0.04, 0.01, 1, 0.5, -10.5, 500, 0, 0]]
        points = [[-2 + i, -2 + j, 0.25 * ((i + 2 * j) % 5) - 0.5] for i in range(5) for j in range(5)]
        factors = []
        for ci, cam in enumerate(cameras):
            for pj, x in enumerate(points):
                q = [a + b for a, b in zip(rotate(cam[0:3], x), cam[3:6])]
                factors.append({"type": "reprojection_snavely", "keys": [ci, 100 + pj],
                                "measurement": [-cam[6] * q[0] / q[2], -cam[6] * q[1] / q[2]], "sigmas": [1.0, 1.0]})
        variables = [{"key": i, "kind": "snavely_camera", "value": c} for i, c in enumerate(cameras)]
        variables += [{"key": 100 + j, "kind": "point3", "value": x} for j, x in enumerate(points)]
        return {"variables": variables, "factors": factors}

    # -- exactly-once ingest and ordering ------------------------------------------------------

    def producers(self) -> None:
        """Numbered batches: acks with producer fields, a repeat answered with its original ack and
        applied no second time, a gap refused, a refused batch not using up its number, the
        producer's status, reads and solves `after` its batches, and the ack events of all that."""
        r = self.report
        sp, robot = self.sp, "robot-7"
        base = f"/v1/sessions/{sp}"
        self.call("producers", "POST", "/v1/sessions", 201, "session-info.schema.json", body={"session": sp, "kind": "pose_graph_2d"})
        self.created.append(sp)

        def acked(events: list) -> bool:  # the three acks and the repeat's
            return sum(1 for n, _ in events if n == "acks") >= 4

        thread, events, problems = self.open_events(sp, {"acks"}, timeout=20, until=acked)

        def batch(seq: int, key: int, **extra) -> dict:
            b = {"producer": robot, "producer_seq": seq, "variables": [{"key": key, "kind": "se2"}],
                 "factors": [{"type": "between_se2", "keys": [key - 1, key], "measurement": [1.0, 0.0, 0.05], "sigmas": [0.1, 0.1, 0.05]}]}
            b.update(extra)
            return b

        first = {"producer": robot, "producer_seq": 1, "variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0], "fixed": True}]}
        ack1 = self.call("producer seq 1", "POST", f"{base}/batches", 200, "batch-ack.schema.json", body=first)
        if ack1:
            r.check("ack of a numbered batch: producer, producer_seq, accepted_through 1, no duplicate",
                    (ack1.get("producer"), ack1.get("producer_seq"), ack1.get("accepted_through"), "duplicate" in ack1) == (robot, 1, 1, False),
                    json.dumps(ack1))
        b2 = batch(2, 1)
        ack2 = self.call("producer seq 2", "POST", f"{base}/batches?wait=true", 200, "batch-ack.schema.json", body=b2,
                         request_example="batch-producer", example="batch-ack-producer")
        before = self.call("before a repeat", "GET", base, 200, "session-stats.schema.json")
        again = self.call("repeat of seq 2", "POST", f"{base}/batches", 200, "batch-ack.schema.json", body=b2, example="batch-ack-duplicate")
        after = self.call("after a repeat", "GET", base, 200, "session-stats.schema.json")
        if ack2 and again:
            same = {k: ack2[k] for k in ("session", "sequence", "factor_ids", "predicted", "producer", "producer_seq", "accepted_through")}
            r.check("repeat: the original ack (sequence, factor_ids, predicted, producer fields) with duplicate true",
                    again.get("duplicate") is True and {k: again.get(k) for k in same} == same, f"{json.dumps(again)} vs {json.dumps(ack2)}")
        if before and after:
            r.check("repeat: nothing applied (sequence, variables and factors unchanged)",
                    [before[k] for k in ("sequence", "num_variables", "num_factors")] == [after[k] for k in ("sequence", "num_variables", "num_factors")],
                    f"{[before[k] for k in ('sequence', 'num_variables', 'num_factors')]} -> {[after[k] for k in ('sequence', 'num_variables', 'num_factors')]}")
        gap = self.call("gap", "POST", f"{base}/batches", 409, "error.schema.json", body=batch(4, 2), error_code="producer_sequence_gap",
                        error_field="producer_seq", example="error-producer-sequence-gap")
        if gap:
            r.check("gap: the message names the number expected (3)", "expects batch 3" in gap["error"]["message"], gap["error"]["message"])
        self.call("refused seq 3", "POST", f"{base}/batches", 422, "error.schema.json", body=batch(3, 2, factors=[
            {"type": "between_se2", "keys": [9, 2], "measurement": [1.0, 0.0, 0.05], "sigmas": [0.1, 0.1, 0.05]}]), error_code="unknown_variable")
        ack3 = self.call("seq 3 after its refusal", "POST", f"{base}/batches", 200, "batch-ack.schema.json", body=batch(3, 2))
        if ack3:
            r.check("a refused batch does not use up its number: seq 3 accepted after a 422", ack3.get("accepted_through") == 3, json.dumps(ack3))
        self.call("producer without seq", "POST", f"{base}/batches", 400, "error.schema.json", body={"producer": robot},
                  error_code="missing_producer_seq", error_field="producer_seq")
        self.call("seq without producer", "POST", f"{base}/batches", 400, "error.schema.json", body={"producer_seq": 4},
                  error_code="missing_producer", error_field="producer")
        self.call("invalid producer", "POST", f"{base}/batches", 400, "error.schema.json", body={"producer": "a/b", "producer_seq": 1},
                  error_code="invalid_producer", error_field="producer")
        self.call("seq 0", "POST", f"{base}/batches", 400, "error.schema.json", body={"producer": robot, "producer_seq": 0},
                  error_code="invalid_producer_seq", error_field="producer_seq")

        status = self.call("", "GET", f"{base}/producers/{robot}", 200, "producer-status.schema.json", example="producer-status")
        if status and ack3:
            r.check("producer status: accepted_through 3 at the sequence of its last batch",
                    (status["producer"], status["accepted_through"], status["sequence"]) == (robot, 3, ack3["sequence"]), json.dumps(status))
        unknown = self.call("unknown producer", "GET", f"{base}/producers/nobody", 200, "producer-status.schema.json")
        if unknown:
            r.check("producer status of a producer never seen: zeros", (unknown["accepted_through"], unknown["sequence"]) == (0, 0), json.dumps(unknown))
        self.call("unknown session", "GET", f"/v1/sessions/no-such-session/producers/{robot}", 404, "error.schema.json", error_code="unknown_session")

        est = self.call("after", "GET", f"{base}/estimate?after_producer={robot}&after_seq=3", 200, "estimate.schema.json")
        if est:
            r.check("estimate after the producer's seq 3 holds its variables 0..2", [v["key"] for v in est["variables"]] == [0, 1, 2],
                    f"{[v['key'] for v in est['variables']]}")
        started = time.monotonic()
        self.call("after, not reached", "GET", f"{base}/estimate?after_producer={robot}&after_seq=4&after_timeout_ms=300", 503,
                  "error.schema.json", error_code="after_timeout", error_field="after_seq", example="error-after-timeout")
        waited = time.monotonic() - started
        r.check("after_timeout_ms=300 waits about that long", 0.25 <= waited < 5, f"{waited:.3f} s")
        self.call("after_producer alone", "GET", f"{base}/estimate?after_producer={robot}", 400, "error.schema.json",
                  error_code="missing_after_seq", error_field="after_seq")
        self.call("after_seq alone", "POST", f"{base}/optimize?after_seq=1", 400, "error.schema.json",
                  error_code="missing_after_producer", error_field="after_producer")
        self.call("after_timeout_ms too long", "GET", f"{base}/estimate?after_producer={robot}&after_seq=1&after_timeout_ms=60001", 400,
                  "error.schema.json", error_code="invalid_value", error_field="after_timeout_ms")
        opt = self.call("after", "POST", f"{base}/optimize?wait=true&after_producer={robot}&after_seq=3", 200, "reply.schema.json#/$defs/optimizing")
        if opt and ack3:
            r.check("optimize after the producer's seq 3 includes it", opt["sequence"] >= ack3["sequence"], json.dumps(opt)[:200])

        thread.join(25)
        r.check("SSE reader ended cleanly (producers)", not problems, "; ".join(problems))
        self.check_events("producers", events, {"acks"}, {})
        acks = [json.loads(d) for n, d in events if n == "acks"]
        got = [(a.get("producer_seq"), a.get("accepted_through"), a.get("duplicate", False)) for a in acks]
        r.check("SSE acks: seq 1, 2, the repeat of 2 (duplicate), 3, each with accepted_through",
                got[:4] == [(1, 1, False), (2, 2, False), (2, 2, True), (3, 3, False)], f"{got}")

    def lag(self, batches: int) -> None:
        """A subscriber that falls behind gets a `lagged` marker, not a silent gap: an SSE client
        with a small receive buffer reads nothing while `batches` numbered one-pose batches are
        posted (manual policy: ack + estimate each), so more events than the session buffers (4096)
        and the sockets hold wait for it. Then its stream must carry the marker (with the producer's
        cumulative accepted_through) followed by an estimate holding the last pose."""
        import http.client
        import socket

        r = self.report
        sl = self.sp + "-lag"
        self.call("lag", "POST", "/v1/sessions", 201, "session-info.schema.json",
                  body={"session": sl, "kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"}})
        self.created.append(sl)
        url = urllib.parse.urlsplit(self.url)
        slow = socket.socket()
        slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        slow.connect((url.hostname, url.port or 80))
        slow.sendall(f"GET /v1/sessions/{sl}/events HTTP/1.1\r\nHost: {url.netloc}\r\nAccept: text/event-stream\r\n\r\n".encode())
        time.sleep(0.3)
        conn = http.client.HTTPConnection(url.hostname, url.port or 80, timeout=60)
        failed = None
        started = time.monotonic()
        for i in range(batches):
            batch = {"producer": "robot-lag", "producer_seq": i + 1, "variables": [{"key": i, "kind": "se2", "value": [i, 0, 0], "fixed": i == 0}]}
            if i:
                batch["factors"] = [{"type": "between_se2", "keys": [i - 1, i], "measurement": [1, 0, 0], "sigmas": [1, 1, 1]}]
            conn.request("POST", f"/v1/sessions/{sl}/batches", body=json.dumps(batch), headers={"Content-Type": "application/json"})
            resp = conn.getresponse()
            resp.read()
            if resp.status != 200:
                failed = f"batch {i + 1}: status {resp.status}"
                break
        conn.close()
        r.check(f"lag: {batches} numbered batches accepted ({time.monotonic() - started:.1f} s)", failed is None, failed or "")
        slow.settimeout(3)
        events, buf = [], b""
        try:
            while True:
                data = slow.recv(1 << 20)
                if not data:
                    break
                buf += data
                *blocks, buf = buf.split(b"\n\n")
                for block in blocks:
                    lines = block.decode(errors="replace").split("\n")
                    name = next((l[6:].strip() for l in lines if l.startswith("event:")), None)
                    data_lines = [l[5:].lstrip(" ") for l in lines if l.startswith("data:")]
                    if name and data_lines:
                        events.append((name, "\n".join(data_lines)))
                if any(n == "lagged" for n, _ in events) and len(events) > 2 and events[-1][0] == "poses":
                    last = json.loads(events[-1][1])
                    if any(v["key"] == batches - 1 for v in last.get("variables", [])):
                        break
        except (socket.timeout, OSError):
            pass
        finally:
            slow.close()
        names = [n for n, _ in events]
        if not r.check("lag: the slow SSE client got a `lagged` event", "lagged" in names, f"{len(events)} events, names {sorted(set(names))}"):
            return
        at = names.index("lagged")
        marker = json.loads(events[at][1])
        self.validate("SSE lag `lagged`", "event.schema.json", marker, "event-lagged")
        r.check("lag: the marker carries the producer's cumulative accepted_through and the session's sequence",
                marker.get("producers", {}).get("robot-lag") == batches and marker.get("sequence") == batches and marker.get("skipped", 0) >= 1,
                json.dumps(marker))
        r.check("lag: an `estimate` (poses) re-synchronisation follows the marker", at + 1 < len(names) and names[at + 1] == "poses",
                f"then {names[at + 1:at + 3]}")
        latest = {}
        for n, d in events[at + 1:]:
            if n == "poses":
                for v in json.loads(d)["variables"]:
                    latest[v["key"]] = v["value"]
        r.check("lag: the latest value of the last pose arrives after the marker", latest.get(batches - 1) == [float(batches - 1), 0.0, 0.0],
                f"{latest.get(batches - 1)}")
        self.check_events("lag", events[at:at + 3], {"lagged", "poses"}, {})

    # -- the scripted sequence -----------------------------------------------------------------

    def run(self) -> None:
        try:
            self.sequence()
        finally:
            for s in self.created:  # leave the server as found
                self.request("DELETE", f"/v1/sessions/{s}")

    def sequence(self) -> None:
        r = self.report
        health = self.call("", "GET", "/v1/health", 200, "health.schema.json", example="health")
        if health is None:
            return
        r.check("health lists pose_graph_2d and pose_graph_3d", {"pose_graph_2d", "pose_graph_3d"} <= set(health.get("session_kinds", [])))

        # Prometheus metrics.
        before = self.scrape("format", check_format=True)
        if before:
            r.check("metrics: factord_workers >= 1", before.get("factord_workers", 0) >= 1, f"{before.get('factord_workers')}")
            r.check("metrics: factord_busy_workers <= factord_workers",
                    before.get("factord_busy_workers", 0) <= before.get("factord_workers", 0))
            r.check("metrics: factord_uptime_seconds > 0", before.get("factord_uptime_seconds", 0) > 0)

        # Sessions.
        self.call("2D", "POST", "/v1/sessions", 201, "session-info.schema.json",
                  body={"session": self.s2, "kind": "pose_graph_2d"}, example="session-info", request_example="create-session")
        self.created.append(self.s2)
        create3 = {"session": self.s3, "kind": "pose_graph_3d",
                   "options": {"method": "levenberg_marquardt", "max_iterations": 50, "initialization": "chordal"},
                   "auto_optimize": {"policy": "manual"}}
        info3 = self.call("3D manual", "POST", "/v1/sessions", 201, "session-info.schema.json", body=create3,
                          example="session-info-3d", request_example="create-session-3d")
        if info3:
            self.example("solver-options", info3["options"])
        self.created.append(self.s3)
        self.call("", "GET", "/v1/sessions", 200, "session-list.schema.json", example="session-list")
        self.call("no summary yet", "GET", f"/v1/sessions/{self.s2}/summary", 404, "error.schema.json",
                  error_code="no_summary", example="error-no-summary")

        # 2D: a square with a loop closure, values predicted from odometry, events watched.
        batch2 = {
            "variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0], "fixed": True}] + [{"key": k, "kind": "se2"} for k in range(1, 5)],
            "factors": [
                {"type": "between_se2", "keys": [0, 1], "measurement": [1.0, 0.02, 1.5708], "sigmas": [0.1, 0.1, 0.05]},
                {"type": "between_se2", "keys": [1, 2], "measurement": [1.05, -0.01, 1.55], "sigmas": [0.1, 0.1, 0.05]},
                {"type": "between_se2", "keys": [2, 3], "measurement": [0.97, 0.03, 1.6], "information": [100, 0, 0, 100, 0, 400]},
                {"type": "between_se2", "keys": [3, 4], "measurement": [1.02, 0.0, 1.5708], "information": [100, 0, 0, 0, 100, 0, 0, 0, 400]},
                {"type": "between_se2", "keys": [4, 0], "measurement": [0.0, 0.0, 0.0], "sigmas": [0.05, 0.05, 0.02],
                 "robust": {"kind": "huber", "scale": 1.0}},
            ],
        }
        want = {"acks", "poses", "stats", "summary"}
        thread, events, problems = self.open_events(self.s2, want)
        before = self.scrape("before a batch")
        ack = self.call("wait", "POST", f"/v1/sessions/{self.s2}/batches?wait=true", 200, "batch-ack.schema.json",
                        body=batch2, example="batch-ack", request_example="batch")
        after = self.scrape("after a batch")
        if before is not None and after is not None and ack:
            accepted = "factord_batches_accepted_total"
            r.check(f"metrics: {accepted} increases after an accepted batch", after.get(accepted, 0) >= before.get(accepted, 0) + 1,
                    f"{before.get(accepted)} -> {after.get(accepted)}")
            solves = "factord_solves_total"
            if ack.get("solved") is True:
                r.check(f"metrics: {solves} increases after a batch solved with wait", after.get(solves, 0) >= before.get(solves, 0) + 1,
                        f"{before.get(solves)} -> {after.get(solves)}")
            r.check("metrics: factord_sessions counts the sessions created", after.get("factord_sessions", 0) >= 2,
                    f"{after.get('factord_sessions')}")
            r.check("metrics: factord_session_memory_bytes > 0 with a session holding a graph",
                    after.get("factord_session_memory_bytes", 0) > 0)
        thread.join(35)
        r.check("SSE reader ended cleanly", not problems, "; ".join(problems))
        self.check_events("2D batch", events, want, {"ack": "event-ack", "estimate": "event", "iteration": "event-iteration", "summary": "event-summary"})
        if ack:
            r.check("batch-ack: one factor id per factor", len(ack["factor_ids"]) == len(batch2["factors"]))
            r.check("batch-ack: predicted keys 1..4", sorted(ack["predicted"]) == [1, 2, 3, 4], f"{ack['predicted']}")
            r.check("batch-ack: solved is true (every_batch, wait)", ack.get("solved") is True, f"{ack.get('solved')!r}")
        seq = ack["sequence"] if ack else 1

        est = self.call("", "GET", f"/v1/sessions/{self.s2}/estimate", 200, "estimate.schema.json", example="estimate")
        if est:
            r.check("estimate has the 5 variables, sorted", [v["key"] for v in est["variables"]] == [0, 1, 2, 3, 4])
        self.example("estimate-query", {"since": seq, "from": 0, "to": 99})
        since = self.call("since", "GET", f"/v1/sessions/{self.s2}/estimate?since={seq}&from=0&to=99", 200, "estimate.schema.json",
                          example="estimate-since")
        if since is not None:
            r.check("estimate?since=<its sequence> is empty", since["variables"] == [], f"{since['variables']}")
        self.call("range", "GET", f"/v1/sessions/{self.s2}/estimate?from=1&to=2", 200, "estimate.schema.json")
        stats = self.call("", "GET", f"/v1/sessions/{self.s2}", 200, "session-stats.schema.json", example="session-stats")
        if stats:
            r.check("stats: solved_sequence == sequence after wait", stats["solved_sequence"] == stats["sequence"])
            r.check("stats: a live session is not recovering", stats["recovering"] is False)
            r.check("stats: memory_bytes > 0 for a session holding a graph", stats["memory_bytes"] > 0, f"{stats['memory_bytes']}")
        self.call("", "GET", f"/v1/sessions/{self.s2}/summary", 200, "summary.schema.json", example="summary")

        # What the web view draws, and marginal covariances, of the solved square.
        base2 = f"/v1/sessions/{self.s2}"
        graph = self.call("", "GET", f"{base2}/graph", 200, "graph.schema.json", example="graph")
        if graph and est:
            r.check("graph: dimension 2, the 5 poses sorted, no points",
                    graph["dimension"] == 2 and [p["key"] for p in graph["poses"]] == [0, 1, 2, 3, 4] and graph["points"] == [],
                    f"dimension {graph['dimension']}, poses {[p['key'] for p in graph['poses']]}, {len(graph['points'])} points")
            r.check("graph: one edge per between factor, keys as given", graph["edges"] == [f["keys"] for f in batch2["factors"]], f"{graph['edges']}")
            r.check("graph: positions are the estimate's (x, y, 0)",
                    [p["position"] for p in graph["poses"]] == [[v["value"][0], v["value"][1], 0.0] for v in est["variables"]])
            r.check("graph: the initial position of key 0 is its given value", graph["poses"][0]["initial"] == [0.0, 0.0, 0.0],
                    f"{graph['poses'][0]['initial']}")
        marg = self.call("", "GET", f"{base2}/marginals?keys=4,1", 200, "marginals.schema.json", example="marginals")
        if marg:
            self.check_covariances("marginals 4,1", marg, [4, 1], [3, 3])
            r.check("marginals: no `joint` unless asked", "joint" not in marg)
            r.check("marginals: gauge_fixed is the client-fixed key 0", marg["gauge_fixed"] == [0], f"{marg['gauge_fixed']}")
            if stats:
                r.check("marginals: at the stats' sequence and solves", (marg["sequence"], marg["solves"]) == (stats["sequence"], stats["solves"]),
                        f"{(marg['sequence'], marg['solves'])} vs {(stats['sequence'], stats['solves'])}")
        joint = self.call("joint", "GET", f"{base2}/marginals?keys=0,1,2&joint=true", 200, "marginals.schema.json", example="marginals-joint")
        if joint:
            self.check_covariances("marginals 0,1,2 joint", joint, [0, 1, 2], [3, 3, 3])
            r.check("marginals: key 0 is fixed", joint["variables"][0]["fixed"] is True)
            r.check("marginals: the same estimate reuses the factorisation", joint["reused_factorization"] is True)
        self.call("not an integer", "GET", f"{base2}/marginals?keys=1,x", 400, "error.schema.json", error_code="invalid_query", error_field="keys[1]")
        self.call("no keys", "GET", f"{base2}/marginals", 400, "error.schema.json", error_code="invalid_query", error_field="keys")
        self.call("bad joint", "GET", f"{base2}/marginals?keys=1&joint=yes", 400, "error.schema.json", error_code="invalid_query", error_field="joint")
        self.call("unknown parameter", "GET", f"{base2}/marginals?keys=1&depth=2", 400, "error.schema.json", error_code="invalid_query", error_field="depth")
        self.call("repeated key", "GET", f"{base2}/marginals?keys=1,1", 400, "error.schema.json", error_code="invalid_value",
                  error_field="keys[1]", example="error-invalid-value")
        self.call("257 keys", "GET", f"{base2}/marginals?keys=" + ",".join(str(k) for k in range(257)), 400, "error.schema.json",
                  error_code="invalid_value", error_field="keys")
        self.call("unknown key", "GET", f"{base2}/marginals?keys=1,999", 422, "error.schema.json", error_code="unknown_variable", error_field="keys[1]")
        self.call("unknown session", "GET", "/v1/sessions/no-such-session/graph", 404, "error.schema.json", error_code="unknown_session")
        self.call("unknown session", "GET", "/v1/sessions/no-such-session/marginals?keys=0", 404, "error.schema.json", error_code="unknown_session")

        # A second 2D batch: guesses, fix/unfix, removal, with no wait (no `solved`).
        batch2b = {"variables": [{"key": 5, "kind": "se2", "value": [1.0, 0.1, 0.0]}],
                   "factors": [{"type": "prior_se2", "keys": [5], "measurement": [1.0, 0.0, 0.0], "sigmas": [0.5, 0.5, 0.2]},
                               {"type": "between_se2", "keys": [0, 5], "measurement": [1.0, 0.0, 0.0], "sigmas": [0.2, 0.2, 0.1]}],
                   "remove_factors": [ack["factor_ids"][-1]] if ack else [],
                   "fix": [5], "unfix": [0], "guesses": [{"key": 3, "value": [0.0, 1.0, -1.5708]}]}
        self.call("no wait", "POST", f"/v1/sessions/{self.s2}/batches", 200, "batch-ack.schema.json", body=batch2b,
                  example="batch-ack-no-wait", request_example="batch-edit")
        edited = self.call("after an edit", "GET", f"{base2}/graph", 200, "graph.schema.json")
        if edited:
            want = [f["keys"] for f in batch2["factors"][:-1]] + [[0, 5]]
            r.check("graph: a removed factor's edge is gone, a new between is an edge, a prior is not", edited["edges"] == want, f"{edited['edges']}")
            initial = {p["key"]: p["initial"] for p in edited["poses"]}
            r.check("graph: `initial` follows a later guess (key 3) and a given value (key 5)",
                    initial.get(3) == [0.0, 1.0, 0.0] and initial.get(5) == [1.0, 0.1, 0.0], f"3: {initial.get(3)}, 5: {initial.get(5)}")

        # Policies.
        for policy, ex in (({"policy": "every_n_factors", "factors": 10}, "auto-optimize"),
                           ({"policy": "every_ms", "milliseconds": 250}, "auto-optimize-every-ms"),
                           ({"policy": "every_batch"}, None)):
            self.call(policy["policy"], "PUT", f"/v1/sessions/{self.s2}/auto_optimize", 200, "reply.schema.json#/$defs/auto_optimize_set",
                      body=policy, request_example=ex, example="reply-auto-optimize-set" if ex == "auto-optimize" else None)
        self.call("", "POST", f"/v1/sessions/{self.s2}/optimize", 202, "reply.schema.json#/$defs/optimizing", example="reply-optimizing")
        self.call("", "POST", f"/v1/sessions/{self.s2}/cancel", 200, "reply.schema.json#/$defs/cancelled", example="reply-cancelled")

        # Exactly-once ingest and ordering, in a session of their own.
        self.producers()
        if self.lag_batches:
            self.lag(self.lag_batches)

        # 3D, manual policy: wait answers solved=false, then optimize?wait=true solves.
        batch3 = {
            "variables": [
                {"key": 10, "kind": "se3", "value": [0, 0, 0, 0, 0, 0, 1], "fixed": True},
                {"key": 11, "kind": "se3"},
                {"key": 12, "kind": "se3", "value": [2.0, 0.2, 0.0, 0.0, 0.0, 0.0998, 0.995]},
            ],
            "factors": [
                {"type": "between_se3", "keys": [10, 11], "measurement": [1.0, 0.0, 0.0, 0.0, 0.0, 0.0499792, 0.9987503],
                 "sigmas": [0.1, 0.1, 0.1, 0.05, 0.05, 0.05]},
                {"type": "between_se3", "keys": [11, 12], "measurement": [1.0, 0.05, 0.0, 0.0, 0.0, 0.0499792, 0.9987503],
                 "information": [100, 0, 0, 0, 0, 0, 100, 0, 0, 0, 0, 100, 0, 0, 0, 400, 0, 0, 400, 0, 400]},
                {"type": "prior_se3", "keys": [12], "measurement": [2.0, 0.1, 0.0, 0.0, 0.0, 0.0998, 0.995],
                 "sigmas": [1, 1, 1, 0.5, 0.5, 0.5], "robust": {"kind": "cauchy", "scale": 2.0}},
            ],
        }
        ack3 = self.call("3D manual wait", "POST", f"/v1/sessions/{self.s3}/batches?wait=true", 200, "batch-ack.schema.json",
                         body=batch3, request_example="batch-3d", example="batch-ack-manual")
        if ack3:
            r.check("batch-ack (manual policy, wait): solved is false", ack3.get("solved") is False, f"{ack3.get('solved')!r}")
        opt = self.call("wait", "POST", f"/v1/sessions/{self.s3}/optimize?wait=true", 200, "reply.schema.json#/$defs/optimizing",
                        example="reply-optimizing-wait")
        if opt:
            st = opt.get("stats") or {}
            r.check("optimize?wait=true: stats present and solved", st.get("solved_sequence") == opt["sequence"] and st.get("last_summary") is not None,
                    f"stats {json.dumps(st)[:200]}")
        self.call("3D", "GET", f"/v1/sessions/{self.s3}/estimate", 200, "estimate.schema.json", example="estimate-3d")
        self.call("3D (LM)", "GET", f"/v1/sessions/{self.s3}/summary", 200, "summary.schema.json", example="summary-lm")
        graph3 = self.call("3D", "GET", f"/v1/sessions/{self.s3}/graph", 200, "graph.schema.json")
        if graph3:
            r.check("graph 3D: dimension 3, edges without the prior", graph3["dimension"] == 3 and graph3["edges"] == [[10, 11], [11, 12]],
                    f"dimension {graph3['dimension']}, edges {graph3['edges']}")
        marg3 = self.call("3D", "GET", f"/v1/sessions/{self.s3}/marginals?keys=12,11,10&joint=true", 200, "marginals.schema.json")
        if marg3:
            self.check_covariances("marginals 3D", marg3, [12, 11, 10], [6, 6, 6])
            r.check("marginals 3D: gauge_fixed is the client-fixed key 10", marg3["gauge_fixed"] == [10], f"{marg3['gauge_fixed']}")

        # Error cases.
        before = self.scrape("before a rejected batch")
        self.call("malformed JSON", "POST", f"/v1/sessions/{self.s2}/batches", 400, "error.schema.json",
                  raw=b'{"variables": [', error_code="malformed_json", example="error-malformed-json")
        after = self.scrape("after a rejected batch")
        if before is not None and after is not None:
            was, now = self.rejected(before, "malformed_json"), self.rejected(after, "malformed_json")
            r.check('metrics: factord_rejected_inputs_total{reason="malformed_json"} after a malformed batch',
                    now is not None and now >= (was or 0) + 1, f"{was} -> {now}")
            accepted = "factord_batches_accepted_total"
            r.check(f"metrics: a rejected batch does not count in {accepted}", after.get(accepted) == before.get(accepted),
                    f"{before.get(accepted)} -> {after.get(accepted)}")
        self.call("unknown session", "POST", "/v1/sessions/no-such-session/batches", 404, "error.schema.json",
                  body={}, error_code="unknown_session", example="error")
        self.call("unknown key", "POST", f"/v1/sessions/{self.s2}/batches", 422, "error.schema.json",
                  body={"factors": [{"type": "between_se2", "keys": [0, 999], "measurement": [1, 0, 0], "sigmas": [1, 1, 1]}]},
                  error_code="unknown_variable", example="error-unknown-variable")
        self.call("wrong dimension", "POST", f"/v1/sessions/{self.s2}/batches", 400, "error.schema.json",
                  body={"factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0], "sigmas": [1, 1, 1]}]},
                  error_code="wrong_dimension", example="error-wrong-dimension")
        self.call("non-PD information", "POST", f"/v1/sessions/{self.s2}/batches", 400, "error.schema.json",
                  body={"factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "information": [1, 0, 0, -1, 0, 1]}]},
                  error_code="bad_information", example="error-bad-information")
        self.call("unknown field", "POST", f"/v1/sessions/{self.s2}/batches", 400, "error.schema.json",
                  body={"variable": []}, error_code="invalid_field", example="error-invalid-field")
        self.call("wrong kind", "POST", f"/v1/sessions/{self.s3}/batches", 400, "error.schema.json",
                  body={"variables": [{"key": 20, "kind": "se2", "value": [0, 0, 0]}]}, error_code="wrong_kind")
        self.call("duplicate variable", "POST", f"/v1/sessions/{self.s2}/batches", 422, "error.schema.json",
                  body={"variables": [{"key": 1, "kind": "se2", "value": [0, 0, 0]}]}, error_code="duplicate_variable")
        self.call("bad query", "GET", f"/v1/sessions/{self.s2}/estimate?since=yesterday", 400, "error.schema.json",
                  error_code="invalid_query", example="error-invalid-query")
        self.call("session exists", "POST", "/v1/sessions", 409, "error.schema.json",
                  body={"session": self.s2, "kind": "pose_graph_2d"}, error_code="session_exists", example="error-session-exists")
        self.call("unknown kind", "POST", "/v1/sessions", 400, "error.schema.json",
                  body={"kind": "no_such_kind"}, error_code="unknown_kind")
        self.call("bad option", "POST", "/v1/sessions", 400, "error.schema.json",
                  body={"kind": "pose_graph_2d", "options": {"max_iterations": 0}}, error_code="invalid_value")
        self.call("bad policy", "PUT", f"/v1/sessions/{self.s2}/auto_optimize", 400, "error.schema.json",
                  body={"policy": "every_n_factors", "factors": 0}, error_code="invalid_value")
        self.call("unknown route", "GET", "/v1/nothing-here", 404, "error.schema.json", error_code="no_route")
        self.call("wrong method", "DELETE", "/v1/health", 405, "error.schema.json", error_code="method_not_allowed",
                  example="error-method-not-allowed")
        self.call("unknown session", "GET", "/v1/sessions/no-such-session/events", 404, "error.schema.json", error_code="unknown_session")

        # A failing solve streams an `error` event: one camera and one point leave the system
        # indeterminate (a cost that would overflow is refused up front, B27).
        self.call("failing", "POST", "/v1/sessions", 201, "session-info.schema.json",
                  body={"session": self.sx, "kind": "bundle_adjustment", "options": {"method": "gauss_newton"}})
        self.created.append(self.sx)
        thread, events, problems = self.open_events(self.sx, {"errors"})
        self.call("indeterminate system", "POST", f"/v1/sessions/{self.sx}/batches?wait=true", 200, "batch-ack.schema.json",
                  body={"variables": [{"key": 1, "kind": "snavely_camera", "value": [0, 0, 0, 0, 0, 0, 500, 0, 0]},
                                      {"key": 1000, "kind": "point3", "value": [0, 0, -5]}],
                        "factors": [{"type": "reprojection_snavely", "keys": [1, 1000], "measurement": [1, 2], "sigmas": [1, 1]}]})
        thread.join(35)
        r.check("SSE reader ended cleanly (failing solve)", not problems, "; ".join(problems))
        self.check_events("failing solve", events, {"errors"}, {"error": "event-error"})
        failed = self.call("after a failed solve", "GET", f"/v1/sessions/{self.sx}", 200, "session-stats.schema.json", example="session-stats-failed")
        if failed:
            r.check("stats after a failed solve: last_error set, chi2 null", failed["last_error"] is not None and failed["chi2"] is None)

        # A sliding window: start, IMU samples, a keyframe with a prior; `state` and `window` events.
        sw = self.sx + "-window"
        self.call("sliding window", "POST", "/v1/sessions", 201, "session-info.schema.json", body={"session": sw, "kind": "sliding_window"})
        self.created.append(sw)
        thread, events, problems = self.open_events(sw, {"state", "window"})
        start = {"type": "start", "t": 0.0, "position": [0, 0, 0], "rotation_xyzw": [0, 0, 0, 1],
                 "sigmas": {"position": 0.01, "rotation": 0.01, "velocity": 0.1, "accel_bias": 0.1, "gyro_bias": 0.01}}
        self.call("start", "POST", f"/v1/sessions/{sw}/fusion", 200, "fusion.schema.json#/$defs/ack", body={"messages": [start]})
        imu = [{"type": "imu", "t": 0.005 * k, "accel": [0, 0, 9.81], "gyro": [0, 0, 0]} for k in range(1, 21)]
        prior = {"type": "pose_prior", "key": 1, "position": [0, 0, 0], "rotation_xyzw": [0, 0, 0, 1], "sigma_position": 0.1, "sigma_rotation": 0.02}
        self.call("keyframe", "POST", f"/v1/sessions/{sw}/fusion", 200, "fusion.schema.json#/$defs/ack",
                  body={"messages": imu + [{"type": "keyframe", "t": 0.1}, prior]})
        thread.join(35)
        r.check("SSE reader ended cleanly (sliding window)", not problems, "; ".join(problems))
        self.check_events("sliding window", events, {"state", "window"}, {"state": "event-state", "window": "event-window"})
        self.call("IMU out of order", "POST", f"/v1/sessions/{sw}/fusion", 422, "error.schema.json",
                  body={"messages": [{"type": "imu", "t": 0.05, "accel": [0, 0, 9.81], "gyro": [0, 0, 0]}]}, error_code="rejected_message")
        self.call("batch to a sliding window", "POST", f"/v1/sessions/{sw}/batches", 400, "error.schema.json",
                  body={"variables": []}, error_code="wrong_kind", error_field="session", example="error-wrong-kind")
        self.call("sliding window: marginals of a keyframe not in the window", "GET", f"/v1/sessions/{sw}/marginals?keys=999999",
                  422, "error.schema.json", error_code="unknown_variable", error_field="keys[0]")
        graph_sw = self.call("sliding window", "GET", f"/v1/sessions/{sw}/graph", 200, "graph.schema.json")
        if graph_sw:
            r.check("graph of a sliding window: dimension 3", graph_sw["dimension"] == 3, f"{graph_sw['dimension']}")

        # Bundle adjustment: cameras are poses, points are points, observations are no edges; with
        # nothing fixed the gauge is free and H singular; fixing a camera and two points makes it regular.
        ba = self.sx + "-ba"
        self.call("bundle adjustment", "POST", "/v1/sessions", 201, "session-info.schema.json", body={"session": ba, "kind": "bundle_adjustment"})
        self.created.append(ba)
        self.call("bundle adjustment", "POST", f"/v1/sessions/{ba}/batches?wait=true", 200, "batch-ack.schema.json", body=self.bal_batch())
        graph_ba = self.call("bundle adjustment", "GET", f"/v1/sessions/{ba}/graph", 200, "graph.schema.json")
        if graph_ba:
            r.check("graph BA: 3 camera poses, 25 points, no edges",
                    (len(graph_ba["poses"]), len(graph_ba["points"]), graph_ba["edges"], graph_ba["dimension"]) == (3, 25, [], 3),
                    f"{len(graph_ba['poses'])} poses, {len(graph_ba['points'])} points, edges {graph_ba['edges']}")
        self.call("free gauge", "GET", f"/v1/sessions/{ba}/marginals?keys=1,105", 422, "error.schema.json", error_code="indeterminate_system",
                  example="error-indeterminate-system")
        self.call("fix the gauge", "POST", f"/v1/sessions/{ba}/batches?wait=true", 200, "batch-ack.schema.json", body={"fix": [0, 100, 101]})
        marg_ba = self.call("bundle adjustment", "GET", f"/v1/sessions/{ba}/marginals?keys=1,105,100&joint=true", 200, "marginals.schema.json")
        if marg_ba:
            self.check_covariances("marginals BA", marg_ba, [1, 105, 100], [9, 3, 3])
            r.check("marginals BA: gauge_fixed is what the client fixed", marg_ba["gauge_fixed"] == [0, 100, 101], f"{marg_ba['gauge_fixed']}")

        # Batch jobs.
        g2o = (b"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1.1 0.1 0.05\nVERTEX_SE2 2 2.0 -0.1 0.1\n"
               b"EDGE_SE2 0 1 1 0 0 100 0 0 100 0 400\nEDGE_SE2 1 2 1 0 0 100 0 0 100 0 400\n"
               b"EDGE_SE2 0 2 2 0.05 0 100 0 0 100 0 400\nFIX 0\n")
        text = {"Content-Type": "text/plain"}
        self.call("g2o", "POST", "/v1/jobs", 200, "job-result.schema.json", raw=g2o, headers=text, example="job-result")
        self.call("g2o lm huber", "POST", "/v1/jobs?method=lm&robust=huber:1&max_iterations=20&init=none", 200, "job-result.schema.json",
                  raw=g2o, headers=text)
        toro = b"VERTEX2 0 0 0 0\nVERTEX2 1 1.2 0.1 0\nEDGE2 0 1 1 0 0 1 0 1 1 0 0\n"
        self.call("toro", "POST", "/v1/jobs?format=toro", 200, "job-result.schema.json", raw=toro, headers=text)
        for label, query, accept, first in (("Accept text/plain", "", "text/plain", b"VERTEX_SE2"),
                                            ("output=tum", "?output=tum", None, b"# vertex_id ")):
            hdrs = dict(text, **({"Accept": accept} if accept else {}))
            resp = self.request("POST", "/v1/jobs" + query, raw=g2o, headers=hdrs)
            name = f"POST /v1/jobs{query} {label}"
            r.check(f"{name}: status 200", resp.status == 200, f"got {resp.status}: {resp.body[:200]!r}")
            r.check(f"{name}: text/plain", resp.content_type.startswith("text/plain"), f"Content-Type {resp.content_type!r}")
            r.check(f"{name}: body is the optimised graph", resp.body.startswith(first), f"{resp.body[:80]!r}")
        self.call("bad parameter", "POST", "/v1/jobs?method=newton", 400, "error.schema.json", raw=g2o, headers=text,
                  error_code="invalid_parameter", example="error-invalid-parameter")
        self.call("unknown parameter", "POST", "/v1/jobs?iterations=3", 400, "error.schema.json", raw=g2o, headers=text, error_code="invalid_query")
        self.call("bad graph", "POST", "/v1/jobs", 400, "error.schema.json", raw=b"VERTEX_SE2 0 0 0\n", headers=text,
                  error_code="invalid_graph", example="error-invalid-graph")

        # The web view (while the sessions exist).
        self.web_page("/", "text/html", b'src="/assets/factord.js"')
        self.web_page(f"/sessions/{self.s2}", "text/html", b'src="/assets/factord.js"')
        self.web_page("/assets/factord.js", "text/javascript", b"/graph")
        self.web_page("/assets/factord.css", "text/css", b"{")
        self.web_page("/v1/docs", "text/html", b'src="/assets/docs.js"')
        self.web_page("/assets/docs.js", "text/javascript", b"/v1/openapi.json")
        served = self.request("GET", "/v1/openapi.json")
        try:
            committed = json.loads((V1 / "openapi.json").read_text())
            same = served.status == 200 and served.json() == committed
        except (OSError, ValueError) as e:
            same = False
        r.check("GET /v1/openapi.json is proto/v1/openapi.json", same, f"status {served.status}")

        # Delete.
        for s in list(self.created):
            self.call("", "DELETE", f"/v1/sessions/{s}", 200, "reply.schema.json#/$defs/deleted",
                      example="reply-deleted" if s == self.s2 else None)
            self.created.remove(s)
        self.call("deleted", "GET", f"/v1/sessions/{self.s2}", 404, "error.schema.json", error_code="unknown_session")


# --------------------------------------------------------------------------------------------


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--server", metavar="URL", help="also drive this running server, e.g. http://127.0.0.1:8080")
    parser.add_argument("--save-examples", action="store_true", help="with --server: rewrite the examples it captures")
    parser.add_argument("--lag", metavar="N", type=int, nargs="?", const=15000, default=0,
                        help="with --server: also make a slow SSE client fall behind N numbered batches (default 15000, ~10 s) "
                             "and check its `lagged` marker and re-synchronisation")
    args = parser.parse_args()
    report = Report()
    schemas = Schemas(report)
    schemas.check_all()
    if args.server:
        live = Live(args.server, schemas, report, args.save_examples, args.lag)
        try:
            live.run()
        except (urllib.error.URLError, OSError) as e:
            report.check(f"server {args.server} reachable", False, str(e))
        if live.saved:
            print(f"saved {len(live.saved)} examples to {EXAMPLES}")
    schemas.check_examples()
    schemas.check_counter_examples()
    check_openapi(schemas, report)
    return report.finish()


if __name__ == "__main__":
    sys.exit(main())
