"""The HUGSIM-protocol server under abuse: one token's junk (new session ids, malformed plans, bursts) never makes
another token wait or get 429; a refused request takes no session slot; slow senders are cut off; every malformed
plan is 422, never 500. A tiny unfitted world (3 frames, one 32x18 camera) keeps each test well under a second."""
from __future__ import annotations

import json
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from urllib.parse import urlparse

import numpy as np
import pytest
import requests

from omniscs.errors import ValidationError
from omniscs.server.hugsim import ServerConfig, TurnLock, create_app, parse_plan
from omniscs.server.transport import start_in_thread

PLAN = [[0.0, 0.5 * k] for k in range(1, 7)]  # [6, 2] planning frame: 1 m/s straight ahead
GOOD_PLAN_TRAJ = json.dumps({"data": PLAN, "shape": [6, 2], "dtype": "float32"})


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(scene, graph, scenarios) of a 3-frame synthetic log with an unfitted graph: renders in milliseconds."""
    from omniscs.closedloop.scenario import log_scenario
    from omniscs.nsg import fit_preset
    from omniscs.nsg.init import initial_graph
    from omniscs.nsg.observations import Observations
    from omniscs.plan import PlanConfig, make_plan
    from omniscs.scene import SyntheticSource, load_scene
    from omniscs.scene.synthetic import write_synthetic_scene

    root = tmp_path_factory.mktemp("server-limits")
    scene = load_scene(write_synthetic_scene(SyntheticSource("straight", 3, n_frames=3, n_cameras=1, width=32,
                                                             height=18), root / "store"))
    config = fit_preset("fast", iterations=1, plan=PlanConfig(gaussians_per_m2=0.05, gaussians_per_agent=50,
                                                               min_gaussians=300, max_gaussians=1000))
    graph = initial_graph(scene, make_plan(scene, None, config.plan), config, Observations(scene))
    log = log_scenario(scene)
    return scene, graph, {log.scenario_id: log}


def make_server(tiny, tokens=("A", "B"), **config):
    from omniscs.closedloop.simulator import ClosedLoopConfig, Simulator

    scene, graph, scenarios = tiny
    app = create_app(lambda: Simulator(graph, scene, ClosedLoopConfig(width=32)), scenarios, tokens,
                     ServerConfig(**config))
    return start_in_thread(app)


def call(server, method, path, token, session=None, **kw):
    headers = {"auth-token": token} | ({"session-id": session} if session else {}) | kw.pop("headers", {})
    return requests.request(method, server.url + path, headers=headers, timeout=10, **kw)


def execute(server, token, plan_traj=GOOD_PLAN_TRAJ, transaction="t", session=None):
    return call(server, "post", "/execute_action", token, session,
                json={"plan_traj": plan_traj, "transaction_id": transaction})


def open_sessions(server) -> int:
    hub = server.server.config.app.state.hub
    with hub.registry:
        return len(hub.sessions)


# ----------------------------------------------------------------------------- fuzz list of malformed plans
def _plan(**fields) -> str:
    spec = {"data": PLAN, "shape": [6, 2], "dtype": "float32"} | fields
    return json.dumps(spec)


MALFORMED_PLANS = {
    "shape 10^30": _plan(shape=[10 ** 30]),
    "shape 10^30 x 2": _plan(shape=[10 ** 30, 2]),
    "shape overflowing int64 when multiplied": _plan(shape=[100_000, 100_000, 100_000, 100_000]),
    "shape of 2^63": _plan(shape=[2 ** 63, 2]),
    "shape wrapping to 0 in int64, no data": _plan(shape=[2 ** 62, 4], data=[]),
    "shape 2^32 x 2^32, no data": _plan(shape=[2 ** 32, 2 ** 32], data=[]),
    "negative dim": _plan(shape=[-6, -2]),
    "five dims": _plan(shape=[1, 1, 1, 6, 2]),
    "no dims": _plan(shape=[]),
    "float dims": _plan(shape=[6.0, 2.0]),
    "bool dims": _plan(shape=[True, 2]),
    "string dims": _plan(shape=["6", "2"]),
    "shape a number": _plan(shape=12),
    "shape null": _plan(shape=None),
    "shape an object": _plan(shape={"rows": 6}),
    "shape of nested lists": _plan(shape=[[6], [2]]),
    "dtype object": _plan(dtype="object"),
    "dtype bool": _plan(dtype="bool"),
    "dtype complex": _plan(dtype="complex128"),
    "dtype datetime": _plan(dtype="M8[s]"),
    "dtype string": _plan(dtype="U10"),
    "dtype structured": _plan(dtype="f4,f4"),
    "dtype subarray": _plan(dtype="(2,)f4"),
    "dtype bracket junk": _plan(dtype="[('a', 'f4')]"),
    "dtype parenthesis junk": _plan(dtype="(((("),
    "dtype a lone comma": _plan(dtype=","),
    "dtype of 2^31 floats": _plan(dtype="2147483648f4"),
    "dtype of a (2^31,) subarray": _plan(dtype="(2147483648,)f4"),
    "dtype over 2 GB": _plan(dtype="(99999999,99999999)f4"),
    "dtype of a negative subarray": _plan(dtype="(-1,)f4"),
    "dtype of 10 kB": _plan(dtype="f" * 10_000),
    "dtype non-ASCII": _plan(dtype="ｆloat32"),
    "dtype a number": _plan(dtype=32),
    "dtype null": _plan(dtype=None),
    "dtype a list": _plan(dtype=["float32"]),
    "data NaN": _plan(data=[[0.0, float("nan")]] * 6),
    "data Infinity": _plan(data=[[0.0, float("inf")]] * 6),
    "data 1e308 (far away)": _plan(data=[[0.0, 1e308]] * 6),
    "data an integer of 400 digits": '{"data": [[0, ' + "9" * 400 + ']], "shape": [1, 2], "dtype": "float32"}',
    "data an integer of 5000 digits": '{"data": [[0, ' + "9" * 5000 + ']], "shape": [1, 2], "dtype": "float32"}',
    "data a float and a huge integer": '{"data": [1.5, ' + "9" * 400 + '], "shape": [2], "dtype": "float32"}',
    "data fractions under an integer dtype": _plan(dtype="int32"),
    "data out of an int8's range": _plan(dtype="int8", data=[[0, 100 * k] for k in range(1, 7)]),
    "data negative under an unsigned dtype": _plan(dtype="uint16", data=[[-1, k] for k in range(1, 7)]),
    "data overflowing float16": _plan(dtype="float16", data=[[0.0, 1e5]] * 6),
    "data strings": _plan(data=[["0", "1"]] * 6),
    "data booleans": _plan(data=[[True, False]] * 6),
    "data nulls": _plan(data=[[None, None]] * 6),
    "data objects": _plan(data=[{"x": 0, "y": 1}] * 6),
    "data a string": _plan(data="0,1,0,2"),
    "data a number": _plan(data=5),
    "data ragged": _plan(data=[[0.0, 1.0], [0.0]]),
    "data nested 80 deep": '{"data": ' + "[" * 80 + "1" + "]" * 80 + ', "shape": [1], "dtype": "float32"}',
    "data nested 5000 deep": '{"data": ' + "[" * 5000 + "]" * 5000 + ', "shape": [1], "dtype": "float32"}',
    "data count differs from shape": _plan(shape=[7, 2]),
    "data empty": _plan(data=[], shape=[0]),
    "data of the wrong layout": _plan(data=[0.0] * 12, shape=[12]),
    "data of 3 columns": _plan(data=[[0.0, 1.0, 2.0]] * 6, shape=[6, 3]),
    "data of 101 waypoints": _plan(data=[[0.0, 0.01 * k] for k in range(101)], shape=[101, 2]),
    "envelope a list": json.dumps([PLAN]),
    "envelope missing dtype": json.dumps({"data": PLAN, "shape": [6, 2]}),
    "envelope a string": json.dumps("plan"),
    "plan_traj not JSON": "{data: [1, 2]",
    "plan_traj empty": "",
    "plan_traj nested 100000 deep": "[" * 100_000,
}

#: Whole execute_action bodies that are malformed around the plan (raw bytes: not only JSON).
MALFORMED_BODIES = {
    "body empty": b"",
    "body not JSON": b"plan please",
    "body not UTF-8": b'{"plan_traj": "\xff\xfe", "transaction_id": "t"}',
    "body a list": json.dumps([GOOD_PLAN_TRAJ, "t"]).encode(),
    "body nested 100000 deep": b"[" * 100_000,
    "body an integer of 5000 digits": b"9" * 5000,
    "plan_traj an object, not a string": json.dumps({"plan_traj": {"data": PLAN}, "transaction_id": "t"}).encode(),
    "plan_traj a number": json.dumps({"plan_traj": 5, "transaction_id": "t"}).encode(),
    "plan_traj missing": json.dumps({"transaction_id": "t"}).encode(),
    "transaction_id a number": json.dumps({"plan_traj": GOOD_PLAN_TRAJ, "transaction_id": 7}).encode(),
    "transaction_id empty": json.dumps({"plan_traj": GOOD_PLAN_TRAJ, "transaction_id": ""}).encode(),
    "transaction_id of 10 kB": json.dumps({"plan_traj": GOOD_PLAN_TRAJ, "transaction_id": "x" * 10_000}).encode(),
    "transaction_id null": json.dumps({"plan_traj": GOOD_PLAN_TRAJ, "transaction_id": None}).encode(),
}


@pytest.mark.parametrize("name", list(MALFORMED_PLANS))
def test_parse_and_check_refuse_every_malformed_plan_with_a_validation_error_only(tiny, name):
    from omniscs.closedloop.simulator import ClosedLoopConfig, Simulator

    scene, graph, _ = tiny
    with pytest.raises(ValidationError):
        Simulator(graph, scene, ClosedLoopConfig(width=32)).check_plan(parse_plan(MALFORMED_PLANS[name]))


def test_every_malformed_plan_or_body_is_one_422_and_opens_no_session(tiny):
    with make_server(tiny, requests_per_s=10_000, request_burst=10_000) as server:
        for i, (name, plan_traj) in enumerate(MALFORMED_PLANS.items()):
            r = execute(server, "A", plan_traj, session=f"fuzz-{i}")
            assert r.status_code == 422, (name, r.status_code, r.text[:200])
            assert r.json()["detail"].startswith("plan refused") and len(r.json()["detail"]) < 400, name
        for i, (name, body) in enumerate(MALFORMED_BODIES.items()):
            r = call(server, "post", "/execute_action", "A", f"body-{i}", data=body,
                     headers={"content-type": "application/json"})
            assert r.status_code == 422, (name, r.status_code, r.text[:200])
        assert open_sessions(server) == 0
        assert execute(server, "A").status_code == 200  # the server still serves, and the good plan drives
        assert open_sessions(server) == 1


def test_refused_requests_take_no_slot(tiny):
    with make_server(tiny, max_sessions=2, max_body_bytes=4096) as server:  # one session per token
        refusals = [
            (422, lambda i: execute(server, "A", "{junk", session=f"a{i}")),
            (422, lambda i: call(server, "post", "/reset", "A", f"b{i}", data=b"[1, 2]")),
            (422, lambda i: call(server, "post", "/reset", "A", f"c{i}", json={"scenario": 5})),
            (404, lambda i: call(server, "post", "/reset", "A", f"d{i}", json={"scenario": "nowhere/log"})),
            (413, lambda i: call(server, "post", "/execute_action", "A", f"e{i}", data=b"x" * 5000)),
            (400, lambda i: call(server, "get", "/get_current_state", "A", f"bad id {i}")),
            (401, lambda i: call(server, "get", "/get_current_state", f"not-a-token-{i}", f"g{i}")),
            (431, lambda i: call(server, "get", "/get_current_state", "A", f"h{i}", headers={"x": "y" * 20_000})),
        ]
        for i in range(3):
            for status, send in refusals:
                assert send(i).status_code == status
        assert open_sessions(server) == 0
        assert call(server, "get", "/get_current_state", "A", "real").status_code == 200
        assert call(server, "get", "/get_current_state", "B", "real").status_code == 200
        assert open_sessions(server) == 2


def test_a_token_past_its_sessions_gets_429_with_retry_after_and_the_other_token_does_not(tiny):
    with make_server(tiny, max_sessions=4, session_idle_s=60) as server:  # a fair share of 2 sessions per token
        for sid in ("a1", "a2"):
            assert call(server, "get", "/get_current_state", "A", sid).status_code == 200
        r = call(server, "get", "/get_current_state", "A", "a3")
        assert r.status_code == 429 and "this token holds its limit of 2" in r.json()["detail"]
        assert 1 <= int(r.headers["Retry-After"]) <= 60
        for sid in ("b1", "b2"):
            assert call(server, "get", "/get_current_state", "B", sid).status_code == 200
        assert call(server, "get", "/get_current_state", "A", "a1").status_code == 200  # its own still serve


def test_a_token_over_its_rate_gets_429_with_retry_after_and_the_other_token_does_not(tiny):
    with make_server(tiny, requests_per_s=1.0, request_burst=3) as server:
        assert call(server, "get", "/get_current_state", "B").status_code == 200  # renders are warm: A's are quick
        start = time.monotonic()
        codes = [call(server, "get", "/get_current_state", "A").status_code for _ in range(4)]
        r = call(server, "get", "/get_current_state", "A")
        if time.monotonic() - start < 1.0:  # else the bucket refilled meanwhile (a very loaded machine)
            assert codes == [200, 200, 200, 429] and r.status_code == 429
            assert r.headers["Retry-After"] == "1" and "requests per second" in r.json()["detail"]
        assert [call(server, "get", "/get_current_state", "B").status_code for _ in range(2)] == [200] * 2
        time.sleep(1.05)  # the bucket refills at 1 per second
        assert call(server, "get", "/get_current_state", "A").status_code == 200


def test_junk_from_one_token_never_makes_another_wait_or_get_429(tiny):
    """The issue's line: token A floods the server (new session ids, malformed plans, bursts, all at once from
    eight threads) while token B drives; B gets every answer, promptly, and never a 429."""
    with make_server(tiny, max_sessions=4, requests_per_s=20.0, request_burst=20) as server:
        stop = threading.Event()
        a_codes: list[int] = []

        def junk(k: int) -> None:
            i = 0
            while not stop.is_set():
                i += 1
                kind = (k + i) % 3
                if kind == 0:
                    r = call(server, "get", "/get_current_state", "A", f"junk-{k}-{i}")
                elif kind == 1:
                    r = execute(server, "A", MALFORMED_PLANS["shape 10^30"], session=f"junk-{k}-{i}")
                else:
                    r = execute(server, "A", GOOD_PLAN_TRAJ, transaction=f"{k}-{i}", session=f"junk-{k}-{i}")
                a_codes.append(r.status_code)

        with ThreadPoolExecutor(8) as pool:
            for k in range(8):
                pool.submit(junk, k)
            time.sleep(0.3)  # A's flood is under way: its burst is spent, its sessions taken
            b_latency = []
            try:
                for sid in ("b1", "b2"):
                    t = time.perf_counter()
                    r = call(server, "post", "/reset", "B", sid)
                    b_latency.append(time.perf_counter() - t)
                    assert r.status_code == 200, r.text
                    for step in range(2):
                        t = time.perf_counter()
                        r = execute(server, "B", transaction=f"{sid}-{step}", session=sid)
                        b_latency.append(time.perf_counter() - t)
                        assert r.status_code == 200, r.text
            finally:
                stop.set()
        assert 429 in a_codes and 422 in a_codes and 500 not in a_codes  # A's flood did hit its own limits
        # B's renders take milliseconds; the bound leaves room for a loaded machine, where A's eight threads, the
        # server and B share one interpreter (a B that queued behind A's pile or its sessions would get 429 or wait
        # for A's renders instead)
        assert max(b_latency) < 2.5, b_latency
        assert open_sessions(server) <= 4


def _raw(server) -> socket.socket:
    url = urlparse(server.url)
    return socket.create_connection((url.hostname, url.port), timeout=5)


def _read_until_closed(sock: socket.socket, limit_s: float) -> tuple[bytes, float]:
    """Everything the server sends until it closes the connection, and how long that took."""
    start, data = time.monotonic(), b""
    sock.settimeout(limit_s)
    try:
        while chunk := sock.recv(4096):
            data += chunk
    except ConnectionResetError:
        pass
    return data, time.monotonic() - start


def test_a_slow_body_gets_408_within_the_deadline_and_its_connection_is_closed(tiny):
    with make_server(tiny, body_timeout_s=0.4) as server:
        with _raw(server) as sock:
            sock.sendall(b"POST /execute_action HTTP/1.1\r\nHost: x\r\nauth-token: A\r\nsession-id: slow\r\n"
                         b"Content-Type: application/json\r\nContent-Length: 200\r\n\r\n{\"plan_traj\"")
            reply, took = _read_until_closed(sock, 5.0)
        assert reply.startswith(b"HTTP/1.1 408") and b"did not arrive within 0.4 s" in reply
        assert 0.3 < took < 2.0
        assert open_sessions(server) == 0
        assert execute(server, "A").status_code == 200


def test_trickled_headers_and_idle_connections_are_closed_after_the_header_deadline(tiny):
    with make_server(tiny, header_timeout_s=0.4, keep_alive_s=30) as server:
        with _raw(server) as idle:
            assert _read_until_closed(idle, 5.0)[1] < 2.0
        with _raw(server) as sock:
            sock.sendall(b"GET /get_current_state HTTP/1.1\r\n")
            start = time.monotonic()
            with pytest.raises(OSError):  # broken pipe or reset once the server has closed it
                while time.monotonic() - start < 5.0:
                    sock.sendall(b"x")
                    time.sleep(0.05)
            assert time.monotonic() - start < 2.0
        # after a reply the deadline is armed again: the rest of a refused body, trickled, holds nothing either
        with _raw(server) as sock:
            sock.sendall(b"POST /execute_action HTTP/1.1\r\nHost: x\r\nauth-token: nope\r\nContent-Length: 100000"
                         b"\r\n\r\n{")
            reply, took = _read_until_closed(sock, 5.0)
            assert reply.startswith(b"HTTP/1.1 401") and took < 2.0
        assert execute(server, "A").status_code == 200


def test_a_transaction_id_reused_for_another_plan_is_409_not_the_stale_reply(tiny):
    with make_server(tiny) as server:
        first = execute(server, "A", transaction="same")
        again = execute(server, "A", transaction="same")
        other = execute(server, "A", plan_traj=_plan(data=[[0.0, 0.4 * k] for k in range(1, 7)]), transaction="same")
        assert first.status_code == again.status_code == 200 and first.content == again.content
        assert other.status_code == 409 and "another plan" in other.json()["detail"]
        assert execute(server, "A", transaction="next").status_code == 200


def test_the_render_lock_takes_turns_by_owner():
    lock, order = TurnLock(), []
    lock.acquire("held")

    def wait(owner: str, k: int) -> None:
        with lock.turn(owner):
            order.append(f"{owner}{k}")

    threads = []
    for owner, k in [("A", 1), ("A", 2), ("A", 3), ("A", 4), ("B", 1), ("C", 1), ("B", 2)]:
        threads.append(threading.Thread(target=wait, args=(owner, k)))
        threads[-1].start()
        while sum(len(q) for q in lock._waiting.values()) < len(threads):  # queued in this order
            time.sleep(0.001)
    lock.release()
    for t in threads:
        t.join(5)
    assert order == ["A1", "B1", "C1", "A2", "B2", "A3", "A4"]


@pytest.mark.parametrize("field, value", [
    ("max_sessions_per_token", 0), ("max_pending_per_token", -1), ("requests_per_s", 0.0),
    ("requests_per_s", float("nan")), ("request_burst", 0), ("body_timeout_s", float("inf")),
    ("header_timeout_s", -1.0), ("keep_alive_s", 0.0), ("max_sessions_per_token", 10 ** 9),
])
def test_server_config_refuses_limits_that_make_no_sense(field, value):
    with pytest.raises(ValidationError, match=field):
        ServerConfig(**{field: value})


def test_the_fair_share_of_sessions_and_requests_in_progress():
    assert ServerConfig().sessions_per_token(1) == 32 and ServerConfig().sessions_per_token(3) == 10
    assert ServerConfig(max_sessions=4).sessions_per_token(10) == 1  # at least one, even past max_sessions
    assert ServerConfig(max_sessions_per_token=5).sessions_per_token(2) == 5
    assert ServerConfig(max_sessions=4).pending_per_token(2) == 8
    assert ServerConfig(max_pending_per_token=3).pending_per_token(2) == 3
    np.testing.assert_array_equal(parse_plan(GOOD_PLAN_TRAJ), np.array(PLAN))
    ints = [[0, k] for k in range(1, 7)]
    np.testing.assert_array_equal(parse_plan(_plan(dtype="int8", data=ints)), np.array(ints, float))
    np.testing.assert_array_equal(parse_plan(_plan(dtype="float16", data=ints)), np.array(ints, float))
    np.testing.assert_array_equal(parse_plan(_plan(dtype="uint8", data=[[0.0, 2.0]], shape=[1, 2])), [[0.0, 2.0]])


def test_a_client_that_does_not_read_its_replies_is_dropped_after_the_reply_deadline(tiny):
    from omniscs.closedloop.simulator import ClosedLoopConfig, Simulator

    scene, graph, scenarios = tiny
    big = ClosedLoopConfig(width=640)  # replies of about 1.6 MB: more than the kernel's buffers take
    app = create_app(lambda: Simulator(graph, scene, big), scenarios, ["A"],
                     ServerConfig(reply_timeout_s=0.5, header_timeout_s=30, keep_alive_s=30))
    with start_in_thread(app) as server:
        url = urlparse(server.url)
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.connect((url.hostname, url.port))
        with sock:
            sock.sendall(b"GET /get_current_state HTTP/1.1\r\nHost: x\r\nauth-token: A\r\n\r\n" * 6)  # never read
            connections = server.server.server_state.connections
            start = time.monotonic()
            while not connections and time.monotonic() - start < 5:
                time.sleep(0.01)
            assert connections
            while connections and time.monotonic() - start < 10:
                time.sleep(0.05)
            assert not connections  # dropped, with the replies it held
            received, _ = _read_until_closed(sock, 5.0)
        length = int(received.split(b"content-length: ")[1].split(b"\r\n")[0])
        assert len(received) < 6 * length  # not every reply went out: the rest were dropped
        assert call(server, "get", "/get_current_state", "A").status_code == 200
