"""``python -m roguenerf`` runs the command-line interface."""

from roguenerf.cli import main

main()
