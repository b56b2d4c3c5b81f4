"""The one benchmark harness: what machine and load the numbers came from, and the report files (JSON +
Markdown + PNG under ``reports/``), written atomically so a cut-short run never leaves half a report."""
from __future__ import annotations

import json
import os
import platform
from pathlib import Path
from typing import BinaryIO, Callable

from omniscs.storage import atomic_write_text, atomic_write_with


def machine_info() -> dict:
    """CPU count, platform, library versions and threads, and the 1/5/15-minute load average now. Shared
    machines are noisy: reports quote this beside every timing (and ``finish`` adds the load at the end).

    Numba's thread count is read from its configuration, never from ``numba.get_num_threads()``: that call
    starts numba's threading layer before the rasterizer's kernels do, which can pick another layer and change
    the kernels' summation order (a fast fit then ends 0.03 dB away from the same fit without the call)."""
    import numba
    import torch

    return {"cpus": os.cpu_count(), "platform": platform.platform(), "machine": platform.machine(),
            "python": platform.python_version(), "torch": torch.__version__,
            "torch_threads": torch.get_num_threads(), "numba_threads": numba.config.NUMBA_NUM_THREADS,
            "load_average_start": list(os.getloadavg())}


def finish(machine: dict) -> dict:
    """``machine`` with the load average at the end of the run."""
    return {**machine, "load_average_end": list(os.getloadavg())}


def load_line(machine: dict) -> str:
    """One Markdown sentence: the machine and its load at start and end."""
    start = machine.get("load_average_start", [float("nan")])[0]
    end = machine.get("load_average_end", [float("nan")])[0]
    return (f"Machine: {machine.get('cpus')} CPUs, {machine.get('platform')}, Python {machine.get('python')}, "
            f"torch {machine.get('torch')}; 1-min load average {start:.1f} at start, {end:.1f} at end "
            "(shared machine: compare ratios within one run).")


def write_report(out_dir: str | Path, name: str, report: dict, markdown: str,
                 pictures: dict[str, Callable[[BinaryIO], object]] | None = None) -> dict[str, Path]:
    """``<name>.json`` and ``<name>.md`` (+ ``<name><suffix>.png`` per picture writer) in ``out_dir``."""
    out_dir = Path(out_dir)
    paths = {"json": atomic_write_text(out_dir / f"{name}.json", json.dumps(report, indent=2, default=str) + "\n"),
             "md": atomic_write_text(out_dir / f"{name}.md", markdown)}
    for suffix, draw in (pictures or {}).items():
        paths[f"png{suffix}"] = atomic_write_with(out_dir / f"{name}{suffix}.png", draw)
    return paths


def save_partial(out_dir: str | Path, name: str, rows: list[dict]) -> Path:
    """The rows measured so far (``<name>.partial.json``): a long run cut short still reports them."""
    return atomic_write_text(Path(out_dir) / f"{name}.partial.json", json.dumps(rows, indent=2, default=str) + "\n")


def drop_partial(out_dir: str | Path, name: str) -> None:
    (Path(out_dir) / f"{name}.partial.json").unlink(missing_ok=True)


def status_bytes(field: str) -> int:
    """A memory field of /proc/self/status (VmRSS, VmHWM) in bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise OSError(f"/proc/self/status has no {field}")
