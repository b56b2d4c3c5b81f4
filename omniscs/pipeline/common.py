"""What every stage shares: how it says it is waiting for another writer, which config fields are execution
settings (left out of stage keys), and the request's device as a config override."""
from __future__ import annotations

from pathlib import Path

from omniscs.pipeline.request import SceneRequest
from omniscs.progress import Progress

#: Config fields that change how fast a stage runs, not what it makes: left out of stage keys.
EXECUTION_FIELDS = ("device", "torch_threads")


def waiting(progress: Progress, out: Path):
    """What a stage reports while another writer (another run, or the same scene twice) holds its output."""
    return lambda who: progress(0, None, f"waiting for {who or 'another writer'} to finish {Path(out).name}")


def result_config(config: dict) -> dict:
    """A config without its execution fields: what a stage key hashes."""
    return {k: v for k, v in config.items() if k not in EXECUTION_FIELDS}


def device_overrides(request: SceneRequest) -> dict:
    """The request's device as a config override (nothing for the CPU, every config's default)."""
    return {} if request.device == "cpu" else {"device": request.device}
