"""``python -m perception_model.cli``: the ``perception-model`` command."""

from . import main

main()
