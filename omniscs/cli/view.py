"""``omniscs view``: a scene store, a fitted scene graph, a dataset or a closed-loop run in the browser (viser), with
agent edits saved as an edit spec."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from omniscs.cli.common import console, print_error, progress_bars
from omniscs.errors import OmniscsError

#: Hosts that reach only this machine; any other --host serves the viewer (and its save button) to the network.
LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


def view(
    target: Path = typer.Argument(..., help="A scene-graph checkpoint folder (omniscs fit --out), a scene store "
                                            "(omniscs ingest, omniscs world make), a dataset (omniscs dataset "
                                            "build), a closed-loop run folder (omniscs closedloop run --out: "
                                            "replayed step by step with its scores) or a workspace's variants "
                                            "folder (variants/<scene id>/<stage>-<key>: opened on the scene's "
                                            "graph, store and pool)."),
    port: int = typer.Option(8080, min=1, max=65535, help="Port to serve on (the next free one when taken)."),
    host: str = typer.Option("127.0.0.1", help="Address to bind; anything but this machine's loopback serves the "
                                               "viewer to the network, without a password."),
    frame: int = typer.Option(0, min=0, help="Frame shown first."),
    splats: int = typer.Option(200_000, min=1, help="Most Gaussians drawn (the most opaque are kept)."),
    scene: Optional[Path] = typer.Option(None, help="With a checkpoint: the scene store it was fitted to (logged "
                                                    "images beside rendered ones, the road map)."),
    pool: Optional[Path] = typer.Option(None, help="With a checkpoint: a model pool whose models can replace agents "
                                                   "or be inserted (render the saved spec with the same --pool)."),
    variants: Optional[Path] = typer.Option(None, help="With a checkpoint: a variants.json of the behaviour or "
                                                       "appearance stage (or its folder) to pick variants from."),
    edits_out: Optional[Path] = typer.Option(None, help="Where 'Save edits' writes the edit spec (default "
                                                        "<scene id>-edits.json here); changeable in the panel."),
) -> None:
    """Open TARGET in a browser viewer at http://HOST:PORT: splats or LiDAR, boxes, trajectories, the rig, the
    camera view through our renderer; move, turn, remove, re-model and insert agents of a fitted graph and save the
    edits as a spec that `omniscs render --edit @spec.json` takes; replay a closed-loop run's steps (ego path,
    agents, contacts, the frames the policy saw, PDMS and EPDMS sub-scores). Serves until Ctrl-C."""
    from omniscs.progress import Stopped
    from omniscs.viewer.app import serve
    from omniscs.viewer.targets import open_target
    from omniscs.viewer.state import ViewerConfig

    config = ViewerConfig(splat_budget=splats)
    if host not in LOCAL_HOSTS:
        print_error(f"serving on {host}: anyone who reaches {host}:{port} can see this scene and save edit files on "
                    "this machine (no password); use the default --host 127.0.0.1 and an SSH tunnel to stay private",
                    label="warning", style="yellow")
    with progress_bars() as bars:
        opened = open_target(target, config, progress=bars.sink("loading"), scene=scene, pool=pool,
                             variants=variants)
    try:
        serve(opened, host=host, port=port, frame=frame, config=config, edits_out=edits_out,
              ready=lambda url: console.print(f"omniscs view: {opened.scene_id} ({opened.kind}) at {url}  "
                                              "(Ctrl-C stops)"))
    except (KeyboardInterrupt, Stopped):
        console.print("viewer stopped")
    except OSError as exc:  # e.g. the address cannot be bound
        raise OmniscsError(f"cannot serve on {host}:{port} ({exc.strerror or exc}); choose another --host or --port") \
            from None
