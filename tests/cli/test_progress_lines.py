"""`omniscs generate ... > log 2>&1` writes plain progress lines while the fit runs (every 10 %, naming the scene and
the stage), whether the stages run in the CLI's process or in a Dask worker."""
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: A fit's progress line: ``<scene id> fit: done/total (pct%)  loss ...  PSNR ...``.
FIT_LINE = re.compile(r"(syn-straight-day-s\d+-[0-9a-f]+) fit: (\d+)/(\d+) \((\d+)%\)  loss [\d.]+  PSNR [\d.]+ dB")


def fit_progress(log: str) -> list[tuple[str, int, int, int]]:
    """(scene id, done, total, percent) of every fit line of a log, in order."""
    return [(m.group(1), int(m.group(2)), int(m.group(3)), int(m.group(4)))
            for m in map(FIT_LINE.fullmatch, log.splitlines()) if m]


@pytest.mark.slow  # a fast-preset fit of a tiny scene: 1 to 2 minutes on 2 shared cores; `make test-slow` runs it
@pytest.mark.parametrize("runner", ["threads", "dask"])
def test_a_generate_run_writing_into_a_file_prints_the_fits_progress_while_it_runs(tmp_path, runner):
    log = tmp_path / "log"
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}  # the CLI's own temporary server
    env.update(PYTHONPATH=str(ROOT), OMNISCS_HOME=str(tmp_path / "ws"), OMP_WAIT_POLICY="PASSIVE")
    command = [sys.executable, "-c", "from omniscs.cli import main; main()", "generate", "syn:straight:21",
               "--frames", "4", "--cameras", "1", "--width", "64", "--height", "36", "--no-previews",
               "--fit-preset", "fast", "--task-runner", runner] + (["--workers", "1"] if runner == "dask" else [])
    started = time.monotonic()
    with open(log, "w") as out:
        proc = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT, env=env)
    seen_while_running = []
    try:
        while proc.poll() is None and time.monotonic() - started < 900:
            seen = fit_progress(log.read_text())
            if seen and proc.poll() is None:
                seen_while_running = seen
            time.sleep(0.5)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
    text = log.read_text()
    assert proc.returncode == 0, text[-3000:]
    seconds = time.monotonic() - started
    # The fit's lines were in the file before the command ended, while the fit still ran.
    assert seen_while_running and min(pct for *_, pct in seen_while_running) == 0
    assert any(pct < 100 for *_, pct in seen_while_running), text[-3000:]
    lines = fit_progress(text)
    assert len({scene for scene, *_ in lines}) == 1  # one scene, named by its id
    pcts = [pct for *_, pct in lines]
    assert pcts[0] == 0 and pcts[-1] == 100 and lines[-1][1] == lines[-1][2]
    assert all(a < b for a, b in zip(pcts, pcts[1:]))  # in order, each line once
    # Every 10 % or 30 s: about 11 lines, never one per step of the fit's 1500.
    assert 6 <= len(lines) <= 11 + seconds / 30, lines
    assert not (tmp_path / "ws" / "progress").exists()  # the run's feed is gone with the command
