"""``omniscs pretrained``: the shipped weights (``omniscs.pretrained``): list them, verify them, train them again."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import typer

from omniscs.cli.common import console, print_table, progress_bars
from omniscs.errors import OmniscsError

app = typer.Typer(help="The shipped weights: list, verify, train again.", no_args_is_help=True)


@app.command("list")
def pretrained_list() -> None:
    """Every shipped model: its files, sizes, sha256 prefixes and whether the files on disk match the registry."""
    from omniscs.pretrained.registry import PREFIX, entries, mismatches

    rows = []
    for model in entries().values():
        bad = mismatches(model)
        for f in model.files:
            rows.append({"model": model.name, "file": f.name, "size": f"{f.size / 2**20:.2f} MiB",
                         "sha256": f.sha256[:PREFIX],
                         "verified": "no" if any(str(model.folder / f.name) in line for line in bad) else "yes"})
    print_table(rows, title="shipped weights (omniscs/pretrained/registry.json)")


@app.command("verify")
def pretrained_verify(
    name: Optional[list[str]] = typer.Argument(None, help="Models to check (default: all)."),
) -> None:
    """Hash every file of the shipped models against the registry; a changed or missing file is one error line
    (exit 2) saying how to restore it."""
    from omniscs.pretrained.registry import entries, entry, verify

    names = list(name or entries())
    for n in names:
        entry(n)
    for n in names:
        verify(n)
    console.print(f"verified {len(names)} shipped model(s): every file matches the registry")


@app.command("train")
def pretrained_train(
    name: str = typer.Argument(..., help="The shipped model to make again: behavior, planner, detector, msnet, "
                                         "reldepth or inpaint."),
    workspace: Optional[Path] = typer.Option(None, help="Where training data are rendered and cached (detector, "
                                                        "msnet, reldepth, inpaint; default $OMNISCS_HOME)."),
    device: str = typer.Option("cpu", help="reldepth: the device of in-process training ('cuda' on a GPU machine: "
                                           "minutes; on 2 CPUs: hours)."),
    export_data: Optional[Path] = typer.Option(None, "--export-data", help="reldepth, inpaint: only write the "
                                               "training data to this pack for infra/<depth|inpaint>_gpu/train.py on "
                                               "a GPU machine, and stop."),
    install: Optional[Path] = typer.Option(None, "--install", help="reldepth, inpaint: only evaluate the weights "
                                           "that infra/<depth|inpaint>_gpu/train.py wrote into this folder on the "
                                           "held-out worlds and install them as the shipped ones."),
    data_seeds: int = typer.Option(0, "--data-seeds", help="inpaint --export-data: only this many of the training "
                                                           "worlds (0: all), to fit a transfer limit."),
) -> None:
    """Train a shipped model again with the command its registry entry names, write it into the package and record
    its new hashes in the registry. The weights only match the code they were trained with: retrain after changing
    anything that feeds a model."""
    from omniscs.pretrained.registry import entry, folder, register

    entry(name)
    if (export_data or install) and name not in ("reldepth", "inpaint"):
        raise OmniscsError(f"--export-data and --install are for reldepth and inpaint; {name} trains here")
    if export_data and install:
        raise OmniscsError("give --export-data or --install, not both")
    out = folder(name)
    with progress_bars() as bars:
        sink = bars.sink(name)
        if name == "behavior":
            from omniscs.pipeline.procedural import procedural_traffic
            from omniscs.scs.behavior.train import train_model, train_preset

            _, record = train_model(train_preset("balanced", seed=0, torch_threads=1), procedural_traffic, out,
                                    command="omniscs pretrained train behavior",
                                    progress=lambda stage, done, total: bars.sink(stage)(done, total),
                                    overwrite=True)
            summary = f"held-out moving ADE {record['heldout_metrics']['moving']['posterior']['ade']:.2f} m"
        elif name == "planner":
            from omniscs.training.planner import train_shipped_planner

            _, record = train_shipped_planner(out=out, progress=sink)
            summary = f"{record['n_examples']} examples, final loss {record['epoch_loss_m'][-1]:.3f} m"
        elif name == "detector":
            from omniscs.training.detector import ShippedDetectorConfig, train_shipped_detector

            _, record = train_shipped_detector(workspace, ShippedDetectorConfig(), out, progress=sink)
            summary = f"{record['n_images']} images, {record['n_boxes']} boxes"
        elif name == "msnet":
            from omniscs.training.msnet import train_shipped_msnet

            info = train_shipped_msnet(workspace, out=out, progress=sink)
            summary = f"{info['n_assets']} assets, loss {info['loss_first']:.3f} -> {info['loss_last']:.3f}"
        elif name == "reldepth":
            from omniscs.training import reldepth

            if export_data:
                facts = reldepth.export_depth_data(export_data, workspace, progress=sink)
                console.print(f"wrote {facts['n_images']} training images ({facts['bytes'] / 2**20:.1f} MiB) to "
                              f"{export_data}")
                return
            info = (reldepth.install_trained_depth(install, out=out) if install
                    else reldepth.train_shipped_depth(workspace, progress=sink, out=out, device=device))
            summary = (f"held-out AbsRel {info['evaluation']['embedded']['images']['absrel_mean']:.3f}, in repair "
                       f"holes {info['evaluation']['embedded']['repair_hole']['absrel_mean']:.3f}")
        else:  # inpaint: trained on a GPU machine from an exported pack
            from omniscs.training import inpaint

            if export_data:
                data = inpaint.InpaintDataConfig()
                if data_seeds:
                    data = dataclasses.replace(data, train_seeds=data.train_seeds[:data_seeds])
                facts = inpaint.export_inpaint_data(export_data, workspace, data, progress=sink)
                console.print(f"wrote {facts['n_pairs']} repair pairs ({facts['bytes'] / 2**20:.1f} MiB) to "
                              f"{export_data}")
                return
            if not install:
                raise OmniscsError("inpaint trains on a GPU machine: run `omniscs pretrained train inpaint "
                                   "--export-data PACK`, infra/inpaint_gpu/train.py PACK OUT there, then "
                                   "`omniscs pretrained train inpaint --install OUT`")
            info = inpaint.install_trained_inpaint(install, out=out, workspace=workspace)
            ev = info["evaluation"]
            summary = (f"held-out hole PSNR {ev['embedded']['hole_psnr_mean']:.2f} dB (OpenCV FSR "
                       f"{ev['fsr_fast']['hole_psnr_mean']:.2f}, Telea {ev['telea']['hole_psnr_mean']:.2f})")
    register(name)
    console.print(f"wrote {out} and its hashes into the registry: {summary}")
