"""``omniscs bench``: the benchmarks (``omniscs.bench``); results go to reports/."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import typer

from omniscs.cli.common import comma_list, console, progress_bars
from omniscs.cli.common import seeds as parse_seeds
from omniscs.errors import OmniscsError

app = typer.Typer(help="Benchmarks; results go to reports/.", no_args_is_help=True)


@app.command("world")
def bench_world(
    seeds: str = typer.Option("0", help="Comma-separated seeds."),
    out: Path = typer.Option(Path("reports"), help="Folder for world_render.json/.md."),
    frames: int = typer.Option(40), cameras: int = typer.Option(3),
) -> None:
    """Time rendering a 40-frame, 3-camera 480x270 scene with LiDAR."""
    from omniscs.bench.world import run_world_benchmark

    result = run_world_benchmark(out, seeds=parse_seeds(seeds), n_frames=frames,
                                 n_cameras=cameras)
    console.print((out / "world_render.md").read_text())
    console.print(f"wrote {out / 'world_render.json'}")
    del result


@app.command("sources")
def bench_sources(
    out: Path = typer.Option(Path("reports"), help="Folder for sources_ingest.json/.md."),
    frames: int = typer.Option(10), cameras: int = typer.Option(6), repeats: int = typer.Option(3),
) -> None:
    """Time reading a 480x270 synthetic log back from nuScenes, KITTI and Waymo v2 (ms per frame)."""
    from omniscs.bench.sources import run_sources_benchmark

    run_sources_benchmark(out, n_frames=frames, n_cameras=cameras, repeats=repeats)
    console.print((out / "sources_ingest.md").read_text())
    console.print(f"wrote {out / 'sources_ingest.json'}")


@app.command("behavior")
def bench_behavior(
    out: Path = typer.Option(Path("reports"), help="Folder for behavior_bench.json/.md/.png."),
    scenes_per_template: int = typer.Option(5, help="Procedural scenes per road template."),
    variants: int = typer.Option(2, help="Variants per scene."),
    preset: str = typer.Option("balanced", help="Adversarial preset: fast, balanced or accurate."),
    checkpoint: Optional[Path] = typer.Option(None, help="Traffic-model checkpoint (default: the shipped one)."),
    rule_planner: bool = typer.Option(True, help="Also run against the reacting rule-based planner."),
    threads: int = typer.Option(1, help="torch CPU threads."),
    appearance_scenes: int = typer.Option(4, help="Rendered scenes fitted with a scene graph for the with/without "
                                                  "L_app comparison (0 skips it)."),
    workspace: Optional[Path] = typer.Option(None, help="Where those scenes and scene graphs go (and are reused)."),
    app_weights: str = typer.Option("1,30", help="Comma-separated L_app weights compared."),
    only_appearance: bool = typer.Option(False, help="Rerun only the L_app comparison in an existing report in --out."),
    seed_offset: int = typer.Option(2000, help="First scene seed: 2000 is the fixed set, any other a fresh one."),
    only_default: bool = typer.Option(False, help="Run only the default configuration on the procedural logs."),
    search_starts: int = typer.Option(192, help="Feasibility search: random starts per candidate adversary."),
) -> None:
    """Adversarial success, plausibility violations, accelerations and time per variant, with and without the
    plausibility penalty, with and without L_app (and its appearance drift), plus the traffic model's ADE/FDE."""
    from omniscs.scs.behavior.adversarial_config import adversarial_preset
    from omniscs.bench.behavior import BenchConfig, rerun_appearance_study, run_behavior_benchmark
    from omniscs.scs.behavior.feasibility import FeasibilityConfig

    adversarial_preset(preset)
    weights = comma_list(app_weights, float, "--app-weights", "1,30")
    if search_starts < 1:
        raise OmniscsError(f"--search-starts must be at least 1; got {search_starts}")
    if not weights or min(weights) <= 0:
        raise OmniscsError(f"--app-weights takes positive numbers like 1,30; got {app_weights!r}")
    config = BenchConfig(scenes_per_template=scenes_per_template, variants_per_scene=variants, preset=preset,
                         rule_planner=rule_planner, torch_threads=threads,
                         appearance_scenes=max(0, appearance_scenes), app_weights=weights,
                         seed_offset=seed_offset, only_default=only_default,
                         feasibility=FeasibilityConfig(starts=search_starts))
    if only_appearance:
        rerun_appearance_study(out, config, checkpoint, workspace)
        console.print((out / "behavior_bench.md").read_text())
        return
    with progress_bars() as bars:
        run_behavior_benchmark(out, config, checkpoint, progress=bars.sink("behaviour variants"),
                               workspace=workspace)
    console.print((out / "behavior_bench.md").read_text())
    console.print(f"wrote {out / 'behavior_bench.json'}")


@app.command("fit")
def bench_fit(
    out: Path = typer.Option(Path("reports"), help="Folder for fit_bench.json/.md/.png."),
    seeds: str = typer.Option("0", help="Comma-separated seeds of the procedural scenes."),
    presets: str = typer.Option("fast,balanced,accurate", help="Comma-separated presets."),
    template: str = typer.Option("straight"), frames: int = typer.Option(40), cameras: int = typer.Option(3),
    width: int = typer.Option(480), height: int = typer.Option(270),
    workspace: Optional[Path] = typer.Option(None, help="Where the benchmark scenes are rendered (and reused)."),
) -> None:
    """Fit the same scenes with each preset: wall time, Gaussians and held-out PSNR/SSIM; a time-vs-PSNR plot."""
    from omniscs.bench.fit import BenchScenes, run_fit_benchmark
    from omniscs.nsg.config import PRESETS

    chosen = comma_list(presets)
    unknown = [p for p in chosen if p not in PRESETS]
    if unknown or not chosen:
        raise OmniscsError(f"unknown preset(s) {unknown}; use some of {list(PRESETS)}")
    scenes = BenchScenes(parse_seeds(seeds), template, "day", frames, cameras, width, height)
    with progress_bars() as bars:
        run_fit_benchmark(out, scenes, chosen, workspace,
                          progress=bars.sink("bench fit"))
    console.print((out / "fit_bench.md").read_text())
    console.print(f"wrote {out / 'fit_bench.json'} and {out / 'fit_bench.png'}")


@app.command("edits")
def bench_edits(
    out: Path = typer.Option(Path("reports"), help="Folder for edits_bench.json/.md/.png."),
    seeds: str = typer.Option("0", help="Comma-separated seeds of the procedural scenes."),
    preset: str = typer.Option("balanced", help="Fit preset of the scene graphs."),
    agents: int = typer.Option(2, help="Edited agents per scene (the most visible ones)."),
    views: int = typer.Option(4, help="Evaluated views per agent and edit."),
    template: str = typer.Option("straight"), frames: int = typer.Option(40), cameras: int = typer.Option(3),
    width: int = typer.Option(480), height: int = typer.Option(270),
    workspace: Optional[Path] = typer.Option(None, help="Where the benchmark scenes are rendered (and reused)."),
) -> None:
    """Edit fidelity against ground truth: translate 2.0/3.5 m, rotate 90/180/270°; PSNR/SSIM full and masked."""
    from omniscs.bench.fit import BenchScenes, run_edit_benchmark
    from omniscs.nsg.config import fit_preset

    fit_preset(preset)
    if agents < 1 or views < 1:
        raise OmniscsError("--agents and --views must be at least 1")
    scenes = BenchScenes(parse_seeds(seeds), template, "day", frames, cameras, width, height)
    with progress_bars() as bars:
        run_edit_benchmark(out, scenes, preset, agents, views, workspace=workspace,
                           progress=bars.sink("bench fit"))
    console.print((out / "edits_bench.md").read_text())
    console.print(f"wrote {out / 'edits_bench.json'} and {out / 'edits_bench.png'}")


@app.command("render")
def bench_render(
    out: Path = typer.Option(Path("reports"), help="Folder for render_bench.json/.md/.png."),
    resolutions: str = typer.Option("320x180,640x360,1280x720", help="Comma-separated WxH."),
    counts: str = typer.Option("10000,100000,1000000", help="Comma-separated Gaussian counts."),
    repeats: int = typer.Option(5, help="Timed repeats per cell (median reported)."),
    reference_budget_s: float = typer.Option(60.0, help="Skip reference cells expected to take longer."),
) -> None:
    """Time the Gaussian rasterizer (forward, forward+backward) per backend; cpu/reference speed-up."""
    from omniscs.bench.render import run_render_benchmark

    sizes = comma_list(resolutions, lambda r: tuple(int(v) for v in r.lower().split("x")), "--resolutions",
                       "640x360,1280x720")
    ns = comma_list(counts, int, "--counts", "10000,100000")
    if not sizes or any(len(s) != 2 or min(s) < 1 for s in sizes) or not ns or min(ns) < 1:
        raise OmniscsError("--resolutions is like 640x360,1280x720 and --counts like 10000,100000")
    run_render_benchmark(out, resolutions=sizes, counts=ns, repeats=repeats, reference_budget_s=reference_budget_s)
    console.print((out / "render_bench.md").read_text())
    console.print(f"wrote {out / 'render_bench.json'}")


@app.command("plan")
def bench_plan(
    out: Path = typer.Option(Path("reports"), help="Folder for plan_bench.json/.md/.png."),
    scenes: str = typer.Option("straight:31,t_junction:32,intersection:33",
                               help="Comma-separated TEMPLATE:SEED procedural scenes."),
    preset: str = typer.Option("fast", help="Scene-graph preset of both modes."),
    variants: int = typer.Option(1, help="Behaviour variants requested per scene."),
    frames: int = typer.Option(40), cameras: int = typer.Option(3),
    width: int = typer.Option(480), height: int = typer.Option(270),
    min_pixels: int = typer.Option(200, help="Views count when the edited agent covers this many pixels."),
    workspace: Optional[Path] = typer.Option(None, help="Where the benchmark scenes are rendered (and reused)."),
) -> None:
    """The pipeline with the scene's plan vs with every track an agent node: time, Gaussians, nodes, held-out and
    edited-agent PSNR against ground truth."""
    from omniscs.bench.plan import PlanBenchConfig, run_plan_benchmark
    from omniscs.nsg.config import fit_preset

    fit_preset(preset)

    def template_seed(item: str) -> tuple[str, int]:
        template, seed = item.split(":")
        return template, int(seed)

    chosen = comma_list(scenes, template_seed, "--scenes", "straight:31,t_junction:32")
    if not chosen or variants < 0:
        raise OmniscsError("--scenes needs at least one TEMPLATE:SEED and --variants must be >= 0")
    config = PlanBenchConfig(scenes=chosen, n_frames=frames, n_cameras=cameras, width=width, height=height,
                             fit_preset=preset, behavior_variants=variants, min_pixels=min_pixels)
    with progress_bars() as bars:
        run_plan_benchmark(out, config, workspace, progress=bars.sink("bench plan"))
    console.print((out / "plan_bench.md").read_text())
    console.print(f"wrote {out / 'plan_bench.json'} and {out / 'plan_bench.png'}")


@app.command("dataset")
def bench_dataset(
    out: Path = typer.Option(Path("reports"), help="Folder for dataset_bench.json/.md/.png."),
    workspace: Optional[Path] = typer.Option(None, help="Where the scenes, fits and variants go (and are reused)."),
    variants: int = typer.Option(2, help="Behaviour variants per scene."),
) -> None:
    """Annotated images per second (480x270 x 3 and 1600x900 x 6) and annotated variants per hour after fitting."""
    from dataclasses import replace

    from omniscs.bench.dataset import DatasetBenchConfig, run_dataset_benchmark

    with progress_bars() as bars:
        run_dataset_benchmark(out, workspace, replace(DatasetBenchConfig(), variants=variants),
                              progress=bars.sink("dataset bench"))
    console.print((out / "dataset_bench.md").read_text())
    console.print(f"wrote {out / 'dataset_bench.json'}")


@app.command("agents")
def bench_agents(
    out: Path = typer.Option(Path("reports"), help="Folder for agents_bench.json/.md/.png."),
    workspace: Optional[Path] = typer.Option(None, help="Where the scenes, fits and the benchmark pool go (and are "
                                                        "reused)."),
    quick: bool = typer.Option(False, "--quick", help="One small scene, the fast preset, a small pool (a smoke run, "
                                                      "not a measurement)."),
    train_msnet: bool = typer.Option(False, "--train-msnet", help="Train MSNet again (MSNetDataConfig's data) "
                                                                  "and write it into the package (its shipped "
                                                                  "weights) before the benchmark."),
    matching_only: bool = typer.Option(False, "--matching-only", help="Matching alone (agents_matching.json/.md): "
                                                                      "minutes instead of hours, for a new MSNet."),
) -> None:
    """The model pool (seconds per model), matching top-1/top-5 against degradation, and the paper's Table 4
    (naive / online / pool / dual / pool with the vehicles' own models, after translate, rotate and overturn) on
    held-out worlds."""
    from omniscs.bench.agents import AgentsBenchConfig, quick_config, run_agents_benchmark, run_matching_benchmark
    from omniscs.bench.msnet_data import train_shipped_msnet

    if train_msnet:
        with progress_bars() as bars:
            info = train_shipped_msnet(workspace, progress=bars.sink("MSNet"))
        console.print(f"MSNet: {info['n_assets']} assets, loss {info['loss_first']:.3f} -> "
                      f"{info['loss_last']:.3f} in {info['seconds']:.0f} s")
    config = quick_config() if quick else AgentsBenchConfig()
    if matching_only:
        with progress_bars() as bars:
            run_matching_benchmark(out, workspace, config, progress=bars.sink("agents matching"))
        console.print((out / "agents_matching.md").read_text())
        return
    with progress_bars() as bars:
        run_agents_benchmark(out, workspace, config, progress=bars.sink("agents bench"))
    console.print((out / "agents_bench.md").read_text())
    console.print(f"wrote {out / 'agents_bench.json'} and {out / 'agents_bench.png'}")


@app.command("scaleout")
def bench_scaleout(
    out: Path = typer.Option(Path("reports"), help="Folder for scaleout_bench.json/.md/.png."),
    workspace: Path = typer.Option(Path("omniscs-data/bench-scaleout"), help="Scratch workspace (emptied per run)."),
    quick: bool = typer.Option(False, help="A tiny set-up that checks the code path (not for numbers)."),
) -> None:
    """generate_dataset on 8 scenes with 1 vs 2 Dask worker processes, the resume cost of a worker killed mid-fit,
    and a projection to 10 and 100 machines."""
    import os

    from omniscs.cli.prefect_api import prefect_api

    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    from flows.bench_scaleout import ScaleoutBenchConfig, quick_config, run_scaleout_benchmark

    with progress_bars() as bars, prefect_api():
        run_scaleout_benchmark(out, workspace, quick_config() if quick else ScaleoutBenchConfig(),
                               progress=bars.sink("scale-out bench"))
    console.print((out / "scaleout_bench.md").read_text())
    console.print(f"wrote {out / 'scaleout_bench.json'} and {out / 'scaleout_bench.png'}")


@app.command("closedloop")
def bench_closedloop(
    out: Path = typer.Option(Path("reports"), help="Folder for closedloop_bench.json/.md/.png."),
    workspace: Optional[Path] = typer.Option(None, help="Workspace for the benchmark's scenes and fits (default "
                                                        "$OMNISCS_HOME or ./omniscs-data)."),
    quick: bool = typer.Option(False, help="A tiny set-up that checks the code path (not for numbers)."),
) -> None:
    """Closed-loop testing: steps per second (1 x 640x360 and 6 x 800x450; render / policy / controller), the
    shipped policies' PDMS and HD-Score on logs vs behaviour-SCS variants, and 20 HUGSIM clients at once."""
    from omniscs.bench.closedloop import ClosedLoopBenchConfig, quick_config, run_closedloop_benchmark

    with progress_bars() as bars:
        run_closedloop_benchmark(out, workspace, quick_config() if quick else ClosedLoopBenchConfig(),
                                 progress=bars.sink("closed-loop bench"))
    console.print((out / "closedloop_bench.md").read_text())
    console.print(f"wrote {out / 'closedloop_bench.json'} and {out / 'closedloop_bench.png'}")


@app.command("appearance")
def bench_appearance(
    out: Path = typer.Option(Path("reports"), help="Folder for appearance_bench.json/.md/.png."),
    workspace: Optional[Path] = typer.Option(None, help="Where the scenes, fits and the benchmark pool go (reused)."),
    quick: bool = typer.Option(False, "--quick", help="The development log, one case (a smoke run, not a "
                                                      "measurement)."),
) -> None:
    """Appearance-level SCS against the world's exact ground truth: pool objects inserted upright, on the side and
    overturned at sampled poses and replacing a vehicle, in the fitted graph and in the world; object masked
    PSNR/SSIM (plain, + colour transform, + contact shadow) against the pool model in isolation, automatic 2D box
    IoU, placements re-checked against the world and the sampler's rejections per check."""
    from omniscs.bench.appearance import AppearanceBenchConfig, quick_config, run_appearance_benchmark

    with progress_bars() as bars:
        run_appearance_benchmark(out, workspace, quick_config() if quick else AppearanceBenchConfig(),
                                 progress=bars.sink("appearance bench"))
    console.print((out / "appearance_bench.md").read_text())
    console.print(f"wrote {out / 'appearance_bench.json'} and {out / 'appearance_bench.png'}")


@app.command("background")
def bench_background(
    out: Path = typer.Option(Path("reports"), help="Folder for background_bench.json/.md/.png."),
    workspace: Optional[Path] = typer.Option(None, help="Where the scenes and fits go (and are reused)."),
    quick: bool = typer.Option(False, "--quick", help="One dev scene, one novel offset, few steps (a smoke run, not "
                                                      "a measurement)."),
    train_depth: bool = typer.Option(False, "--train-depth", help="Train the embedded relative-depth network again "
                                                                  "on procedural renders and write it into the "
                                                                  "package (its shipped weights) before the "
                                                                  "benchmark."),
    depth_device: str = typer.Option("cpu", "--depth-device", help="Device of --train-depth ('cuda' on a GPU "
                                                                   "machine: minutes; on 2 CPUs: hours)."),
    export_depth_data: Optional[Path] = typer.Option(None, "--export-depth-data", help="Only write the relative-"
                                                     "depth network's training data to this file (a depth pack) "
                                                     "for infra/depth_gpu/train.py on a GPU machine, and stop."),
    install_depth: Optional[Path] = typer.Option(None, "--install-depth", help="Only evaluate the weights that "
                                                 "infra/depth_gpu/train.py wrote into this folder on the held-out "
                                                 "worlds and install them as the shipped ones, and stop."),
    export_inpaint_data: Optional[Path] = typer.Option(None, "--export-inpaint-data", help="Only write the "
                                                       "inpainting network's repair pairs to this file (an inpainting "
                                                       "pack) for infra/inpaint_gpu/train.py, and stop."),
    inpaint_seeds: int = typer.Option(0, "--inpaint-seeds", help="With --export-inpaint-data: only this many of the "
                                                                 "training worlds (0: all), to fit a transfer limit."),
    install_inpaint: Optional[Path] = typer.Option(None, "--install-inpaint", help="Only evaluate the weights that "
                                                   "infra/inpaint_gpu/train.py wrote into this folder on the held-out "
                                                   "worlds against OpenCV's inpainters and install them as the "
                                                   "shipped ones, and stop."),
    no_ablations: bool = typer.Option(False, "--no-ablations", help="Only the main rows (naive, hidden Gaussians "
                                                                    "removed, the issue's rows, the default repair): "
                                                                    "about half the time."),
    ablation: Optional[list[str]] = typer.Option(None, "--ablation", help="Only this ablation row (repeatable; "
                                                 "default: all of them), e.g. 'planes + DRNet + RoI refit, planes "
                                                 "first where the cleaned background covers'."),
) -> None:
    """Removing a large static object: naive removal, 2D inpainting only, least-squares depth, DRNet, DRNet +
    RoI refit and the default repair (planes + DRNet + RoI refit) against the world re-rendered without it (hole
    PSNR/SSIM, depth AbsRel/delta, full PSNR, seconds), at held-out logged and novel views; RoI refit vs a full
    background refit."""
    from omniscs.bench.background import BackgroundBenchConfig, quick_config, run_background_benchmark

    if export_depth_data is not None:
        from omniscs.bench.depth_data import export_depth_data as export

        with progress_bars() as bars:
            facts = export(export_depth_data, workspace, progress=bars.sink("depth data"))
        console.print(f"wrote {facts['n_images']} training images ({facts['bytes'] / 2**20:.1f} MiB) to "
                      f"{export_depth_data}")
        return
    if export_inpaint_data is not None:
        from omniscs.bench.inpaint_data import InpaintDataConfig, export_inpaint_data as export_pairs

        data = InpaintDataConfig()
        if inpaint_seeds:
            data = dataclasses.replace(data, train_seeds=data.train_seeds[:inpaint_seeds])
        with progress_bars() as bars:
            facts = export_pairs(export_inpaint_data, workspace, data, progress=bars.sink("inpainting data"))
        console.print(f"wrote {facts['n_pairs']} repair pairs ({facts['bytes'] / 2**20:.1f} MiB) to "
                      f"{export_inpaint_data}")
        return
    if install_inpaint is not None:
        from omniscs.bench.inpaint_data import install_trained_inpaint

        info = install_trained_inpaint(install_inpaint, workspace=workspace)
        ev = info["evaluation"]
        console.print(f"installed the inpainting weights from {install_inpaint}: held-out hole PSNR "
                      f"{ev['embedded']['hole_psnr_mean']:.2f} dB (OpenCV FSR {ev['fsr_fast']['hole_psnr_mean']:.2f}, "
                      f"Telea {ev['telea']['hole_psnr_mean']:.2f}) over {ev['n_pairs']} pairs")
        return
    if install_depth is not None:
        from omniscs.bench.depth_data import install_trained_depth

        info = install_trained_depth(install_depth)
        console.print(f"installed the relative-depth weights from {install_depth}: held-out AbsRel "
                      f"{info['evaluation']['embedded']['images']['absrel_mean']:.3f}, in repair holes "
                      f"{info['evaluation']['embedded']['repair_hole']['absrel_mean']:.3f}")
        return
    if train_depth:
        from omniscs.bench.depth_data import train_shipped_depth

        with progress_bars() as bars:
            info = train_shipped_depth(workspace, progress=bars.sink("relative depth"), device=depth_device)
        console.print(f"relative depth: {info['n_images']} images, loss {info['loss_first']:.3f} -> "
                      f"{info['loss_last']:.3f} in {info['seconds']:.0f} s")
    with progress_bars() as bars:
        config = quick_config() if quick else BackgroundBenchConfig()
        if no_ablations:
            config = dataclasses.replace(config, full_comparison=False)
        if ablation:
            config = dataclasses.replace(config, ablations=tuple(ablation))
        run_background_benchmark(out, workspace, config, progress=bars.sink("background bench"))
    console.print((out / "background_bench.md").read_text())
    console.print(f"wrote {out / 'background_bench.json'} and {out / 'background_bench.png'}")


@app.command("downstream")
def bench_downstream(
    out: Path = typer.Option(Path("reports"), help="Folder for downstream_bench.json/.md/.png."),
    workspace: Optional[Path] = typer.Option(None, help="Where the benchmark's variants and solutions go (and are "
                                                        "reused)."),
    train_base: bool = typer.Option(False, "--train-base", help="Train the base proxy planner again on the train "
                                                                "logs and write it into the package (its shipped "
                                                                "weights)."),
    quick: bool = typer.Option(False, "--quick", help="A few scenes and epochs (a smoke run, not a measurement)."),
    detection: bool = typer.Option(False, "--detection", help="The detection protocol instead (base vs fine-tuned "
                                                              "with appearance-SCS data; mAP/NDS on an "
                                                              "appearance-SCS and the original test set) with the "
                                                              "embedded proxy camera detector: "
                                                              "downstream_detection_bench.*."),
) -> None:
    """The planning protocol (base vs fine-tuned with behaviour-SCS data; L2 and collision rate on a behaviour-SCS
    and the original test set) with the embedded proxy planner; with --detection, the detection protocol."""
    if detection:
        from omniscs.bench.detection_protocol import DetectionProtocolConfig, quick_config as quick_detection, \
            run_detection_protocol

        with progress_bars() as bars:
            run_detection_protocol(out, workspace, quick_detection() if quick else DetectionProtocolConfig(),
                                   progress=bars.sink("detection protocol"))
        console.print((out / "downstream_detection_bench.md").read_text())
        console.print(f"wrote {out / 'downstream_detection_bench.json'}")
        return
    from omniscs.bench.downstream import DownstreamBenchConfig, quick_config, run_downstream_benchmark

    with progress_bars() as bars:
        run_downstream_benchmark(out, workspace, quick_config() if quick else DownstreamBenchConfig(),
                                 train_base=train_base, progress=bars.sink("downstream bench"))
    console.print((out / "downstream_bench.md").read_text())
    console.print(f"wrote {out / 'downstream_bench.json'}")


@app.command("reliability")
def bench_reliability(
    out: Path = typer.Option(Path("reports"), help="Folder for reliability.json/.md."),
    kills: int = typer.Option(10, help="SIGKILL moments of the fault-injection check (each then rerun)."),
    processes: int = typer.Option(4, help="Concurrent generate processes of the concurrency check."),
    seed: int = typer.Option(2026, help="Seed of the kill moments."),
) -> None:
    """Kill `omniscs generate` at random moments and rerun it (catalog and files must equal a clean run's, no
    temporaries, no orphaned server); run several at once on one workspace (each scene once per run)."""
    from omniscs.bench.reliability import ReliabilityConfig, run_bench

    if not 1 <= kills <= 100 or not 2 <= processes <= 16 or seed < 0:
        raise OmniscsError("--kills must be 1..100, --processes 2..16 and --seed >= 0")
    with progress_bars() as bars:
        run_bench(ReliabilityConfig(kills=kills, processes=processes, seed=seed), out,
                  progress=bars.sink("bench reliability"))
    console.print((out / "reliability.md").read_text())
    console.print(f"wrote {out / 'reliability.json'}")


@app.command("bad-inputs")
def bench_bad_inputs(
    out: Path = typer.Option(Path("reports"), help="Folder for bad_inputs.json/.md."),
    subprocess_mode: bool = typer.Option(False, "--subprocess", help="Run each case as a new omniscs process "
                                                                     "(slower; in-process by default)."),
) -> None:
    """Try every bad input of the table over every command; count one clear line / traceback / silently wrong /
    left files / other, by category."""
    from omniscs.bench.bad_inputs import run_bench

    with progress_bars() as bars:
        run_bench(out, subprocess_mode=subprocess_mode, progress=bars.sink("bench bad-inputs"))
    console.print((out / "bad_inputs.md").read_text())
    console.print(f"wrote {out / 'bad_inputs.json'}")
