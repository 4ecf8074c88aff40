"""``python -m roguecli`` runs the ``roguenerf`` console script."""

from roguecli import main

main()
