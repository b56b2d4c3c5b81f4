"""The ``omniscs`` command line: the top floor. Each command group lives in its own module; a handler parses its
options and calls the pipeline's stages (or the flow), nothing more."""
from __future__ import annotations

import sys

import typer

from omniscs.cli import (bench, catalog, closedloop, dataset, evaluation, export, generate, nsg, pool, predict,
                         pretrained, scene, scs, view, world)
from omniscs.cli.common import print_error
from omniscs.errors import OmniscsError

app = typer.Typer(help="OmniSCS data factory: safety-critical driving scenarios from ordinary logs.",
                  pretty_exceptions_enable=False, no_args_is_help=True)
app.command("generate")(generate.generate)
app.command("demo")(generate.demo)
app.command("ingest")(scene.ingest)
app.command("fit")(nsg.fit)
app.command("render")(nsg.render)
app.command("view")(view.view)
app.add_typer(world.app, name="world")
app.add_typer(scs.app, name="scs")
app.add_typer(scene.app, name="scene")
app.add_typer(catalog.app, name="catalog")
app.add_typer(dataset.app, name="dataset")
app.add_typer(predict.app, name="predict")
app.add_typer(export.app, name="export")
app.add_typer(evaluation.app, name="eval")
app.add_typer(pool.app, name="pool")
app.add_typer(closedloop.app, name="closedloop")
app.command("finetune")(evaluation.finetune)
app.add_typer(bench.app, name="bench")
app.add_typer(pretrained.app, name="pretrained")


#: Click's usage error (typer ships its own copy of click; found through a public subclass of it).
UsageError = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "UsageError")


def main() -> None:
    """The ``omniscs`` entry point: a user's mistake, in the domain (OmniscsError) or in the command line (an
    unknown option, a value of the wrong type), is one ``error:`` line on stderr and exit code 2."""
    try:
        code = app(standalone_mode=False)
    except OmniscsError as exc:
        print_error(str(exc))
        sys.exit(2)
    except UsageError as exc:
        ctx = getattr(exc, "ctx", None)
        if type(exc).__name__ == "NoArgsIsHelpError" and ctx is not None:
            print(ctx.get_help())
            sys.exit(2)
        hint = f" (see: {ctx.command_path} --help)" if ctx is not None else ""
        print_error(exc.format_message() + hint)
        sys.exit(2)
    except (typer.Abort, KeyboardInterrupt, EOFError):
        print_error("aborted")
        sys.exit(130)
    sys.exit(code if isinstance(code, int) else 0)


if __name__ == "__main__":
    main()
