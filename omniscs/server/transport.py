"""How the render server (``omniscs.server.hugsim``) is put on the network: uvicorn's h11 protocol with a header and
a reply deadline, the keep-alive timeout and head size limit from the app's ``ServerConfig``, serving in the
foreground (``omniscs closedloop serve``) or on a background thread (tests, benchmarks)."""
from __future__ import annotations

import asyncio
import logging
import socket
import threading
import time

from fastapi import FastAPI

from omniscs.errors import OmniscsError
from omniscs.server.hugsim import MAX_HEAD_BYTES, ServerConfig

log = logging.getLogger(__name__)


def _deadline_protocol(header_timeout_s: float, reply_timeout_s: float) -> type:
    """uvicorn's h11 protocol with two deadlines. One on each request's head: armed when a connection opens and
    after each reply, disarmed when the next request's headers are complete; when it passes the connection is
    closed. uvicorn's own keep-alive timer is disarmed by any byte received, so without this a client sending one
    byte a second (of headers, or of the rest of a body the server has already refused) holds its connection
    forever. One on replies: when the connection's send buffer stays full (the client does not read) for
    ``reply_timeout_s`` the connection is aborted, dropping the buffered reply (a plain close would wait for it to
    be sent)."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class DeadlineH11Protocol(H11Protocol):
        _deadline: asyncio.TimerHandle | None = None
        _stalled: asyncio.TimerHandle | None = None

        def _arm(self) -> None:
            self._disarm()
            self._deadline = self.loop.call_later(header_timeout_s, self._expired)

        def _disarm(self) -> None:
            if self._deadline is not None:
                self._deadline.cancel()
                self._deadline = None

        def _expired(self) -> None:
            self._deadline = None
            if self.transport.get_write_buffer_size():  # the last reply is still going out: the stall timer
                self._arm()                             # decides about a client that does not take it
            elif not self.transport.is_closing():
                self.transport.close()

        def pause_writing(self) -> None:
            super().pause_writing()
            if self._stalled is None:
                self._stalled = self.loop.call_later(reply_timeout_s, self._stalled_too_long)

        def resume_writing(self) -> None:
            if self._stalled is not None:
                self._stalled.cancel()
                self._stalled = None
            super().resume_writing()

        def _stalled_too_long(self) -> None:
            self._stalled = None
            self.transport.abort()

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self._arm()

        def handle_events(self) -> None:
            cycle = self.cycle
            super().handle_events()
            if self.cycle is not cycle:  # a new request's headers are complete: its body has its own deadline
                self._disarm()

        def on_response_complete(self) -> None:
            self._arm()  # before the parent's, which starts a pipelined request (disarming it again)
            super().on_response_complete()

        def connection_lost(self, exc) -> None:
            self._disarm()
            if self._stalled is not None:
                self._stalled.cancel()
                self._stalled = None
            super().connection_lost(exc)

    return DeadlineH11Protocol


def uvicorn_options(app) -> dict:
    """uvicorn settings for ``app``: the h11 protocol with a header deadline, the keep-alive timeout and the head
    size limit, from the app's ``ServerConfig`` (the defaults for an app not made by ``create_app``)."""
    hub = getattr(getattr(app, "state", None), "hub", None)
    config = hub.config if isinstance(getattr(hub, "config", None), ServerConfig) else ServerConfig()
    return {"http": _deadline_protocol(config.header_timeout_s, config.reply_timeout_s),
            "timeout_keep_alive": config.keep_alive_s,
            "h11_max_incomplete_event_size": MAX_HEAD_BYTES}


def serve(app: FastAPI, host: str = "127.0.0.1", port: int = 8065, log_level: str = "info") -> None:
    """Serve ``app`` with uvicorn until interrupted; loopback unless ``host`` says otherwise."""
    import uvicorn

    if host not in ("127.0.0.1", "localhost", "::1"):
        log.warning("serving on %s: anyone who reaches it with a token drives the simulator", host)
    uvicorn.run(app, host=host, port=port, log_level=log_level, **uvicorn_options(app))


class ServerHandle:
    """A server running on a background thread: its ``url``; ``stop()`` ends it (also as a context manager)."""

    def __init__(self, server, thread: threading.Thread, url: str) -> None:
        self.server, self.thread, self.url = server, thread, url

    def stop(self, timeout_s: float = 10.0) -> None:
        self.server.should_exit = True
        self.thread.join(timeout_s)

    def __enter__(self) -> "ServerHandle":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def start_in_thread(app, host: str = "127.0.0.1", port: int = 0, log_level: str = "warning",
                    startup_timeout_s: float = 10.0) -> ServerHandle:
    """Serve ``app`` (any ASGI app) on a daemon thread, for tests and benchmarks; ``port=0`` picks a free port."""
    import uvicorn

    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
    except OSError as e:
        sock.close()
        raise OmniscsError(f"cannot listen on {host}:{port}: {e}; choose another port") from None
    bound = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level=log_level, lifespan="off", **uvicorn_options(app)))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True,
                              name=f"uvicorn-{host}:{bound}")
    thread.start()
    deadline = time.monotonic() + startup_timeout_s
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            server.should_exit = True
            sock.close()
            raise OmniscsError(f"the server on {host}:{bound} did not start within {startup_timeout_s:.0f} s")
        time.sleep(0.01)
    url_host = f"[{host}]" if ":" in host else host
    return ServerHandle(server, thread, f"http://{url_host}:{bound}")
