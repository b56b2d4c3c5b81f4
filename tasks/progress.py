"""Progress of a task run as a Prefect progress artifact, fed through the pipeline's one throttle."""
from __future__ import annotations

from prefect.artifacts import create_progress_artifact, update_progress_artifact

from omniscs.progress import Progress, Throttled, percent


def artifact_progress(description: str) -> Progress:
    """A progress callback that keeps one artifact of this task run up to date (every 5 %, or every 10 s)."""
    artifact = create_progress_artifact(0.0, description=description)
    return Throttled(lambda done, total, note: update_progress_artifact(
        artifact, percent(done, total), description=f"{description}: {note}" if note else None))
