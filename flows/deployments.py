"""The factory's deployments in Python, the same as ``infra/prefect.yaml`` (a test keeps the two equal): nightly
generation on a cron schedule, and fine-tune + evaluate started by the completion of a generation run, the
run's datasets found from its flow run id (the trigger passes the ``prefect.flow-run.Completed`` event's
resource). Register them against a server with ``python -m flows.deployments`` (or ``prefect deploy`` with the
YAML), then start a worker for the pool."""
from __future__ import annotations

from prefect.deployments.runner import EntrypointType
from prefect.events import DeploymentEventTrigger

from flows.downstream import finetune_evaluate
from flows.generate import generate_dataset

WORK_POOL = "omniscs-process"
GENERATE_NIGHTLY = "generate-nightly"
NIGHTLY_CRON = "0 2 * * *"
NIGHTLY_PARAMETERS = {"sources": ["syn:straight:0", "syn:t_junction:1:dusk", "syn:intersection:2:night"],
                      "n_frames": 40, "n_cameras": 3, "fit_preset": "fast", "behavior_variants": 2,
                      "behavior_preset": "fast", "annotate": True}
FINETUNE_ON_GENERATION = "finetune-evaluate-on-generation"
MODULE = EntrypointType.MODULE_PATH


def generation_completed_trigger(upstream: str = GENERATE_NIGHTLY) -> DeploymentEventTrigger:
    """Fires once per completed run of the ``upstream`` generation deployment; passes the run to the flow."""
    return DeploymentEventTrigger(expect={"prefect.flow-run.Completed"},
                                  match_related={"prefect.resource.role": "deployment",
                                                 "prefect.resource.name": upstream},
                                  parameters={"upstream_flow_run": "{{ event.resource.id }}", "model": "proxy"})


def deployments() -> list:
    """The runner deployments (``RunnerDeployment``) of the factory. Entry points are module paths
    (``flows.generate.generate_dataset``): a process worker starts each run in a fresh temporary folder, where a file
    path relative to the checkout would not be found; the project is installed in the worker's environment."""
    return [generate_dataset.to_deployment(name=GENERATE_NIGHTLY, cron=NIGHTLY_CRON, parameters=NIGHTLY_PARAMETERS,
                                           entrypoint_type=MODULE,
                                           description="Nightly dataset generation over the synthetic templates."),
            generate_dataset.to_deployment(name="generate-on-demand", entrypoint_type=MODULE,
                                           description="Dataset generation for sources given at run time."),
            finetune_evaluate.to_deployment(name=FINETUNE_ON_GENERATION, triggers=[generation_completed_trigger()],
                                            entrypoint_type=MODULE,
                                            description="Fine-tune and evaluate the proxy planner on what a "
                                                        "nightly generation run made.")]


if __name__ == "__main__":
    for d in deployments():
        print(d.name, d.apply(work_pool_name=WORK_POOL))
