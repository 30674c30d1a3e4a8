#!/usr/bin/env python3
"""The HTTP client's retry rules against a scripted network peer (a local HTTP server that
answers 503/429 with Retry-After, or drops the connection, before answering normally). It stands
in for the network, not for factord: the service's own 429s are exercised in test_recovery.py.

    python clients/python/tests/test_http_retry.py

Prints one line per check; exits non-zero when one fails.
"""

from __future__ import annotations

import json
import sys
import threading
import time
import traceback
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

HERE = Path(__file__).resolve()
sys.path.insert(0, str(HERE.parents[1]))
from factord_client import FactordConnectionError, FactordError, HttpClient  # noqa: E402


class Peer:
    """Answers each request with the next scripted reply: ``(status, headers, body)`` or
    ``"drop"`` (close the connection without answering). Records what it received."""

    def __init__(self) -> None:
        self.script: list = []
        self.seen: list = []
        peer = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args):  # quiet
                pass

            def _serve(self):
                length = int(self.headers.get("Content-Length") or 0)
                body = self.rfile.read(length) if length else b""
                peer.seen.append((self.command, self.path, dict(self.headers), body,
                                  time.monotonic()))
                reply = peer.script.pop(0) if peer.script else (200, {}, {"ok": True})
                if reply == "drop":
                    self.close_connection = True
                    self.connection.close()
                    return
                status, headers, payload = reply
                raw = json.dumps(payload).encode()
                self.send_response(status)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(raw)))
                for k, v in headers.items():
                    self.send_header(k, v)
                self.end_headers()
                self.wfile.write(raw)

            do_GET = do_POST = do_PUT = do_DELETE = _serve

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def reset(self, *script) -> None:
        self.script = list(script)
        self.seen = []

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def error(status: int, code: str, retry_after=None) -> tuple:
    body = {"error": {"code": code, "message": f"scripted {code}", "status": status}}
    headers = {}
    if retry_after is not None:
        body["error"]["retry_after"] = retry_after
        headers["Retry-After"] = str(retry_after)
    return (status, headers, body)


def expect(condition: bool, message: str) -> None:
    if not condition:
        raise AssertionError(message)


def main() -> int:
    peer = Peer()
    failed: list = []

    def check(name, fn):
        try:
            detail = fn()
        except Exception as e:  # noqa: BLE001
            failed.append(name)
            print(f"FAIL  {name}: {e!r}", flush=True)
            traceback.print_exc(limit=3, file=sys.stdout)
            return
        print(f"ok    {name}: {detail}", flush=True)

    client = HttpClient(peer.url, timeout=10, token="s3cret")

    def retry_after_503():
        peer.reset(error(503, "journal_failed", 1), (200, {}, {"session": "a", "sequence": 3}))
        t0 = time.monotonic()
        answer = client.stats("a")
        waited = peer.seen[1][4] - peer.seen[0][4]
        expect(answer["sequence"] == 3, str(answer))
        expect(len(peer.seen) == 2, f"{len(peer.seen)} requests")
        expect(0.95 <= waited < 3.0, f"second attempt {waited:.2f} s after the first")
        return (f"GET answered 503 Retry-After 1, then 200: resent after {waited:.2f} s "
                f"(total {time.monotonic() - t0:.2f} s)")

    def retry_after_429_on_a_plain_batch():
        peer.reset(error(429, "too_many_pending", 1), (200, {}, {"sequence": 7}))
        ack = client.apply_batch("a", {"variables": [], "factors": []})
        expect(ack["sequence"] == 7 and len(peer.seen) == 2, f"{ack}, {len(peer.seen)}")
        waited = peer.seen[1][4] - peer.seen[0][4]
        expect(waited >= 0.95, f"resent after {waited:.2f} s, before Retry-After")
        return f"a 429 refused before applying: even a plain batch is resent ({waited:.2f} s)"

    def no_503_retry_for_a_plain_batch():
        peer.reset(error(503, "solving", 1), (200, {}, {"sequence": 8}))
        try:
            client.apply_batch("a", {"variables": []}, wait=True)
        except FactordError as e:
            expect((e.status, e.code, e.retry_after) == (503, "solving", 1.0), str(e))
        else:
            raise AssertionError("a plain batch was resent after a 503 (it may be applied)")
        expect(len(peer.seen) == 1, f"{len(peer.seen)} requests")
        return "503 on a batch without producer: raised at once (status, code, retry_after)"

    def producer_batch_retried_after_drop():
        peer.reset("drop", error(503, "journal_failed", 1), (200, {}, {"sequence": 9}))
        ack = client.apply_batch("a", {"variables": [], "producer": "r1", "producer_seq": 4})
        expect(ack["sequence"] == 9 and len(peer.seen) == 3, f"{ack} after {len(peer.seen)}")
        bodies = {json.loads(s[3])["producer_seq"] for s in peer.seen}
        expect(bodies == {4}, f"resent bodies {bodies}")
        return "dropped connection then 503: the stamped batch was sent 3 times, same number"

    def plain_batch_not_retried_after_drop():
        peer.reset("drop", (200, {}, {"sequence": 10}))
        try:
            client.apply_batch("a", {"variables": []})
        except FactordConnectionError as e:
            expect(e.status is None and e.code == "connection_failed", str(e))
            expect(isinstance(e, OSError), "not an OSError")
        else:
            raise AssertionError("a plain batch was resent after a dropped connection")
        expect(len(peer.seen) == 1, f"{len(peer.seen)} requests")
        return "dropped connection on a plain batch: FactordConnectionError (an OSError), 1 attempt"

    def bounded():
        c = HttpClient(peer.url, timeout=10, retries=2, max_retry_wait=0.2)
        peer.reset(*[error(503, "journal_failed", 30)] * 5)
        t0 = time.monotonic()
        try:
            c.stats("a")
        except FactordError as e:
            expect(e.status == 503 and e.retry_after == 30, str(e))
        else:
            raise AssertionError("answered")
        took = time.monotonic() - t0
        expect(len(peer.seen) == 3, f"{len(peer.seen)} attempts")
        expect(took < 2.0, f"took {took:.2f} s: Retry-After 30 not cut to max_retry_wait")
        return f"Retry-After 30 cut to 0.2 s, 3 attempts then the 503 raised ({took:.2f} s)"

    def token():
        peer.reset((200, {}, {"status": "ok"}))
        client.health()
        auth = peer.seen[0][2].get("Authorization")
        expect(auth == "Bearer s3cret", f"Authorization {auth!r}")
        import os  # noqa: PLC0415

        os.environ["FACTORD_TOKEN"] = "from-env"
        try:
            peer.reset((200, {}, {"status": "ok"}))
            HttpClient(peer.url).health()
            auth = peer.seen[0][2].get("Authorization")
        finally:
            del os.environ["FACTORD_TOKEN"]
        expect(auth == "Bearer from-env", f"Authorization {auth!r} from FACTORD_TOKEN")
        return "Authorization: Bearer <token> (parameter, and $FACTORD_TOKEN)"

    def refused_connection():
        dead = Peer()
        url = dead.url
        dead.close()  # nothing listens on that port any more
        c = HttpClient(url, timeout=2, retries=2)
        t0 = time.monotonic()
        try:
            c.health()
        except FactordConnectionError as e:
            expect(e.attempts == 3, f"{e.attempts} attempts")
        else:
            raise AssertionError("answered")
        return f"connection refused: 3 attempts with backoff ({time.monotonic() - t0:.2f} s)"

    check("503 + Retry-After on a read is retried after it", retry_after_503)
    check("429 + Retry-After is retried for any request", retry_after_429_on_a_plain_batch)
    check("503 on a plain batch is not retried", no_503_retry_for_a_plain_batch)
    check("a batch with producer/producer_seq is retried", producer_batch_retried_after_drop)
    check("a plain batch is not retried after a dropped connection",
          plain_batch_not_retried_after_drop)
    check("retries are bounded", bounded)
    check("bearer token", token)
    check("connection refused", refused_connection)
    peer.close()
    print(f"\n{8 - len(failed)} passed, {len(failed)} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
