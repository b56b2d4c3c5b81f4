"""``omniscs bench``: the benchmarks (``omniscs.bench``), one table (name -> options -> run) and one handler.

Each benchmark's command-line options are the fields of its options dataclass (help text from the field docs); its
run function checks them, runs the benchmark and returns the Markdown report it wrote under
``<out>/<name>/`` (``report.md``, or ``<part>.md`` for a second report of the same benchmark)."""
from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap
import typing
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Callable, Optional

import typer

from omniscs.checks import MAX_SEED, MAX_THREADS
from omniscs.cli.common import Bars, comma_list, console, progress_bars
from omniscs.cli.common import seeds as parse_seeds
from omniscs.errors import OmniscsError

app = typer.Typer(help="Benchmarks; each writes reports/<name>/report.json and report.md (+ pictures).",
                  no_args_is_help=True)

WORKSPACE_HELP = "Where the benchmark's scenes and fits go (and are reused)."


def _flag(name: str):
    """A field that appears on the command line under another flag than its name."""
    return {"flag": name}


def _bounded(low: int, high: int) -> dict:
    """A count the option itself bounds (refused with exit 2 before any work): threads, seeds."""
    return {"min": low, "max": high}


# ----------------------------------------------------------------------------- options and runs, one per benchmark
@dataclass(frozen=True)
class WorldOptions:
    seeds: str = "0"
    """Comma-separated seeds."""
    frames: int = 40
    """Frames of each log (10 Hz)."""
    cameras: int = 3
    """Cameras per frame."""


def run_world(o: WorldOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.world import run_world_benchmark

    run_world_benchmark(out, seeds=parse_seeds(o.seeds), n_frames=o.frames, n_cameras=o.cameras)
    return out / "world" / "report.md"


@dataclass(frozen=True)
class SourcesOptions:
    frames: int = 10
    """Frames of the synthetic log."""
    cameras: int = 6
    """Cameras per frame."""
    repeats: int = 3
    """Reads per format (the first is a cold read)."""


def run_sources(o: SourcesOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.sources import run_sources_benchmark

    run_sources_benchmark(out, n_frames=o.frames, n_cameras=o.cameras, repeats=o.repeats)
    return out / "sources" / "report.md"


@dataclass(frozen=True)
class BehaviorOptions:
    scenes_per_template: int = 5
    """Procedural scenes per road template."""
    variants: int = 2
    """Variants per scene."""
    preset: str = "balanced"
    """Adversarial preset: fast, balanced or accurate."""
    checkpoint: Optional[Path] = None
    """Traffic-model checkpoint (default: the shipped one)."""
    rule_planner: bool = True
    """Also run against the reacting rule-based planner."""
    threads: int = field(default=1, metadata=_bounded(1, MAX_THREADS))
    """torch CPU threads."""
    appearance_scenes: int = 4
    """Rendered scenes fitted with a scene graph for the with/without L_app comparison (0 skips it)."""
    workspace: Optional[Path] = None
    """Where those scenes and scene graphs go (and are reused)."""
    app_weights: str = "1,30"
    """Comma-separated L_app weights compared."""
    only_appearance: bool = False
    """Rerun only the L_app comparison in an existing report in --out."""
    seed_offset: int = field(default=2000, metadata=_bounded(0, MAX_SEED))
    """First scene seed: 2000 is the fixed set, any other a fresh one."""
    only_default: bool = False
    """Run only the default configuration on the procedural logs."""
    search_starts: int = 192
    """Feasibility search: random starts per candidate adversary."""


def run_behavior(o: BehaviorOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.behavior import BenchConfig, rerun_appearance_study, run_behavior_benchmark
    from omniscs.scs.behavior.adversarial_config import adversarial_preset
    from omniscs.scs.behavior.feasibility import FeasibilityConfig

    adversarial_preset(o.preset)
    weights = comma_list(o.app_weights, float, "--app-weights", "1,30")
    if o.search_starts < 1:
        raise OmniscsError(f"--search-starts must be at least 1; got {o.search_starts}")
    if not weights or min(weights) <= 0:
        raise OmniscsError(f"--app-weights takes positive numbers like 1,30; got {o.app_weights!r}")
    config = BenchConfig(scenes_per_template=o.scenes_per_template, variants_per_scene=o.variants, preset=o.preset,
                         rule_planner=o.rule_planner, torch_threads=o.threads,
                         appearance_scenes=max(0, o.appearance_scenes), app_weights=weights,
                         seed_offset=o.seed_offset, only_default=o.only_default,
                         feasibility=FeasibilityConfig(starts=o.search_starts))
    if o.only_appearance:
        rerun_appearance_study(out, config, o.checkpoint, o.workspace)
    else:
        run_behavior_benchmark(out, config, o.checkpoint, progress=bars.sink("behaviour variants"),
                               workspace=o.workspace)
    return out / "behavior" / "report.md"


@dataclass(frozen=True)
class SceneRigOptions:
    """The procedural scenes' rig and where they go: the options every benchmark of fitted scenes shares."""

    frames: int = 40
    """Frames per scene."""
    cameras: int = 3
    """Cameras per frame."""
    width: int = 480
    """Image width (pixels)."""
    height: int = 270
    """Image height (pixels)."""
    workspace: Optional[Path] = None
    """Where the benchmark scenes are rendered (and reused)."""


@dataclass(frozen=True)
class FitOptions(SceneRigOptions):
    seeds: str = "0"
    """Comma-separated seeds of the procedural scenes."""
    presets: str = "fast,balanced,accurate"
    """Comma-separated presets."""
    template: str = "straight"
    """Road layout template of the scenes."""
    baseline: Optional[str] = None
    """A git revision of the project (branch, tag, hash) that fits the same scenes with the same presets, in turns
    with the current code, each fit in a fresh interpreter: the report gives both sides and the ratios."""
    baseline_rounds: int = 1
    """Turns per side and preset with --baseline (medians over them)."""
    curve_iterations: str = ""
    """Comma-separated iteration counts: extra points of the speed/accuracy curve, each a fit of --curve-preset with
    its whole schedule compressed to that many iterations (current code)."""
    curve_preset: str = "balanced"
    """The preset whose schedule --curve-iterations compresses."""
    quick: bool = False
    """Smoke run: a 10-frame, 1-camera 96x54 log fitted for 30 iterations (overrides the rig options)."""


def run_fit(o: FitOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.baseline import baseline_tree
    from omniscs.bench.fit import QUICK_OVERRIDES, QUICK_SCENES, BenchScenes, run_fit_benchmark
    from omniscs.nsg.config import PRESETS
    from omniscs.storage import workspace_path

    chosen = comma_list(o.presets)
    unknown = [p for p in (*chosen, o.curve_preset) if p not in PRESETS]
    if unknown or not chosen:
        raise OmniscsError(f"unknown preset(s) {unknown}; use some of {list(PRESETS)}")
    curve = comma_list(o.curve_iterations, int, "--curve-iterations", "750,1500,2250")
    if any(n < 1 for n in curve):
        raise OmniscsError(f"--curve-iterations takes positive counts like 750,1500,2250; got {o.curve_iterations!r}")
    if o.baseline_rounds < 1:
        raise OmniscsError("--baseline-rounds must be at least 1")
    rig = QUICK_SCENES if o.quick else {"n_frames": o.frames, "n_cameras": o.cameras, "width": o.width,
                                        "height": o.height}
    scenes = BenchScenes(parse_seeds(o.seeds), o.template, "day", **rig)
    baseline = None
    if o.baseline is not None:
        commit, tree = baseline_tree(o.baseline, workspace_path(o.workspace) / "cache")
        baseline = (o.baseline, commit, tree)
    run_fit_benchmark(out, scenes, chosen, o.workspace, overrides=dict(QUICK_OVERRIDES) if o.quick else None,
                      progress=bars.sink("bench fit"), baseline=baseline,
                      rounds=o.baseline_rounds if baseline is not None else 1, curve_iterations=tuple(curve),
                      curve_preset=o.curve_preset)
    return out / "fit" / "report.md"


@dataclass(frozen=True)
class EditsOptions(SceneRigOptions):
    seeds: str = "0"
    """Comma-separated seeds of the procedural scenes."""
    preset: str = "balanced"
    """Fit preset of the scene graphs."""
    agents: int = 2
    """Edited agents per scene (the most visible ones)."""
    views: int = 4
    """Evaluated views per agent and edit."""
    template: str = "straight"
    """Road layout template of the scenes."""


def run_edits(o: EditsOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.fit import BenchScenes, run_edit_benchmark
    from omniscs.nsg.config import fit_preset

    fit_preset(o.preset)
    if o.agents < 1 or o.views < 1:
        raise OmniscsError("--agents and --views must be at least 1")
    scenes = BenchScenes(parse_seeds(o.seeds), o.template, "day", o.frames, o.cameras, o.width, o.height)
    run_edit_benchmark(out, scenes, o.preset, o.agents, o.views, workspace=o.workspace,
                       progress=bars.sink("bench fit"))
    return out / "edits" / "report.md"


@dataclass(frozen=True)
class RenderOptions:
    resolutions: str = "320x180,640x360,1280x720"
    """Comma-separated WxH."""
    counts: str = "10000,100000,1000000"
    """Comma-separated Gaussian counts."""
    repeats: int = 5
    """Timed repeats per cell (median reported)."""
    reference_budget_s: float = 60.0
    """Skip reference cells expected to take longer."""
    baseline: Optional[str] = None
    """A git revision of the project (branch, tag, hash) whose rasteriser is timed beside the current one, in turns,
    for every resolution and count: the report gives the speed-ups."""
    baseline_rounds: int = 3
    """Alternating turns per side and cell with --baseline."""
    workspace: Optional[Path] = None
    """Where the baseline revision is extracted (and reused)."""


def run_render(o: RenderOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.baseline import baseline_tree
    from omniscs.bench.render import run_render_benchmark
    from omniscs.storage import workspace_path

    sizes = comma_list(o.resolutions, lambda r: tuple(int(v) for v in r.lower().split("x")), "--resolutions",
                       "640x360,1280x720")
    ns = comma_list(o.counts, int, "--counts", "10000,100000")
    if not sizes or any(len(s) != 2 or min(s) < 1 for s in sizes) or not ns or min(ns) < 1:
        raise OmniscsError("--resolutions is like 640x360,1280x720 and --counts like 10000,100000")
    if o.baseline_rounds < 1:
        raise OmniscsError("--baseline-rounds must be at least 1")
    baseline = None
    if o.baseline is not None:
        commit, tree = baseline_tree(o.baseline, workspace_path(o.workspace) / "cache")
        baseline = (o.baseline, commit, tree)
    run_render_benchmark(out, resolutions=sizes, counts=ns, repeats=o.repeats,
                         reference_budget_s=o.reference_budget_s, baseline=baseline,
                         baseline_rounds=o.baseline_rounds)
    return out / "render" / "report.md"


@dataclass(frozen=True)
class PlanOptions(SceneRigOptions):
    scenes: str = "straight:31,t_junction:32,intersection:33"
    """Comma-separated TEMPLATE:SEED procedural scenes."""
    preset: str = "fast"
    """Scene-graph preset of both modes."""
    variants: int = 1
    """Behaviour variants requested per scene."""
    min_pixels: int = 200
    """Views count when the edited agent covers this many pixels."""


def run_plan(o: PlanOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.plan import PlanBenchConfig, run_plan_benchmark
    from omniscs.nsg.config import fit_preset

    fit_preset(o.preset)

    def template_seed(item: str) -> tuple[str, int]:
        template, seed = item.split(":")
        return template, int(seed)

    chosen = comma_list(o.scenes, template_seed, "--scenes", "straight:31,t_junction:32")
    if not chosen or o.variants < 0:
        raise OmniscsError("--scenes needs at least one TEMPLATE:SEED and --variants must be >= 0")
    config = PlanBenchConfig(scenes=chosen, n_frames=o.frames, n_cameras=o.cameras, width=o.width, height=o.height,
                             fit_preset=o.preset, behavior_variants=o.variants, min_pixels=o.min_pixels)
    run_plan_benchmark(out, config, o.workspace, progress=bars.sink("bench plan"))
    return out / "plan" / "report.md"


@dataclass(frozen=True)
class DatasetOptions:
    workspace: Optional[Path] = None
    """Where the scenes, fits and variants go (and are reused)."""
    variants: int = 2
    """Behaviour variants per scene."""


def run_dataset(o: DatasetOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.dataset import DatasetBenchConfig, run_dataset_benchmark

    run_dataset_benchmark(out, o.workspace, dataclasses.replace(DatasetBenchConfig(), variants=o.variants),
                          progress=bars.sink("dataset bench"))
    return out / "dataset" / "report.md"


@dataclass(frozen=True)
class AgentsOptions:
    workspace: Optional[Path] = None
    """Where the scenes, fits and the benchmark pool go (and are reused)."""
    quick: bool = False
    """One small scene, the fast preset, a small pool (a smoke run, not a measurement)."""
    matching_only: bool = False
    """Matching alone (agents/matching.json/.md): minutes instead of hours, for a new MSNet."""


def run_agents(o: AgentsOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.agents import AgentsBenchConfig, quick_config, run_agents_benchmark, run_matching_benchmark

    config = quick_config() if o.quick else AgentsBenchConfig()
    if o.matching_only:
        run_matching_benchmark(out, o.workspace, config, progress=bars.sink("agents matching"))
        return out / "agents" / "matching.md"
    run_agents_benchmark(out, o.workspace, config, progress=bars.sink("agents bench"))
    return out / "agents" / "report.md"


@dataclass(frozen=True)
class ScaleoutOptions:
    workspace: Path = Path("omniscs-data/bench-scaleout")
    """Scratch workspace (emptied per run)."""
    quick: bool = False
    """A tiny set-up that checks the code path (not for numbers)."""


def run_scaleout(o: ScaleoutOptions, out: Path, bars: Bars) -> Path:
    import os

    from omniscs.cli.prefect_api import prefect_api

    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    from flows.generate import generate_dataset
    from omniscs.bench.scaleout import ScaleoutBenchConfig, quick_config, run_scaleout_benchmark

    with prefect_api():
        run_scaleout_benchmark(out, o.workspace, generate_dataset,
                               quick_config() if o.quick else ScaleoutBenchConfig(),
                               progress=bars.sink("scale-out bench"))
    return out / "scaleout" / "report.md"


@dataclass(frozen=True)
class ClosedloopOptions:
    workspace: Optional[Path] = None
    """Workspace for the benchmark's scenes and fits (default $OMNISCS_HOME or ./omniscs-data)."""
    quick: bool = False
    """A tiny set-up that checks the code path (not for numbers)."""


def run_closedloop(o: ClosedloopOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.closedloop import ClosedLoopBenchConfig, quick_config, run_closedloop_benchmark

    run_closedloop_benchmark(out, o.workspace, quick_config() if o.quick else ClosedLoopBenchConfig(),
                             progress=bars.sink("closed-loop bench"))
    return out / "closedloop" / "report.md"


@dataclass(frozen=True)
class ViewOptions:
    workspace: Optional[Path] = None
    """Where the benchmark's scene and fit go (reused)."""
    quick: bool = False
    """A tiny world and two small counts, one pass (a smoke run of the code path, not a measurement)."""


def run_view(o: ViewOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.view import ViewBenchConfig, quick_config, run_view_benchmark

    run_view_benchmark(out, o.workspace, quick_config() if o.quick else ViewBenchConfig(),
                       progress=bars.sink("viewer bench"))
    return out / "view" / "report.md"


@dataclass(frozen=True)
class AppearanceOptions:
    workspace: Optional[Path] = None
    """Where the scenes, fits and the benchmark pool go (reused)."""
    quick: bool = False
    """The development log, one case (a smoke run, not a measurement)."""


def run_appearance(o: AppearanceOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.appearance import AppearanceBenchConfig, quick_config, run_appearance_benchmark

    run_appearance_benchmark(out, o.workspace, quick_config() if o.quick else AppearanceBenchConfig(),
                             progress=bars.sink("appearance bench"))
    return out / "appearance" / "report.md"


@dataclass(frozen=True)
class BackgroundOptions:
    workspace: Optional[Path] = None
    """Where the scenes and fits go (and are reused)."""
    quick: bool = False
    """One dev scene, one novel offset, few steps (a smoke run, not a measurement)."""
    no_ablations: bool = field(default=False, metadata=_flag("--no-ablations"))
    """Only the main rows (naive, hidden Gaussians removed, the issue's rows, the default repair): about half the
    time."""
    ablation: Optional[list[str]] = None
    """Only this ablation row (repeatable; default: all of them), e.g. 'planes + DRNet + RoI refit, planes first
    where the cleaned background covers'."""
    replacement: bool = False
    """Instead of the removal arms, the replacement case: the large object replaced by a smaller pool object, without
    and with the background repair (ghost area and hole PSNR; reports/background/replacement.md)."""


def run_background(o: BackgroundOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.background import BackgroundBenchConfig, quick_config, run_background_benchmark

    if o.replacement:
        from omniscs.bench import replacement

        config = replacement.quick_config() if o.quick else replacement.ReplacementBenchConfig()
        replacement.run_replacement_benchmark(out, o.workspace, config, progress=bars.sink("replacement bench"))
        return out / "background" / f"{replacement.PART}.md"
    config = quick_config() if o.quick else BackgroundBenchConfig()
    if o.no_ablations:
        config = dataclasses.replace(config, full_comparison=False)
    if o.ablation:
        config = dataclasses.replace(config, ablations=tuple(o.ablation))
    run_background_benchmark(out, o.workspace, config, progress=bars.sink("background bench"))
    return out / "background" / "report.md"


@dataclass(frozen=True)
class DownstreamOptions:
    workspace: Optional[Path] = None
    """Where the benchmark's variants and solutions go (and are reused)."""
    quick: bool = False
    """A few scenes and epochs (a smoke run, not a measurement)."""
    detection: bool = False
    """The detection protocol instead (base vs fine-tuned with appearance-SCS data; mAP/NDS on an appearance-SCS
    and the original test set) with the embedded proxy camera detector: downstream/detection.json/.md."""


def run_downstream(o: DownstreamOptions, out: Path, bars: Bars) -> Path:
    if o.detection:
        from omniscs.bench.detection_protocol import DetectionProtocolConfig, quick_config as quick_detection, \
            run_detection_protocol

        run_detection_protocol(out, o.workspace, quick_detection() if o.quick else DetectionProtocolConfig(),
                               progress=bars.sink("detection protocol"))
        return out / "downstream" / "detection.md"
    from omniscs.bench.downstream import DownstreamBenchConfig, quick_config, run_downstream_benchmark

    run_downstream_benchmark(out, o.workspace, quick_config() if o.quick else DownstreamBenchConfig(),
                             progress=bars.sink("downstream bench"))
    return out / "downstream" / "report.md"


@dataclass(frozen=True)
class ReliabilityOptions:
    kills: int = 10
    """SIGKILL moments of the fault-injection check (each then rerun)."""
    processes: int = 4
    """Concurrent generate processes of the concurrency check."""
    seed: int = field(default=2026, metadata=_bounded(0, MAX_SEED))
    """Seed of the kill moments."""


def run_reliability(o: ReliabilityOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.reliability import ReliabilityConfig, run_bench

    if not 1 <= o.kills <= 100 or not 2 <= o.processes <= 16 or o.seed < 0:
        raise OmniscsError("--kills must be 1..100, --processes 2..16 and --seed >= 0")
    run_bench(ReliabilityConfig(kills=o.kills, processes=o.processes, seed=o.seed), out,
              progress=bars.sink("bench reliability"))
    return out / "reliability" / "report.md"


@dataclass(frozen=True)
class BadInputsOptions:
    subprocess_mode: bool = field(default=False, metadata=_flag("--subprocess"))
    """Run each case as a new omniscs process (slower; in-process by default)."""


def run_bad_inputs(o: BadInputsOptions, out: Path, bars: Bars) -> Path:
    from omniscs.bench.bad_inputs import run_bench

    run_bench(out, subprocess_mode=o.subprocess_mode, progress=bars.sink("bench bad-inputs"))
    return out / "bad-inputs" / "report.md"


# ----------------------------------------------------------------------------- the table
@dataclass(frozen=True)
class Benchmark:
    """One ``omniscs bench NAME`` command."""

    name: str
    """The command name, also its report folder under the reports root."""
    options: type
    """A frozen dataclass: its fields are the command's options (help from the field docs)."""
    run: Callable[..., Path]
    """``run(options, reports_root, bars)``: checks the options, runs, returns the Markdown report written."""
    help: str
    """What it measures (the command's help)."""


BENCHMARKS: tuple[Benchmark, ...] = (
    Benchmark("world", WorldOptions, run_world, "Time rendering a 40-frame, 3-camera 480x270 scene with LiDAR."),
    Benchmark("sources", SourcesOptions, run_sources, "Time reading a 480x270 synthetic log back from nuScenes, "
              "KITTI and Waymo v2 (ms per frame)."),
    Benchmark("behavior", BehaviorOptions, run_behavior, "Adversarial success, plausibility violations, "
              "accelerations and time per variant, with and without the plausibility penalty, with and without L_app "
              "(and its appearance drift), plus the traffic model's ADE/FDE."),
    Benchmark("fit", FitOptions, run_fit, "Fit the same scenes with each preset, each fit in a fresh interpreter: "
              "wall time, Gaussians, held-out PSNR/SSIM and peak memory; with --baseline REF the same fits by that "
              "revision in turns, and the ratios; the speed/accuracy curve as a plot."),
    Benchmark("edits", EditsOptions, run_edits, "Edit fidelity against ground truth: translate 2.0/3.5 m, rotate "
              "90/180/270°; PSNR/SSIM full and masked."),
    Benchmark("render", RenderOptions, run_render, "Time the Gaussian rasterizer (forward, forward+backward) per "
              "backend; cpu/reference speed-up."),
    Benchmark("plan", PlanOptions, run_plan, "The pipeline with the scene's plan vs with every track an agent node: "
              "time, Gaussians, nodes, held-out and edited-agent PSNR against ground truth."),
    Benchmark("dataset", DatasetOptions, run_dataset, "Annotated images per second (480x270 x 3 and 1600x900 x 6) "
              "and annotated variants per hour after fitting."),
    Benchmark("agents", AgentsOptions, run_agents, "The model pool (seconds per model), matching top-1/top-5 "
              "against degradation, and the paper's Table 4 (naive / online / pool / dual / pool with the vehicles' "
              "own models, after translate, rotate and overturn) on held-out worlds."),
    Benchmark("scaleout", ScaleoutOptions, run_scaleout, "generate_dataset on 8 scenes with 1 vs 2 Dask worker "
              "processes, the resume cost of a worker killed mid-fit, and a projection to 10 and 100 machines."),
    Benchmark("closedloop", ClosedloopOptions, run_closedloop, "Closed-loop testing: steps per second (1 x 640x360 "
              "and 6 x 800x450; render / policy / controller), the shipped policies' PDMS and HD-Score on logs vs "
              "behaviour-SCS variants, and 20 HUGSIM clients at once."),
    Benchmark("view", ViewOptions, run_view, "The viewer in headless chromium (software WebGL): time to first "
              "frame and orbiting frame rate of the splat view for 50k / 200k / 500k Gaussians, and the edit-to-camera-"
              "image latency at 640x360 against the 1 s target; a screenshot."),
    Benchmark("appearance", AppearanceOptions, run_appearance, "Appearance-level SCS against the world's exact "
              "ground truth: pool objects inserted upright, on the side and overturned at sampled poses and "
              "replacing a vehicle, in the fitted graph and in the world; object masked PSNR/SSIM (plain, + colour "
              "transform, + contact shadow) against the pool model in isolation, automatic 2D box IoU, placements "
              "re-checked against the world and the sampler's rejections per check."),
    Benchmark("background", BackgroundOptions, run_background, "Removing a large static object: naive removal, 2D "
              "inpainting only, least-squares depth, DRNet, DRNet + RoI refit and the default repair (planes + DRNet "
              "+ RoI refit) against the world re-rendered without it (hole PSNR/SSIM, depth AbsRel/delta, full PSNR, "
              "seconds), at held-out logged and novel views; RoI refit vs a full background refit."),
    Benchmark("downstream", DownstreamOptions, run_downstream, "The planning protocol (base vs fine-tuned with "
              "behaviour-SCS data; L2 and collision rate on a behaviour-SCS and the original test set) with the "
              "embedded proxy planner; with --detection, the detection protocol."),
    Benchmark("reliability", ReliabilityOptions, run_reliability, "Kill `omniscs generate` at random moments and "
              "rerun it (catalog and files must equal a clean run's, no temporaries, no orphaned server); run "
              "several at once on one workspace (each scene once per run)."),
    Benchmark("bad-inputs", BadInputsOptions, run_bad_inputs, "Try every bad input of the table over every "
              "command; count one clear line / traceback / silently wrong / left files / other, by category; then "
              "abuse the closed-loop server with a second token watching."),
)


# ----------------------------------------------------------------------------- one handler for all of them
def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of a dataclass (the string literal that follows its annotation), its base
    classes' fields included."""
    docs = {}
    for klass in reversed([k for k in cls.__mro__ if dataclasses.is_dataclass(k)]):
        body = ast.parse(textwrap.dedent(inspect.getsource(klass))).body[0].body
        for node, after in zip(body, body[1:]):
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) \
                    and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant) \
                    and isinstance(after.value.value, str):
                docs[node.target.id] = " ".join(after.value.value.split())
    return docs


def _handler(bench: Benchmark) -> Callable[..., None]:
    """A typer command whose options are ``--out`` and the fields of ``bench.options``."""
    hints = typing.get_type_hints(bench.options)
    docs = field_docs(bench.options)
    params = [inspect.Parameter("out", inspect.Parameter.KEYWORD_ONLY, annotation=Path, default=typer.Option(
        Path("reports"), help=f"Reports root: writes <out>/{bench.name}/report.json and report.md (+ pictures); a "
                              "rerun replaces them."))]
    for f in fields(bench.options):
        decls = [f.metadata["flag"]] if "flag" in f.metadata else []
        bounds = {k: f.metadata[k] for k in ("min", "max") if k in f.metadata}
        params.append(inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, annotation=hints[f.name],
                                        default=typer.Option(f.default, *decls, help=docs.get(f.name), **bounds)))

    def handler(**given) -> None:
        out = Path(given.pop("out"))
        options = bench.options(**given)
        with progress_bars() as bars:
            report = bench.run(options, out, bars)
        console.print(report.read_text())
        console.print(f"wrote {report.parent}")

    handler.__signature__ = inspect.Signature(params)
    handler.__doc__ = bench.help
    handler.__name__ = f"bench_{bench.name.replace('-', '_')}"
    return handler


for _bench in BENCHMARKS:
    app.command(_bench.name)(_handler(_bench))
