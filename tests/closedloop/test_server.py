"""The HUGSIM-protocol server driven by HUGSIM's own client over loopback: episodes run as the client expects, a
transaction executes once, bad tokens, plans and bodies are refused without moving anything, sessions stay apart."""
from __future__ import annotations

import json
import pickle
import time

import numpy as np
import pytest
import requests

from annotate_fixtures import logged_variant
from omniscs.closedloop.scenario import variant_scenario
from omniscs.closedloop.simulator import ClosedLoopConfig, Simulator
from omniscs.errors import ValidationError
from omniscs.server.hugsim import ServerConfig, create_app
from omniscs.server.transport import start_in_thread

CAMERA = "CAM_FRONT"
RENDER = ClosedLoopConfig(cameras=(CAMERA,), width=64)
HUGSIM_INFO_KEYS = {"ego_pos", "ego_rot", "ego_velo", "ego_steer", "accelerate", "steer_rate", "timestamp", "command",
                    "ego_box", "obj_boxes", "cam_params", "collision", "rc"}
#: Every test drives its own session: one token each (the module's server accepts all of them).
TOKENS = tuple(f"token-{i:02d}" for i in range(48))
_unused_tokens = iter(TOKENS)
BODY_LIMIT = 16 * 1024


@pytest.fixture(scope="module")
def served(world):
    """(scene, graph, scenarios): the shared fitted log (``conftest.world``) and a behaviour variant of it."""
    scene, graph, log = world
    variant = variant_scenario(scene, logged_variant(scene), log)
    return scene, graph, {log.scenario_id: log, variant.scenario_id: variant}


def make_server(served, tokens=TOKENS, **config):
    scene, graph, scenarios = served
    app = create_app(lambda: Simulator(graph, scene, RENDER), scenarios, tokens, ServerConfig(**config))
    return start_in_thread(app)


@pytest.fixture(scope="module")
def server(served):
    with make_server(served, max_body_bytes=BODY_LIMIT, max_sessions=64, max_sessions_per_token=4) as handle:
        yield handle


@pytest.fixture
def token():
    return next(_unused_tokens)


@pytest.fixture
def client(server, token, monkeypatch):
    monkeypatch.setenv("IN_HF_SPACE", "false")  # else the client starts a web server of its own on port 7860
    from hugsim_client import HugsimClient

    return HugsimClient(host=server.url, api_token=token)


def straight(speed: float) -> np.ndarray:  # [6, 2] planning frame: straight ahead at ``speed`` m/s
    return np.array([[0.0, speed * 0.5 * k] for k in range(1, 7)], np.float32)


def encoded(plan: np.ndarray) -> str:
    """A plan as HUGSIM's client encodes it."""
    return json.dumps({"data": plan.tolist(), "shape": list(plan.shape), "dtype": str(plan.dtype)})


def post_plan(server, token, plan_traj: str, transaction_id: str = "t-1", session: str | None = None):
    headers = {"auth-token": token} | ({"session-id": session} if session else {})
    return requests.post(f"{server.url}/execute_action", headers=headers,
                         json={"plan_traj": plan_traj, "transaction_id": transaction_id}, timeout=30)


def state_of(server, token, session: str | None = None) -> dict:
    headers = {"auth-token": token} | ({"session-id": session} if session else {})
    r = requests.get(f"{server.url}/get_current_state", headers=headers, timeout=30)
    assert r.status_code == 200, r.text
    return pickle.loads(r.content)


def test_the_client_gets_the_rendered_camera_and_hugsims_info_keys_after_reset(client, served):
    client.reset_env()
    state = client.get_current_state()
    obs, info = state.state.obs, state.state.info
    assert not state.done and not state.cur_scene_done
    assert obs["rgb"][CAMERA].shape == (36, 64, 3) and obs["rgb"][CAMERA].dtype == np.uint8
    assert obs["depth"][CAMERA].shape == (36, 64) and obs["depth"][CAMERA].dtype == np.float32
    assert obs["semantic"][CAMERA].shape == (36, 64) and obs["semantic"][CAMERA].dtype == np.uint8
    assert obs["instance"][CAMERA].shape == (36, 64)
    assert obs["rgb"][CAMERA].std() > 0, "a blank image: nothing was rendered"
    assert HUGSIM_INFO_KEYS <= set(info)
    assert info["timestamp"] == 0.0 and info["scenario_id"] == next(iter(served[2]))


def test_a_straight_plan_through_the_client_advances_the_clock_and_moves_the_ego_ahead(client):
    client.reset_env()
    before = client.get_current_state().state.info
    after = client.execute_action(straight(before["ego_velo"])).state.info
    assert after["timestamp"] == pytest.approx(0.1) and after["step"] == 1
    heading = np.array([np.cos(before["ego_yaw"]), np.sin(before["ego_yaw"])])
    moved = np.subtract(after["ego_xyz"][:2], before["ego_xyz"][:2])
    assert moved @ heading == pytest.approx(before["ego_velo"] * 0.1, rel=0.3)


def test_driving_to_each_scenarios_end_reports_it_then_the_queue_moves_on_and_ends_done(client, served):
    first, second = served[2]
    client.reset_env()
    state = client.get_current_state()
    ended = []
    for _ in range(100):
        state = client.execute_action(straight(state.state.info["ego_velo"]))
        if state.cur_scene_done:
            ended.append((state.state.info["scenario_id"], state.done, state.state.info["reason"]))
            if state.done:
                break
            state = client.execute_action(straight(0.0))  # starts the next scenario: nothing is driven
            assert not state.cur_scene_done and state.state.info["step"] == 0
            assert state.state.info["scenario_id"] == second
    assert [(sid, done) for sid, done, _ in ended] == [(first, False), (second, True)]
    assert all(reason in ("route_completed", "scenario_end") for *_, reason in ended)
    assert "pdms" in state.state.info["scores"]
    again = client.execute_action(straight(0.0))  # nothing left: the final state again
    assert again.done and again.state.info["step"] == state.state.info["step"]


def test_an_episode_capped_by_max_steps_ends_done_and_writes_its_run_folder(served, tmp_path):
    variant_id = list(served[2])[1]
    with make_server(served, tokens=("tok",), max_steps_per_episode=3, out_dir=tmp_path) as server:
        r = requests.post(f"{server.url}/reset", headers={"auth-token": "tok"}, json={"scenario": variant_id})
        assert r.json() == {"success": True, "scenario": variant_id}
        replies = [pickle.loads(post_plan(server, "tok", encoded(straight(5.0)), f"t{k}").content) for k in range(3)]
    assert [(p["cur_scene_done"], p["done"]) for p in replies] == [(False, False), (False, False), (True, True)]
    assert replies[-1]["state"]["info"]["reason"] == "max_steps"
    folders = list(tmp_path.iterdir())
    assert len(folders) == 1 and variant_id.replace("/", "__") in folders[0].name
    run = json.loads((folders[0] / "run.json").read_text())
    assert run["steps"] == 3 and run["reason"] == "max_steps" and run["scenario_id"] == variant_id
    replay = json.loads((folders[0] / "replay.json").read_text())  # what omniscs view replays: every step's frame
    assert len(replay["agents"]) == 4 and all((folders[0] / f).is_file() for f in replay["frames"])


def test_the_same_transaction_id_twice_executes_once(server, token):
    first = post_plan(server, token, encoded(straight(5.0)), "fixed-id")
    second = post_plan(server, token, encoded(straight(5.0)), "fixed-id")
    assert first.status_code == second.status_code == 200
    assert first.content == second.content
    assert state_of(server, token)["state"]["info"]["step"] == 1
    post_plan(server, token, encoded(straight(5.0)), "another-id")
    assert state_of(server, token)["state"]["info"]["step"] == 2


@pytest.mark.parametrize("headers", [{}, {"auth-token": "not-a-token"}, {"auth-token": ""}])
def test_a_missing_or_wrong_token_is_refused_and_the_server_keeps_serving(server, token, headers):
    for method, path in (("post", "/reset"), ("get", "/get_current_state"), ("post", "/execute_action")):
        r = requests.request(method, server.url + path, headers=headers, timeout=30)
        assert r.status_code == 401 and "auth-token" in r.json()["detail"]
    assert state_of(server, token)["state"]["info"]["step"] == 0


def test_a_nan_plan_is_refused_and_the_episode_does_not_move(server, token):
    plan = straight(5.0)
    plan[3, 1] = np.nan
    r = post_plan(server, token, encoded(plan))
    assert r.status_code == 422 and "NaN" in r.json()["detail"]
    info = state_of(server, token)["state"]["info"]
    assert info["step"] == 0 and info["timestamp"] == 0.0


def test_a_plan_reaching_10_km_away_is_refused(server, token):
    plan = straight(5.0)
    plan[-1] = [0.0, 10_000.0]
    r = post_plan(server, token, encoded(plan))
    assert r.status_code == 422 and "m from the ego" in r.json()["detail"]
    assert state_of(server, token)["state"]["info"]["step"] == 0


@pytest.mark.parametrize("plan_traj", [
    "not json",
    json.dumps([[0, 1], [0, 2]]),                                             # no data/shape/dtype envelope
    json.dumps({"data": [[0, 1], [0, 2]], "shape": [2, 2], "dtype": "object"}),
    json.dumps({"data": [[0, 1], [0, 2]], "shape": [2, 2], "dtype": "not-a-type"}),
    json.dumps({"data": [["0", "1"], ["0", "2"]], "shape": [2, 2], "dtype": "float32"}),
    json.dumps({"data": [[0, 1], [0, 2]], "shape": [3, 2], "dtype": "float32"}),  # shape says more than data holds
    json.dumps({"data": [0.0] * 1002, "shape": [501, 2], "dtype": "float64"}),  # over 1000 numbers
    json.dumps({"data": [[0, 1], [0]], "shape": [2, 2], "dtype": "float32"}),   # ragged
])
def test_a_malformed_plan_is_422_and_moves_nothing(server, token, plan_traj):
    r = post_plan(server, token, plan_traj)
    assert r.status_code == 422 and r.json()["detail"]
    assert state_of(server, token)["state"]["info"]["step"] == 0


def test_a_pickled_body_is_refused_not_unpickled(server, token):
    body = pickle.dumps({"plan_traj": straight(5.0), "transaction_id": "p"})
    r = requests.post(f"{server.url}/execute_action", headers={"auth-token": token}, data=body, timeout=30)
    assert r.status_code == 422
    assert state_of(server, token)["state"]["info"]["step"] == 0


def test_an_unknown_scenario_is_404_and_a_named_one_is_driven_alone(server, token, served):
    headers = {"auth-token": token}
    r = requests.post(f"{server.url}/reset", headers=headers, json={"scenario": "nowhere/log"}, timeout=30)
    assert r.status_code == 404 and "nowhere/log" in r.json()["detail"]
    chosen = list(served[2])[1]
    r = requests.post(f"{server.url}/reset", headers=headers, json={"scenario": chosen}, timeout=30)
    assert r.json() == {"success": True, "scenario": chosen}
    assert state_of(server, token)["state"]["info"]["scenario_id"] == chosen


def test_a_body_over_the_limit_is_413_whether_declared_or_streamed(server, token):
    headers = {"auth-token": token}
    r = requests.post(f"{server.url}/execute_action", headers=headers, data=b"x" * (BODY_LIMIT + 1), timeout=30)
    assert r.status_code == 413 and "limit" in r.json()["detail"]
    chunked = (b"x" * 4096 for _ in range(BODY_LIMIT // 4096 + 2))  # no Content-Length: only reading shows it
    r = requests.post(f"{server.url}/execute_action", headers=headers, data=chunked, timeout=30)
    assert r.status_code == 413
    assert post_plan(server, token, encoded(straight(5.0))).status_code == 200


def test_two_session_ids_under_one_token_are_independent(server, token):
    assert post_plan(server, token, encoded(straight(5.0)), session="left").status_code == 200
    assert state_of(server, token, "left")["state"]["info"]["timestamp"] == pytest.approx(0.1)
    assert state_of(server, token, "right")["state"]["info"]["timestamp"] == 0.0
    r = requests.get(f"{server.url}/get_current_state", headers={"auth-token": token, "session-id": "bad id!"})
    assert r.status_code == 400


def test_the_status_page_needs_no_token_and_shows_no_secret(server, served):
    r = requests.get(server.url + "/", timeout=30)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert all(sid in r.text for sid in served[2])
    assert "sessions open" in r.text
    assert not any(t in r.text for t in TOKENS)


def test_sessions_beyond_the_limit_get_429_until_one_goes_idle(served):
    with make_server(served, tokens=("a", "b"), max_sessions=1, session_idle_s=0.3) as server:
        assert requests.get(f"{server.url}/get_current_state", headers={"auth-token": "a"}).status_code == 200
        r = requests.get(f"{server.url}/get_current_state", headers={"auth-token": "b"})
        assert r.status_code == 429 and "sessions" in r.json()["detail"]
        time.sleep(0.5)
        assert requests.get(f"{server.url}/get_current_state", headers={"auth-token": "b"}).status_code == 200


def test_create_app_refuses_a_server_nobody_could_use(served):
    scene, graph, scenarios = served

    def make():
        return Simulator(graph, scene, RENDER)

    with pytest.raises(ValidationError, match="token"):
        create_app(make, scenarios, [])
    with pytest.raises(ValidationError, match="token"):
        create_app(make, scenarios, "secret")  # a string is not a collection of tokens
    with pytest.raises(ValidationError, match="default scenario"):
        create_app(make, scenarios, ["t"], ServerConfig(default_scenario="nowhere/log"))
    with pytest.raises(ValidationError, match="at least one scenario"):
        create_app(make, {}, ["t"])


def test_a_client_that_disconnects_mid_request_leaves_the_server_serving_everyone(server, token):
    import socket
    from urllib.parse import urlparse

    url = urlparse(server.url)
    other = next(_unused_tokens)
    post_plan(server, other, encoded(straight(5.0)), "before")
    body = json.dumps({"plan_traj": encoded(straight(5.0)), "transaction_id": "cut"}).encode()
    with socket.create_connection((url.hostname, url.port), timeout=10) as sock:  # half a request, then gone
        sock.sendall(b"POST /execute_action HTTP/1.1\r\nHost: x\r\nauth-token: " + token.encode()
                     + b"\r\nContent-Type: application/json\r\nContent-Length: " + str(len(body)).encode()
                     + b"\r\n\r\n" + body[: len(body) // 2])
    time.sleep(0.2)
    assert state_of(server, token)["state"]["info"]["step"] == 0  # the cut request moved nothing
    assert post_plan(server, token, encoded(straight(5.0)), "after").status_code == 200
    assert state_of(server, token)["state"]["info"]["step"] == 1
    assert post_plan(server, other, encoded(straight(5.0)), "after").status_code == 200
    assert state_of(server, other)["state"]["info"]["step"] == 2
