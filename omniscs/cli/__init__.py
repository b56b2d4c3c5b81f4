"""The ``omniscs`` command line: the top floor. Each command group lives in its own module; a handler parses its
options and calls the pipeline's stages (or the flow), nothing more."""
from __future__ import annotations

import sys

import typer

from omniscs.cli import bench, catalog, generate, nsg, scene, scs, world
from omniscs.cli.common import print_error
from omniscs.errors import OmniscsError

app = typer.Typer(help="OmniSCS data factory: safety-critical driving scenarios from ordinary logs.",
                  pretty_exceptions_enable=False, no_args_is_help=True)
app.command("generate")(generate.generate)
app.command("demo")(generate.demo)
app.command("ingest")(scene.ingest)
app.command("fit")(nsg.fit)
app.command("render")(nsg.render)
app.add_typer(world.app, name="world")
app.add_typer(scs.app, name="scs")
app.add_typer(scene.app, name="scene")
app.add_typer(catalog.app, name="catalog")
app.add_typer(bench.app, name="bench")


def main() -> None:
    try:
        app()
    except OmniscsError as exc:
        print_error(str(exc))
        sys.exit(2)


if __name__ == "__main__":
    main()
