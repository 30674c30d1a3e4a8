"""What the client's check scripts share: a check runner that reports every failure and goes on,
and a `factord serve` started with a tokens file (auth on) on free loopback ports."""

from __future__ import annotations

import secrets
import socket
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any, Callable, List, Optional

HERE = Path(__file__).resolve()
CLIENT_ROOT = HERE.parents[1]
REPO_ROOT = HERE.parents[3]
try:
    import factord_client  # noqa: F401 - installed in the venv
except ImportError:  # running from a checkout without `pip install`
    sys.path.insert(0, str(CLIENT_ROOT))


class Skip(Exception):
    pass


class Checks:
    """Runs named checks, prints one line each (ok / FAIL / SKIP) and counts them."""

    def __init__(self) -> None:
        self.failed: List[str] = []
        self.passed = 0
        self.skipped = 0

    def run(self, name: str, fn: Callable[..., Any], *args: Any) -> Any:
        started = time.monotonic()
        try:
            detail = fn(*args)
        except Skip as e:
            self.skipped += 1
            print(f"SKIP  {name}: {e}", flush=True)
            return None
        except Exception as e:  # noqa: BLE001 - report every failure and go on
            self.failed.append(name)
            print(f"FAIL  {name}: {e!r}", flush=True)
            traceback.print_exc(limit=4, file=sys.stdout)
            return None
        self.passed += 1
        ms = (time.monotonic() - started) * 1e3
        tail = f": {detail}" if isinstance(detail, str) and detail else ""
        print(f"ok    {name}{tail}  [{ms:.0f} ms]", flush=True)
        return detail

    def exit_code(self) -> int:
        print(f"\n{self.passed} passed, {len(self.failed)} failed, {self.skipped} skipped")
        for name in self.failed:
            print(f"  failed: {name}")
        return 1 if self.failed else 0


def expect(condition: bool, message: str) -> None:
    if not condition:
        raise AssertionError(message)


def expect_raises(error_type: type, fn: Callable[[], Any], what: str) -> Any:
    """Runs ``fn`` and returns the exception it raised, which must be an ``error_type``."""
    try:
        fn()
    except error_type as e:  # noqa: PERF203
        return e
    except Exception as e:  # noqa: BLE001
        raise AssertionError(f"{what}: raised {e!r}, not {error_type.__name__}") from e
    raise AssertionError(f"{what}: raised nothing, expected {error_type.__name__}")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class TokenServer:
    """`factord serve` with authentication on: a tokens file with two labels (``alice``,
    ``bob``), HTTP and zenoh on free loopback ports, its own state directory. A context
    manager: stopped (SIGTERM, then SIGKILL) on exit."""

    def __init__(self, binary: str) -> None:
        self.root = Path(tempfile.mkdtemp(prefix="factord-pyclient-"))
        self.token = secrets.token_hex(16)
        self.other_token = secrets.token_hex(16)
        tokens = self.root / "tokens"
        tokens.write_text(f"# label token\nalice {self.token}\nbob {self.other_token}\n")
        self.http = f"http://127.0.0.1:{free_port()}"
        self.zenoh = f"tcp/127.0.0.1:{free_port()}"
        self.log = self.root / "factord.log"
        self.cmd = [binary, "serve", "--listen", self.http.removeprefix("http://"),
                    "--zenoh-listen", self.zenoh, "--zenoh-multicast", "off",
                    "--state-dir", str(self.root / "state"), "--fsync", "never",
                    "--tokens-file", str(tokens)]
        self.proc: Optional[subprocess.Popen] = None

    def __enter__(self) -> "TokenServer":
        info = self.root / "state" / "server.json"
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen(self.cmd, stdout=subprocess.DEVNULL, stderr=log)
        deadline = time.monotonic() + 30
        while not info.exists():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"factord did not start:\n{self.log.read_text()[-3000:]}")
            time.sleep(0.02)
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.proc is None:
            return
        self.proc.terminate()
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.proc = None

    def panicked(self) -> bool:
        return "panicked" in self.log.read_text(errors="replace")
