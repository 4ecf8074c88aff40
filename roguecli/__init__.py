"""The ``roguenerf`` command line (``python -m roguecli``): the one typer app, one module per
command group.

    training.py  finetune, pretrain        enhance.py  evaluate, enhance
    pairs.py     make-pairs (roguefit)     imports.py  import-nerfstudio, import-gsplat, import-3dgs
    paths.py     enhance-path              serve.py    serve (service)
    common.py    errors and exit codes, logging, bars, shared options

A command is a plain function in its group's module, registered by one line below (the order of
the lines is the order of ``--help``). This package sits above all the others: ``serve`` and
``make-pairs`` import their package (``service``, ``roguefit``) only when they run, so ``--help``
and the other commands load neither; nothing imports this package, and the library imports
nothing above it (docs/architecture.md, Layers).
"""

from __future__ import annotations

import typer

from roguecli import enhance, imports, pairs, paths, serve, training
from roguecli.common import run_app

# rich_markup_mode=None: typer's rich help shows flags (--json, --help) as taking a "<bool>" value.
app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  rich_markup_mode=None,
                  help="RoGUENeRF: enhance radiance-field renders with geometry-aligned training photos.")

app.command("finetune")(training.finetune)
app.command("pretrain")(training.pretrain)
app.command("make-pairs")(pairs.make_pairs_command)
app.command("evaluate")(enhance.evaluate)
app.command("enhance")(enhance.enhance)
app.command("import-nerfstudio")(imports.import_nerfstudio)
app.command("import-gsplat")(imports.import_gsplat)
app.command("import-3dgs")(imports.import_3dgs_command)
app.command("enhance-path")(paths.enhance_path_command)
app.command("serve")(serve.serve)


def main() -> None:
    """Console-script entry point (``roguenerf``; ``python -m roguecli``)."""
    run_app(app, fast_exit=True)
