"""The factory as a service: ``generate_dataset`` deployed to a real ``prefect server`` (SQLite), run by a real
process worker in its own process, and catalogued in the workspace the worker was given; and the service files in
``infra/`` (no Docker or cluster here): the compose file wires Postgres, server, pool and workers on one workspace,
and the Kubernetes work pool's base job template declares every variable it uses and mounts the shared workspace."""
from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from omniscs import catalog
from omniscs.cli.prefect_api import die_with_parent

ROOT = Path(__file__).resolve().parents[2]
K8S_TEMPLATE = ROOT / "infra" / "k8s-base-job-template.json"
COMPOSE = ROOT / "infra" / "compose.yaml"
POOL = "omniscs-test-process"
DEPLOYMENT = "server-test"
#: The first start of a server creates and migrates its SQLite database.
SERVER_START_TIMEOUT_S = 120.0
#: Pick-up by the worker (it polls every second here) plus a flow-run process that imports torch and runs one
#: 4-frame 64x36 scene through ingest, plan and catalog.
RUN_TIMEOUT_S = 240.0
#: How long a child gets after SIGTERM before it is killed.
STOP_GRACE_S = 15.0


def _prefect_cli() -> list[str]:
    """The venv's Prefect command line (the one beside this interpreter, whatever PATH says)."""
    return [sys.executable, "-m", "prefect"]


def _child_env(prefect_home: Path, **extra: str) -> dict[str, str]:
    """The environment of a child: this one, without the test session's Prefect home or API, plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_HOME", "PREFECT_PROFILE")}
    env.update(PREFECT_HOME=str(prefect_home), PREFECT_SERVER_ANALYTICS_ENABLED="false",
               OMP_WAIT_POLICY="PASSIVE", **extra)
    return env


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _tail(log: Path, n_chars: int = 3_000) -> str:
    return log.read_text(errors="replace")[-n_chars:] if log.exists() else "(no output)"


class _Child:
    """A long-running child process in a process group of its own. Stopping it stops the group and every process
    it started, also those that left the group (Prefect runs each flow run in a session of its own), so that
    nothing is left behind; if the test run itself is killed, the child gets SIGTERM from the kernel."""

    def __init__(self, args: list[str], env: dict[str, str], log: Path, cwd: Path = ROOT):
        self.log = log
        self._out = log.open("wb")
        # stop() runs from the fixtures' finalisers; the parent-death signal covers a test run killed outright
        self.proc = subprocess.Popen(args, env=env, cwd=cwd, stdout=self._out, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, start_new_session=True,
                                     preexec_fn=die_with_parent(os.getpid()))

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> None:
        """SIGTERM to the group and the descendants, SIGKILL to whatever is left after a grace period."""
        started = _descendants(self.proc.pid)  # {pid: start time}, before the leader exits and they are reparented
        for sig in (signal.SIGTERM, signal.SIGKILL):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, sig)  # start_new_session: the child leads its own group
            for pid, start in started.items():
                if _start_time(pid) == start:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, sig)
            deadline = time.monotonic() + STOP_GRACE_S
            while time.monotonic() < deadline and (self.alive() or _group_alive(self.proc.pid)
                                                   or any(_start_time(p) == t for p, t in started.items())):
                time.sleep(0.2)
            if not self.alive() and not _group_alive(self.proc.pid) and not any(
                    _start_time(p) == t for p, t in started.items()):
                break
        self.proc.wait()
        self._out.close()


def _start_time(pid: int) -> int | None:
    """When a process started (clock ticks since boot), to tell it from a later one with the same id; None once
    it is gone or a zombie."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return None if fields[0] == "Z" else int(fields[19])


def _descendants(root: int) -> dict[int, int]:
    """Every live descendant of ``root`` with its start time (from /proc; empty where there is none)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(stat.parent.name))
    found, todo = {}, list(children.get(root, []))
    while todo:
        pid = todo.pop()
        start = _start_time(pid)
        if start is not None:
            found[pid] = start
        todo.extend(children.get(pid, []))
    return found


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _wait_healthy(server: _Child, url: str) -> None:
    """Polls ``/api/health`` until the server answers; skips if the server process could not start at all."""
    deadline = time.monotonic() + SERVER_START_TIMEOUT_S
    while time.monotonic() < deadline:
        if not server.alive():
            pytest.skip(f"`prefect server start` exited with {server.proc.returncode} before answering "
                        f"(binary failed or port not bound):\n{_tail(server.log)}")
        try:
            with urllib.request.urlopen(f"{url}/health", timeout=2) as answer:
                if answer.status == 200:
                    return
        except (urllib.error.URLError, ConnectionError, TimeoutError, OSError):
            pass
        time.sleep(0.5)
    pytest.fail(f"the Prefect server did not answer {url}/health in {SERVER_START_TIMEOUT_S:.0f} s:\n"
                f"{_tail(server.log)}")


@pytest.fixture
def prefect_server(tmp_path):
    """A ``prefect server start`` on a free loopback port with its own SQLite home; yields its API URL."""
    try:
        port = _free_port()
    except OSError as exc:
        pytest.skip(f"cannot bind a loopback port for the Prefect server: {exc}")
    home = tmp_path / "server-home"
    home.mkdir()
    server = _Child([*_prefect_cli(), "server", "start", "--host", "127.0.0.1", "--port", str(port)],
                    _child_env(home, PREFECT_UI_ENABLED="false"), tmp_path / "server.log")
    api_url = f"http://127.0.0.1:{port}/api"
    try:
        _wait_healthy(server, api_url)
        yield api_url
    finally:
        server.stop()


@pytest.fixture
def process_worker(prefect_server, tmp_path):
    """A process work pool on the server, and ``prefect worker start`` for it (cwd: the repository, its own
    Prefect home, ``OMNISCS_HOME`` a workspace under ``tmp_path``); yields (pool name, workspace, worker)."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.actions import WorkPoolCreate
    from prefect.settings import PREFECT_API_URL, temporary_settings
    from prefect.workers.process import ProcessWorker

    workspace = tmp_path / "workspace"
    with temporary_settings(updates={PREFECT_API_URL: prefect_server}), get_client(sync_client=True) as client:
        # what `prefect work-pool create POOL --type process` does, without starting another interpreter
        client.create_work_pool(WorkPoolCreate(name=POOL, type="process",
                                               base_job_template=ProcessWorker.get_default_base_job_template()))
    home = tmp_path / "worker-home"
    home.mkdir()
    worker = _Child([*_prefect_cli(), "worker", "start", "--pool", POOL, "--type", "process"],
                    _child_env(home, PREFECT_API_URL=prefect_server, OMNISCS_HOME=str(workspace),
                               PREFECT_WORKER_QUERY_SECONDS="1", PREFECT_WORKER_PREFETCH_SECONDS="5"),
                    tmp_path / "worker.log")
    try:
        yield POOL, workspace, worker
    finally:
        worker.stop()


@pytest.mark.slow
def test_a_deployment_run_by_a_process_worker_on_a_real_server_completes_and_catalogues_its_scene(
        prefect_server, process_worker):
    from prefect.deployments import run_deployment
    from prefect.flows import Flow
    from prefect.settings import PREFECT_API_URL, temporary_settings

    pool, workspace, worker = process_worker
    parameters = {"request": {"sources": ["syn:straight:7"], "n_frames": 4, "n_cameras": 1, "width": 64,
                              "height": 36, "previews": False, "workspace": str(workspace)}}
    with temporary_settings(updates={PREFECT_API_URL: prefect_server}):
        # code from the local checkout: the deployment's pull step sets the worker's flow-run process's working
        # directory to ROOT, and the entrypoint is loaded from there, as a worker on a machine with the checkout
        flow = Flow.from_source(source=str(ROOT), entrypoint="flows/generate.py:generate_dataset")
        flow.deploy(name=DEPLOYMENT, work_pool_name=pool, print_next_steps=False, ignore_warnings=True)
        flow_run = run_deployment(name=f"{flow.name}/{DEPLOYMENT}", parameters=parameters, timeout=RUN_TIMEOUT_S,
                                  poll_interval=1)
    assert worker.alive(), f"the worker died:\n{_tail(worker.log)}"
    state = flow_run.state
    assert state is not None and state.is_completed(), (
        f"flow run ended {state.name if state else 'without a state'}: {state.message if state else ''}\n"
        f"worker log:\n{_tail(worker.log)}")
    root = catalog.catalog_root(workspace)
    runs = catalog.query(root, "SELECT run_id, status, flow_run_id, n_scenes FROM runs").to_pylist()
    assert len(runs) == 1
    assert runs[0]["status"] == "completed" and runs[0]["n_scenes"] == 1
    assert runs[0]["flow_run_id"] == str(flow_run.id)  # the row is this deployment run's, written by the worker
    scenes = catalog.query(root, "SELECT scene_id, template, seed, n_frames, run_id FROM scenes").to_pylist()
    assert len(scenes) == 1
    assert (scenes[0]["template"], scenes[0]["seed"], scenes[0]["n_frames"]) == ("straight", 7, 4)
    assert scenes[0]["run_id"] == runs[0]["run_id"]


# -- the Kubernetes work pool's base job template (no server) ---------------------------------------------------

def _k8s_template() -> dict:
    return json.loads(K8S_TEMPLATE.read_text())


def _rendered_k8s_job(values: dict) -> dict:
    """The Job manifest a worker would start: the template's variable defaults, overridden by ``values``,
    applied to its placeholders (Prefect's own templating)."""
    from prefect.utilities.templating import apply_values

    template = _k8s_template()
    defaults = {k: v["default"] for k, v in template["variables"]["properties"].items() if "default" in v}
    return apply_values(template["job_configuration"]["job_manifest"], defaults | values)


def test_every_placeholder_of_the_k8s_job_configuration_is_a_declared_variable():
    from prefect.server.schemas.actions import validate_base_job_template
    from prefect.utilities.templating import find_placeholders

    template = _k8s_template()
    assert set(template) == {"job_configuration", "variables"}
    job = template["job_configuration"]
    for key in ("command", "env", "labels", "name", "namespace", "job_manifest", "cluster_config",
                "job_watch_timeout_seconds", "pod_watch_timeout_seconds", "stream_output"):
        assert key in job, f"job_configuration lacks {key}"
    used = {p.name for p in find_placeholders(job)}
    declared = set(template["variables"]["properties"])
    assert used <= declared, f"used but not declared: {sorted(used - declared)}"
    assert {"image", "command", "env", "namespace", "workspace_pvc", "workspace_path", "cpu_request",
            "cpu_limit", "memory_request", "memory_limit"} <= used
    validate_base_job_template(template)  # what the server checks when the pool is created


def test_the_k8s_job_runs_the_image_and_command_and_mounts_the_workspace_pvc_at_omniscs_home():
    manifest = _k8s_template()["job_configuration"]["job_manifest"]
    assert (manifest["apiVersion"], manifest["kind"]) == ("batch/v1", "Job")
    container = manifest["spec"]["template"]["spec"]["containers"][0]
    assert (container["image"], container["args"]) == ("{{ image }}", "{{ command }}")

    job = _rendered_k8s_job({"image": "registry.example/omniscs-worker:1", "command": "python -m prefect.engine",
                             "name": "gen", "workspace_pvc": "factory-data", "workspace_path": "/mnt/omniscs",
                             "memory_limit": "24Gi"})
    pod = job["spec"]["template"]["spec"]
    container = pod["containers"][0]
    assert container["image"] == "registry.example/omniscs-worker:1"
    assert container["args"] == "python -m prefect.engine"
    assert container["resources"] == {"requests": {"cpu": "2", "memory": "8Gi"},
                                      "limits": {"cpu": "4", "memory": "24Gi"}}
    claims = {v["name"]: v["persistentVolumeClaim"]["claimName"] for v in pod["volumes"]}
    mounts = {m["name"]: m["mountPath"] for m in container["volumeMounts"]}
    assert [mounts[name] for name, claim in claims.items() if claim == "factory-data"] == ["/mnt/omniscs"]
    env = {e["name"]: e["value"] for e in container["env"]}
    assert env["OMNISCS_HOME"] == "/mnt/omniscs"
    assert "serviceAccountName" not in pod and "nodeSelector" not in pod  # unset variables leave no key


# -- the one-box service (no Docker) -------------------------------------------------------------------------------

def test_compose_runs_the_server_on_postgres_and_workers_of_the_deployments_pool_on_one_workspace():
    import yaml

    from flows.deployments import WORK_POOL

    services = yaml.safe_load(COMPOSE.read_text())["services"]
    postgres, server, pool, worker = (services[k] for k in ("postgres", "prefect-server", "create-pool", "worker"))
    assert postgres["image"].startswith("postgres:16") and "healthcheck" in postgres
    db_url = server["environment"]["PREFECT_API_DATABASE_CONNECTION_URL"]
    assert db_url.startswith("postgresql+asyncpg://") and "@postgres:5432/" in db_url
    assert server["depends_on"]["postgres"]["condition"] == "service_healthy"
    assert "/api/health" in " ".join(server["healthcheck"]["test"])
    assert pool["depends_on"]["prefect-server"]["condition"] == "service_healthy"
    assert f"work-pool create {WORK_POOL} --type process" in " ".join(pool["command"])
    assert worker["depends_on"]["create-pool"]["condition"] == "service_completed_successfully"
    assert worker["command"][worker["command"].index("--pool") + 1] == WORK_POOL
    assert "replicas" in worker["deploy"]
    for client in (pool, worker):
        assert client["environment"]["PREFECT_API_URL"] == "http://prefect-server:4200/api"
    assert worker["environment"]["OMNISCS_HOME"] == "/data"
    assert [v.split(":")[1] for v in worker["volumes"]] == ["/data"]


def test_a_server_child_dies_with_a_test_run_that_is_killed_outright():
    # What _Child relies on when no finaliser runs: the kernel's parent-death signal reaches the child.
    code = ("import os, subprocess, sys, time; from omniscs.cli.prefect_api import die_with_parent; "
            "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'], "
            "preexec_fn=die_with_parent(os.getpid())); print(p.pid, flush=True); time.sleep(60)")
    parent = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    child = int(parent.stdout.readline())
    assert _start_time(child) is not None
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and _start_time(child) is not None:
        time.sleep(0.1)
    assert _start_time(child) is None

