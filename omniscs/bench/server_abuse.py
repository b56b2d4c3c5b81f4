"""The server-abuse section of ``omniscs bench bad-inputs``: hostile requests to the closed-loop render server
(``omniscs.server.hugsim``), each against a fresh in-thread server on a tiny unfitted world, classified.

Two tokens share each server: ``A`` (the abuser) sends the case's requests, then ``B`` (a bystander) opens a
session and drives a step. A case is ``clean`` when every answer to A is one of the case's expected refusals,
A's refused requests took no session slot, and B was served at once. Otherwise it is ``server error`` (a 500),
``hang`` (no answer, or a connection held, past its deadline), ``accepted`` (a 2xx the case should not get),
``took a slot`` (a refused request opened a session), ``starved the bystander`` (B got a 429 or waited) or
``other`` (an unexpected status).
"""
from __future__ import annotations

import json
import pickle
import socket
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable
from urllib.parse import urlparse

import requests

from omniscs.progress import Progress, no_progress

SERVER_OUTCOMES = ("clean", "server error", "hang", "accepted", "took a slot", "starved the bystander", "other")
ABUSER, BYSTANDER = "token-A", "token-B"
#: A plan HUGSIM's client would send: [6, 2] planning frame, 1 m/s straight ahead.
PLAN = [[0.0, 0.5 * k] for k in range(1, 7)]
GOOD_PLAN = json.dumps({"data": PLAN, "shape": [6, 2], "dtype": "float32"})
#: Limits of the bench's servers: the defaults' session and rate limits, short deadlines so that a slow-sender
#: case takes a second, not the defaults' 10-20 s (the deadlines work the same at any length).
BENCH_LIMITS = dict(max_sessions=8, max_body_bytes=64 * 1024, requests_per_s=20.0, request_burst=40,
                    body_timeout_s=0.5, header_timeout_s=0.5, keep_alive_s=5.0)
#: Longest the bystander's reset or step may take after a case (its renders take milliseconds).
BYSTANDER_LIMIT_S = 2.5
#: Longest any one request of a case may go unanswered.
REQUEST_LIMIT_S = 10.0
HANG = -1     # a request not answered within REQUEST_LIMIT_S
CLOSED = -2   # the server closed the connection without an answer (expected of a header deadline)


class Probe:
    """One fresh server (two tokens) and the ways a case talks to it."""

    def __init__(self, handle) -> None:
        self.handle, self.url = handle, handle.url
        self.hub = handle.server.config.app.state.hub

    def sessions_of(self, token: str) -> int:
        with self.hub.registry:
            return sum(1 for s in self.hub.sessions.values() if s.owner == token.encode())

    def send(self, method: str, path: str, token: str | None = ABUSER, session: str | None = None,
             headers: dict | None = None, **kw) -> int:
        h = ({"auth-token": token} if token is not None else {}) | ({"session-id": session} if session else {})
        try:
            return requests.request(method, self.url + path, headers=h | (headers or {}), timeout=REQUEST_LIMIT_S,
                                    **kw).status_code
        except requests.Timeout:
            return HANG
        except requests.ConnectionError:
            return CLOSED

    def execute(self, plan_traj: str = GOOD_PLAN, token: str = ABUSER, session: str | None = None,
                transaction: str = "t") -> int:
        return self.send("post", "/execute_action", token, session,
                         json={"plan_traj": plan_traj, "transaction_id": transaction})

    def raw(self, head: bytes, trickle: bytes = b"", every_s: float = 0.05) -> int:
        """Send ``head`` on a raw connection, then ``trickle`` one byte every ``every_s``; the status the server
        answers with, ``CLOSED`` when it closes the connection without one, ``HANG`` when it holds it."""
        url = urlparse(self.url)
        deadline = time.monotonic() + REQUEST_LIMIT_S
        with socket.create_connection((url.hostname, url.port), timeout=REQUEST_LIMIT_S) as sock:
            sock.settimeout(every_s)
            reply = b""
            try:
                sock.sendall(head)
                for i in range(10 ** 6):
                    if time.monotonic() > deadline:
                        return HANG
                    if trickle:
                        sock.sendall(trickle[i % len(trickle):i % len(trickle) + 1])
                    try:
                        chunk = sock.recv(4096)
                    except socket.timeout:
                        continue
                    if not chunk:
                        break
                    reply += chunk
            except (ConnectionResetError, BrokenPipeError):
                pass
        if reply.startswith(b"HTTP/1.1 "):
            return int(reply[9:12])
        return CLOSED


@dataclass(frozen=True)
class ServerCase:
    """One abuse of the server: ``run`` sends it as token A and returns every status A got; ``expect`` are the
    statuses of a clean refusal; ``slots`` how many sessions A may hold afterwards (those it opened legitimately)."""

    name: str
    run: Callable[[Probe], list[int]]
    expect: frozenset[int]
    slots: int = 0


def _plan(**fields) -> str:
    return json.dumps({"data": PLAN, "shape": [6, 2], "dtype": "float32"} | fields)


def _each_session(plans: list[str]) -> Callable[[Probe], list[int]]:
    """Each plan from a new session id (so any of them that opened a session would show)."""
    return lambda p: [p.execute(plan, session=f"junk-{i}") for i, plan in enumerate(plans)]


def _flood_sessions(p: Probe) -> list[int]:
    return [p.send("get", "/get_current_state", session=f"flood-{i}") for i in range(30)]


def _burst(p: Probe) -> list[int]:
    p.send("get", "/get_current_state")
    return [p.send("get", "/get_current_state") for _ in range(80)]


def _concurrent_junk(p: Probe) -> list[int]:
    def one(i: int) -> int:
        kind = i % 3
        if kind == 0:
            return p.send("get", "/get_current_state", session=f"c-{i}")
        if kind == 1:
            return p.execute(_plan(shape=[10 ** 30]), session=f"c-{i}")
        return p.execute(session=f"c-{i}", transaction=str(i))

    with ThreadPoolExecutor(8) as pool:
        return list(pool.map(one, range(120)))


def _slow_bodies_at_once(p: Probe) -> list[int]:
    head = (b"POST /execute_action HTTP/1.1\r\nHost: x\r\nauth-token: " + ABUSER.encode()
            + b"\r\nContent-Type: application/json\r\nContent-Length: 5000\r\n\r\n{")
    with ThreadPoolExecutor(24) as pool:
        return list(pool.map(lambda i: p.raw(head, b" "), range(24)))


def _reused_transaction(p: Probe) -> list[int]:
    first = p.execute(transaction="same")  # a step (200, opening A's session) is the setting, not the abuse
    return [p.execute(_plan(data=[[0.0, 0.4 * k] for k in range(1, 7)]), transaction="same")] if first == 200 \
        else [first]


def _chunked_over_limit(p: Probe) -> list[int]:
    chunks = (b"x" * 8192 for _ in range(BENCH_LIMITS["max_body_bytes"] // 8192 + 2))
    return [p.send("post", "/execute_action", data=chunks)]


MALFORMED_PLANS = [
    _plan(shape=[10 ** 30]), _plan(shape=[2 ** 62, 4], data=[]), _plan(shape=[-6, -2]), _plan(shape=[1] * 5 + [2]),
    _plan(shape=[6.0, 2.0]), _plan(shape="6x2"), _plan(dtype=","), _plan(dtype="(2147483648,)f4"),
    _plan(dtype="object"), _plan(dtype="complex64"), _plan(dtype=None), _plan(data=[[0.0, float("nan")]] * 6),
    _plan(data=[[0.0, float("inf")]] * 6), _plan(data=[[0.0, 1e300]] * 6), _plan(data=[["0", "1"]] * 6),
    _plan(dtype="int8", data=[[0, 100 * k] for k in range(1, 7)]), _plan(dtype="float16", data=[[0.0, 1e5]] * 6),
    _plan(data=[[True, False]] * 6), _plan(data=[[0.0, 1.0], [0.0]]),
    '{"data": [1.5, ' + "9" * 400 + '], "shape": [2], "dtype": "float32"}',
    '{"data": ' + "[" * 3000 + "]" * 3000 + ', "shape": [1], "dtype": "float32"}', "[" * 50_000, "not json", "",
]

SERVER_CASES: tuple[ServerCase, ...] = (
    ServerCase("24 malformed plans, each from a new session id", _each_session(MALFORMED_PLANS), frozenset({422})),
    ServerCase("bodies that are not the envelope (not JSON, not UTF-8, pickled, deep, wrong types)",
               lambda p: [p.send("post", "/execute_action", session=f"b-{i}", data=body,
                                 headers={"content-type": "application/json"})
                          for i, body in enumerate([b"", b"plan", b'{"plan_traj": "\xff"}', b"[" * 50_000,
                                                    pickle.dumps({"plan_traj": PLAN}), b"9" * 5000,
                                                    json.dumps({"plan_traj": {"data": PLAN}}).encode(),
                                                    json.dumps({"plan_traj": GOOD_PLAN,
                                                                "transaction_id": 7}).encode()])],
               frozenset({422})),
    ServerCase("reset bodies: not JSON, a list, a numeric scenario, an unknown one",
               lambda p: [p.send("post", "/reset", session=f"r-{i}", data=body) for i, body in
                          enumerate([b"{", b"[1]", b'{"scenario": 5}', b'{"scenario": "nowhere/log"}'])],
               frozenset({422, 404})),
    ServerCase("no token, an empty token, a wrong one, 10 kB of token",
               lambda p: [p.send("get", "/get_current_state", token=t, session=f"t-{i}")
                          for i, t in enumerate([None, "", "token-C", "x" * 10_000])],
               frozenset({401})),
    ServerCase("session-id headers that are not ids", lambda p: [p.send("get", "/get_current_state", session=s)
                                                                 for s in ("a b", "../x", "x" * 65, "ü")],
               frozenset({400})),
    ServerCase("body over the limit, declared", lambda p: [p.send(
        "post", "/execute_action", data=b"x" * (BENCH_LIMITS["max_body_bytes"] + 1))], frozenset({413})),
    ServerCase("body over the limit, chunked (no length)", _chunked_over_limit, frozenset({413})),
    ServerCase("Content-Length not a number", lambda p: [p.raw(
        b"POST /reset HTTP/1.1\r\nHost: x\r\nauth-token: token-A\r\nContent-Length: ab\r\n\r\n")],
               frozenset({400})),
    ServerCase("headers of 64 kB", lambda p: [p.send("get", "/get_current_state", headers={"x-junk": "x" * 65_536})],
               frozenset({400, 431})),
    ServerCase("a body trickled a byte at a time", lambda p: [p.raw(
        b"POST /execute_action HTTP/1.1\r\nHost: x\r\nauth-token: token-A\r\nContent-Length: 5000\r\n\r\n{", b" ")],
               frozenset({408})),
    ServerCase("headers trickled a byte at a time", lambda p: [p.raw(b"GET /get_current_state HTTP/1.1\r\n",
                                                                     b"x-slow: 1")],
               frozenset({CLOSED})),
    ServerCase("a connection that sends nothing", lambda p: [p.raw(b"")], frozenset({CLOSED})),
    ServerCase("the rest of a refused body, trickled", lambda p: [p.raw(
        b"POST /execute_action HTTP/1.1\r\nHost: x\r\nauth-token: nope\r\nContent-Length: 99999\r\n\r\n{", b" ")],
               frozenset({401})),
    ServerCase("24 slow bodies at once", _slow_bodies_at_once, frozenset({408, 429})),
    ServerCase("a transaction id reused for another plan (after a step with it)", _reused_transaction,
               frozenset({409}), slots=1),
    ServerCase("30 new session ids (valid requests)", _flood_sessions, frozenset({200, 429}),
               slots=BENCH_LIMITS["max_sessions"] // 2),
    ServerCase("a burst of 80 requests", _burst, frozenset({200, 429}), slots=1),
    ServerCase("120 requests from 8 threads: new sessions, malformed and valid plans", _concurrent_junk,
               frozenset({200, 422, 429}), slots=BENCH_LIMITS["max_sessions"] // 2),
)


@dataclass(frozen=True)
class ServerOutcome:
    case: str
    outcome: str
    statuses: tuple[int, ...]
    abuser_sessions: int
    bystander: str


def tiny_world(root: Path):
    """(make_simulator, scenarios): a 3-frame, one-camera 32x18 synthetic log and an unfitted scene graph, which
    renders in milliseconds (the server's protocol does not care what the pictures show)."""
    from omniscs.closedloop.scenario import log_scenario
    from omniscs.closedloop.simulator import ClosedLoopConfig, Simulator
    from omniscs.nsg import fit_preset
    from omniscs.nsg.init import initial_graph
    from omniscs.nsg.observations import Observations
    from omniscs.plan import PlanConfig, make_plan
    from omniscs.scene import SyntheticSource, load_scene
    from omniscs.scene.synthetic import write_synthetic_scene

    scene = load_scene(write_synthetic_scene(SyntheticSource("straight", 3, n_frames=3, n_cameras=1, width=32,
                                                             height=18), root / "store"))
    config = fit_preset("fast", iterations=1, plan=PlanConfig(gaussians_per_m2=0.05, gaussians_per_agent=50,
                                                               min_gaussians=300, max_gaussians=1000))
    graph = initial_graph(scene, make_plan(scene, None, config.plan), config, Observations(scene))
    log = log_scenario(scene)
    render = ClosedLoopConfig(width=32)
    return (lambda: Simulator(graph, scene, render)), {log.scenario_id: log}


def _bystander(p: Probe) -> str:
    """'' when B opens a session and drives a step, each promptly; else what went wrong."""
    for what, send in (("reset", lambda: p.send("post", "/reset", BYSTANDER, "b")),
                       ("step", lambda: p.execute(token=BYSTANDER, session="b", transaction="b-1"))):
        start = time.perf_counter()
        status = send()
        took = time.perf_counter() - start
        if status != 200 or took > BYSTANDER_LIMIT_S:
            return f"{what}: {status} after {took:.2f} s"
    return ""


def classify_server(case: ServerCase, statuses: list[int], abuser_sessions: int, bystander: str) -> str:
    if 500 in statuses:
        return "server error"
    if HANG in statuses:
        return "hang"
    if any(200 <= s < 300 for s in statuses) and not any(200 <= s < 300 for s in case.expect):
        return "accepted"
    if not set(statuses) <= case.expect:
        return "other"
    if abuser_sessions > case.slots:
        return "took a slot"
    if bystander:
        return "starved the bystander"
    return "clean"


def run_server_case(case: ServerCase, make_simulator, scenarios) -> ServerOutcome:
    from omniscs.server.hugsim import ServerConfig, create_app
    from omniscs.server.transport import start_in_thread

    app = create_app(make_simulator, scenarios, (ABUSER, BYSTANDER), ServerConfig(**BENCH_LIMITS))
    with start_in_thread(app) as handle:
        probe = Probe(handle)
        statuses = case.run(probe)
        abuser_sessions = probe.sessions_of(ABUSER)
        bystander = _bystander(probe)
    return ServerOutcome(case.name, classify_server(case, statuses, abuser_sessions, bystander), tuple(statuses),
                         abuser_sessions, bystander)


def run_server_abuse(cases: tuple[ServerCase, ...] = SERVER_CASES, progress: Progress = no_progress) -> dict:
    """Every case against a fresh server; the outcomes and their counts."""
    with tempfile.TemporaryDirectory(prefix="omniscs-server-abuse-") as tmp:
        make_simulator, scenarios = tiny_world(Path(tmp))
        outcomes = []
        for i, case in enumerate(cases):
            outcomes.append(run_server_case(case, make_simulator, scenarios))
            progress(i + 1, len(cases), f"server: {case.name}")
    counts = {k: sum(o.outcome == k for o in outcomes) for k in SERVER_OUTCOMES}
    return {"limits": BENCH_LIMITS, "tried": len(outcomes), "counts": counts,
            "cases": [o.__dict__ for o in outcomes]}


def _status_text(statuses) -> str:
    names = {HANG: "no answer", CLOSED: "closed"}
    seen: dict[str, int] = {}
    for s in statuses:
        key = names.get(s, str(s))
        seen[key] = seen.get(key, 0) + 1
    return ", ".join(f"{k} x{n}" if n > 1 else k for k, n in seen.items())


def server_markdown(section: dict) -> list[str]:
    """The report's server-abuse section (markdown lines)."""
    limits = section["limits"]
    lines = ["", "## Server abuse", "",
             f"{section['tried']} hostile requests or floods to `closedloop serve`'s server "
             f"(`omniscs.bench.server_abuse.SERVER_CASES`), each against a fresh in-thread server with two tokens: "
             "A sends the case, then B opens a session and steps. Clean: A gets only the case's refusals, its "
             f"refused requests open no session, and B is served within {BYSTANDER_LIMIT_S:g} s. Limits: "
             f"{limits['max_sessions']} sessions (a fair share of {limits['max_sessions'] // 2} per token), "
             f"{limits['requests_per_s']:g} requests/s per token after a burst of {limits['request_burst']}, body "
             f"and header deadlines {limits['body_timeout_s']:g} s (shortened for the bench).", "",
             "| " + " | ".join(SERVER_OUTCOMES) + " |", "|" + "---|" * len(SERVER_OUTCOMES),
             "| " + " | ".join(str(section["counts"][k]) for k in SERVER_OUTCOMES) + " |", "",
             "| case | outcome | A got | A's sessions after | B |", "|---|---|---|---|---|"]
    for c in section["cases"]:
        lines.append(f"| {c['case']} | {c['outcome']} | {_status_text(c['statuses'])} | {c['abuser_sessions']} | "
                     f"{c['bystander'] or 'served'} |")
    return lines

