"""``python -m lidarloc.app.cli``: the same as the ``lidarloc`` command."""

from . import main

main()
