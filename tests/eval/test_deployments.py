"""Deployments: the Python registry and infra/prefect.yaml say the same; the nightly generation is a cron schedule;
a completed generation run creates a run of the fine-tune + evaluate deployment with the run passed along (the
trigger wiring, on the test harness's server, which runs event triggers)."""
from __future__ import annotations

import time
import uuid
from pathlib import Path

import pytest
import yaml

from flows import deployments as reg

ROOT = Path(__file__).resolve().parents[2]


def _yaml() -> dict:
    return {d["name"]: d for d in yaml.safe_load((ROOT / "infra" / "prefect.yaml").read_text())["deployments"]}


def _labels(spec) -> dict:
    """A match_related spec (YAML mapping or Prefect's model) as {label: [values]}."""
    if hasattr(spec, "model_dump"):
        spec = spec.model_dump()
    if isinstance(spec, dict) and set(spec) == {"root"}:
        spec = spec["root"]
    if isinstance(spec, list):
        spec = {k: v for part in spec for k, v in part.items()}
    return {k: v if isinstance(v, list) else [v] for k, v in spec.items()}


def test_the_yaml_and_the_registry_agree_on_schedule_parameters_and_trigger():
    y = _yaml()
    nightly = y[reg.GENERATE_NIGHTLY]
    assert nightly["schedules"][0]["cron"] == reg.NIGHTLY_CRON
    assert nightly["parameters"] == reg.NIGHTLY_PARAMETERS
    trig = y[reg.FINETUNE_ON_GENERATION]["triggers"][0]
    ours = reg.generation_completed_trigger()
    assert set(trig["expect"]) == set(ours.expect)
    assert _labels(trig["match_related"]) == _labels(ours.match_related)
    assert trig["parameters"] == ours.parameters
    assert y[reg.FINETUNE_ON_GENERATION]["entrypoint"] == "flows/downstream.py:finetune_evaluate"
    built = {d.name: d for d in reg.deployments()}
    assert set(built) == set(y)
    assert built[reg.GENERATE_NIGHTLY].schedules[0].schedule.cron == reg.NIGHTLY_CRON
    pooled = {d.name: d for d in reg.deployments(work_pool=True)}
    for name, d in y.items():  # every run sends heartbeats at the rate the zombie automation expects
        assert d["work_pool"]["job_variables"]["env"]["PREFECT_FLOWS_HEARTBEAT_FREQUENCY"] == str(reg.HEARTBEAT_SECONDS)
        assert pooled[name].job_variables["env"]["PREFECT_FLOWS_HEARTBEAT_FREQUENCY"] == str(reg.HEARTBEAT_SECONDS)


def test_a_completed_generation_run_creates_a_fine_tune_run_with_it(prefect_harness):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import DeploymentFilter, DeploymentFilterId
    from prefect.events import emit_event

    built = {d.name: d for d in reg.deployments()}
    upstream_id = built[reg.GENERATE_NIGHTLY].apply()
    downstream_id = built[reg.FINETUNE_ON_GENERATION].apply()
    time.sleep(2)  # the trigger's automation is loaded by the server's triggers service
    flow_run = uuid.uuid4()
    emit_event(event="prefect.flow-run.Completed", resource={"prefect.resource.id": f"prefect.flow-run.{flow_run}"},
               related=[{"prefect.resource.id": f"prefect.deployment.{upstream_id}",
                         "prefect.resource.role": "deployment", "prefect.resource.name": reg.GENERATE_NIGHTLY}])
    runs = []
    with get_client(sync_client=True) as client:
        deadline = time.time() + 90
        while time.time() < deadline and not runs:
            runs = client.read_flow_runs(deployment_filter=DeploymentFilter(id=DeploymentFilterId(any_=[downstream_id])))
            time.sleep(1)
    assert runs, "no fine-tune run was created by the completed generation run"
    assert runs[0].parameters["upstream_flow_run"] == f"prefect.flow-run.{flow_run}"
    assert runs[0].parameters["model"] == "proxy"


@pytest.mark.slow
def test_a_run_whose_heartbeats_stop_is_marked_crashed_and_one_that_finishes_is_not(prefect_harness):
    """The zombie automation on the harness's server (its proactive triggers run every few seconds), with a 10 s
    window instead of 3 minutes: a Running flow run that sent one heartbeat and then nothing becomes Crashed; one
    that sent a heartbeat and then its Completed event stays as it is. Creating it twice keeps one automation."""
    from datetime import timedelta

    from prefect import flow
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.objects import StateType
    from prefect.events import emit_event
    from prefect.states import Running

    @flow(name="zombie-probe")
    def probe():
        return None

    name = f"zombie-test-{uuid.uuid4().hex[:8]}"
    made = reg.ensure_zombie_automation(reg.zombie_automation(timedelta(seconds=10), name=name))
    again = reg.ensure_zombie_automation(reg.zombie_automation(timedelta(seconds=10), name=name))
    assert made.id == again.id
    time.sleep(2)  # the server's triggers service loads the automation
    with get_client(sync_client=True) as client:
        dead, done = (client.create_flow_run(probe, state=Running()) for _ in range(2))
        for run in (dead, done):
            emit_event(event="prefect.flow-run.heartbeat",
                       resource={"prefect.resource.id": f"prefect.flow-run.{run.id}"})
        time.sleep(2)  # a run's terminal event comes after its last heartbeat
        emit_event(event="prefect.flow-run.Completed", resource={"prefect.resource.id": f"prefect.flow-run.{done.id}"})
        deadline = time.time() + 90
        state = None
        while time.time() < deadline:
            state = client.read_flow_run(dead.id).state
            if state.type == StateType.CRASHED:
                break
            time.sleep(1)
        assert state is not None and state.type == StateType.CRASHED, state
        assert "heartbeat" in (state.message or "")
        assert client.read_flow_run(done.id).state.type == StateType.RUNNING
