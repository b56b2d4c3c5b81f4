"""``omniscs bench reliability``: runs that survive kills and run side by side, measured on real ``omniscs
generate`` processes.

- Fault injection: a small ``generate`` run is killed with SIGKILL at random moments (each in its own fresh
  workspace), then run again with the same command. After the rerun the catalog's logical rows and the
  workspace's files must equal those of one clean run; no temporary folder or lock file may be left, and the
  killed run's temporary Prefect server must be gone (it dies with the CLI).
- Concurrency: several ``generate`` processes start at once on one workspace with overlapping new sources.
  Every process must succeed, each scene is rendered once, and every run catalogues each of its scenes exactly
  once.
"""
from __future__ import annotations

import hashlib
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from omniscs import catalog
from omniscs.bench.harness import finish, load_line, machine_info, write_report
from omniscs.progress import Progress, no_progress

#: Catalog tables compared between runs (``runs`` differs by design: a killed run is one more row).
DATA_TABLES = ("scenes", "agents", "frames", "plans", "models", "variants")
#: Columns that say when or by which run a row was made, not what it holds.
VOLATILE_COLUMNS = ("run_id", "reused")


@dataclass(frozen=True)
class ReliabilityConfig:
    """The run that is killed and repeated (held-out seeds: no other test or benchmark uses them)."""

    sources: tuple[str, ...] = ("syn:straight:41", "syn:t_junction:42:dusk", "syn:intersection:43")
    """Sources of the run."""
    options: tuple[str, ...] = ("--frames", "16", "--cameras", "2", "--width", "160", "--height", "90")
    """Further ``omniscs generate`` options."""
    kills: int = 10
    """SIGKILL moments, drawn uniformly between 0 and the clean run's duration."""
    seed: int = 2026
    """Seed of the kill moments."""
    processes: int = 4
    """Concurrent ``generate`` processes of the concurrency check."""
    timeout_s: float = 600.0
    """Longest a single ``generate`` may take."""


# ----------------------------------------------------------------------------- processes
def cli_command() -> list[str]:
    """The ``omniscs`` command line of this interpreter (as a user's shell would start it)."""
    return [sys.executable, "-c", "from omniscs.cli import main; main()"]


def cli_env(workspace: Path, prefect_home: Path) -> dict:
    return {**os.environ, "OMNISCS_HOME": str(workspace), "PREFECT_HOME": str(prefect_home),
            "PREFECT_LOGGING_LEVEL": "WARNING", "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
            "OMP_WAIT_POLICY": "PASSIVE", "PREFECT_API_URL": ""}


def children(pid: int) -> list[int]:
    """Pids of the processes whose parent is ``pid`` (Linux /proc)."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2:].split()
        if len(fields) > 1 and int(fields[1]) == pid:
            out.append(int(entry.name))
    return out


def running(pid: int) -> bool:
    """True while ``pid`` runs (a zombie counts as gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rfind(")") + 2:].split()[0] != "Z"


def generate(sources, options, workspace: Path, prefect_home: Path, timeout_s: float) -> tuple[int, float, str]:
    """Run ``omniscs generate`` to its end: exit code, seconds, the last lines of its output."""
    started = time.perf_counter()
    proc = subprocess.run(cli_command() + ["generate", *sources, *options], env=cli_env(workspace, prefect_home),
                          capture_output=True, text=True, timeout=timeout_s)
    tail = "\n".join((proc.stdout + proc.stderr).strip().splitlines()[-3:])
    return proc.returncode, time.perf_counter() - started, tail


def generate_killed(sources, options, workspace: Path, prefect_home: Path, after_s: float) -> dict:
    """Start ``omniscs generate``, SIGKILL it after ``after_s`` seconds (if still running); report whether its
    child processes (the temporary Prefect server) were gone 10 s later and what it had finished."""
    proc = subprocess.Popen(cli_command() + ["generate", *sources, *options], env=cli_env(workspace, prefect_home),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + after_s
    kids: set[int] = set()
    while time.monotonic() < deadline and proc.poll() is None:
        kids.update(children(proc.pid))
        time.sleep(0.05)
    kids.update(children(proc.pid))
    ended_before_kill = proc.poll() is not None
    if not ended_before_kill:
        proc.send_signal(signal.SIGKILL)
    proc.wait()
    gone_by = time.monotonic() + 10.0
    while time.monotonic() < gone_by and any(running(k) for k in kids):
        time.sleep(0.1)
    orphans = [k for k in kids if running(k)]
    for k in orphans:  # do not leave them to the machine
        os.kill(k, signal.SIGKILL)
    state = workspace_state(workspace)
    return {"kill_after_s": round(after_s, 2), "ended_before_kill": ended_before_kill,
            "children_seen": len(kids), "orphaned_processes": len(orphans),
            "temporaries_after_kill": len(state["temporaries"]), "scene_stores_after_kill": state["scene_stores"]}


# ----------------------------------------------------------------------------- what a workspace holds
def workspace_state(workspace: Path) -> dict:
    """Files of a workspace: temporaries and lock files left by writers, finished scene stores, and a digest of
    every other file outside the catalog (stage manifests and plots excluded from the digest: they hold times)."""
    workspace = Path(workspace)
    temporaries, files = [], {}
    if workspace.is_dir():
        for path in sorted(workspace.rglob("*")):
            rel = path.relative_to(workspace).as_posix()
            if ".tmp-" in path.name or path.name.endswith(".lock"):
                temporaries.append(rel)
                continue
            if not path.is_file() or rel.startswith("catalog/") or any(".tmp-" in p for p in path.parts):
                continue
            volatile = path.name in ("stage.json",) or path.suffix == ".png" and rel.startswith("previews/")
            files[rel] = "-" if volatile else hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    scenes = workspace / "scenes"
    stores = sorted(p.name for p in scenes.iterdir() if p.is_dir() and not p.name.startswith(".")) \
        if scenes.is_dir() else []
    return {"temporaries": temporaries, "files": files, "scene_stores": len(stores)}


def catalog_state(workspace: Path, view_suffix: str = "") -> dict[str, list[tuple]]:
    """Every data table's rows as the catalog's views show them, without the columns that say when or by which
    run a row was made (``*_seconds``, ``run_id``, ``reused``), with the workspace path written as ``<ws>``."""
    root = catalog.catalog_root(workspace)
    out = {}
    for table in DATA_TABLES:
        rows = catalog.query(root, f"SELECT * FROM {table}{view_suffix}").to_pylist()
        norm = []
        for row in rows:
            items = []
            for k, v in sorted(row.items()):
                if k in VOLATILE_COLUMNS or k.endswith("_seconds"):
                    continue
                if isinstance(v, str):
                    v = v.replace(str(workspace), "<ws>")
                items.append((k, repr(v)))
            norm.append(tuple(items))
        out[table] = sorted(norm)
    return out


def _diff(a: dict, b: dict) -> list[str]:
    """Names of what differs between two states (tables or files)."""
    keys = sorted(set(a) | set(b))
    return [k for k in keys if a.get(k) != b.get(k)]


# ----------------------------------------------------------------------------- the two checks
def fault_injection(config: ReliabilityConfig, workdir: Path, progress: Progress = no_progress) -> dict:
    """A clean run, then ``config.kills`` kill + rerun pairs, each in a fresh workspace."""
    prefect_home = workdir / "prefect"
    clean_ws = workdir / "clean"
    # a first run in a new Prefect home migrates its database: keep that out of the clean run's duration
    generate(["syn:straight:0"], ["--frames", "1", "--cameras", "1", "--width", "8", "--height", "8",
                                  "--no-previews"], workdir / "warm-up", prefect_home, config.timeout_s)
    rc, clean_s, tail = generate(config.sources, config.options, clean_ws, prefect_home, config.timeout_s)
    if rc != 0:
        raise RuntimeError(f"the clean run failed (exit {rc}): {tail}")
    clean_catalog = catalog_state(clean_ws)
    clean_files = workspace_state(clean_ws)["files"]
    rng = random.Random(config.seed)
    moments = sorted(rng.uniform(0.5, clean_s) for _ in range(config.kills))
    rows = []
    for i, moment in enumerate(moments):
        ws = workdir / f"kill-{i}"
        killed = generate_killed(config.sources, config.options, ws, prefect_home, moment)
        rc, rerun_s, tail = generate(config.sources, config.options, ws, prefect_home, config.timeout_s)
        state = workspace_state(ws)
        catalog_diff = _diff(catalog_state(ws), clean_catalog) if rc == 0 else ["(rerun failed)"]
        file_diff = _diff(state["files"], clean_files)
        rows.append({**killed, "rerun_exit": rc, "rerun_s": round(rerun_s, 1),
                     "catalog_equal": not catalog_diff, "catalog_diff": catalog_diff,
                     "files_equal": not file_diff, "file_diff": file_diff[:5],
                     "temporaries_after_rerun": len(state["temporaries"]), "rerun_tail": tail if rc else ""})
        shutil.rmtree(ws, ignore_errors=True)
        progress(i + 1, len(moments), f"kill at {moment:.1f} s")
    return {"clean_run_s": round(clean_s, 1), "clean_rows": {t: len(r) for t, r in clean_catalog.items()},
            "clean_files": len(clean_files), "kills": rows}


def concurrency(config: ReliabilityConfig, workdir: Path, progress: Progress = no_progress) -> dict:
    """``config.processes`` generate processes at once on one new workspace, sources overlapping: each gets a
    rotating pair of the sources, and the last one all of them."""
    ws, prefect_home = workdir / "shared", workdir / "prefect-concurrent"
    n = len(config.sources)
    assignments = [[config.sources[i % n], config.sources[(i + 1) % n]] for i in range(config.processes - 1)]
    assignments.append(list(config.sources))
    started = time.perf_counter()
    procs = [subprocess.Popen(cli_command() + ["generate", *s, *config.options], env=cli_env(ws, prefect_home),
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for s in assignments]
    outputs = [p.communicate(timeout=config.timeout_s)[0] for p in procs]
    seconds = time.perf_counter() - started
    progress(1, 1, "concurrent runs done")
    runs = catalog.query(catalog.catalog_root(ws), "SELECT run_id, status, n_scenes FROM runs").to_pylist()
    per_run = catalog.query(catalog.catalog_root(ws), """
        SELECT run_id, count(*) AS rows, count(DISTINCT scene_id) AS scenes FROM scenes_by_run GROUP BY run_id
        """).to_pylist()
    raw = catalog.query(catalog.catalog_root(ws), """
        SELECT run_id, scene_id, count(*) AS n FROM scenes_raw GROUP BY ALL HAVING count(*) > 1""").to_pylist()
    state = workspace_state(ws)
    return {"processes": len(procs), "exit_codes": [p.returncode for p in procs], "seconds": round(seconds, 1),
            "sources_per_process": [len(s) for s in assignments], "runs": runs, "scenes_per_run": per_run,
            "scenes_twice_in_a_run": raw, "scene_stores": state["scene_stores"],
            "distinct_sources": len(set(config.sources)), "temporaries_left": state["temporaries"],
            "failed_output": [o[-2000:] for p, o in zip(procs, outputs) if p.returncode != 0]}


# ----------------------------------------------------------------------------- report
def run_bench(config: ReliabilityConfig, out_dir: str | Path = "reports", progress: Progress = no_progress,
              workdir: str | Path | None = None) -> dict:
    machine = machine_info()
    with tempfile.TemporaryDirectory(prefix="omniscs-reliability-", dir=workdir) as tmp:
        faults = fault_injection(config, Path(tmp), progress)
        shared = concurrency(config, Path(tmp), progress)
    report = {"config": asdict(config), "machine": finish(machine), "fault_injection": faults,
              "concurrency": shared}
    write_report(out_dir, "reliability", report, markdown(report))
    return report


def markdown(report: dict) -> str:
    cfg, faults, shared = report["config"], report["fault_injection"], report["concurrency"]
    kills = faults["kills"]
    lines = ["# Reliability: kills and concurrent runs", "",
             f"`omniscs generate {' '.join(cfg['sources'])} {' '.join(cfg['options'])}` "
             f"(clean run {faults['clean_run_s']} s; catalog rows {faults['clean_rows']}; "
             f"{faults['clean_files']} files outside the catalog).", "",
             f"## Fault injection: SIGKILL at {len(kills)} random moments (seed {cfg['seed']}), each then rerun", "",
             "| # | killed after s | Prefect server up | scene stores at kill | temporaries at kill | orphaned "
             "processes | rerun exit | rerun s | catalog = clean | files = clean | temporaries after rerun |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for i, k in enumerate(kills):
        lines.append(f"| {i} | {k['kill_after_s']}{' (had ended)' if k['ended_before_kill'] else ''} | "
                     f"{'yes' if k['children_seen'] else 'not yet'} | {k['scene_stores_after_kill']} | {k['temporaries_after_kill']} | {k['orphaned_processes']} | "
                     f"{k['rerun_exit']} | {k['rerun_s']} | {'yes' if k['catalog_equal'] else k['catalog_diff']} | "
                     f"{'yes' if k['files_equal'] else k['file_diff']} | {k['temporaries_after_rerun']} |")
    ok = sum(k["rerun_exit"] == 0 and k["catalog_equal"] and k["files_equal"] and not k["temporaries_after_rerun"]
             and not k["orphaned_processes"] for k in kills)
    lines += ["", f"{ok} of {len(kills)} kills: rerun succeeded, catalog and files equal to the clean run's, "
              "no temporaries, no orphaned process.", "",
              f"## Concurrency: {shared['processes']} `generate` processes at once on one new workspace", "",
              f"Sources per process {shared['sources_per_process']} over {shared['distinct_sources']} distinct "
              f"sources; exit codes {shared['exit_codes']}; {shared['seconds']} s for all.", "",
              "| run | status | scenes asked | scene rows | distinct scenes |", "|---|---|---|---|---|"]
    per_run = {r["run_id"]: r for r in shared["scenes_per_run"]}
    for r in sorted(shared["runs"], key=lambda r: r["run_id"]):
        p = per_run.get(r["run_id"], {"rows": 0, "scenes": 0})
        lines.append(f"| {r['run_id']} | {r['status']} | {r['n_scenes']} | {p['rows']} | {p['scenes']} |")
    lines += ["", f"Scene stores rendered: {shared['scene_stores']} (distinct sources: {shared['distinct_sources']}); "
              f"scenes catalogued twice within one run (raw files): {len(shared['scenes_twice_in_a_run'])}; "
              f"temporaries left: {len(shared['temporaries_left'])}.", "", load_line(report["machine"]), ""]
    return "\n".join(lines)
