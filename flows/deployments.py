"""The factory's deployments in Python, the same as ``infra/prefect.yaml`` (a test keeps the two equal): nightly
generation on a cron schedule, and fine-tune + evaluate started by the completion of a generation run, the
run's datasets found from its flow run id (the trigger passes the ``prefect.flow-run.Completed`` event's
resource). Register them against a server with ``python -m flows.deployments`` (or ``prefect deploy`` with the
YAML), then start a worker for the pool.

A run whose machine dies (killed, evicted, powered off) would stay ``Running`` for ever. Deployment runs send a
heartbeat event every ``HEARTBEAT_SECONDS`` (the work pool's ``PREFECT_FLOWS_HEARTBEAT_FREQUENCY``), and the
automation ``zombie_automation`` (created by ``python -m flows.deployments``; ``prefect deploy`` cannot declare it)
marks a run ``Crashed`` when ``ZOMBIE_AFTER_HEARTBEATS`` heartbeats in a row are missing, as Prefect's guide to
zombie flow runs does. Runs started outside a worker (``python -m flows...``, the benchmarks) send none."""
from __future__ import annotations

from datetime import timedelta

from prefect.automations import Automation
from prefect.client.schemas.objects import StateType
from prefect.deployments.runner import EntrypointType
from prefect.events import DeploymentEventTrigger
from prefect.events.actions import ChangeFlowRunState
from prefect.events.schemas.automations import EventTrigger, Posture
from prefect.events.schemas.events import ResourceSpecification

from flows.downstream import finetune_evaluate
from flows.generate import generate_dataset
from omniscs.pipeline.request import RunRequest

WORK_POOL = "omniscs-process"
GENERATE_NIGHTLY = "generate-nightly"
NIGHTLY_CRON = "0 2 * * *"
#: The nightly run's request (a ``RunRequest``'s fields; the rest keep their defaults).
NIGHTLY_REQUEST = RunRequest(sources=["syn:straight:0", "syn:t_junction:1:dusk", "syn:intersection:2:night"],
                             n_frames=40, n_cameras=3, fit_preset="fast", behavior_variants=2, behavior_preset="fast",
                             annotate=True)
NIGHTLY_PARAMETERS = {"request": NIGHTLY_REQUEST.model_dump(mode="json", exclude_unset=True)}
FINETUNE_ON_GENERATION = "finetune-evaluate-on-generation"
MODULE = EntrypointType.MODULE_PATH
HEARTBEAT_SECONDS = 60
JOB_VARIABLES = {"env": {"PREFECT_FLOWS_HEARTBEAT_FREQUENCY": str(HEARTBEAT_SECONDS)}}
ZOMBIE_AFTER_HEARTBEATS = 3
ZOMBIE_AUTOMATION = "omniscs-crash-zombie-runs"
TERMINAL_EVENTS = ("prefect.flow-run.Completed", "prefect.flow-run.Failed", "prefect.flow-run.Cancelled",
                   "prefect.flow-run.Crashed")


def generation_completed_trigger(upstream: str = GENERATE_NIGHTLY) -> DeploymentEventTrigger:
    """Fires once per completed run of the ``upstream`` generation deployment; passes the run to the flow."""
    return DeploymentEventTrigger(expect={"prefect.flow-run.Completed"},
                                  match_related={"prefect.resource.role": "deployment",
                                                 "prefect.resource.name": upstream},
                                  parameters={"upstream_flow_run": "{{ event.resource.id }}", "model": "proxy"})


def zombie_automation(after: timedelta = timedelta(seconds=ZOMBIE_AFTER_HEARTBEATS * HEARTBEAT_SECONDS),
                      name: str = ZOMBIE_AUTOMATION) -> Automation:
    """Marks a flow run ``Crashed`` when, ``after`` its last heartbeat, neither another heartbeat nor a terminal
    state's event has come (a proactive trigger, one bucket per flow run)."""
    return Automation(
        name=name, description="Flow runs that stopped sending heartbeats (their machine died) are marked Crashed.",
        trigger=EventTrigger(after={"prefect.flow-run.heartbeat"},
                             expect={"prefect.flow-run.heartbeat", *TERMINAL_EVENTS},
                             match=ResourceSpecification({"prefect.resource.id": ["prefect.flow-run.*"]}),
                             for_each={"prefect.resource.id"}, posture=Posture.Proactive, threshold=1, within=after),
        actions=[ChangeFlowRunState(state=StateType.CRASHED,
                                    message=f"No heartbeat for {after.total_seconds():.0f} s: the run's process or "
                                            "machine is gone")])


def ensure_zombie_automation(automation: Automation | None = None):
    """Create ``automation`` (default ``zombie_automation()``) on the current server unless one of that name exists;
    returns the stored automation."""
    automation = automation or zombie_automation()
    try:
        existing = Automation.read(name=automation.name)
    except ValueError:  # Prefect's way of saying there is none of that name
        existing = None
    return existing if existing is not None else automation.create()


def deployments(work_pool: bool = False) -> list:
    """The runner deployments (``RunnerDeployment``) of the factory; ``work_pool``: with the job variables of
    ``WORK_POOL`` (the heartbeat rate), which Prefect accepts only when they are applied to a work pool. Entry
    points are module paths (``flows.generate.generate_dataset``): a process worker starts each run in a fresh
    temporary folder, where a file path relative to the checkout would not be found; the project is installed in
    the worker's environment."""
    out = [generate_dataset.to_deployment(name=GENERATE_NIGHTLY, cron=NIGHTLY_CRON, parameters=NIGHTLY_PARAMETERS,
                                           entrypoint_type=MODULE,
                                           description="Nightly dataset generation over the synthetic templates."),
            generate_dataset.to_deployment(name="generate-on-demand", entrypoint_type=MODULE,
                                           description="Dataset generation for sources given at run time."),
            finetune_evaluate.to_deployment(name=FINETUNE_ON_GENERATION, triggers=[generation_completed_trigger()],
                                            entrypoint_type=MODULE,
                                            description="Fine-tune and evaluate the proxy planner on what a "
                                                        "nightly generation run made.")]
    if work_pool:
        for d in out:
            d.job_variables = {**d.job_variables, **JOB_VARIABLES}
    return out


if __name__ == "__main__":
    for d in deployments(work_pool=True):
        print(d.name, d.apply(work_pool_name=WORK_POOL))
    print(ZOMBIE_AUTOMATION, ensure_zombie_automation().id)
