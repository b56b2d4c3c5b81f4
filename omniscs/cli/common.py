"""What every command group shares: consoles, the progress sink, tables, and one parser each for comma lists,
edit lists, seeds and output paths (all checked before any work starts), and the depth picture."""
from __future__ import annotations

import contextlib
import sys
import time
from pathlib import Path
from typing import Callable, Iterator, Optional, TypeVar

import numpy as np
import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table
from rich.text import Text

from omniscs.errors import OmniscsError
from omniscs.progress import FeedReport, LineProgress, Throttled, following, watched_run

# Output is text, never markup: ids, paths, SQL results and error messages may hold '[...]' or ':x:', which rich
# would otherwise swallow or turn into emoji. Paths and ids stay whole when output is not a terminal.
console = Console(soft_wrap=True, markup=False, emoji=False, highlight=False)
err_console = Console(stderr=True, markup=False, emoji=False, highlight=False)


def print_error(message: str, label: str = "error", style: str = "red") -> None:
    """``error: message`` on stderr as one line of plain text (the label coloured on a terminal)."""
    from rich.text import Text

    err_console.print(Text.assemble((f"{label}:", style), " ", " ".join(str(message).split())), soft_wrap=True)

T = TypeVar("T")


# ----------------------------------------------------------------------------- progress
class Bars:
    """Progress sinks for one command: rich bars on a terminal, plain periodic lines otherwise (every 10 % or 30 s,
    whichever comes first). ``bars.sink(label)`` is an ``omniscs.progress.Progress`` callback; asking again for
    the same label gives the same bar or the same throttle."""

    def __init__(self, rich: Progress | None) -> None:
        self._rich = rich
        self._tasks: dict[str, int] = {}
        self._lines: dict[str, Callable[[int, int | None, str], None]] = {}

    def sink(self, label: str) -> Callable[[int, int | None, str], None]:
        if self._rich is None:
            if label not in self._lines:
                self._lines[label] = Throttled(LineProgress(label, sys.stderr), step_pct=LINE_STEP_PCT,
                                               min_interval_s=LINE_INTERVAL_S)
            return self._lines[label]
        rich = self._rich

        def update(done: int, total: int | None = None, note: str = "") -> None:
            if label not in self._tasks:
                self._tasks[label] = rich.add_task(label, total=total, note="")
            rich.update(self._tasks[label], completed=done, total=total, note=note)
        return update

    def remind(self, label: str, note: str) -> None:
        """In a log: the latest line of ``label`` again, with ``note``, when it printed nothing for
        LINE_INTERVAL_S (a bar on a terminal shows its elapsed time itself)."""
        if self._rich is None and label in self._lines:
            self._lines[label].remind(note)


#: Plain progress lines (a log, a pipe): one each time a stage moved this many percent ...
LINE_STEP_PCT = 10.0
#: ... or this many seconds passed with any movement, whichever comes first.
LINE_INTERVAL_S = 30.0


@contextlib.contextmanager
def progress_bars() -> Iterator[Bars]:
    """``with progress_bars() as bars: stage(..., progress=bars.sink("fit"))``."""
    if not err_console.is_terminal:
        yield Bars(None)
        return
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                  TextColumn("{task.fields[note]}"), TimeElapsedColumn(), TimeRemainingColumn(),
                  console=err_console, transient=False) as rich:
        yield Bars(rich)


@contextlib.contextmanager
def run_progress(workspace: Path, run_id: str) -> Iterator[None]:
    """Show the progress of every stage of run ``run_id`` as this command's bars or lines (``<scene> <stage>: ...``)
    while the block runs the flow, wherever the stages run: this process or Dask workers (the run's feed,
    ``omniscs.progress``). In a log each stage says when it starts, and one that reports nothing for 30 s says
    that it still runs."""
    running: dict[str, float] = {}  # label -> when its stage started (monotonic seconds)

    with progress_bars() as bars, watched_run(workspace, run_id) as feed:
        def deliver(report: FeedReport) -> None:
            if report.event == "end":
                running.pop(report.label, None)
                return
            if report.event == "start":
                running[report.label] = time.monotonic()
            bars.sink(report.label)(report.done, report.total, report.note)

        def tick() -> None:
            for label, started in list(running.items()):
                bars.remind(label, f"still running after {time.monotonic() - started:.0f} s")

        with following(feed, deliver, tick):
            yield


# ----------------------------------------------------------------------------- output
def print_table(rows: list[dict], title: str | None = None) -> None:
    table = Table(title=Text(title) if title else None)
    if not rows:
        console.print("(no rows)")
        return
    for col in rows[0]:
        table.add_column(str(col), overflow="fold")
    for row in rows:
        table.add_row(*[Text(_fmt(v)) for v in row.values()])
    if console.is_terminal:
        console.print(table)
    else:  # in a log or pipe rich assumes 80 columns and would fold ids and paths into many short lines
        Console(file=sys.stdout, width=240, markup=False, emoji=False, highlight=False).print(table)


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def depth_picture(depth: np.ndarray) -> np.ndarray:  # float [H, W] metres (0 = none) -> uint8 [H, W] (near bright)
    """Depth as grey levels scaled to its 95th percentile; 0 where there is no surface."""
    valid = depth > 0
    far = float(np.percentile(depth[valid], 95)) if np.any(valid) else 1.0
    grey = (255 * (1 - np.clip(depth / max(far, 1e-6), 0, 1))).astype(np.uint8)
    grey[~valid] = 0
    return grey


# ----------------------------------------------------------------------------- option parsing
def comma_list(text: Optional[str], parse: Callable[[str], T] = str, option: str = "the option",
               example: str = "a,b") -> tuple[T, ...]:
    """``a,b,c`` as a tuple (blank items dropped), each item parsed by ``parse``; a bad item is one error line."""
    if not text:
        return ()
    items = []
    for item in (p.strip() for p in text.split(",")):
        if not item:
            continue
        try:
            items.append(parse(item))
        except (ValueError, TypeError):
            raise OmniscsError(f"{option} takes a comma-separated list like {example}; got {text!r}") from None
    return tuple(items)


def seeds(text: str) -> tuple[int, ...]:
    """``--seeds 0,1,2``; at least one, each in ASCII digits and in range (``checks.check_seed``)."""
    from omniscs.checks import check_seed

    def one(item: str) -> int:
        if not (item.isascii() and item.isdigit()):
            raise ValueError(item)
        return check_seed(int(item), "each of --seeds")

    out = comma_list(text, one, "--seeds", "0,1,2")
    if not out:
        raise OmniscsError("--seeds needs at least one seed")
    return out


def read_edits(edit: Optional[str]) -> list:
    """Edits from a JSON string, or from a file when the option starts with '@'."""
    from omniscs.edits import parse_edits

    if not edit:
        return []
    if edit.startswith("@"):
        from omniscs.untrusted import read_json

        path = Path(edit[1:])
        if not path.exists():
            raise OmniscsError(f"edit file {path} does not exist")
        return parse_edits(read_json(path, 'give a file of one edit object or a list of them, e.g. '
                                           '[{"op": "remove", "track_id": 3}]', what="edit file"))
    return parse_edits(edit)


def edited_graph(graph, edits: list, pool: Path | None = None):
    """``graph`` with ``edits`` applied (``omniscs.nsg.edit.apply_graph_edits``); model ids (``pm-...``) resolve in
    ``pool`` when given, other ids to the graph's own nodes."""
    if not edits:
        return graph
    from omniscs.nsg.edit import apply_graph_edits, node_model_resolver

    resolve = None
    if pool is not None:
        from omniscs.agents.pool import model_resolver

        resolve = model_resolver(pool, node_model_resolver(graph))
    return apply_graph_edits(graph, edits, resolve)


def check_out(out: Path, overwrite: bool = False, suffix: str | None = None) -> Path:
    """An ``--out`` path checked before work starts: the right suffix, the path policy (``storage.check_output``:
    no symbolic link, names that fit, a writable folder), not under a file, and not already there unless
    ``overwrite`` (a folder is then replaced only when omniscs wrote it)."""
    from omniscs.storage import check_output, check_replaceable

    if suffix is not None and out.suffix.lower() != suffix:
        raise OmniscsError(f"--out must end in {suffix}; got {out}")
    check_output(out)
    for parent in Path(out).absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise OmniscsError(f"--out {out} lies under {parent}, which is a file; choose another --out")
            break
    if out.exists() and not overwrite:
        raise OmniscsError(f"{out} already exists; choose another --out or pass --overwrite")
    if out.exists() and suffix is None:
        check_replaceable(out)  # a folder output replaces only a folder omniscs wrote
    return out


def workspace_option() -> Optional[Path]:
    return typer.Option(None, help="Workspace root (default $OMNISCS_HOME or ./omniscs-data).")


def show_dataset(path: Path) -> None:
    """A dataset's card as a table of variants and a few lines: counts, fidelity, where things are."""
    from omniscs.annotate.dataset import CARD_JSON, gate_counts
    from omniscs.checks import read_json

    card = read_json(path / CARD_JSON, "the dataset card is damaged; build the dataset again")
    c = card["counts"]
    shown = ("scene_id", "variant_id", "level", "passed_gates", "ego_solved", "n_images", "n_annotations",
             "fidelity_psnr", "feature_drift")  # the rest is in the card (dataset.json, README.md)
    print_table([{k: row.get(k) for k in shown} for row in card["variants"]], title=f"dataset {card['dataset_id']}")
    fid, drift = card["fidelity"]["variant_psnr"], card["fidelity"].get("variant_feature_drift")
    console.print(f"{c['variants']} variant(s) of {c['scenes']} scene(s): {c['frames']} frames, {c['images']} images, "
                  f"{c['annotations']} box annotations; ego solved in {c['ego_solved']}; "
                  + (f"fidelity PSNR mean {fid['mean']:.2f} dB" if fid else "no exact reference")
                  + (f"; feature drift mean {drift['mean']:.3f}" if drift else ""))
    gates, lidar = card.get("gates"), card.get("lidar")
    if gates is not None:
        console.print(f"quality gates: {gate_counts(gates)}")
        for r in gates["rejections"]:
            console.print(f"  rejected {r['scene_id']} {r['variant_id']} ({r['level']}"
                          f"{', in the dataset' if r['in_dataset'] else ''}): {'; '.join(r['reasons'])}")
    if lidar is not None and lidar.get("boxes_within"):
        console.print(f"LiDAR: {lidar['with_points_within']} of {lidar['boxes_within']} boxes within "
                      f"{lidar['within_m']:g} m have points ({lidar['with_points']} of {lidar['boxes']} in all; "
                      f"{lidar.get('unlabelled', 0)} box(es) no sensor captures are not labelled)")
    for warning in card.get("warnings") or []:
        print_error(warning, label="warning", style="yellow")
    console.print(f"folder:  {path}")
    console.print(f"card:    {path / 'README.md'}")
    console.print(f"preview: {path / 'preview.png'}  (BEVs with the ego's solution: {path / 'bev'})")
