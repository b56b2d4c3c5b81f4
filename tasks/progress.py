"""Progress of a task run as a Prefect progress artifact, fed through the pipeline's one throttle, and into the run's
feed when a command watches the run (``omniscs.progress.stage_feed``); a run's summary as a table artifact."""
from __future__ import annotations

from prefect.artifacts import create_progress_artifact, create_table_artifact, update_progress_artifact

import contextlib
from typing import Iterator

from omniscs.progress import Progress, Throttled, percent, stage_feed, stoppable, tee


def artifact_progress(description: str) -> Progress:
    """A progress callback that keeps one artifact of this task run up to date (every 5 %, or every 10 s)."""
    artifact = create_progress_artifact(0.0, description=description)
    return Throttled(lambda done, total, note: update_progress_artifact(
        artifact, percent(done, total), description=f"{description}: {note}" if note else None))


@contextlib.contextmanager
def task_progress(description: str, workspace: str, run_id: str | None, label: str) -> Iterator[Progress]:
    """The progress of one task run of run ``run_id`` for the block: its artifact (``description``) and, when the
    command that started the run watches it, lines or a bar named ``label`` (``<scene> <stage>``) there, wherever
    the task runs (this process or a Dask worker)."""
    with stage_feed(workspace, run_id, label) as feed:
        yield stoppable(tee(artifact_progress(description), feed))


def run_summary_artifact(run_id: str, results: list[dict], dataset_id: str | None,
                         warnings: list[str] | tuple[str, ...] = ()) -> str:
    """One table row per scene of a ``generate_dataset`` run: its stages (made, reused or skipped), variants and
    how many passed the quality gates, the dataset and why it failed; the dataset card's warnings in the
    description. Shown in the Prefect UI under the flow run (key ``run-summary``)."""
    rows = []
    for r in results:
        stages = r.get("stages", {})
        made = [s for s, rec in stages.items() if not rec["skipped"] and not rec["reused"]]
        reused = [s for s, rec in stages.items() if rec["reused"]]
        variants = stages.get("behavior", {}).get("info", {}).get("n_variants")
        verdicts = stages.get("annotate", {}).get("info", {}).get("verdicts") or {}
        rows.append({"scene": r.get("scene_id") or r.get("label"), "status": "failed" if "error" in r else "done",
                     "made": ", ".join(made), "reused": ", ".join(reused),
                     "variants": "" if variants is None else int(variants),
                     "passed gates": f"{sum(bool(v['passed']) for v in verdicts.values())} of {len(verdicts)}"
                     if verdicts else "", "dataset": dataset_id or "",
                     "error": r.get("error", "")})
    warned = "; warnings: " + "; ".join(warnings) if warnings else ""
    return str(create_table_artifact(rows, key="run-summary", description=f"generate_dataset run {run_id}: "
                                                                           f"{len(rows)} scene(s){warned}"))
