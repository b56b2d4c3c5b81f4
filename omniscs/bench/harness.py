"""The one benchmark harness: what machine and load the numbers came from, and the report files, one folder per
benchmark (``reports/<bench>/report.json``, ``report.md`` and its pictures; a second report of the same benchmark
as ``<part>.json/.md`` beside them), each file written atomically so a cut-short run never leaves half a report
and a rerun replaces the files instead of adding folders."""
from __future__ import annotations

import json
import os
import platform
from pathlib import Path
from typing import BinaryIO, Callable

import torch

from omniscs.storage import atomic_write_text, atomic_write_with


def machine_info() -> dict:
    """CPU count, platform, library versions and threads, and the 1/5/15-minute load average now. Shared
    machines are noisy: reports quote this beside every timing (and ``finish`` adds the load at the end).

    Numba's thread count is read from its configuration, never from ``numba.get_num_threads()``: that call
    starts numba's threading layer before the rasterizer's kernels do, which can pick another layer and change
    the kernels' summation order (a fast fit then ends 0.03 dB away from the same fit without the call)."""
    import numba

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


#: The file stem of a benchmark's main report inside its folder.
MAIN_PART = "report"


def report_folder(reports_root: str | Path, bench: str) -> Path:
    """The folder of benchmark ``bench`` (its ``omniscs bench`` name) under the reports root."""
    return Path(reports_root) / bench


def write_report(reports_root: str | Path, bench: str, report: dict, markdown: str,
                 pictures: dict[str, Callable[[BinaryIO], object]] | None = None,
                 part: str = MAIN_PART) -> dict[str, Path]:
    """``<reports_root>/<bench>/<part>.json`` and ``.md``, and one PNG per picture writer: key ``""`` is the part's
    own picture (``<part>.png``), any other key its file stem (``preview`` -> ``preview.png``)."""
    folder = report_folder(reports_root, bench)
    paths = {"json": atomic_write_text(folder / f"{part}.json", json.dumps(report, indent=2, default=str) + "\n"),
             "md": atomic_write_text(folder / f"{part}.md", markdown)}
    for stem, draw in (pictures or {}).items():
        paths[f"png:{stem}"] = atomic_write_with(folder / f"{stem or part}.png", draw)
    if "" not in (pictures or {}):  # a run without the part's picture must not leave an earlier run's beside it
        (folder / f"{part}.png").unlink(missing_ok=True)
    return paths


def save_partial(reports_root: str | Path, bench: str, rows: list[dict]) -> Path:
    """The rows measured so far (``<bench>/report.partial.json``): a long run cut short still reports them."""
    return atomic_write_text(report_folder(reports_root, bench) / f"{MAIN_PART}.partial.json",
                             json.dumps(rows, indent=2, default=str) + "\n")


def drop_partial(reports_root: str | Path, bench: str) -> None:
    (report_folder(reports_root, bench) / f"{MAIN_PART}.partial.json").unlink(missing_ok=True)


def status_bytes(field: str) -> int:
    """A memory field of /proc/self/status (VmRSS, VmHWM) in bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise OSError(f"/proc/self/status has no {field}")
