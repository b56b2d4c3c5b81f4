"""``omniscs catalog``: read-only DuckDB SQL over the Parquet catalog."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from omniscs.cli.common import print_table

app = typer.Typer(help="Query the Parquet catalog with DuckDB (read-only).", no_args_is_help=True)


@app.command("query")
def catalog_query(
    sql: str = typer.Argument(..., help="One SELECT over the views runs, scenes, agents, frames, plans, models, "
                                        "variants (each logical row once), <table>_by_run (per run) or <table>_raw "
                                        "(every row of every file)."),
    workspace: Optional[Path] = typer.Option(None, help="Workspace root (default $OMNISCS_HOME or ./omniscs-data); "
                                                        "it must exist."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON rows."),
    as_csv: bool = typer.Option(False, "--csv", help="Print CSV."),
) -> None:
    """Run one read-only DuckDB SELECT over the catalog and print the result."""
    from omniscs import catalog
    from omniscs.storage import existing_workspace

    table = catalog.query(catalog.catalog_root(existing_workspace(workspace)), sql)
    if as_json:
        typer.echo(json.dumps(table.to_pylist(), indent=2, default=str))
    elif as_csv:
        typer.echo(table.to_pandas().to_csv(index=False), nl=False)
    else:
        print_table(table.to_pylist())


@app.command("views")
def catalog_views(workspace: Optional[Path] = typer.Option(None, help="Workspace root (default $OMNISCS_HOME or "
                                                                      "./omniscs-data); it must exist.")) -> None:
    """Print DuckDB statements that create the catalog views (for the duckdb shell)."""
    from omniscs import catalog
    from omniscs.storage import existing_workspace

    typer.echo(catalog.views_sql(str(catalog.catalog_root(existing_workspace(workspace)))), nl=False)
