"""``python -m flows.cli``: the ``thermocal`` command line."""

from flows.cli import main

main()
