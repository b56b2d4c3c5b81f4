"""HUGSIM's closed-loop HTTP protocol over our simulator, so HUGSIM's own client (``hugsim_client``) drives the
edited world unchanged: its configuration, sessions, per-token limits and endpoints (``create_app``); serving
it is ``omniscs.server.transport``."""
from __future__ import annotations

import asyncio
import contextlib
import hmac
import html
import json
import logging
import math
import pickle
import re
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, replace
from datetime import datetime
from pathlib import Path
from typing import Callable, Collection

import numpy as np
from anyio import CapacityLimiter, to_thread
from fastapi import FastAPI, HTTPException, Request
from fastapi.responses import HTMLResponse, JSONResponse, Response

from omniscs.closedloop.epdms import score_with_epdms
from omniscs.closedloop.run import run_summary, scored_trace, write_run
from omniscs.closedloop.scenario import ClosedLoopScenario
from omniscs.closedloop.simulator import Simulator, StepResult
from omniscs.errors import OmniscsError, ValidationError

log = logging.getLogger(__name__)

class TurnLock:
    """A lock whose waiters take turns by owner (round robin over the owners waiting, each owner's own waiters in
    arrival order), so an owner with many requests queued makes another wait for at most one turn of its own, not
    for its whole queue. ``with lock.turn(owner):`` holds it; a plain ``threading.Lock`` wakes waiters in no set
    order."""

    def __init__(self) -> None:
        self._cond = threading.Condition(threading.Lock())
        self._held = False
        self._waiting: OrderedDict[object, deque[object]] = OrderedDict()  # owner -> its waiters' tickets
        self._granted: object | None = None  # the ticket the lock was handed to, until its thread wakes

    def acquire(self, owner: object) -> None:
        with self._cond:
            if not self._held and not self._waiting:
                self._held = True
                return
            ticket = object()
            self._waiting.setdefault(owner, deque()).append(ticket)
            while self._granted is not ticket:
                self._cond.wait()
            self._granted = None  # the lock stayed held while handed over: nobody could barge in

    def release(self) -> None:
        with self._cond:
            if not self._waiting:
                self._held = False
                return
            owner, queue = next(iter(self._waiting.items()))
            self._granted = queue.popleft()
            if queue:
                self._waiting.move_to_end(owner)  # its next waiter goes after every other owner's
            else:
                del self._waiting[owner]
            self._cond.notify_all()

    @contextlib.contextmanager
    def turn(self, owner: object):
        self.acquire(owner)
        try:
            yield
        finally:
            self.release()


#: Serialises simulator resets and steps across every session of every app in this process, taking turns by token.
#: The CPU renderer's numba kernels already spread one render over every core, so two renders at once only thrash
#: the cores and make both slower (and numba's fallback "workqueue" threading layer must never be entered from two
#: threads at once). Decoding, validation and pickling run outside it; each session's own lock serialises that
#: session's requests.
RENDER_LOCK = TurnLock()
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
#: Largest request head accepted (bytes): a larger one gets 431, or 400 from h11 when it arrives in pieces.
MAX_HEAD_BYTES = 16 * 1024
#: Most dimensions a plan's declared shape may have (HUGSIM's client sends [P, 2] or [1, P, 2]).
MAX_PLAN_DIMS = 4
#: Requests a token may have in progress per session it may hold, unless ``ServerConfig.max_pending_per_token``
#: says otherwise: one running, one retry of it (a client that lost an answer) and a little slack.
PENDING_PER_SESSION = 4


@dataclass(frozen=True)
class ServerConfig:
    """How the HUGSIM-protocol server shares one scene among clients."""

    default_scenario: str | None = None
    """The scenario a session starts with (its queue then runs through the others in order, wrapping round);
    None = the first one given."""
    max_sessions: int = 32
    """Open sessions at most, over all tokens; a request that would open one more gets 429."""
    max_sessions_per_token: int | None = None
    """Open sessions one token may hold (None = a fair share, ``max(1, max_sessions // number of tokens)``); a
    request of that token that would open one more gets 429 with Retry-After, other tokens are not affected. With
    the fair share every token can always open its share whatever the others do (while there are no more tokens
    than ``max_sessions``)."""
    requests_per_s: float = 20.0
    """Requests per second one token may make on average (a token bucket refilled at this rate); past it (and its
    burst) that token's requests get 429 with Retry-After, other tokens are not affected."""
    request_burst: int = 40
    """Requests one token may make at once before ``requests_per_s`` applies (the bucket's size)."""
    max_pending_per_token: int | None = None
    """Requests of one token in progress at once (None = four per session it may hold); one more gets 429. In
    progress means reading a body, waiting for its session or the renderer, or running: the cap keeps one token's
    pile of requests from holding the server's connections and memory."""
    body_timeout_s: float = 20.0
    """A request body must arrive within this long once its headers have (seconds); a slower one gets 408 and its
    connection is closed."""
    header_timeout_s: float = 10.0
    """A connection must deliver a request's headers within this long of opening or of its previous reply
    (seconds), else it is closed: a client trickling headers, or the rest of a refused body, holds nothing."""
    keep_alive_s: float = 5.0
    """An idle connection between requests is closed after this long (seconds; uvicorn's keep-alive timeout)."""
    reply_timeout_s: float = 30.0
    """A reply the client stops taking (its connection's send buffer stays full) for this long is dropped with the
    connection (seconds): a client that never reads holds no memory."""
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
        for name, high in (("max_sessions_per_token", self.max_sessions),
                           ("max_pending_per_token", self.max_sessions * PENDING_PER_SESSION)):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, int) and 1 <= value <= high):
                raise ValidationError(f"{name} must be None or 1 to {high} (got {value!r})")
        if not (isinstance(self.request_burst, int) and 1 <= self.request_burst <= 100_000):
            raise ValidationError(f"request_burst must be 1 to 100000 requests (got {self.request_burst!r})")
        for name, low, high in (("requests_per_s", 0.01, 100_000.0), ("body_timeout_s", 0.01, 3600.0),
                                ("header_timeout_s", 0.01, 3600.0), ("keep_alive_s", 0.01, 3600.0),
                                ("reply_timeout_s", 0.01, 3600.0)):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and low <= value <= high):  # also refuses NaN
                raise ValidationError(f"{name} must be {low:g} to {high:g} (got {value!r})")
        if self.max_body_bytes < 1024:
            raise ValidationError(f"max_body_bytes {self.max_body_bytes} is too small for any plan (at least 1024)")
        if not self.session_idle_s > 0:
            raise ValidationError(f"session_idle_s must be > 0 (got {self.session_idle_s})")
        if self.max_steps_per_episode is not None and self.max_steps_per_episode < 1:
            raise ValidationError(f"max_steps_per_episode must be >= 1 or None (got {self.max_steps_per_episode})")

    def sessions_per_token(self, n_tokens: int) -> int:
        """The open sessions one of ``n_tokens`` tokens may hold (``max_sessions_per_token`` or the fair share)."""
        if self.max_sessions_per_token is not None:
            return self.max_sessions_per_token
        return max(1, self.max_sessions // max(1, n_tokens))

    def pending_per_token(self, n_tokens: int) -> int:
        """The requests one of ``n_tokens`` tokens may have in progress at once."""
        if self.max_pending_per_token is not None:
            return self.max_pending_per_token
        return PENDING_PER_SESSION * self.sessions_per_token(n_tokens)


def parse_plan(plan_traj: str, max_values: int = 1000) -> np.ndarray:  # -> float64 array of the declared shape
    """Decode HUGSIM's plan encoding, JSON ``{"data": nested list, "shape": [...], "dtype": "float32"}``; raises
    ``ValidationError`` saying what is wrong (whatever the string holds: never another exception). Whether the
    numbers make a drivable plan (finite, near, slow enough) is the simulator's check."""
    try:
        spec = json.loads(plan_traj)
    except (ValueError, RecursionError) as e:  # ValueError includes an integer of too many digits
        raise ValidationError(f"plan_traj is not JSON: {str(e)[:120]}") from None
    if not isinstance(spec, dict) or not {"data", "shape", "dtype"} <= set(spec):
        raise ValidationError('plan_traj must be JSON {"data": [...], "shape": [...], "dtype": "..."}')
    dtype, shape = spec["dtype"], spec["shape"]
    declared = None
    if isinstance(dtype, str) and len(dtype) <= 32 and dtype.isascii():
        try:
            declared = np.dtype(dtype)
        except Exception:  # noqa: BLE001 - numpy's parser raises TypeError, ValueError, SyntaxError, ... on junk
            declared = None
    kind = declared.kind if declared is not None else None
    if kind is None or kind not in PLAN_KINDS:
        raise ValidationError(f"plan_traj dtype {str(dtype)[:40]!r} is not a numeric type (e.g. float32)")
    # every dimension is checked against the limit before they are multiplied: a shape of 10^30, or four of 10^5
    # (whose product overflows a 64-bit integer), is refused here, not turned into a wrong size or an exception
    if (not isinstance(shape, list) or not 1 <= len(shape) <= MAX_PLAN_DIMS
            or not all(isinstance(n, int) and not isinstance(n, bool) and 0 <= n <= max_values for n in shape)):
        raise ValidationError(f"plan_traj shape must be 1 to {MAX_PLAN_DIMS} integers from 0 to {max_values} "
                              f"(got {str(shape)[:80]})")
    size = math.prod(shape)
    if size > max_values:
        raise ValidationError(f"plan_traj holds {size} numbers (limit {max_values})")
    try:
        data = np.asarray(spec["data"])
    except (ValueError, TypeError, OverflowError) as e:  # ragged, or an integer too large for a float beside it
        raise ValidationError(f"plan_traj data is not a regular array of numbers: {str(e)[:120]}") from None
    if data.dtype.kind not in PLAN_KINDS:
        raise ValidationError("plan_traj data must hold only numbers")
    if data.size != size:
        raise ValidationError(f"plan_traj data holds {data.size} numbers, its shape {shape} says {size}")
    # the numbers must be what the declared dtype can hold (HUGSIM's client sends ``array.tolist()`` with the
    # array's dtype, so they always are): else the plan the client meant is not the one these numbers make
    if kind in "iu" and data.size:
        info = np.iinfo(declared)
        whole = data.dtype.kind != "f" or bool(np.isfinite(data).all() and (data == np.round(data)).all())
        if not whole or data.min() < info.min or data.max() > info.max:
            raise ValidationError(f"plan_traj data does not fit its dtype {declared} (whole numbers from {info.min} "
                                  f"to {info.max})")
    if kind == "f":
        with np.errstate(over="ignore", invalid="ignore"):
            cast = data.astype(declared)
        if (np.isfinite(data) & ~np.isfinite(cast)).any():
            raise ValidationError(f"plan_traj data overflows its dtype {declared}")
    return data.astype(np.float64).reshape(shape)


class _Session:
    """One client's episode: its simulator, scenario queue, last state and recent replies."""

    def __init__(self, label: str, owner: bytes) -> None:
        self.label = label                  # what logs and the status page call it (never the token)
        self.owner = owner                  # the token it belongs to (its turns at the renderer are that token's)
        self.lock = threading.Lock()
        self.sim: Simulator | None = None
        self.current: str | None = None     # scenario id of the episode under way
        self.pending: list[str] = []        # scenario ids still to drive after it
        self.last: StepResult | None = None
        self.scene_done = False
        self.replies: OrderedDict[str, tuple[str, bytes]] = OrderedDict()  # transaction id -> (its plan_traj, reply)
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
        self.tokens = tuple(dict.fromkeys(t.encode() for t in tokens))  # a repeated token is one client, not two
        i = order.index(start)
        self.order = order[i:] + order[:i]
        # One simulator now: its scene is checked against every scenario before a client comes, and the first
        # session takes it over.
        self._spare: Simulator | None = make_simulator()
        wrong = [k for k, sc in scenarios.items() if sc.scene_id != self._spare.scene.scene_id]
        if wrong:
            raise ValidationError(f"scenario(s) {wrong} are not of the simulator's scene {self._spare.scene.scene_id}")
        # A plan is checked before its session is looked up or opened (a refused request takes no slot): the
        # check reads only the simulators' shared configuration, so this first one answers for all of them.
        self.plan_checker: Simulator = self._spare
        self.sessions: dict[tuple[bytes, str], _Session] = {}
        self.registry = threading.Lock()
        self.opened = 0
        self.per_token = config.sessions_per_token(len(self.tokens))
        self.pending_limit = config.pending_per_token(len(self.tokens))
        if self.per_token * len(self.tokens) > config.max_sessions:
            log.warning("%d tokens x %d sessions each exceed max_sessions %d: a token may find the server full",
                        len(self.tokens), self.per_token, config.max_sessions)
        # per token, touched only on the event loop: [requests left in its bucket, when it was last refilled],
        # requests in progress, and the limiter of its worker threads (so one token's queue of requests waits for
        # its own threads, never for another's)
        self.buckets: dict[bytes, list[float]] = {t: [float(config.request_burst), time.monotonic()]
                                                  for t in self.tokens}
        self.pending: dict[bytes, int] = dict.fromkeys(self.tokens, 0)
        self.limiters: dict[bytes, CapacityLimiter] = {}
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

    def admit(self, token: bytes) -> None:
        """Take one request from ``token``'s bucket, or refuse it with 429 and when to retry (this token only)."""
        bucket, now = self.buckets[token], time.monotonic()
        rate, burst = self.config.requests_per_s, self.config.request_burst
        bucket[0] = min(float(burst), bucket[0] + (now - bucket[1]) * rate)
        bucket[1] = now
        if bucket[0] < 1.0:
            wait = (1.0 - bucket[0]) / rate
            raise HTTPException(429, f"this token is over its {rate:g} requests per second (burst {burst}); "
                                     f"retry in {wait:.2f} s", headers={"Retry-After": str(max(1, math.ceil(wait)))})
        bucket[0] -= 1.0

    @contextlib.contextmanager
    def in_progress(self, token: bytes):
        """Count one request of ``token`` while it is in progress; 429 past ``pending_limit`` at once."""
        if self.pending[token] >= self.pending_limit:
            raise HTTPException(429, f"this token already has {self.pending_limit} requests in progress; retry "
                                     "when one has been answered", headers={"Retry-After": "1"})
        self.pending[token] += 1
        try:
            yield
        finally:
            self.pending[token] -= 1

    def limiter(self, token: bytes) -> CapacityLimiter:
        """``token``'s worker threads: as many as it may hold sessions (made on the event loop, on first use)."""
        if token not in self.limiters:
            self.limiters[token] = CapacityLimiter(self.per_token)
        return self.limiters[token]

    @staticmethod
    def session_id(request: Request) -> str:
        sid = request.headers.get(SESSION_HEADER, "")
        if sid and not SESSION_ID.fullmatch(sid):
            raise HTTPException(400, f"{SESSION_HEADER} must be 1 to 64 letters, digits or ._:- characters")
        return sid

    def session(self, token: bytes, sid: str) -> _Session:
        """The session of (``token``, ``sid``), opened if new; call it only for a request already found valid, so
        that a refused one never takes a slot. 429 (with Retry-After) when ``token`` holds its ``per_token``
        sessions or the server its ``max_sessions``."""
        now = time.monotonic()
        idle_s = self.config.session_idle_s
        with self.registry:
            for key, s in list(self.sessions.items()):
                if now - s.last_used > idle_s and not s.lock.locked():
                    del self.sessions[key]
                    self.note(f"{s.label}: dropped after {now - s.last_used:.0f} s idle")
            s = self.sessions.get((token, sid))
            if s is None:
                own = [x for x in self.sessions.values() if x.owner == token]
                if len(own) >= self.per_token:
                    wait = idle_s - (now - min(x.last_used for x in own))
                    raise HTTPException(429, f"this token holds its limit of {self.per_token} sessions; retry when "
                                             f"one has been idle {idle_s:.0f} s (in {max(0.0, wait):.0f} s)",
                                        headers={"Retry-After": str(max(1, math.ceil(wait)))})
                if len(self.sessions) >= self.config.max_sessions:
                    wait = idle_s - (now - min(x.last_used for x in self.sessions.values()))
                    raise HTTPException(429, f"the server holds its limit of {self.config.max_sessions} sessions; "
                                             f"retry when one has been idle {idle_s:.0f} s",
                                        headers={"Retry-After": str(max(1, math.ceil(wait)))})
                self.opened += 1
                s = self.sessions[(token, sid)] = _Session(f"session {self.opened}", token)
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
        with RENDER_LOCK.turn(s.owner):
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
        with RENDER_LOCK.turn(s.owner):
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
        scores = score_with_epdms(scored_trace(sim))
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

    # -- requests (each checked whole before its session is opened, then run under the session's lock) ------
    def do_reset(self, token: bytes, sid: str, body: bytes) -> dict:
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
        s = self.session(token, sid)
        with s.lock:
            return {"success": True, "scenario": self.reset(s, only)}

    def do_state(self, token: bytes, sid: str) -> bytes:
        s = self.session(token, sid)
        with s.lock:
            self.ensure_started(s)
            return self.state_bytes(s)

    def do_execute(self, token: bytes, sid: str, body: bytes) -> bytes:
        envelope = 'execute_action takes JSON {"plan_traj": "<json>", "transaction_id": "<id>"}'
        try:
            request = json.loads(body)
        except (ValueError, RecursionError):
            raise HTTPException(422, envelope) from None
        if not isinstance(request, dict) or not isinstance(request.get("plan_traj"), str):
            raise HTTPException(422, envelope)
        transaction = request.get("transaction_id")
        if not isinstance(transaction, str) or not 1 <= len(transaction) <= MAX_TRANSACTION_ID:
            raise HTTPException(422, f"transaction_id must be a string of 1 to {MAX_TRANSACTION_ID} characters")
        try:
            plan = self.plan_checker.check_plan(parse_plan(request["plan_traj"], self.config.max_plan_values))
        except ValidationError as e:
            raise HTTPException(422, f"plan refused, the episode did not move: {e}") from None
        s = self.session(token, sid)
        with s.lock:
            cached = s.replies.get(transaction)
            if cached is not None:
                if cached[0] != request["plan_traj"]:  # a retry resends its plan; another plan would get a stale reply
                    raise HTTPException(409, f"transaction_id {transaction[:40]!r} was already executed with another "
                                             "plan; send each plan with a new id")
                s.replies.move_to_end(transaction)
                return cached[1]
            self.ensure_started(s)
            if not s.scene_done:
                self.step(s, plan)
            elif s.pending:  # the plan was made for the ended scenario: start the next one and show it
                self.begin(s, s.pending.pop(0))
            reply = self.state_bytes(s)
            s.replies[transaction] = (request["plan_traj"], reply)
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
                f"POST /execute_action (auth-token header).</p><p>{n} of {self.config.max_sessions} sessions open "
                f"(at most {self.per_token} per token).</p>"
                "<h2>Scenarios</h2><table><tr><th>id</th><th>kind</th><th>steps</th><th>duration</th></tr>"
                f"{rows}</table><h2>Recent events</h2><pre>{lines}</pre></body></html>")


async def _read_body(request: Request, limit: int, timeout_s: float) -> bytes:
    """The request body, refused with 413 past ``limit`` bytes (whether declared or only seen while reading) and
    with 408 when it has not all arrived within ``timeout_s``; both close the connection, so the rest of the body
    is not read either."""
    close = {"Connection": "close"}
    declared = request.headers.get("content-length")
    if declared is not None:
        if not (declared.isascii() and declared.isdigit()):
            raise HTTPException(400, "Content-Length is not a number", headers=close)
        if int(declared) > limit:
            raise HTTPException(413, f"request body of {int(declared)} bytes is over the server's {limit}-byte limit",
                                headers=close)

    async def receive() -> bytes:
        chunks, size = [], 0
        async for chunk in request.stream():
            size += len(chunk)
            if size > limit:
                raise HTTPException(413, f"request body is over the server's {limit}-byte limit", headers=close)
            chunks.append(chunk)
        return b"".join(chunks)

    try:
        return await asyncio.wait_for(receive(), timeout_s)
    except asyncio.TimeoutError:
        raise HTTPException(408, f"the request body did not arrive within {timeout_s:g} s", headers=close) from None


async def _guarded(limiter: CapacityLimiter, work: Callable, *args):
    """Run ``work`` on a worker thread of ``limiter``; anything but an HTTP refusal becomes a 500 for this request
    only."""
    try:
        return await to_thread.run_sync(work, *args, limiter=limiter)
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
    - One token cannot starve another: each token may hold ``max_sessions_per_token`` sessions (by default a fair
      share of ``max_sessions``), make ``requests_per_s`` requests a second (after a burst of ``request_burst``)
      and have ``max_pending_per_token`` in progress; past any of these only that token gets 429 with
      Retry-After. Each token's requests run on worker threads of its own and take turns at the renderer by token
      (``RENDER_LOCK``). A request is checked whole (token, headers, body, plan) before its session is opened, so
      a refused one never takes a slot.
    - A body that has not arrived ``body_timeout_s`` after its headers gets 408; a connection that has not sent a
      request's headers ``header_timeout_s`` after opening or after its last reply is closed, one whose reply the
      client has not taken for ``reply_timeout_s`` is dropped (``omniscs.server.transport.uvicorn_options``, which
      its ``serve`` and ``start_in_thread`` use).
    - ``GET /get_current_state`` (resetting implicitly before the first ``/reset``) and ``POST /execute_action``
      reply ``pickle.dumps({"done", "cur_scene_done", "state": {"obs", "info"}})`` as application/octet-stream, as
      HUGSIM's client expects: ``obs`` maps each output (rgb uint8 [H, W, 3], depth float32 [H, W], semantic uint8
      [H, W], instance int32 [H, W]) to per-camera arrays, ``info`` is the simulator's (HUGSIM's keys and ours, plus
      ``scores`` when a scenario ends). The server never unpickles anything: a plan arrives as the JSON string
      ``plan_traj`` = ``{"data", "shape", "dtype"}``.
    - ``execute_action`` checks the plan before anything moves (422 with the reason; the episode is not stepped)
      and replays the stored reply for a ``transaction_id`` it has already executed with the same plan (the client
      retries calls whose answer it lost; the same id with another plan is 409, not a stale reply). When a
      scenario ends the reply says ``cur_scene_done``; the next call starts the session's next scenario and returns
      its first state (the plan, made for the ended one, is not driven), or repeats the final state with ``done``
      once the queue is empty.
    - Bodies over ``max_body_bytes`` get 413, whether declared or only seen while reading. Errors are JSON
      ``{"detail": ...}``; a failing request affects only its own reply. A malformed plan (any shape, dtype,
      value or JSON type) is 422, never 500.
    - Resets and steps of all sessions take turns under ``RENDER_LOCK``."""
    hub = _Hub(make_simulator, scenarios, tokens, config)
    app = FastAPI(title="OmniSCS closed-loop server (HUGSIM protocol)", docs_url=None, redoc_url=None,
                  openapi_url=None)
    app.state.hub = hub

    @app.get("/", response_class=HTMLResponse)
    async def status_page() -> HTMLResponse:
        return HTMLResponse(hub.page())

    async def handle(request: Request, work: Callable, with_body: bool):
        # the order matters: cheap refusals first (token, rate, pile of requests), on the event loop; then the body
        # (size and deadline); then, on one of this token's worker threads, the request is checked whole before
        # its session is looked up or opened, so a refused request never takes a slot
        head = sum(len(k) + len(v) for k, v in request.headers.raw)
        if head > MAX_HEAD_BYTES:  # h11 bounds only a head that arrives in pieces, not one read whole
            raise HTTPException(431, f"request headers of {head} bytes are over the server's {MAX_HEAD_BYTES}-byte "
                                     "limit", headers={"Connection": "close"})
        token = hub.authorise(request)
        hub.admit(token)
        sid = hub.session_id(request)
        with hub.in_progress(token):
            args = (token, sid)
            if with_body:
                args += (await _read_body(request, config.max_body_bytes, config.body_timeout_s),)
            return await _guarded(hub.limiter(token), work, *args)

    @app.post("/reset")
    async def reset(request: Request):
        return await handle(request, hub.do_reset, True)

    @app.get("/get_current_state")
    async def get_current_state(request: Request):
        out = await handle(request, hub.do_state, False)
        return out if isinstance(out, Response) else Response(out, media_type=PICKLED)

    @app.post("/execute_action")
    async def execute_action(request: Request):
        out = await handle(request, hub.do_execute, True)
        return out if isinstance(out, Response) else Response(out, media_type=PICKLED)

    return app
