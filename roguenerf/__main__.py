"""``python -m roguenerf``: the library has no command line of its own. The command line is the
``roguenerf`` console script, package ``roguecli`` above the library (which imports nothing above
it: docs/architecture.md, Layers); say so, exit 2."""

import sys

command = sys.argv[1] if len(sys.argv) > 1 and not sys.argv[1].startswith("-") else "COMMAND"
sys.stderr.write(f"error: the command line is the `roguenerf` console script: run `roguenerf {command}` "
                 f"or `python -m roguecli {command}`\n")
raise SystemExit(2)
