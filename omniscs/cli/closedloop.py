"""``omniscs closedloop run / serve``: drive a policy inside an edited world (the closed_loop_eval flow), or serve a
scene graph over HUGSIM's HTTP protocol so HUGSIM's own client (or any driving stack speaking it) can drive."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import typer

from omniscs.cli.common import console

app = typer.Typer(help="Closed-loop testing inside the edited world: run a policy, or serve HUGSIM's protocol.",
                  no_args_is_help=True)


@app.command("run")
def run(
    scenarios: list[str] = typer.Argument(..., help="SCENE_ID/log or SCENE_ID/VARIANT_ID (a behaviour variant); "
                                                    "repeat for several."),
    policy: str = typer.Option("rule", help="replay, rule, proxy, proxy:PATH, or http://HOST:PORT (a DriveArena "
                                            "driver)."),
    steps: Optional[int] = typer.Option(None, help="Stop after this many steps (default: the scenario's end)."),
    out: Optional[Path] = typer.Option(None, help="Folder for the run folders (default: the workspace's "
                                                  "closedloop/<eval id>/)."),
    reactive: bool = typer.Option(False, help="Agents brake (IDM) when the ego is ahead in their path."),
    camera: list[str] = typer.Option([], "--camera", help="Render these cameras only (repeat; default all)."),
    width: Optional[int] = typer.Option(None, min=8, max=4096, help="Render width in pixels (default the camera's)."),
    workspace: Optional[Path] = typer.Option(None, help="Workspace root (default $OMNISCS_HOME or ./omniscs-data)."),
    run_id: Optional[str] = typer.Option(None, help="Run id (default: time-stamped)."),
    task_runner: str = typer.Option("threads", help="Where scenarios run: threads or dask (see omniscs generate)."),
    workers: int = typer.Option(1, help="Scenarios at once (threads) or local Dask worker processes."),
    dask_address: Optional[str] = typer.Option(None, help="tcp://HOST:PORT of an existing Dask scheduler."),
    ttc: str = typer.Option("ours", help="How EPDMS scores time to collision: ours (PDMS's check: every agent at "
                                         "constant velocity) or navsim (NAVSIM's: only the ego moves, agents at "
                                         "their recorded positions)."),
) -> None:
    """Drive each scenario with the policy, score it (PDMS, EPDMS, HD-Score, route completion) and write a run folder
    (run.json, steps.json, bev.png, frames.png, replay.gif; replay.json and frames/ for `omniscs view RUN`) and a
    closed_loop_runs catalog row."""
    import os

    from omniscs.cli.prefect_api import prefect_api
    from omniscs.ids import check_id
    from omniscs.pipeline.closedloop import parse_ref, resolve
    from omniscs.scene import load_scene
    from omniscs.storage import check_output, workspace_path

    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    if steps is not None and steps < 1:
        raise typer.BadParameter("must be >= 1", param_hint="--steps")
    from omniscs.closedloop.epdms import TTC_MODES

    if ttc not in TTC_MODES:
        raise typer.BadParameter(f"choose one of {', '.join(TTC_MODES)}", param_hint="--ttc")
    if run_id is not None:
        check_id("run id", run_id)
    if out is not None:
        out = check_output(out, follow=True)
    ws = workspace_path(workspace)
    for ref in scenarios:  # unknown scenes, graphs, variants and cameras fail here, before Prefect starts
        parse_ref(ref)
        check_cameras(load_scene(resolve(ws, ref).scene_path), camera)
    from flows.runners import check_runner

    check_runner(task_runner, None if dask_address else workers, dask_address)
    from omniscs.closedloop.policies import make_policy

    if not policy.startswith(("http://", "https://")):
        make_policy(policy)
    from flows.closedloop import closed_loop_eval

    with prefect_api():
        result = closed_loop_eval(list(scenarios), policy=policy, workspace=str(ws), run_id=run_id,
                                  reactive=reactive, max_steps=steps, cameras=list(camera) or None, width=width,
                                  out_dir=str(out) if out is not None else None, task_runner=task_runner,
                                  workers=None if dask_address else workers, dask_address=dask_address,
                                  ttc=ttc)
    from rich.table import Table

    table = Table(title=f"closed loop: {policy} (run {result['run_id']}, evaluation {result['eval_id']})")
    for col in ("scenario", "ended", "PDMS", "EPDMS", "HD-Score", "RC"):
        table.add_column(col, justify="left" if col in ("scenario", "ended") else "right")
    for r in result["runs"]:
        table.add_row(str(r.get("scenario_id")), str(r.get("reason")), _num(r.get("pdms")), _num(r.get("epdms")),
                      _num(r.get("hd_score")), _num(r.get("route_completion")))
    console.print(table)
    console.print(f"EPDMS: TTC scored as {ttc}; no traffic lights in the world (TLC 1); sub-scores in each run.json")
    console.print(f"see: omniscs catalog query \"SELECT scenario_id, reason, pdms, epdms, hd_score, route_completion, "
                  f"run_path FROM closed_loop_runs WHERE run_id = '{result['run_id']}'\"")


def _num(v) -> str:
    return "n/a" if v is None else f"{float(v):.3f}"


def check_cameras(scene, cameras: list[str]) -> None:
    """Every asked-for camera is one of the scene's (one line naming them otherwise)."""
    from omniscs.errors import ValidationError

    unknown = [c for c in cameras if c not in scene.camera_names]
    if unknown:
        raise ValidationError(f"--camera {', '.join(unknown)}: not a camera of scene {scene.scene_id}; it has "
                              f"{', '.join(scene.camera_names)}")


#: Environment variable with accepted tokens (separated by commas or newlines), read beside --token/--token-file.
TOKENS_ENV = "OMNISCS_SERVER_TOKENS"


def server_tokens(given: list[str], token_file: Path | None, env: str | None) -> list[str]:
    """The accepted tokens from the command line, a token file and the environment; at least one, none empty."""
    from omniscs.errors import ValidationError

    tokens = list(given)
    if token_file is not None:
        try:
            if not token_file.is_file():
                raise ValidationError(f"--token-file {token_file} is not a file")
            text = token_file.read_bytes().decode("utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ValidationError(f"--token-file {token_file} cannot be read as text ({exc})") from None
        tokens += [t.strip() for t in text.splitlines() if t.strip() and not t.strip().startswith("#")]
    if env:
        tokens += [t.strip() for t in env.replace(",", "\n").splitlines() if t.strip()]
    if not tokens:
        raise ValidationError(f"the server needs at least one auth token: give --token-file FILE (one per line), set "
                              f"${TOKENS_ENV}, or --token VALUE")
    if any(len(t) > 4096 or not t.isprintable() for t in tokens):
        raise ValidationError("an auth token must be printable text of at most 4096 characters")
    return sorted(set(tokens))


def check_bindable(host: str, port: int) -> None:
    """One clear error when ``host`` does not resolve or ``host:port`` cannot be bound (in use, not ours)."""
    import socket

    from omniscs.errors import ValidationError

    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except (socket.gaierror, UnicodeError, OverflowError) as exc:
        raise ValidationError(f"--host {host!r} does not resolve to an address here ({exc})") from None
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as exc:
            raise ValidationError(f"cannot serve on {host}:{port}: {exc.strerror or exc}; choose another --port "
                                  "or stop what holds it") from None


@app.command("serve")
def serve(
    checkpoint: Optional[Path] = typer.Option(None, help="Scene-graph checkpoint (default: the scene's newest)."),
    scenario: list[str] = typer.Option(..., "--scenario", help="SCENE_ID/log or SCENE_ID/VARIANT_ID served (repeat; "
                                                               "one scene); clients run them in order."),
    token: list[str] = typer.Option([], "--token", help="An accepted auth-token header value (repeat); each token "
                                                        "gets its own sessions. Other local users can read a command "
                                                        "line: prefer --token-file or $OMNISCS_SERVER_TOKENS."),
    token_file: Optional[Path] = typer.Option(None, help="A file of accepted tokens, one per line (blank lines and "
                                                         "lines starting with # are skipped)."),
    host: str = typer.Option("127.0.0.1", help="Address to bind (loopback unless told otherwise)."),
    port: int = typer.Option(8065, min=1, max=65535, help="Port (HUGSIM's client defaults to 8065)."),
    camera: list[str] = typer.Option([], "--camera", help="Render these cameras only (repeat; default all)."),
    width: Optional[int] = typer.Option(None, min=8, max=4096, help="Render width in pixels (default the camera's)."),
    reactive: bool = typer.Option(False, help="Agents brake (IDM) when the ego is ahead in their path."),
    out: Optional[Path] = typer.Option(None, help="Write each finished episode's run folder here."),
    max_sessions: int = typer.Option(32, min=1, max=4096, help="Open sessions at most, over all tokens."),
    sessions_per_token: Optional[int] = typer.Option(None, min=1, help="Open sessions one token may hold (default "
                                                                       "a fair share: max-sessions / tokens)."),
    requests_per_s: float = typer.Option(20.0, min=0.01, max=100_000.0, help="Requests per second one token may "
                                                                              "make (after a burst of 40)."),
    workspace: Optional[Path] = typer.Option(None, help="Workspace root (default $OMNISCS_HOME or ./omniscs-data)."),
) -> None:
    """Serve HUGSIM's HTTP protocol (GET /, POST /reset, GET /get_current_state, POST /execute_action) over one
    scene graph, so HUGSIM's client (hugsim-client) drives the edited world unchanged."""
    from omniscs.closedloop.simulator import ClosedLoopConfig, Simulator
    from omniscs.errors import ValidationError
    from omniscs.pipeline.closedloop import load_world, resolve
    from omniscs.server.hugsim import ServerConfig, create_app
    from omniscs.server.transport import serve as serve_app
    from omniscs.storage import workspace_path

    if any(not t for t in token):
        raise typer.BadParameter("a token must not be empty", param_hint="--token")
    if sessions_per_token is not None and sessions_per_token > max_sessions:
        raise typer.BadParameter(f"at most --max-sessions ({max_sessions})", param_hint="--sessions-per-token")
    token = server_tokens(token, token_file, os.environ.get(TOKENS_ENV))
    server_config = ServerConfig(out_dir=str(out) if out else None, max_sessions=max_sessions,
                                 max_sessions_per_token=sessions_per_token, requests_per_s=requests_per_s)
    check_bindable(host, port)  # an unknown host or a port in use: one line now, not uvicorn's log at the end
    ws = workspace_path(workspace)
    refs = [resolve(ws, s, checkpoint) for s in scenario]
    if len({r.scene_id for r in refs}) != 1:
        raise ValidationError("serve one scene's scenarios at a time (one scene graph per server)")
    worlds = [load_world(r) for r in refs]
    scene, graph = worlds[0][0], worlds[0][1]
    scenarios = {r.scenario_id: w[2] for r, w in zip(refs, worlds)}
    config = ClosedLoopConfig(cameras=tuple(camera) if camera else None, width=width, reactive=reactive)
    Simulator(graph, scene, config)  # camera and size errors now, not at the first request

    def make_simulator() -> Simulator:
        return Simulator(graph, scene, config)

    app_ = create_app(make_simulator, scenarios, set(token), server_config)
    per_token = server_config.sessions_per_token(len(token))
    console.print(f"serving {', '.join(scenarios)} on http://{host}:{port} ({len(token)} token(s), "
                  f"{per_token} session(s) and {requests_per_s:g} requests/s each)")
    serve_app(app_, host=host, port=port)
