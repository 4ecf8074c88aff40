"""``serve``: the HTTP API with its embedded job worker (package ``service``), imported only when
the command runs."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from roguecli.common import fail, handle_errors


def serve(
    host: Annotated[str, typer.Option("--host", help="Address to listen on.")] = "127.0.0.1",
    port: Annotated[int, typer.Option("--port", help="Port to listen on.")] = 8000,
    data_dir: Annotated[Path, typer.Option(
        "--data-dir", help="Where scenes, jobs and checkpoints live.")] = Path("./data"),
) -> None:
    """Start the HTTP API with its embedded job worker."""
    # OpenMP's wait policy was chosen when this package imported roguenerf (roguenerf.runtime:
    # PASSIVE unless the user set one), before torch loads; the worker inherits it.
    with handle_errors():
        try:
            from service.server import run
        except ImportError as exc:
            missing = exc.name or str(exc)
            fail(f"the service cannot start: {missing} is not installed "
                  "(install the extras: pip install 'roguenerf[service]')", 1)
        run(host=host, port=port, data_dir=data_dir)
