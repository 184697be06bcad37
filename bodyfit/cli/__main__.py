"""``python -m bodyfit.cli``: the ``bodyfit`` command."""

from bodyfit.cli.app import main

main()
