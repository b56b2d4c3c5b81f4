"""HUGSIM's closed-loop HTTP protocol over our simulator, so HUGSIM's own client (``hugsim_client``) drives the
edited world unchanged: sessions, endpoints, and a helper to serve the app on a background thread."""
from __future__ import annotations

import hmac
import html
import json
import logging
import pickle
import re
import socket
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, replace
from datetime import datetime
from pathlib import Path
from typing import Callable, Collection

import numpy as np
from fastapi import FastAPI, HTTPException, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, JSONResponse, Response

from omniscs.closedloop import metrics
from omniscs.closedloop.run import run_summary, write_run
from omniscs.closedloop.scenario import ClosedLoopScenario
from omniscs.closedloop.simulator import Simulator, StepResult
from omniscs.errors import OmniscsError, ValidationError

log = logging.getLogger(__name__)

#: Serialises simulator resets and steps across every session of every app in this process. The CPU renderer's
#: numba kernels already spread one render over every core, so two renders at once only thrash the cores and make
#: both slower (and numba's fallback "workqueue" threading layer must never be entered from two threads at once).
#: Decoding, validation and pickling run outside it; each session's own lock serialises that session's requests.
RENDER_LOCK = threading.Lock()
#: Serialises writing run folders: the pictures go through matplotlib's pyplot, which is not thread-safe.
_WRITE_LOCK = threading.Lock()

TOKEN_HEADER = "auth-token"
SESSION_HEADER = "session-id"
#: What a ``session-id`` header may look like (it only tells a client's sessions apart).
SESSION_ID = re.compile(r"[A-Za-z0-9._:-]{1,64}")
#: Longest accepted ``transaction_id`` (HUGSIM's client sends 32 hex digits).
MAX_TRANSACTION_ID = 128
#: Numeric kinds a plan's declared dtype may have: signed and unsigned integers, floats.
PLAN_KINDS = "iuf"
PICKLED = "application/octet-stream"


@dataclass(frozen=True)
class ServerConfig:
    """How the HUGSIM-protocol server shares one scene among clients."""

    default_scenario: str | None = None
    """The scenario a session starts with (its queue then runs through the others in order, wrapping round);
    None = the first one given."""
    max_sessions: int = 32
    """Open sessions at most; a request that would open one more gets 429."""
    max_body_bytes: int = 1 << 20
    """Largest request body accepted (bytes); larger ones get 413."""
    transaction_cache: int = 64
    """Replies kept per session for repeated ``transaction_id`` values (oldest dropped first)."""
    session_idle_s: float = 600.0
    """A session without a request for this long is dropped, with its episode (seconds)."""
    max_steps_per_episode: int | None = None
    """An episode ends after this many steps (reason ``max_steps``); None = when the scenario ends."""
    out_dir: str | Path | None = None
    """Where each finished episode's run folder (run.json, steps.json, pictures) is written; None = nowhere."""
    max_plan_values: int = 1000
    """Most numbers a plan may hold (the product of its declared shape)."""
    log_lines: int = 100
    """Recent events kept for the status page."""

    def __post_init__(self):
        if self.max_sessions < 1 or self.transaction_cache < 1 or self.max_plan_values < 2 or self.log_lines < 1:
            raise ValidationError("max_sessions, transaction_cache and log_lines must be >= 1, max_plan_values >= 2")
        if self.max_body_bytes < 1024:
            raise ValidationError(f"max_body_bytes {self.max_body_bytes} is too small for any plan (at least 1024)")
        if not self.session_idle_s > 0:
            raise ValidationError(f"session_idle_s must be > 0 (got {self.session_idle_s})")
        if self.max_steps_per_episode is not None and self.max_steps_per_episode < 1:
            raise ValidationError(f"max_steps_per_episode must be >= 1 or None (got {self.max_steps_per_episode})")


def parse_plan(plan_traj: str, max_values: int = 1000) -> np.ndarray:  # -> float64 array of the declared shape
    """Decode HUGSIM's plan encoding, JSON ``{"data": nested list, "shape": [...], "dtype": "float32"}``; raises
    ``ValidationError`` saying what is wrong. Whether the numbers make a drivable plan is the simulator's check."""
    try:
        spec = json.loads(plan_traj)
    except (ValueError, RecursionError) as e:
        raise ValidationError(f"plan_traj is not JSON: {e}") from None
    if not isinstance(spec, dict) or not {"data", "shape", "dtype"} <= set(spec):
        raise ValidationError('plan_traj must be JSON {"data": [...], "shape": [...], "dtype": "..."}')
    dtype, shape = spec["dtype"], spec["shape"]
    try:
        kind = np.dtype(dtype).kind if isinstance(dtype, str) and len(dtype) <= 32 else None
    except TypeError:
        kind = None
    if kind is None or kind not in PLAN_KINDS:
        raise ValidationError(f"plan_traj dtype {str(dtype)[:40]!r} is not a numeric type (e.g. float32)")
    if (not isinstance(shape, list) or not 1 <= len(shape) <= 4
            or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)):
        raise ValidationError(f"plan_traj shape must be 1 to 4 non-negative integers (got {str(shape)[:80]})")
    size = int(np.prod(shape))
    if size > max_values:
        raise ValidationError(f"plan_traj holds {size} numbers (limit {max_values})")
    try:
        data = np.asarray(spec["data"])
    except (ValueError, TypeError) as e:
        raise ValidationError(f"plan_traj data is not a regular array of numbers: {e}") from None
    if data.dtype.kind not in PLAN_KINDS:
        raise ValidationError("plan_traj data must hold only numbers")
    if data.size != size:
        raise ValidationError(f"plan_traj data holds {data.size} numbers, its shape {shape} says {size}")
    return data.astype(np.float64).reshape(shape)


class _Session:
    """One client's episode: its simulator, scenario queue, last state and recent replies."""

    def __init__(self, label: str) -> None:
        self.label = label                  # what logs and the status page call it (never the token)
        self.lock = threading.Lock()
        self.sim: Simulator | None = None
        self.current: str | None = None     # scenario id of the episode under way
        self.pending: list[str] = []        # scenario ids still to drive after it
        self.last: StepResult | None = None
        self.scene_done = False
        self.replies: OrderedDict[str, bytes] = OrderedDict()
        self.frames: list = []              # (step, rgb) of the first camera, kept only to write run folders
        self.started = 0.0
        self.episodes = 0
        self.last_used = time.monotonic()


class _Hub:
    """The server's state: scenarios, sessions and recent events; every method below runs off the event loop."""

    def __init__(self, make_simulator: Callable[[], Simulator], scenarios: dict[str, ClosedLoopScenario],
                 tokens: Collection[str], config: ServerConfig) -> None:
        if not scenarios:
            raise ValidationError("a server needs at least one scenario")
        bad = [k for k, v in scenarios.items() if not isinstance(v, ClosedLoopScenario)]
        if bad:
            raise ValidationError(f"scenario(s) {bad} are not ClosedLoopScenario objects (omniscs.closedloop.scenario)")
        if isinstance(tokens, str) or not tokens or any(not isinstance(t, str) or not t for t in tokens):
            raise ValidationError("a server needs a collection of non-empty auth tokens (clients send one as the "
                                  "auth-token header)")
        order = list(scenarios)
        start = config.default_scenario if config.default_scenario is not None else order[0]
        if start not in scenarios:
            raise ValidationError(f"default scenario {start!r} is not among the served ones {order}")
        self.make_simulator, self.scenarios, self.config = make_simulator, dict(scenarios), config
        self.tokens = tuple(t.encode() for t in tokens)
        i = order.index(start)
        self.order = order[i:] + order[:i]
        # One simulator now: its scene is checked against every scenario before a client comes, and the first
        # session takes it over.
        self._spare: Simulator | None = make_simulator()
        wrong = [k for k, sc in scenarios.items() if sc.scene_id != self._spare.scene.scene_id]
        if wrong:
            raise ValidationError(f"scenario(s) {wrong} are not of the simulator's scene {self._spare.scene.scene_id}")
        self.sessions: dict[tuple[bytes, str], _Session] = {}
        self.registry = threading.Lock()
        self.opened = 0
        self.events: deque[str] = deque(maxlen=config.log_lines)
        self.events_lock = threading.Lock()

    # -- bookkeeping ---------------------------------------------------------------------------
    def note(self, message: str) -> None:
        log.info(message)
        with self.events_lock:
            self.events.append(f"{datetime.now():%Y-%m-%d %H:%M:%S} {message}")

    def authorise(self, request: Request) -> bytes:
        given = request.headers.get(TOKEN_HEADER)
        if not given:
            raise HTTPException(401, f"missing {TOKEN_HEADER} header")
        given_b = given.encode()
        for token in self.tokens:
            if hmac.compare_digest(given_b, token):
                return token
        raise HTTPException(401, f"unknown {TOKEN_HEADER}")

    def session(self, token: bytes, request: Request) -> _Session:
        sid = request.headers.get(SESSION_HEADER, "")
        if sid and not SESSION_ID.fullmatch(sid):
            raise HTTPException(400, f"{SESSION_HEADER} must be 1 to 64 letters, digits or ._:- characters")
        now = time.monotonic()
        with self.registry:
            for key, s in list(self.sessions.items()):
                if now - s.last_used > self.config.session_idle_s and not s.lock.locked():
                    del self.sessions[key]
                    self.note(f"{s.label}: dropped after {now - s.last_used:.0f} s idle")
            s = self.sessions.get((token, sid))
            if s is None:
                if len(self.sessions) >= self.config.max_sessions:
                    raise HTTPException(429, f"the server holds its limit of {self.config.max_sessions} sessions; "
                                             f"retry when one has been idle {self.config.session_idle_s:.0f} s")
                self.opened += 1
                s = self.sessions[(token, sid)] = _Session(f"session {self.opened}")
                self.note(f"{s.label}: opened")
            s.last_used = now
            return s

    def simulator(self, s: _Session) -> Simulator:
        if s.sim is None:
            with self.registry:
                spare, self._spare = self._spare, None
            s.sim = spare if spare is not None else self.make_simulator()
        return s.sim

    # -- episodes ------------------------------------------------------------------------------
    def begin(self, s: _Session, scenario_id: str) -> None:
        sim = self.simulator(s)
        with RENDER_LOCK:
            res = sim.reset(self.scenarios[scenario_id])
        s.current, s.last, s.scene_done = scenario_id, res, False
        s.started = time.perf_counter()
        s.frames = [(0, next(iter(res.observation.rgb.values()), None))] if self.config.out_dir is not None else []
        s.episodes += 1
        self.note(f"{s.label}: started {scenario_id}")

    def reset(self, s: _Session, only: str | None = None) -> str:
        queue = [only] if only is not None else list(self.order)
        s.pending = queue[1:]
        self.begin(s, queue[0])
        return queue[0]

    def ensure_started(self, s: _Session) -> None:
        if s.current is None:
            self.reset(s)

    def step(self, s: _Session, plan: np.ndarray) -> None:
        sim = self.simulator(s)
        with RENDER_LOCK:
            res = sim.step(plan)
        ep = sim.episode
        limit = self.config.max_steps_per_episode
        if not res.done and limit is not None and ep.step >= limit:
            sim.stop("max_steps")
            res = StepResult(res.observation, sim.info(), True, "max_steps")
        s.last = res
        if self.config.out_dir is not None:
            s.frames.append((ep.step, next(iter(res.observation.rgb.values()), None)))
        if res.done:
            self.finish(s)

    def finish(self, s: _Session) -> None:
        sim, res = s.sim, s.last
        scores = metrics.score_run(sim.trace())
        s.last = replace(res, info=dict(res.info, scores=scores.to_dict()))
        s.scene_done = True
        self.note(f"{s.label}: {s.current} ended ({res.reason}) after {sim.episode.step} steps, "
                  f"route completion {res.info['rc']:.2f}")
        if self.config.out_dir is not None:
            self.write(s, scores)

    def write(self, s: _Session, scores) -> None:
        sim = s.sim
        sc = sim.episode.scenario
        summary = dict(run_summary(sim, scores, "http-client", time.perf_counter() - s.started), session=s.label)
        number = s.label.rsplit(" ", 1)[-1]
        folder = Path(self.config.out_dir) / (f"{datetime.now():%Y%m%dT%H%M%S}-s{number}e{s.episodes}-"
                                              f"{sc.scenario_id.replace('/', '__')}")
        try:
            with _WRITE_LOCK:
                write_run(sim, scores, summary, s.frames, folder, overwrite=False)
        except (OSError, OmniscsError) as e:  # the episode's reply matters more than its folder
            log.exception("writing %s failed", folder)
            self.note(f"{s.label}: could not write its run folder: {e}")
            return
        s.last = replace(s.last, info=dict(s.last.info, run_folder=str(folder)))
        self.note(f"{s.label}: wrote {folder.name}")

    def state_bytes(self, s: _Session) -> bytes:
        res = s.last
        obs = {key: getattr(res.observation, key) for key in s.sim.config.outputs}
        return pickle.dumps({"done": bool(s.scene_done and not s.pending), "cur_scene_done": bool(s.scene_done),
                             "state": {"obs": obs, "info": res.info}})

    # -- requests (each under the session's lock) -------------------------------------------------
    def do_reset(self, s: _Session, body: bytes) -> dict:
        only = None
        if body.strip():
            try:
                request = json.loads(body)
            except (ValueError, RecursionError):
                raise HTTPException(422, 'a reset body must be empty or JSON {"scenario": "<id>"}') from None
            if not isinstance(request, dict):
                raise HTTPException(422, 'a reset body must be empty or JSON {"scenario": "<id>"}')
            only = request.get("scenario")
            if only is not None and not isinstance(only, str):
                raise HTTPException(422, "scenario must be a string id")
            if only is not None and only not in self.scenarios:
                raise HTTPException(404, f"unknown scenario {only[:200]!r}; this server serves {list(self.scenarios)}")
        with s.lock:
            return {"success": True, "scenario": self.reset(s, only)}

    def do_state(self, s: _Session) -> bytes:
        with s.lock:
            self.ensure_started(s)
            return self.state_bytes(s)

    def do_execute(self, s: _Session, body: bytes) -> bytes:
        try:
            request = json.loads(body)
        except (ValueError, RecursionError):
            raise HTTPException(422, 'execute_action takes JSON {"plan_traj": "<json>", "transaction_id": "<id>"}') \
                from None
        if not isinstance(request, dict) or not isinstance(request.get("plan_traj"), str):
            raise HTTPException(422, 'execute_action takes JSON {"plan_traj": "<json>", "transaction_id": "<id>"}')
        transaction = request.get("transaction_id")
        if not isinstance(transaction, str) or not 1 <= len(transaction) <= MAX_TRANSACTION_ID:
            raise HTTPException(422, f"transaction_id must be a string of 1 to {MAX_TRANSACTION_ID} characters")
        with s.lock:
            cached = s.replies.get(transaction)
            if cached is not None:
                s.replies.move_to_end(transaction)
                return cached
            try:
                plan = self.simulator(s).check_plan(parse_plan(request["plan_traj"], self.config.max_plan_values))
            except ValidationError as e:
                raise HTTPException(422, f"plan refused, the episode did not move: {e}") from None
            self.ensure_started(s)
            if not s.scene_done:
                self.step(s, plan)
            elif s.pending:  # the plan was made for the ended scenario: start the next one and show it
                self.begin(s, s.pending.pop(0))
            reply = self.state_bytes(s)
            s.replies[transaction] = reply
            while len(s.replies) > self.config.transaction_cache:
                s.replies.popitem(last=False)
            return reply

    # -- status page ---------------------------------------------------------------------------
    def page(self) -> str:
        with self.registry:
            n = len(self.sessions)
        with self.events_lock:
            events = list(self.events)
        rows = "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(sc.kind)}</td><td>{sc.n_steps}</td>"
                       f"<td>{sc.duration_s:.1f} s</td></tr>" for k, sc in self.scenarios.items())
        lines = html.escape("\n".join(events)) or "(nothing yet)"
        return ("<!doctype html><html><head><meta charset='utf-8'><meta http-equiv='refresh' content='5'>"
                "<title>OmniSCS closed-loop server</title></head><body>"
                "<h1>OmniSCS closed-loop server</h1><p>HUGSIM's protocol: POST /reset, GET /get_current_state, "
                f"POST /execute_action (auth-token header).</p><p>{n} of {self.config.max_sessions} sessions open.</p>"
                "<h2>Scenarios</h2><table><tr><th>id</th><th>kind</th><th>steps</th><th>duration</th></tr>"
                f"{rows}</table><h2>Recent events</h2><pre>{lines}</pre></body></html>")


async def _read_body(request: Request, limit: int) -> bytes:
    """The request body, refused with 413 past ``limit`` bytes, whether declared or only seen while reading."""
    declared = request.headers.get("content-length")
    if declared is not None:
        if not declared.isdigit():
            raise HTTPException(400, "Content-Length is not a number")
        if int(declared) > limit:
            raise HTTPException(413, f"request body of {int(declared)} bytes is over the server's {limit}-byte limit")
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise HTTPException(413, f"request body is over the server's {limit}-byte limit")
        chunks.append(chunk)
    return b"".join(chunks)


async def _guarded(work: Callable, *args):
    """Run ``work`` on a worker thread; anything but an HTTP refusal becomes a 500 for this request only."""
    try:
        return await run_in_threadpool(work, *args)
    except HTTPException:
        raise
    except OmniscsError as e:
        log.warning("request failed: %s", e)
        return JSONResponse({"detail": f"the simulator failed: {e}"}, status_code=500)
    except Exception as e:  # noqa: BLE001 - one bad request must not take the server down
        log.exception("request failed")
        return JSONResponse({"detail": f"internal error ({type(e).__name__}); see the server's log"}, status_code=500)


def create_app(make_simulator: Callable[[], Simulator], scenarios: dict[str, ClosedLoopScenario],
               tokens: Collection[str], config: ServerConfig = ServerConfig()) -> FastAPI:
    """A FastAPI app serving ``scenarios`` over HUGSIM's protocol. ``make_simulator`` makes one simulator per
    session (they may share one scene graph); it is called once here, so a scene or camera mistake shows before the
    first client. ``tokens`` are the accepted ``auth-token`` values.

    - Every call but ``GET /`` (a status page) carries an ``auth-token`` header: 401 when missing or unknown. A
      session is one token, or one (token, ``session-id`` header) pair, so one client may drive several. Each
      session owns a simulator and a queue of scenarios: all of the server's, in order from ``default_scenario``,
      or the one named by ``POST /reset {"scenario": id}`` (404 when unknown). Sessions idle for
      ``session_idle_s`` are dropped; a request that would open one past ``max_sessions`` gets 429.
    - ``GET /get_current_state`` (resetting implicitly before the first ``/reset``) and ``POST /execute_action``
      reply ``pickle.dumps({"done", "cur_scene_done", "state": {"obs", "info"}})`` as application/octet-stream, as
      HUGSIM's client expects: ``obs`` maps each output (rgb uint8 [H, W, 3], depth float32 [H, W], semantic uint8
      [H, W], instance int32 [H, W]) to per-camera arrays, ``info`` is the simulator's (HUGSIM's keys and ours, plus
      ``scores`` when a scenario ends). The server never unpickles anything: a plan arrives as the JSON string
      ``plan_traj`` = ``{"data", "shape", "dtype"}``.
    - ``execute_action`` checks the plan before anything moves (422 with the reason; the episode is not stepped)
      and replays the stored reply for a ``transaction_id`` it has already executed (the client retries calls whose
      answer it lost). When a scenario ends the reply says ``cur_scene_done``; the next call starts the session's
      next scenario and returns its first state (the plan, made for the ended one, is not driven), or repeats the
      final state with ``done`` once the queue is empty.
    - Bodies over ``max_body_bytes`` get 413, whether declared or only seen while reading. Errors are JSON
      ``{"detail": ...}``; a failing request affects only its own reply.
    - Resets and steps of all sessions take turns under ``RENDER_LOCK``."""
    hub = _Hub(make_simulator, scenarios, tokens, config)
    app = FastAPI(title="OmniSCS closed-loop server (HUGSIM protocol)", docs_url=None, redoc_url=None,
                  openapi_url=None)
    app.state.hub = hub

    @app.get("/", response_class=HTMLResponse)
    async def status_page() -> HTMLResponse:
        return HTMLResponse(hub.page())

    @app.post("/reset")
    async def reset(request: Request):
        s = hub.session(hub.authorise(request), request)
        body = await _read_body(request, config.max_body_bytes)
        return await _guarded(hub.do_reset, s, body)

    @app.get("/get_current_state")
    async def get_current_state(request: Request):
        s = hub.session(hub.authorise(request), request)
        out = await _guarded(hub.do_state, s)
        return out if isinstance(out, Response) else Response(out, media_type=PICKLED)

    @app.post("/execute_action")
    async def execute_action(request: Request):
        s = hub.session(hub.authorise(request), request)
        body = await _read_body(request, config.max_body_bytes)
        out = await _guarded(hub.do_execute, s, body)
        return out if isinstance(out, Response) else Response(out, media_type=PICKLED)

    return app


def serve(app: FastAPI, host: str = "127.0.0.1", port: int = 8065, log_level: str = "info") -> None:
    """Serve ``app`` with uvicorn until interrupted; loopback unless ``host`` says otherwise."""
    import uvicorn

    if host not in ("127.0.0.1", "localhost", "::1"):
        log.warning("serving on %s: anyone who reaches it with a token drives the simulator", host)
    uvicorn.run(app, host=host, port=port, log_level=log_level)


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
    server = uvicorn.Server(uvicorn.Config(app, log_level=log_level, lifespan="off"))
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
