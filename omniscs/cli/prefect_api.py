"""The Prefect API a CLI run talks to, and what happens to it when the CLI stops.

When no API is configured (``PREFECT_API_URL`` unset, the usual case on a workstation), Prefect would start a
temporary server as a plain child process and stop it from an ``atexit`` hook. That hook does not run on SIGTERM,
and nothing runs on SIGKILL, so the server (about 200 MB and a port) was orphaned. Here the CLI starts that same
temporary server itself, with two guarantees:

- the child asks the kernel for a parent-death signal (Linux ``PR_SET_PDEATHSIG``): when the CLI process dies,
  however it dies, SIGKILL included, the server gets SIGTERM and exits;
- on a normal end, an error, SIGINT or SIGTERM the CLI stops it itself (``stop_server``).

A configured API (a long-lived ``prefect server start``, or a test harness) is used as is and left running.
"""
from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
from typing import Iterator

from omniscs.errors import OmniscsError

#: Seconds to wait for the temporary server to answer (its first start migrates its database).
STARTUP_TIMEOUT_S = 180.0
_PR_SET_PDEATHSIG = 1

_server: subprocess.Popen | None = None


def die_with_parent(parent: int):
    """A ``preexec_fn`` for ``subprocess.Popen``: the child gets SIGTERM when process ``parent`` dies, however it
    dies (also SIGKILL), so a server started for a run or a test never outlives it."""
    def preexec() -> None:  # runs in the child between fork and exec
        try:
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
        except (OSError, AttributeError):
            pass  # not Linux: the CLI's own stop_server is then the only guard
        if os.getppid() != parent:  # the parent died before the request took effect
            os._exit(0)
    return preexec


def _free_port() -> int:
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _start_server() -> tuple[subprocess.Popen, str]:
    import httpx
    import prefect
    from prefect.settings import get_current_settings

    for _ in range(5):
        port = _free_port()
        env = {**os.environ, **get_current_settings().to_environment_variables(exclude_unset=True),
               "PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1", "PREFECT__SERVER_FINAL": "1"}
        proc = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "--app-dir", str(prefect.__module_path__.parent), "--factory",
             "prefect.server.api.server:create_app", "--host", "127.0.0.1", "--port", str(port), "--log-level",
             "error", "--lifespan", "on"],
            env=env, preexec_fn=die_with_parent(os.getpid()), stdin=subprocess.DEVNULL)
        url = f"http://127.0.0.1:{port}/api"
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        with httpx.Client() as client:
            while time.monotonic() < deadline:
                if proc.poll() is not None:
                    break  # e.g. the port was taken meanwhile: try another
                try:
                    if client.get(f"{url}/health", timeout=2.0).status_code == 200:
                        return proc, url
                except httpx.HTTPError:
                    pass
                time.sleep(0.1)
        _stop(proc)
    raise OmniscsError("the temporary Prefect server did not start; set PREFECT_API_URL to a running server "
                       "(prefect server start) or see `prefect server start` for what fails")


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def stop_server() -> None:
    """Stop the temporary server this process started (nothing when none runs); safe in a signal handler."""
    global _server
    if _server is not None:
        proc, _server = _server, None
        _stop(proc)


@contextlib.contextmanager
def prefect_api() -> Iterator[str]:
    """Yield the API URL flows started in the block will use: the configured one, or a temporary server that
    lives exactly as long as the block (and never longer than this process)."""
    global _server
    from prefect.settings import PREFECT_API_URL, temporary_settings

    configured = PREFECT_API_URL.value()
    if configured:
        yield configured
        return
    proc, url = _start_server()
    _server = proc
    try:
        with temporary_settings(updates={PREFECT_API_URL: url}):
            try:
                yield url
            finally:
                _drain()
    finally:
        stop_server()


def _drain(timeout_s: float = 5.0) -> None:
    """Send Prefect's queued logs and events while the server still answers (else they are retried against a
    stopped server at exit, for a minute, and reported as connection errors)."""
    from prefect.events.worker import EventsWorker
    from prefect.logging.handlers import APILogWorker

    for worker in (APILogWorker, EventsWorker):
        try:
            worker.drain_all(timeout=timeout_s)
        except Exception:  # noqa: BLE001 - a worker that never started has nothing to send
            pass
